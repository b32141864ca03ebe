"""Build the robot assets shipped in ``src/monose3/assets/robots/``: each built-in robot's URDF
and one compact mesh file (``meshes.npz``, a :class:`monose3.robot.meshes.RobotMesh`) made by
simplifying the URDF's visual meshes once, so that nothing at run time needs pybullet, and
closing the holes of the simplified meshes where the caps stay hidden
(:func:`monose3.robot.mesh_repair.capped_mesh`), so that the renderer can skip back faces.

Offline, from a checkout with pybullet and fast-simplification installed:

    pip install pybullet fast-simplification
    python tools/build_robot_assets.py [--keep 0.15]

Sources: pybullet_data's ``franka_panda`` (Franka Emika's meshes, Apache-2.0, licence copied
beside the asset) and ``kuka_iiwa``.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import fast_simplification
import numpy as np
import pybullet_data

from monose3.robot.mesh_repair import capped_mesh
from monose3.robot.meshes import mesh_from_visuals
from monose3.robot.model import parse_urdf

OUT = Path(__file__).resolve().parent.parent / "src" / "monose3" / "assets" / "robots"
SOURCES = {
    "panda": ("franka_panda/panda.urdf", "panda.urdf", "franka_panda/LICENSE.txt"),
    "kuka": ("kuka_iiwa/model.urdf", "model.urdf", None),
}


def simplify(verts: np.ndarray, faces: np.ndarray, colors: np.ndarray, keep: float, min_faces: int):
    """Quadric decimation to ``keep`` of the faces; each new face takes the colour of the
    original vertex nearest to its corners (colours live on faces, decimation keeps none)."""
    if len(faces) <= min_faces:
        return verts, faces, colors
    target = 1.0 - max(keep, min_faces / len(faces))
    new_v, new_f = fast_simplification.simplify(verts.astype(np.float32), faces.astype(np.int32), target)
    vert_color = np.zeros((len(verts), 3))
    count = np.zeros(len(verts))
    for k in range(3):
        np.add.at(vert_color, faces[:, k], colors)
        np.add.at(count, faces[:, k], 1)
    vert_color /= np.maximum(count, 1)[:, None]
    nearest = np.empty(len(new_v), np.int64)
    for start in range(0, len(new_v), 512):
        d = ((new_v[start : start + 512, None] - verts[None]) ** 2).sum(-1)
        nearest[start : start + 512] = d.argmin(1)
    return new_v.astype(np.float64), new_f.astype(np.int64), vert_color[nearest][new_f].mean(1)


def build(name: str, keep: float, min_faces: int) -> None:
    src_rel, urdf_name, licence = SOURCES[name]
    src = Path(pybullet_data.getDataPath()) / src_rel
    out = OUT / name
    out.mkdir(parents=True, exist_ok=True)
    shutil.copy(src, out / urdf_name)
    if licence:
        shutil.copy(Path(pybullet_data.getDataPath()) / licence, out / "LICENSE.txt")
    _, links, _, visuals = parse_urdf(src)
    before = 0

    def prepare(verts: np.ndarray, faces: np.ndarray, colors: np.ndarray):
        nonlocal before
        before += len(faces)
        return simplify(verts, faces, colors, keep, min_faces)

    mesh, holes = capped_mesh(mesh_from_visuals(visuals, links, src, prepare))
    mesh.save(out / "meshes.npz")
    size = (out / "meshes.npz").stat().st_size / 1e6
    print(f"{name}: {before} -> {len(mesh.faces)} faces (+ {len(mesh.caps)} caps), {len(mesh.vertices)} vertices, "
          f"{size:.2f} MB")  # fmt: skip
    for link, what in holes.items():
        print(f"  {link}: {what}")
    print(f"  back faces skipped on {mesh.closed_faces().mean():.0%} of the faces drawn")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keep", type=float, default=0.15, help="fraction of each mesh's faces to keep")
    parser.add_argument("--min-faces", type=int, default=400, help="meshes this small are kept whole")
    args = parser.parse_args()
    for name in SOURCES:
        build(name, args.keep, args.min_faces)


if __name__ == "__main__":
    main()
