"""DREAM (NDDS) datasets: reading real and synthetic frames, writing synthetic ones.

A DREAM folder holds ``NNNNNN.rgb.jpg`` + ``NNNNNN.json`` per frame and a
``_camera_settings.json``. Two flavours exist and are told apart per frame:

* real frames (no ``quaternion_xyzw``): keypoints in meters; the camera-from-base pose is not
  stored, so it is recovered by a rigid fit of the robot's forward-kinematics keypoints to the
  annotated ones (the RMS residual is kept: it says how well the annotation fits the model);
* synthetic frames (``objects[0].quaternion_xyzw``): centimetres, and a rotation in Unreal's
  axes that is converted to OpenCV axes the way RoboPose does.

Every frame is turned into a :class:`Frame` in the project's conventions (meters, OpenCV
camera axes, camera-from-base 4x4). The dataset indexes all annotations once at
construction (compact arrays, never images), so bad frames are found and reported up front
instead of stopping a long job half-way.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from monose3.errors import Monose3Error
from monose3.geometry.poses import rigid_fit
from monose3.geometry.rotations import matrix_to_quat_xyzw, quat_xyzw_to_matrix
from monose3.robot import RobotModel, RobotSpec

log = logging.getLogger("monose3")

CAMERA_SETTINGS = "_camera_settings.json"
# Synthetic DREAM rotations are in Unreal's axes; right-multiplying gives OpenCV camera axes.
UNREAL_TO_OPENCV = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
IMAGE_SUFFIXES = (".rgb.jpg", ".rgb.png", ".jpg", ".png", ".jpeg")
# Below this many frames no progress bar is shown while indexing.
_PROGRESS_MIN = 5000


@dataclass
class Frame:
    """One annotated image in the project's conventions (meters, OpenCV axes).

    ``joints`` follow ``RobotModel.joint_names``; ``keypoints_3d`` are camera-frame points of
    ``keypoint_names``; ``pose`` is camera-from-base. ``pose_residual`` is the RMS error (m)
    of the rigid fit that produced the pose for real frames, 0.0 when the pose was stored.
    """

    name: str
    image_path: Path
    K: np.ndarray
    image_size: tuple[int, int]
    joints: np.ndarray
    keypoint_names: list[str]
    keypoints_3d: np.ndarray
    keypoints_2d: np.ndarray
    pose: np.ndarray
    pose_residual: float = 0.0

    def load_image(self) -> np.ndarray:
        """The image as RGB uint8 ``[H, W, 3]`` (read on demand: datasets never hold images)."""
        if not self.image_path.is_file():
            raise Monose3Error(f"image of frame {self.name} not found: {self.image_path} (restore the file)")
        bgr = cv2.imread(str(self.image_path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise Monose3Error(f"cannot decode image {self.image_path}; the file is corrupt, re-export it")
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


class FrameError(ValueError):
    """Why one frame's annotation cannot be used (the frame is skipped, the job goes on)."""


class _NoIntrinsics(FrameError):
    """The frame has no intrinsics and the folder has no camera settings."""


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=np.float64)


def _finite(values: object, shape: tuple[int, ...], what: str) -> np.ndarray:
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise FrameError(f"{what} is not numeric: {values!r}") from None
    if arr.shape != shape:
        raise FrameError(f"{what} has shape {arr.shape}, expected {shape}")
    if not np.all(np.isfinite(arr)):
        raise FrameError(f"{what} contains NaN or infinity")
    return arr


def read_camera_settings(path: Path) -> tuple[np.ndarray, tuple[int, int]]:
    """K and (width, height) from a DREAM ``_camera_settings.json``."""
    try:
        data = json.loads(Path(path).read_text())
        cam = data["camera_settings"][0]
        intr = cam["intrinsic_settings"]
        K = intrinsics_matrix(*(float(intr[k]) for k in ("fx", "fy", "cx", "cy")))
        size = cam.get("captured_image_size") or {}
        width = int(size.get("width", intr.get("resX", 0)))
        height = int(size.get("height", intr.get("resY", 0)))
    except (OSError, ValueError, KeyError, IndexError, TypeError) as err:
        raise Monose3Error(
            f"malformed camera settings {path}: {err!r}; expected camera_settings[0].intrinsic_settings "
            "{fx, fy, cx, cy} and captured_image_size {width, height}"
        ) from None
    if width <= 0 or height <= 0 or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise Monose3Error(
            f"camera settings {path} lack a positive focal length or the image size; "
            "add captured_image_size {width, height} and fx, fy > 0"
        )
    return K, (width, height)


def _frame_intrinsics(data: Mapping) -> tuple[np.ndarray, tuple[int, int]] | None:
    """Per-frame intrinsics ``camera_data.intrinsics`` {fx, fy, cx, cy, width, height}, if any."""
    cam = data.get("camera_data")
    intr = cam.get("intrinsics") if isinstance(cam, Mapping) else None
    if intr is None:
        return None
    if not isinstance(intr, Mapping):
        raise FrameError("camera_data.intrinsics is not an object")
    try:
        vals = [float(intr[k]) for k in ("fx", "fy", "cx", "cy")]
        size = (int(intr["width"]), int(intr["height"]))
    except (KeyError, TypeError, ValueError) as err:
        raise FrameError(f"camera_data.intrinsics lacks {err}") from None
    K = _finite(intrinsics_matrix(*vals), (3, 3), "camera_data.intrinsics")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or size[0] <= 0 or size[1] <= 0:
        raise FrameError("camera_data.intrinsics has a non-positive focal length or image size")
    return K, size


def parse_joints(entries: object, model: RobotModel, name_key: str = "name", value_key: str = "position") -> np.ndarray:
    """A list of ``{name, position}`` to a vector in ``model.joint_names`` order.

    Names may carry a ``prefix/``; joints the robot does not have (fixed or mimic joints some
    exporters add) are ignored, but every required joint must be present.
    """
    if not isinstance(entries, list) or not entries:
        raise FrameError("no joint list")
    known = set(model.joint_names) | set(model._mimic)
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
        locs.append(_finite(entry[location_key], (3,), f"keypoint {name} {location_key}"))
    return np.stack(locs), chosen


def projected_keypoints(entries: list, points_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Annotated ``projected_location`` when every keypoint has one, else the pinhole projection."""
    try:
        return _finite([e["projected_location"] for e in entries], (len(entries), 2), "projected_location")
    except (KeyError, TypeError, FrameError):
        z = np.clip(points_cam[:, 2:3], 1e-9, None)
        return points_cam[:, :2] / z * K[[0, 1], [0, 1]] + K[[0, 1], [2, 2]]


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


def unreal_quat_to_rotation(q_xyzw: object) -> np.ndarray:
    q = _finite(q_xyzw, (4,), "quaternion_xyzw")
    if np.linalg.norm(q) < 1e-6:
        raise FrameError("quaternion_xyzw is zero")
    return quat_xyzw_to_matrix(q) @ UNREAL_TO_OPENCV


@dataclass
class _Index:
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


def _progress(items: Sequence, desc: str) -> Iterator:
    if len(items) < _PROGRESS_MIN:
        return iter(items)
    from tqdm import tqdm

    return iter(tqdm(items, desc=desc, unit="frame", leave=False))


class _FrameSequence(Sequence):
    """Shared Sequence behaviour of the dataset readers (built from an :class:`_Index`)."""

    folder: Path
    robot: RobotModel
    skipped: list[tuple[str, str]]
    _index: _Index

    def __len__(self) -> int:
        return len(self._index.names)

    def __getitem__(self, i):  # type: ignore[override]
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"frame index {i} out of range for {n} frames")
        i %= n
        ix = self._index
        return Frame(
            name=ix.names[i],
            image_path=ix.image_paths[i],
            K=ix.K[i].copy(),
            image_size=(int(ix.sizes[i, 0]), int(ix.sizes[i, 1])),
            joints=ix.joints[i].copy(),
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

    def _report_skipped(self, total: int) -> None:
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
class _Parsed:
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


def build_index(parsed: list[_Parsed], model: RobotModel, units: str, skipped: list) -> _Index:
    """Turn parsed annotations into poses and metric keypoints (batched FK, per-frame fit)."""
    if parsed:
        fk = model.keypoints(np.stack([p.joints for p in parsed]))
    keep, K, sizes, joints, kp3, kp2, poses, resid = [], [], [], [], [], [], [], []
    for p, model_kp in zip(parsed, fk if parsed else [], strict=True):
        try:
            scale = resolve_units(units, p.synthetic, model_kp, p.locations)
            points = p.locations * scale
            if p.synthetic:
                pose = np.eye(4)
                pose[:3, :3] = p.rotation
                pose[:3, 3] = p.translation * scale
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
    return _Index(
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


_FRAME_JSON = re.compile(r"^(?!_).+\.json$")


def _find_image(stem: str, files: set[str], folder: Path) -> Path | None:
    for suffix in IMAGE_SUFFIXES:
        if stem + suffix in files:
            return folder / (stem + suffix)
    return None


class DreamDataset(_FrameSequence):
    """A DREAM folder as a sequence of :class:`Frame` (``len``, indexing, iteration).

    ``units``: 'auto' (synthetic frames are cm; real frames are checked against the robot's
    size), 'm' or 'cm' to force. Frames whose annotation cannot be used are listed in
    ``skipped`` as ``(file name, reason)`` and one warning summarises them.
    """

    def __init__(self, folder: str | Path, robot: RobotModel | RobotSpec | str = "panda", units: str = "auto"):
        self.folder = Path(folder)
        self.robot = robot if isinstance(robot, RobotModel) else RobotModel(robot)
        if units not in ("auto", "m", "cm"):
            raise Monose3Error(f"units must be 'auto', 'm' or 'cm', got {units!r}")
        self.units = units
        if not self.folder.is_dir():
            raise Monose3Error(f"dataset folder not found: {self.folder} (check the path)")
        files = {e.name for e in os.scandir(self.folder) if e.is_file()}
        json_files = sorted(f for f in files if _FRAME_JSON.match(f))
        if not json_files:
            raise Monose3Error(
                f"no DREAM frames (NNNNNN.json + NNNNNN.rgb.jpg) in {self.folder}; "
                "point to the folder that holds the frame files"
            )
        self.default_K: np.ndarray | None = None
        self.default_size: tuple[int, int] | None = None
        if CAMERA_SETTINGS in files:
            self.default_K, self.default_size = read_camera_settings(self.folder / CAMERA_SETTINGS)
        self.skipped: list[tuple[str, str]] = []
        parsed = []
        for fname in _progress(json_files, f"indexing {self.folder.name}"):
            try:
                parsed.append(self._parse(fname, files))
            except _NoIntrinsics as err:
                if not parsed:  # the set as a whole lacks intrinsics: say so before reading on
                    raise Monose3Error(
                        f"no {CAMERA_SETTINGS} in {self.folder} and no per-frame camera_data.intrinsics "
                        f"(e.g. {fname}); add the camera settings file (fx, fy, cx, cy, width, height) "
                        "next to the frames"
                    ) from None
                self.skipped.append((fname, str(err)))
            except FrameError as err:
                self.skipped.append((fname, str(err)))
        self._index = build_index(parsed, self.robot, units, self.skipped)
        self._report_skipped(len(json_files))
        if len(self) == 0:
            first = self.skipped[0] if self.skipped else ("-", "-")
            raise Monose3Error(
                f"none of the {len(json_files)} frames in {self.folder} could be read "
                f"(e.g. {first[0]}: {first[1]}); check the robot ({self.robot.name}) and the files"
            )

    def _parse(self, fname: str, files: set[str]) -> _Parsed:
        path = self.folder / fname
        stem = fname[: -len(".json")]
        try:
            data = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, ValueError) as err:
            raise FrameError(f"unreadable JSON ({type(err).__name__}: {err})") from None
        if not isinstance(data, Mapping):
            raise FrameError("not a DREAM frame (top level is not an object)")
        image = _find_image(stem, files, self.folder)
        if image is None:
            raise FrameError(f"no image file {stem}.rgb.jpg")
        intr = _frame_intrinsics(data)
        if intr is None:
            if self.default_K is None:
                raise _NoIntrinsics(f"no intrinsics (no {CAMERA_SETTINGS}, no camera_data.intrinsics)")
            intr = (self.default_K, self.default_size)
        objects = data.get("objects")
        if not isinstance(objects, list) or not objects or not isinstance(objects[0], Mapping):
            raise FrameError("no objects[0]")
        obj = objects[0]
        sim = data.get("sim_state")
        joints = parse_joints(sim.get("joints") if isinstance(sim, Mapping) else None, self.robot)
        locs, entries = match_keypoints(obj.get("keypoints"), self.robot, "name", "location")
        synthetic = "quaternion_xyzw" in obj
        rotation = translation = None
        if synthetic:
            rotation = unreal_quat_to_rotation(obj["quaternion_xyzw"])
            if "location" not in obj:
                raise FrameError("synthetic frame without objects[0].location")
            translation = _finite(obj["location"], (3,), "objects[0].location")
        return _Parsed(stem, image, intr[0], intr[1], joints, locs, entries, synthetic, rotation, translation, fname)


# ---- writing ---------------------------------------------------------------------------------


def _json_dump(path: Path, data: object) -> None:
    """Write JSON atomically: a frame's JSON exists only once it is complete."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=1))
    os.replace(tmp, path)


def write_camera_settings(folder: str | Path, K: np.ndarray, width: int, height: int) -> Path:
    """Write a DREAM ``_camera_settings.json`` (the folder's default intrinsics)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    K = np.asarray(K, np.float64)
    hfov = math.degrees(2 * math.atan2(width / 2, K[0, 0]))
    data = {
        "camera_settings": [
            {
                "name": "Viewpoint",
                "horizontal_fov": hfov,
                "intrinsic_settings": {
                    "resX": int(width),
                    "resY": int(height),
                    "fx": float(K[0, 0]),
                    "fy": float(K[1, 1]),
                    "cx": float(K[0, 2]),
                    "cy": float(K[1, 2]),
                    "s": 0,
                },
                "captured_image_size": {"width": int(width), "height": int(height)},
            }
        ]
    }
    path = folder / CAMERA_SETTINGS
    _json_dump(path, data)
    return path


def frame_record(
    K: np.ndarray,
    size: tuple[int, int],
    joints: Mapping[str, float],
    pose: np.ndarray,
    keypoint_names: Sequence[str],
    keypoints_base: np.ndarray,
    object_class: str = "robot",
    visibility: float = 1.0,
) -> dict:
    """The synthetic-DREAM JSON of one frame (cm, Unreal-axes quaternion, per-frame intrinsics)."""
    K = np.asarray(K, np.float64)
    pose = np.asarray(pose, np.float64)
    kp_cam = np.asarray(keypoints_base, np.float64) @ pose[:3, :3].T + pose[:3, 3]
    uv = kp_cam[:, :2] / kp_cam[:, 2:3] * K[[0, 1], [0, 1]] + K[[0, 1], [2, 2]]
    quat = matrix_to_quat_xyzw(pose[:3, :3] @ UNREAL_TO_OPENCV.T)
    return {
        "camera_data": {
            "location_worldframe": [0.0, 0.0, 0.0],
            "quaternion_xyzw_worldframe": [0.0, 0.0, 0.0, 1.0],
            "intrinsics": {
                "fx": float(K[0, 0]),
                "fy": float(K[1, 1]),
                "cx": float(K[0, 2]),
                "cy": float(K[1, 2]),
                "width": int(size[0]),
                "height": int(size[1]),
            },
        },
        "objects": [
            {
                "class": object_class,
                "visibility": float(visibility),
                "location": (pose[:3, 3] * 100.0).tolist(),
                "quaternion_xyzw": quat.tolist(),
                "keypoints": [
                    {"name": n, "location": (p * 100.0).tolist(), "projected_location": q.tolist()}
                    for n, p, q in zip(keypoint_names, kp_cam, uv, strict=True)
                ],
            }
        ],
        "sim_state": {"joints": [{"name": n, "position": float(v)} for n, v in joints.items()]},
    }


def write_frame(
    folder: str | Path,
    index: int,
    rgb: np.ndarray,
    K: np.ndarray,
    joints: Mapping[str, float] | np.ndarray,
    pose: np.ndarray,
    keypoint_names: Sequence[str] | None = None,
    keypoints_base: np.ndarray | None = None,
    *,
    robot: RobotModel | RobotSpec | str = "panda",
    quality: int = 95,
    visibility: float = 1.0,
) -> Path:
    """Write ``NNNNNN.rgb.jpg`` and ``NNNNNN.json`` in synthetic-DREAM style; returns the JSON path.

    Keypoints default to the robot's forward kinematics of ``joints`` (base frame), so the
    annotation is exactly FK under ``pose``. The JSON is written last and atomically, so a
    frame whose JSON exists is complete (what resuming a generation relies on).
    ``visibility`` is NDDS's visible fraction of the robot (informational).
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise Monose3Error(f"write_frame needs an RGB uint8 [H, W, 3] image, got {rgb.dtype} {rgb.shape}")
    model = None
    if not isinstance(joints, Mapping) or keypoints_base is None:
        model = robot if isinstance(robot, RobotModel) else RobotModel(robot)
    if not isinstance(joints, Mapping):
        joints = model.joint_dict(model.joint_vector(joints))
    if keypoints_base is None:
        keypoints_base = model.keypoints(model.joint_vector(joints)[None])[0]
        keypoint_names = model.keypoint_names
    if keypoint_names is None or len(keypoint_names) != len(keypoints_base):
        raise Monose3Error("write_frame: give one keypoint name per keypoint")
    stem = f"{int(index):06d}"
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:  # pragma: no cover - OpenCV failure
        raise Monose3Error(f"could not encode frame {stem} as JPEG")
    name = model.name if model is not None else (robot.name if isinstance(robot, RobotModel | RobotSpec) else robot)
    size = (rgb.shape[1], rgb.shape[0])
    record = frame_record(K, size, joints, pose, keypoint_names, keypoints_base, name, visibility)
    path = folder / f"{stem}.json"
    try:
        (folder / f"{stem}.rgb.jpg").write_bytes(buf.tobytes())
        _json_dump(path, record)
    except OSError as err:
        raise Monose3Error(
            f"cannot write frame {stem} to {folder}: {err}; check free disk space and permissions"
        ) from None
    return path


# ---- layout detection -----------------------------------------------------------------------


def detect_layout(path: str | Path) -> str:
    """'dream' or 'robokeygen' for a dataset folder (RoboKeyGen: ``*_meta.json`` files in it or in
    its sequence sub-folders, or frame JSONs whose top level is a list)."""
    path = Path(path)
    if not path.is_dir():
        raise Monose3Error(f"dataset folder not found: {path} (check the path)")
    from monose3.data.robokeygen import find_sequences

    if find_sequences(path):
        return "robokeygen"
    names = sorted(e.name for e in os.scandir(path) if e.is_file() and _FRAME_JSON.match(e.name))
    if names:
        return "dream"
    raise Monose3Error(
        f"{path} holds neither DREAM frames (NNNNNN.json) nor RoboKeyGen sequences (NNNN_meta.json); "
        "point to the dataset folder"
    )


def open_dataset(
    path: str | Path, robot: RobotModel | RobotSpec | str = "panda", units: str = "auto"
) -> _FrameSequence:
    """Open a DREAM folder or a RoboKeyGen sequence (or folder of sequences) by its layout."""
    if detect_layout(path) == "robokeygen":
        from monose3.data.robokeygen import RoboKeyGenDataset

        return RoboKeyGenDataset(path, robot)
    return DreamDataset(path, robot, units)
