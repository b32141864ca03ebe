"""Robot model: URDF kinematics, keypoints and surface points.

The URDF is parsed here (joints, link visuals) and forward kinematics is a batched numpy
product over the kinematic tree, so the training loss, the metrics and the renderer never
call a simulator. Tests check it against pybullet's forward kinematics.
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from monose3.errors import Monose3Error
from monose3.geometry.rotations import axis_angle_to_matrix
from monose3.robot.meshes import RobotMesh, Visual, check_visual_files, mesh_from_visuals, parse_visuals, urdf_origin

NUM_SURFACE_POINTS = 2000


@dataclass(frozen=True)
class Keypoint:
    """A named point: the origin of ``link`` shifted by ``offset`` (meters, link frame)."""

    name: str
    link: str
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class RobotSpec:
    """What identifies a robot: its URDF, its keypoints and defaults for optional joints."""

    name: str
    urdf: str
    keypoints: tuple[Keypoint, ...]
    optional_joints: Mapping[str, float] = field(default_factory=dict)
    # A compact mesh file (RobotMesh.save) used instead of the URDF's visual files.
    mesh_asset: str | None = None


ASSETS = Path(__file__).resolve().parent.parent / "assets" / "robots"


PANDA = RobotSpec(
    name="panda",
    urdf=str(ASSETS / "panda" / "panda.urdf"),
    mesh_asset=str(ASSETS / "panda" / "meshes.npz"),
    keypoints=tuple(
        Keypoint(n, n)
        for n in (
            "panda_link0",
            "panda_link2",
            "panda_link3",
            "panda_link4",
            "panda_link6",
            "panda_link7",
            "panda_hand",
        )
    ),
    # The gripper is not part of DREAM's annotations; an open-ish default keeps renders honest.
    optional_joints={"panda_finger_joint1": 0.02, "panda_finger_joint2": 0.02},
)

KUKA = RobotSpec(
    name="kuka",
    urdf=str(ASSETS / "kuka" / "model.urdf"),
    mesh_asset=str(ASSETS / "kuka" / "meshes.npz"),
    # DREAM's Kuka sets name the keypoints iiwa7_link_N; pybullet's URDF names the links lbr_iiwa_link_N.
    keypoints=tuple(Keypoint(f"iiwa7_link_{i}", f"lbr_iiwa_link_{i}") for i in range(8)),
)

ROBOTS = {"panda": PANDA, "kuka": KUKA}


def _parse_keypoints(entries: object, source: Path) -> tuple[Keypoint, ...]:
    try:
        return tuple(Keypoint(e["name"], e["link"], tuple(e.get("offset", (0, 0, 0)))) for e in entries)
    except (KeyError, TypeError, ValueError) as err:
        raise Monose3Error(
            f"malformed keypoint spec {source}: {err!r}; expected "
            '{"keypoints": [{"name": ..., "link": ..., "offset": [x, y, z]}]}'
        ) from None


def _read_json(path: Path) -> dict:
    if not path.is_file():
        raise Monose3Error(f"robot file not found: {path} (pass an existing URDF and keypoint JSON)")
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise Monose3Error(f"malformed keypoint spec {path}: not valid JSON ({err}); fix its syntax") from None
    if not isinstance(data, dict) or "keypoints" not in data:
        raise Monose3Error(f'malformed keypoint spec {path}: no "keypoints" list; give {{"keypoints": [...]}}')
    return data


def spec_from_files(urdf: str | Path, keypoints_json: str | Path, name: str | None = None) -> RobotSpec:
    """A spec for any URDF. The keypoint file is ``{"keypoints": [{"name", "link", "offset"?}]}``
    (and optionally ``"optional_joints": {name: default}``)."""
    urdf, kp_path = Path(urdf), Path(keypoints_json)
    if not urdf.is_file():
        raise Monose3Error(f"robot file not found: {urdf} (pass an existing URDF and keypoint JSON)")
    data = _read_json(kp_path)
    # The shipped URDFs come with their meshes as one compact asset, not as files beside them.
    shipped = next((s.mesh_asset for s in ROBOTS.values() if Path(s.urdf).resolve() == urdf.resolve()), None)
    return RobotSpec(
        name=name or urdf.stem,
        urdf=str(urdf),
        keypoints=_parse_keypoints(data["keypoints"], kp_path),
        optional_joints=dict(data.get("optional_joints", {})),
        mesh_asset=shipped,
    )


def spec_from_robot_file(path: str | Path) -> RobotSpec:
    """A robot described by one JSON file: ``{"urdf": "arm.urdf", "keypoints": [...]}``, the URDF
    path relative to the file; its name is ``"name"`` or the file's stem."""
    path = Path(path)
    data = _read_json(path)
    if "urdf" not in data:
        raise Monose3Error(f'robot file {path} does not name its URDF; add "urdf": "robot.urdf" (relative to the file)')
    return spec_from_files(path.parent / data["urdf"], path, data.get("name") or path.stem)


def robot_reference(robot: str) -> str:
    """How a robot is named in configs and checkpoints: a shipped robot's name, or the absolute
    path of a robot file (so a model trained on it finds it again from any folder)."""
    return robot if robot in ROBOTS else str(Path(robot).resolve())


def get_spec(robot: str | RobotSpec) -> RobotSpec:
    """Resolve a robot name ('panda', 'kuka') or a robot file (``*.json``, see
    :func:`spec_from_robot_file`), or pass a spec through."""
    if isinstance(robot, RobotSpec):
        return robot
    if robot in ROBOTS:
        return ROBOTS[robot]
    if str(robot).endswith(".json"):
        return spec_from_robot_file(robot)
    raise Monose3Error(
        f"unknown robot {robot!r}; choose one of {sorted(ROBOTS)} or give a robot file "
        '(robot.json: {"urdf": "robot.urdf", "keypoints": [...]})'
    )


@dataclass
class _Joint:
    name: str
    kind: str
    parent: str
    child: str
    origin: np.ndarray  # 4x4, parent link frame -> joint frame at zero position
    axis: np.ndarray
    lower: float
    upper: float
    mimic: str | None = None
    multiplier: float = 1.0
    offset: float = 0.0


def parse_urdf(path: Path) -> tuple[str, list[str], list[_Joint], list[Visual]]:
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as err:
        raise Monose3Error(f"cannot read URDF {path}: {err}") from None
    links = [link.get("name") for link in root.findall("link")]
    joints = []
    for j in root.findall("joint"):
        limit, axis, mimic = j.find("limit"), j.find("axis"), j.find("mimic")
        joints.append(
            _Joint(
                name=j.get("name"),
                kind=j.get("type"),
                parent=j.find("parent").get("link"),
                child=j.find("child").get("link"),
                origin=urdf_origin(j.find("origin")),
                axis=np.array((axis.get("xyz") if axis is not None else "1 0 0").split(), float),
                lower=float(limit.get("lower", "-inf")) if limit is not None else -np.inf,
                upper=float(limit.get("upper", "inf")) if limit is not None else np.inf,
                mimic=mimic.get("joint") if mimic is not None else None,
                multiplier=float(mimic.get("multiplier", 1)) if mimic is not None else 1.0,
                offset=float(mimic.get("offset", 0)) if mimic is not None else 0.0,
            )
        )
    children = {j.child for j in joints}
    roots = [n for n in links if n not in children]
    if len(roots) != 1:
        raise Monose3Error(f"URDF {path} must have exactly one root link, found {roots}")
    return roots[0], links, joints, parse_visuals(root, path.parent)


def _sample_surface(
    verts: np.ndarray, faces: np.ndarray, n: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points uniform over the mesh surface and the face each lies on."""
    tri = verts[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    pick = rng.choice(len(faces), size=n, p=area / area.sum())
    u, v = rng.random((2, n))
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    t = tri[pick]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0]), pick


class RobotModel:
    """Kinematics, keypoints and surface points of one robot.

    Joint configurations are mappings ``{name: radians}``; names may carry a ``prefix/``
    path (DREAM writes ``panda/panda_joint1``), only the last part counts.
    """

    def __init__(self, robot: str | RobotSpec = "panda"):
        self.spec = get_spec(robot)
        self.urdf_path = Path(self.spec.urdf)
        if not self.urdf_path.is_file():
            raise Monose3Error(f"URDF not found: {self.urdf_path}")
        self.root, self.links, self._joints, self._visuals = parse_urdf(self.urdf_path)
        self.link_index = {name: i for i, name in enumerate(self.links)}
        self._order = self._topological_joints()
        movable = [j for j in self._joints if j.kind in ("revolute", "continuous", "prismatic")]
        self.joint_names = [j.name for j in movable if j.mimic is None]
        self._mimic = {j.name: j for j in movable if j.mimic is not None}
        self._joint_by_name = {j.name: j for j in movable}
        for kp in self.spec.keypoints:
            if kp.link not in self.link_index:
                raise Monose3Error(f"keypoint {kp.name!r} names unknown link {kp.link!r} in {self.urdf_path.name}")
        if not self.spec.mesh_asset:
            check_visual_files(self._visuals, self.urdf_path)
        self._last_kinematics: tuple[bytes, np.ndarray] | None = None

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def required_joints(self) -> list[str]:
        return [n for n in self.joint_names if n not in self.spec.optional_joints]

    @property
    def keypoint_names(self) -> list[str]:
        return [kp.name for kp in self.spec.keypoints]

    @property
    def mimic_joint_names(self) -> list[str]:
        """Joints driven by another (URDF ``<mimic>``): not inputs, but files may list them."""
        return list(self._mimic)

    def joint_limits(self) -> np.ndarray:
        """``[n_joints, 2]`` lower/upper limits of the independent joints."""
        return np.array([[self._joint_by_name[n].lower, self._joint_by_name[n].upper] for n in self.joint_names])

    def _topological_joints(self) -> list[_Joint]:
        order, frontier = [], [self.root]
        by_parent: dict[str, list[_Joint]] = {}
        for j in self._joints:
            by_parent.setdefault(j.parent, []).append(j)
        while frontier:
            link = frontier.pop(0)
            for j in by_parent.get(link, []):
                order.append(j)
                frontier.append(j.child)
        return order

    # ---- joint configurations -------------------------------------------------------------

    def joint_vector(self, joints: Mapping[str, float] | Sequence[float] | np.ndarray) -> np.ndarray:
        """Validate a configuration and return it as a vector in ``joint_names`` order.

        A sequence is taken in URDF order: either all independent joints or only the
        required ones (optional joints take their defaults).
        """
        if isinstance(joints, Mapping):
            given = {str(k).rsplit("/", 1)[-1]: v for k, v in joints.items()}
            unknown = sorted(set(given) - set(self.joint_names) - set(self._mimic))
            if unknown:
                raise Monose3Error(f"unknown joint(s) {unknown} for robot {self.name}; expected {self.required_joints}")
            missing = [n for n in self.required_joints if n not in given]
            if missing:
                raise Monose3Error(
                    f"missing joint(s) {missing} for robot {self.name}; give all of {self.required_joints}"
                )
            values = [given.get(n, self.spec.optional_joints.get(n)) for n in self.joint_names]
        else:
            try:
                values = list(np.asarray(joints, dtype=np.float64).reshape(-1))
            except (TypeError, ValueError):
                raise Monose3Error(f"joint values must be numbers (radians), got {joints!r}") from None
            if len(values) == len(self.required_joints) and len(values) != len(self.joint_names):
                it = iter(values)
                values = [
                    self.spec.optional_joints[n] if n in self.spec.optional_joints else next(it)
                    for n in self.joint_names
                ]
            elif len(values) != len(self.joint_names):
                raise Monose3Error(
                    f"got {len(values)} joint values, robot {self.name} has {len(self.required_joints)} "
                    f"({self.required_joints})"
                )
        try:
            vec = np.asarray(values, dtype=np.float64)
        except (TypeError, ValueError):
            raise Monose3Error(f"joint values must be numbers (radians), got {values}") from None
        if not np.all(np.isfinite(vec)):
            bad = [n for n, v in zip(self.joint_names, vec, strict=True) if not np.isfinite(v)]
            raise Monose3Error(f"joint value(s) for {bad} are NaN or infinite; give finite radians")
        return vec

    def joint_dict(self, vector: np.ndarray) -> dict[str, float]:
        return {n: float(v) for n, v in zip(self.joint_names, vector, strict=True)}

    def random_joints(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``[n, n_joints]`` configurations uniform within the joint limits."""
        lim = self.joint_limits()
        lo = np.where(np.isfinite(lim[:, 0]), lim[:, 0], -np.pi)
        hi = np.where(np.isfinite(lim[:, 1]), lim[:, 1], np.pi)
        return lo + rng.random((n, len(lo))) * (hi - lo)

    # ---- kinematics -----------------------------------------------------------------------

    def all_joint_values(self, joints: np.ndarray) -> dict[str, np.ndarray]:
        """``{name: [B] values}`` of every movable joint, the URDF ``<mimic>`` ones derived from
        the ``[B, n_joints]`` independent ones."""
        joints = np.atleast_2d(np.asarray(joints, np.float64))
        value = {n: joints[:, i] for i, n in enumerate(self.joint_names)}
        for name, j in self._mimic.items():
            value[name] = value[j.mimic] * j.multiplier + j.offset
        return value

    def link_poses(self, joints: np.ndarray) -> np.ndarray:
        """Forward kinematics: ``[B, n_joints]`` vectors to ``[B, n_links, 4, 4]`` base-frame poses,
        each distinct row solved once and the last answer kept (a fit renders one configuration
        in a dozen calls of many poses each: 6 % of a tracked frame's time went to kinematics)."""
        distinct, row = np.unique(np.atleast_2d(np.asarray(joints, np.float64)), axis=0, return_inverse=True)
        if self._last_kinematics is None or self._last_kinematics[0] != distinct.tobytes():
            self._last_kinematics = distinct.tobytes(), self._kinematics(distinct)
        return self._last_kinematics[1][row.reshape(-1)]

    def _kinematics(self, joints: np.ndarray) -> np.ndarray:
        batch = joints.shape[0]
        value = self.all_joint_values(joints)
        poses = np.zeros((batch, len(self.links), 4, 4))
        poses[:, self.link_index[self.root]] = np.eye(4)
        for j in self._order:
            motion = np.broadcast_to(np.eye(4), (batch, 4, 4)).copy()
            if j.kind in ("revolute", "continuous"):
                motion[:, :3, :3] = axis_angle_to_matrix(j.axis / np.linalg.norm(j.axis), value[j.name])
            elif j.kind == "prismatic":
                motion[:, :3, 3] = value[j.name][:, None] * j.axis
            poses[:, self.link_index[j.child]] = poses[:, self.link_index[j.parent]] @ j.origin @ motion
        return poses

    def keypoints(self, joints: np.ndarray, camera_from_base: np.ndarray | None = None) -> np.ndarray:
        """``[B, n_keypoints, 3]`` keypoints in the base frame, or in the camera frame when
        ``camera_from_base`` ``[B, 4, 4]`` is given."""
        idx = [self.link_index[kp.link] for kp in self.spec.keypoints]
        poses = self.link_poses(joints)[:, idx]
        offsets = np.array([kp.offset for kp in self.spec.keypoints])
        points = np.einsum("bkij,kj->bki", poses[..., :3, :3], offsets) + poses[..., :3, 3]
        if camera_from_base is None:
            return points
        cam = np.asarray(camera_from_base, np.float64).reshape(-1, 4, 4)
        return np.einsum("bij,bkj->bki", cam[:, :3, :3], points) + cam[:, None, :3, 3]

    @cached_property
    def mesh(self) -> RobotMesh:
        """The visual triangles in link frames: the shipped asset, or the URDF's OBJ/STL files."""
        if self.spec.mesh_asset:
            mesh = RobotMesh.load(self.spec.mesh_asset)
            if mesh.links != tuple(self.links):
                raise Monose3Error(f"mesh asset {self.spec.mesh_asset} belongs to another URDF than {self.urdf_path}")
            return mesh
        return mesh_from_visuals(self._visuals, self.links, self.urdf_path)

    @cached_property
    def _surface_local(self) -> tuple[np.ndarray, np.ndarray]:
        """Surface samples in their link frames and the link each belongs to (seed 0)."""
        mesh = self.mesh
        points, faces = _sample_surface(mesh.vertices, mesh.faces, NUM_SURFACE_POINTS, np.random.default_rng(0))
        return points, mesh.face_link[faces]

    def surface_points(self, joints: np.ndarray) -> np.ndarray:
        """``[B, 2000, 3]`` fixed surface samples of the posed robot in the base frame."""
        local, link_ids = self._surface_local
        poses = self.link_poses(joints)[:, link_ids]
        return np.einsum("bnij,nj->bni", poses[..., :3, :3], local) + poses[..., :3, 3]

    @staticmethod
    def centroid(points: np.ndarray) -> np.ndarray:
        """Centre of the axis-aligned bounding box of ``[..., N, 3]`` points (RoboPose's reference point)."""
        return 0.5 * (points.min(-2) + points.max(-2))
