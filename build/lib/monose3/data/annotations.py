"""What the DREAM and RoboKeyGen readers share: parsing one frame's joints and keypoints,
units, and the packed index of a whole dataset behind a :class:`FrameSequence` of
:class:`~monose3.data.frame.Frame`.

A reader parses each annotation file into a :class:`ParsedFrame` (bad ones raise
:class:`FrameError` and are skipped with their reason), then :func:`build_index` turns them
into poses and metric keypoints with one batched forward-kinematics call.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from monose3.data.frame import Frame
from monose3.errors import Monose3Error
from monose3.geometry.camera import project
from monose3.geometry.poses import make_pose, rigid_fit
from monose3.robot import RobotModel

log = logging.getLogger("monose3")

# Below this many frames no progress bar is shown while indexing.
PROGRESS_MIN_FRAMES = 5000
UNITS = ("auto", "m", "cm")


class FrameError(ValueError):
    """Why one frame's annotation cannot be used (the frame is skipped, the job goes on)."""


def finite_array(values: object, shape: tuple[int, ...], what: str) -> np.ndarray:
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise FrameError(f"{what} is not numeric: {values!r}") from None
    if arr.shape != shape:
        raise FrameError(f"{what} has shape {arr.shape}, expected {shape}")
    if not np.all(np.isfinite(arr)):
        raise FrameError(f"{what} contains NaN or infinity")
    return arr


def parse_joints(entries: object, model: RobotModel, name_key: str = "name", value_key: str = "position") -> np.ndarray:
    """A list of ``{name, position}`` to a vector in ``model.joint_names`` order.

    Names may carry a ``prefix/``; joints the robot does not have (fixed or mimic joints some
    exporters add) are ignored, but every required joint must be present.
    """
    if not isinstance(entries, list) or not entries:
        raise FrameError("no joint list")
    known = set(model.joint_names) | set(model.mimic_joint_names)
    given = {}
    for entry in entries:
        if not isinstance(entry, Mapping) or name_key not in entry or value_key not in entry:
            raise FrameError(f"joint entry without {name_key}/{value_key}: {entry!r}")
        name = str(entry[name_key]).rsplit("/", 1)[-1]
        if name in known:
            value = entry[value_key]
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise FrameError(f"joint {name} value is not a number: {value!r}")
            given[name] = float(value)
    missing = [n for n in model.required_joints if n not in given]
    if missing:
        raise FrameError(f"missing joint(s) {missing}")
    try:
        return model.joint_vector(given)
    except Monose3Error as err:
        raise FrameError(str(err)) from None


def match_keypoints(entries: object, model: RobotModel, name_key: str, location_key: str) -> tuple[np.ndarray, list]:
    """Camera-frame locations ``[K, 3]`` (file units) of the robot's keypoints, found by name,
    and the matching entries (for their projected locations)."""
    if not isinstance(entries, list):
        raise FrameError("no keypoint list")
    by_name = {}
    for entry in entries:
        if isinstance(entry, Mapping) and name_key in entry:
            by_name.setdefault(str(entry[name_key]).rsplit("/", 1)[-1], entry)
    missing = [n for n in model.keypoint_names if n not in by_name]
    if missing:
        raise FrameError(f"missing keypoint(s) {missing}")
    chosen = [by_name[n] for n in model.keypoint_names]
    locs = []
    for name, entry in zip(model.keypoint_names, chosen, strict=True):
        if location_key not in entry:
            raise FrameError(f"keypoint {name} has no {location_key}")
        locs.append(finite_array(entry[location_key], (3,), f"keypoint {name} {location_key}"))
    return np.stack(locs), chosen


def projected_keypoints(entries: list, points_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Annotated ``projected_location`` when every keypoint has one, else the pinhole projection."""
    try:
        return finite_array([e["projected_location"] for e in entries], (len(entries), 2), "projected_location")
    except (KeyError, TypeError, FrameError):
        return project(points_cam, K)


def fit_scale_ratio(model_points: np.ndarray, annotated: np.ndarray) -> float:
    """Spread of the annotated keypoints over the spread of the model's (unit check)."""
    a = annotated - annotated.mean(0)
    m = model_points - model_points.mean(0)
    return float(np.sqrt((a**2).sum() / max((m**2).sum(), 1e-12)))


def resolve_units(units: str, synthetic: bool, model_points: np.ndarray, annotated: np.ndarray) -> float:
    """Scale from file units to meters: 'm', 'cm', or 'auto' (synthetic frames are centimetres,
    real ones are checked against the robot's size, so a real set stored in cm is still read right)."""
    if units == "m":
        return 1.0
    if units == "cm":
        return 0.01
    if synthetic:
        return 0.01
    ratio = fit_scale_ratio(model_points, annotated)
    if 0.5 < ratio < 2.0:
        return 1.0
    if 50.0 < ratio < 200.0:
        return 0.01
    raise FrameError(
        f"keypoint spread is {ratio:.3g}x the robot's: neither meters nor centimetres "
        "(wrong robot, or wrong joints for these keypoints)"
    )


@dataclass
class FrameIndex:
    """Packed annotations of the readable frames (images stay on disk)."""

    names: list[str]
    image_paths: list[Path]
    K: np.ndarray
    sizes: np.ndarray
    joints: np.ndarray
    keypoints_3d: np.ndarray
    keypoints_2d: np.ndarray
    poses: np.ndarray
    residuals: np.ndarray


def check_units(units: str) -> str:
    """``units`` of a reader: 'auto' (decided per frame), 'm' or 'cm'."""
    if units not in UNITS:
        raise Monose3Error(f"units must be 'auto', 'm' or 'cm', got {units!r}")
    return units


def progress(items: Sequence, desc: str) -> Iterator:
    if len(items) < PROGRESS_MIN_FRAMES:
        return iter(items)
    from tqdm import tqdm

    return iter(tqdm(items, desc=desc, unit="frame", leave=False))


class FrameSequence(Sequence):
    """Shared Sequence behaviour of the dataset readers (built from an :class:`FrameIndex`)."""

    folder: Path
    robot: RobotModel
    skipped: list[tuple[str, str]]
    packed: FrameIndex

    def __len__(self) -> int:
        return len(self.packed.names)

    def __getitem__(self, i):  # type: ignore[override]
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"frame index {i} out of range for {n} frames")
        i %= n
        ix = self.packed
        return Frame(
            name=ix.names[i],
            K=ix.K[i].copy(),
            image_size=(int(ix.sizes[i, 0]), int(ix.sizes[i, 1])),
            joints=ix.joints[i].copy(),
            image_path=ix.image_paths[i],
            keypoint_names=list(self.robot.keypoint_names),
            keypoints_3d=ix.keypoints_3d[i].copy(),
            keypoints_2d=ix.keypoints_2d[i].copy(),
            pose=ix.poses[i].copy(),
            pose_residual=float(ix.residuals[i]),
        )

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self.folder)!r}, robot={self.robot.name!r}, frames={len(self)})"

    def report_skipped(self, total: int) -> None:
        if self.skipped:
            first_name, first_reason = self.skipped[0]
            log.warning(
                "%s: skipped %d of %d frames with missing or malformed annotations (first: %s: %s); "
                "the list is in dataset.skipped",
                self.folder,
                len(self.skipped),
                total,
                first_name,
                first_reason,
            )


@dataclass
class ParsedFrame:
    """One frame's annotation after parsing, before the batched kinematics."""

    name: str
    image_path: Path
    K: np.ndarray
    size: tuple[int, int]
    joints: np.ndarray
    locations: np.ndarray  # camera frame, file units
    projected: list  # the keypoint entries, for projected_location
    synthetic: bool
    rotation: np.ndarray | None = None
    translation: np.ndarray | None = None  # file units
    source: str = ""  # the annotation file's name, for the skipped list


def build_index(parsed: list[ParsedFrame], model: RobotModel, units: str, skipped: list) -> FrameIndex:
    """Turn parsed annotations into poses and metric keypoints (batched FK, per-frame fit)."""
    if parsed:
        fk = model.keypoints(np.stack([p.joints for p in parsed]))
    keep, K, sizes, joints, kp3, kp2, poses, resid = [], [], [], [], [], [], [], []
    for p, model_kp in zip(parsed, fk if parsed else [], strict=True):
        try:
            scale = resolve_units(units, p.synthetic, model_kp, p.locations)
            points = p.locations * scale
            if p.synthetic:
                pose = make_pose(p.rotation, p.translation * scale)
                residual = 0.0
            else:
                pose, residual = rigid_fit(model_kp, points)
            uv = projected_keypoints(p.projected, points, p.K)
        except FrameError as err:
            skipped.append((p.source or p.name, str(err)))
            continue
        keep.append(p)
        K.append(p.K)
        sizes.append(p.size)
        joints.append(p.joints)
        kp3.append(points)
        kp2.append(uv)
        poses.append(pose)
        resid.append(residual)
    nk, nj = len(model.keypoint_names), len(model.joint_names)
    return FrameIndex(
        names=[p.name for p in keep],
        image_paths=[p.image_path for p in keep],
        K=np.asarray(K, np.float64).reshape(-1, 3, 3),
        sizes=np.asarray(sizes, np.int64).reshape(-1, 2),
        joints=np.asarray(joints, np.float64).reshape(-1, nj),
        keypoints_3d=np.asarray(kp3, np.float64).reshape(-1, nk, 3),
        keypoints_2d=np.asarray(kp2, np.float64).reshape(-1, nk, 2),
        poses=np.asarray(poses, np.float64).reshape(-1, 4, 4),
        residuals=np.asarray(resid, np.float64),
    )
