"""The robot's triangle meshes, in their link frames, with a colour per face.

A :class:`RobotMesh` is what the renderer draws and what surface points are sampled from.
It comes either from a compact ``.npz`` asset shipped with the package (the built-in robots,
simplified once by ``tools/build_robot_assets.py``) or straight from a URDF's visual OBJ/STL
files (a user's own robot). Colours are the OBJ materials' diffuse colour times their
texture at the face's mean texture coordinate, or the URDF material colour, or grey.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from monose3.atomic import atomic_path
from monose3.errors import Monose3Error

DEFAULT_COLOR = (0.7, 0.7, 0.7)
MESH_FORMATS = (".obj", ".stl")


@dataclass(frozen=True)
class Visual:
    """One ``<visual>`` mesh of a URDF link: file name as written, its origin and scale."""

    link: str
    filename: str
    origin: np.ndarray  # 4x4 link frame -> mesh frame
    scale: np.ndarray  # [3]
    color: tuple[float, float, float] | None = None  # the URDF material's rgb, if given


@dataclass(frozen=True)
class RobotMesh:
    """All visual triangles of a robot, grouped by link (each link's vertices contiguous).

    ``vertices`` ``[V, 3]`` are in the frame of link ``links[vertex_link[i]]`` (metres);
    ``faces`` ``[F, 3]`` index ``vertices``; ``face_colors`` ``[F, 3]`` are RGB in [0, 1].
    ``caps`` ``[C, 3]`` close the holes of open links (``mesh_repair.py``): drawn, so that back
    faces can be skipped, but not the robot's surface (no surface points, no normals on them).
    """

    links: tuple[str, ...]
    vertices: np.ndarray
    vertex_link: np.ndarray
    faces: np.ndarray
    face_colors: np.ndarray
    caps: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int64))

    @property
    def face_link(self) -> np.ndarray:
        """``[F]`` index into ``links`` of each face."""
        return self.vertex_link[self.faces[:, 0]]

    @property
    def drawn_faces(self) -> np.ndarray:
        """``[F + C, 3]``: the faces, then the caps."""
        return np.concatenate([self.faces, self.caps])

    @property
    def drawn_face_link(self) -> np.ndarray:
        """``[F + C]`` index into ``links`` of each drawn face."""
        return self.vertex_link[self.drawn_faces[:, 0]]

    @property
    def drawn_colors(self) -> np.ndarray:
        """``[F + C, 3]``: the faces' colours, then each cap's, its link's mean face colour."""
        link_colors = np.zeros((len(self.links), 3))
        np.add.at(link_colors, self.face_link, self.face_colors)
        link_colors /= np.maximum(np.bincount(self.face_link, minlength=len(self.links)), 1)[:, None]
        return np.concatenate([self.face_colors, link_colors[self.vertex_link[self.caps[:, 0]]]])

    def closed_faces(self) -> np.ndarray:
        """``[F + C]`` bool per drawn face (:attr:`drawn_faces`): it belongs to a link whose mesh
        (with its caps) is closed and consistently wound (vertices welded by position, every
        edge used as often in one direction as in the other: :func:`surplus_edges` finds none),
        so its back faces are hidden and need not be drawn."""
        faces = welded_vertex_ids(self.vertices)[self.drawn_faces]
        face_link = self.drawn_face_link
        closed = np.zeros(len(faces), bool)
        for link in np.unique(face_link):
            sel = face_link == link
            closed[sel] = not surplus_edges(faces[sel])
        return closed

    def save(self, path: str | Path) -> None:
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:  # a file object: numpy adds no ".npz"
            np.savez_compressed(
                fh,
                links=np.array(self.links),
                vertices=self.vertices.astype(np.float32),
                vertex_link=self.vertex_link.astype(np.int16),
                faces=self.faces.astype(np.int32),
                face_colors=np.round(self.face_colors * 255).astype(np.uint8),
                caps=self.caps.astype(np.int32),
            )

    @staticmethod
    def load(path: str | Path) -> RobotMesh:
        try:
            data = np.load(path)
            return RobotMesh(
                links=tuple(str(n) for n in data["links"]),
                vertices=data["vertices"].astype(np.float64),
                vertex_link=data["vertex_link"].astype(np.int64),
                faces=data["faces"].astype(np.int64),
                face_colors=data["face_colors"].astype(np.float64) / 255.0,
                caps=data["caps"].astype(np.int64) if "caps" in data else np.zeros((0, 3), np.int64),
            )
        except (OSError, KeyError, ValueError) as err:
            raise Monose3Error(f"cannot read robot mesh asset {path}: {err}; reinstall monose3") from None


def _read_mtl(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray | None]]:
    """Material name -> (Kd rgb, texture image float RGB or None)."""
    import cv2

    materials: dict[str, tuple[np.ndarray, np.ndarray | None]] = {}
    name, kd, tex = None, np.ones(3), None
    textures: dict[str, np.ndarray | None] = {}

    def close() -> None:
        if name is not None:
            materials[name] = (kd, tex)

    for line in path.read_text(errors="replace").splitlines():
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "newmtl":
            close()
            name, kd, tex = " ".join(parts[1:]), np.ones(3), None
        elif parts[0] == "Kd" and len(parts) >= 4:
            kd = np.array([float(x) for x in parts[1:4]])
        elif parts[0] == "map_Kd" and len(parts) >= 2:
            file = path.parent / parts[-1]
            if str(file) not in textures:
                img = cv2.imread(str(file), cv2.IMREAD_COLOR) if file.is_file() else None
                textures[str(file)] = None if img is None else img[..., ::-1].astype(np.float64) / 255.0
            tex = textures[str(file)]
    close()
    return materials


def _sample_texture(tex: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Nearest texel of ``[N, 2]`` texture coordinates (v up, wrapped) -> ``[N, 3]``."""
    h, w = tex.shape[:2]
    u = np.mod(uv[:, 0], 1.0)
    v = np.mod(uv[:, 1], 1.0)
    col = np.clip((u * w).astype(int), 0, w - 1)
    row = np.clip(((1.0 - v) * h).astype(int), 0, h - 1)
    return tex[row, col]


def load_obj(
    path: Path, fallback: tuple[float, float, float] | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices ``[V, 3]``, triangles ``[F, 3]`` (polygons fan-split) and face colours ``[F, 3]``
    of a Wavefront OBJ, colours from its ``.mtl`` (diffuse x texture) or ``fallback``."""
    verts, texcoords, faces, face_uv, face_mtl = [], [], [], [], []
    materials: dict[str, tuple[np.ndarray, np.ndarray | None]] = {}
    current = None
    with open(path, errors="replace") as fh:
        for line in fh:
            if line.startswith("v "):
                verts.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("vt "):
                texcoords.append([float(x) for x in line.split()[1:3]])
            elif line.startswith("f "):
                toks = [tok.split("/") for tok in line.split()[1:]]
                idx = [int(t[0]) for t in toks]
                idx = [i - 1 if i > 0 else len(verts) + i for i in idx]
                tidx = [int(t[1]) - 1 if len(t) > 1 and t[1] else -1 for t in toks]
                for k in range(1, len(idx) - 1):
                    faces.append([idx[0], idx[k], idx[k + 1]])
                    face_uv.append([tidx[0], tidx[k], tidx[k + 1]])
                    face_mtl.append(current)
            elif line.startswith("usemtl"):
                current = line.split(maxsplit=1)[1].strip() if len(line.split()) > 1 else None
            elif line.startswith("mtllib"):
                mtl = path.parent / line.split(maxsplit=1)[1].strip()
                if mtl.is_file():
                    materials.update(_read_mtl(mtl))
    verts_np = np.asarray(verts, np.float64).reshape(-1, 3)
    faces_np = np.asarray(faces, np.int64).reshape(-1, 3)
    colors = np.tile(np.asarray(fallback or DEFAULT_COLOR, np.float64), (len(faces_np), 1))
    uv_np = np.asarray(texcoords, np.float64).reshape(-1, 2)
    face_uv_np = np.asarray(face_uv, np.int64).reshape(-1, 3)
    for name, (kd, tex) in materials.items():
        sel = np.array([m == name for m in face_mtl], bool)
        if not sel.any():
            continue
        colors[sel] = kd
        has_uv = sel & (face_uv_np >= 0).all(1)
        if tex is not None and has_uv.any() and len(uv_np):
            colors[has_uv] = kd * _sample_texture(tex, uv_np[face_uv_np[has_uv]].mean(1))
    return verts_np, faces_np, np.clip(colors, 0.0, 1.0)


def load_stl(path: Path, color: tuple[float, float, float] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Binary or ASCII STL as (vertices, triangles, face colours)."""
    data = path.read_bytes()
    if data[:5].lower() == b"solid" and b"facet" in data[:1000]:
        coords = [
            [float(x) for x in line.split()[1:4]]
            for line in data.decode(errors="replace").splitlines()
            if line.strip().startswith("vertex")
        ]
        tri = np.asarray(coords, np.float64).reshape(-1, 3, 3)
    else:
        n = int(np.frombuffer(data[80:84], np.uint32)[0])
        if len(data) < 84 + 50 * n:
            raise Monose3Error(f"STL file {path} is truncated; re-export the mesh")
        rec = np.frombuffer(data[84 : 84 + 50 * n], np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")]))
        tri = rec["v"].astype(np.float64)
    faces = np.arange(len(tri) * 3).reshape(-1, 3)
    colors = np.tile(np.asarray(color or DEFAULT_COLOR, np.float64), (len(faces), 1))
    return tri.reshape(-1, 3), faces, colors


def resolve_mesh(filename: str, urdf_dir: Path) -> Path:
    """A URDF mesh reference (``package://pkg/x``, relative or absolute) to an existing file."""
    rel = filename.split("://", 1)[1] if "://" in filename else filename
    # package://pkg/x resolves against the URDF folder in pybullet's data layout.
    for cand in (urdf_dir / rel, urdf_dir / rel.split("/", 1)[-1], Path(rel)):
        if cand.is_file():
            return cand
    raise Monose3Error(
        f"mesh {filename!r} referenced by the URDF not found next to {urdf_dir}; put the mesh files beside the URDF"
    )


def urdf_origin(elem: ET.Element | None) -> np.ndarray:
    """The 4x4 transform of a URDF ``<origin rpy xyz>`` element (identity when absent)."""
    from monose3.geometry.rotations import euler_xyz_to_matrix

    pose = np.eye(4)
    if elem is not None:
        pose[:3, :3] = euler_xyz_to_matrix(np.array(elem.get("rpy", "0 0 0").split(), float))
        pose[:3, 3] = np.array(elem.get("xyz", "0 0 0").split(), float)
    return pose


def parse_visuals(root: ET.Element, urdf_dir: Path) -> list[Visual]:
    """The mesh visuals of a parsed URDF (primitive shapes are skipped)."""
    colors = {}
    for mat in root.findall("material"):
        col = mat.find("color")
        if col is not None and mat.get("name"):
            colors[mat.get("name")] = tuple(float(x) for x in col.get("rgba", "0.7 0.7 0.7 1").split()[:3])
    visuals = []
    for link in root.findall("link"):
        for vis in link.findall("visual"):
            mesh = vis.find("geometry/mesh")
            if mesh is None:
                continue
            mat = vis.find("material")
            color = None
            if mat is not None:
                inline = mat.find("color")
                if inline is not None:
                    color = tuple(float(x) for x in inline.get("rgba").split()[:3])
                else:
                    color = colors.get(mat.get("name"))
            visuals.append(
                Visual(
                    link=link.get("name"),
                    filename=mesh.get("filename"),
                    origin=urdf_origin(vis.find("origin")),
                    scale=np.array(mesh.get("scale", "1 1 1").split(), float),
                    color=color,
                )
            )
    return visuals


def welded_vertex_ids(vertices: np.ndarray) -> np.ndarray:
    """``[V]`` one id per distinct position of ``vertices`` ``[V, 3]`` (to the micrometre): meshes
    repeat a vertex where its normal or texture coordinate changes."""
    return np.unique(np.round(vertices * 1e6).astype(np.int64), axis=0, return_inverse=True)[1].reshape(-1)


def surplus_edges(faces: np.ndarray) -> dict[int, list[int]]:
    """Where the mesh ``faces`` ``[F, 3]`` (welded vertex ids) is open: ``{a: [b, ...]}``, the
    edge a -> b once for each time the faces use it more often that way than b -> a. Empty for a
    closed, consistently wound mesh; otherwise the edges form closed loops (each face's edges do)."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    edges = edges[edges[:, 0] != edges[:, 1]]
    pairs, inverse = np.unique(np.sort(edges, 1), axis=0, return_inverse=True)
    flow = np.zeros(len(pairs), np.int64)
    np.add.at(flow, inverse.reshape(-1), np.where(edges[:, 0] < edges[:, 1], 1, -1))
    out: dict[int, list[int]] = {}
    for (lo, hi), k in zip(pairs[flow != 0].tolist(), flow[flow != 0].tolist(), strict=True):
        a, b = (lo, hi) if k > 0 else (hi, lo)
        out.setdefault(a, []).extend([b] * abs(k))
    return out


def check_visual_files(visuals: list[Visual], urdf_path: Path) -> None:
    """Every visual mesh exists and is OBJ or STL, and there is at least one: else a clear error."""
    if not visuals:
        raise Monose3Error(f"URDF {urdf_path.name} has no visual meshes; the renderer needs OBJ or STL visuals")
    for vis in visuals:
        path = resolve_mesh(vis.filename, urdf_path.parent)
        if path.suffix.lower() not in MESH_FORMATS:
            raise Monose3Error(
                f"mesh {path.name} of link {vis.link} is {path.suffix or 'of no known format'}; "
                "convert it to OBJ or STL (e.g. with trimesh or Blender)"
            )


def mesh_from_visuals(
    visuals: list[Visual], links: list[str], urdf_path: Path, prepare: Callable | None = None
) -> RobotMesh:
    """Load every visual of a URDF into one :class:`RobotMesh` (links in ``links`` order).

    ``prepare(vertices, faces, colors) -> (vertices, faces, colors)``, when given, is applied to
    each mesh in its own frame before it is placed (``tools/build_robot_assets.py`` simplifies there)."""
    check_visual_files(visuals, urdf_path)
    order = {name: i for i, name in enumerate(links)}
    parts = []
    for vis in sorted(visuals, key=lambda v: order[v.link]):
        path = resolve_mesh(vis.filename, urdf_path.parent)
        loader = load_obj if path.suffix.lower() == ".obj" else load_stl
        verts, faces, colors = loader(path, vis.color)
        if prepare is not None:
            verts, faces, colors = prepare(verts, faces, colors)
        verts = verts * vis.scale @ vis.origin[:3, :3].T + vis.origin[:3, 3]
        parts.append((order[vis.link], verts, faces, colors))
    return concatenate(tuple(links), parts)


def concatenate(links: tuple[str, ...], parts: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]]) -> RobotMesh:
    """One mesh from (link index, vertices, faces, face colours) parts, in the given order."""
    offset, faces = 0, []
    for _, verts, f, _ in parts:
        faces.append(f + offset)
        offset += len(verts)
    if not parts or offset == 0:
        raise Monose3Error("the robot has no visual triangles to render")
    return RobotMesh(
        links=links,
        vertices=np.concatenate([p[1] for p in parts]),
        vertex_link=np.concatenate([np.full(len(p[1]), p[0]) for p in parts]),
        faces=np.concatenate(faces),
        face_colors=np.concatenate([p[3] for p in parts]),
    )
