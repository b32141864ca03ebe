"""Loading what a user brings: an image, joint angles and camera intrinsics.

Running without ROS means these come from files in whatever format the user already has,
so each loader accepts the common ones (our plain JSON, DREAM's NDDS files, ROS
CameraInfo YAML) and rejects anything doubtful with a one-line ``Monose3Error`` that names
the problem and the fix, instead of producing a silently wrong calibration.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from monose3.errors import Monose3Error
from monose3.geometry.camera import Intrinsics, is_number
from monose3.robot import RobotModel

# A DREAM folder's default camera (NDDS layout; per-frame intrinsics override it).
CAMERA_SETTINGS = "_camera_settings.json"
# A joint value further than this outside its URDF limits is taken as a unit mistake (degrees).
JOINT_LIMIT_SLACK_RAD = 0.5


# ---- images ---------------------------------------------------------------------------------


def load_image(path: str | Path) -> np.ndarray:
    """Read an image file as an ``H x W x 3`` RGB uint8 array (grey and RGBA are converted)."""
    p = Path(path)
    if not p.exists():
        raise Monose3Error(f"image not found: {p}; check the path")
    if not p.is_file():
        raise Monose3Error(f"{p} is not a file; give the path of an image file (PNG or JPEG)")
    data = np.fromfile(p, dtype=np.uint8)
    bgr = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
    if bgr is None:
        raise Monose3Error(f"could not read {p} as an image (empty, corrupt or not an image); give a PNG or JPEG file")
    return np.ascontiguousarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))


# ---- structured files -----------------------------------------------------------------------


def _read_structured(path: Path, what: str) -> Any:
    """Parse a JSON or YAML file, with errors that say which file and what to give instead."""
    if not path.exists():
        raise Monose3Error(f"{what} file not found: {path}; check the path")
    if not path.is_file():
        raise Monose3Error(f"{what} path {path} is not a file; give a JSON or YAML file")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise Monose3Error(f"could not read {what} file {path} ({err}); give a UTF-8 JSON or YAML file") from None
    try:
        if path.suffix.lower() == ".json":
            return json.loads(text)
        # YAML 1.1 is (nearly) a superset of JSON, so it reads both.
        return yaml.safe_load(text)
    except (json.JSONDecodeError, yaml.YAMLError) as err:
        msg = " ".join(str(err).split())
        raise Monose3Error(f"{what} file {path} is not valid JSON/YAML ({msg}); fix its syntax") from None


# ---- joints ---------------------------------------------------------------------------------


def _joints_from_obj(obj: Any, source: str) -> dict[str, Any] | list[Any]:
    """Normalise the accepted joint layouts to a ``{name: value}`` dict or a list of values."""
    if isinstance(obj, Mapping):
        # A whole DREAM frame file, or a wrapper like {"joints": ...}.
        if isinstance(obj.get("sim_state"), Mapping) and "joints" in obj["sim_state"]:
            return _joints_from_obj(obj["sim_state"]["joints"], source)
        if "joints" in obj and not is_number(obj["joints"]):
            return _joints_from_obj(obj["joints"], source)
        return dict(obj)
    if isinstance(obj, (list, tuple, np.ndarray)):
        items = list(obj)
        if len(items) == 1 and isinstance(items[0], (list, tuple, np.ndarray)):
            items = list(items[0])  # the one row of a [1, n] array
        if items and all(isinstance(it, Mapping) for it in items):
            # DREAM sim_state style: [{"name": ..., "position": ...}, ...]
            out: dict[str, Any] = {}
            for it in items:
                if "name" not in it or "position" not in it:
                    raise Monose3Error(
                        f"{source}: joint entries must each have 'name' and 'position' (radians); got keys {sorted(it)}"
                    )
                name = str(it["name"]).rsplit("/", 1)[-1]
                if name in out:
                    raise Monose3Error(f"{source}: joint {name!r} is given twice; give each joint once")
                out[name] = it["position"]
            return out
        return items
    raise Monose3Error(
        f"{source}: joints must be a mapping {{name: radians}} or a list of radians in URDF order, "
        f"got {type(obj).__name__}"
    )


def load_joints(path_or_obj: str | Path | Mapping[str, Any] | list[Any], robot: RobotModel) -> np.ndarray:
    """Joint angles in radians as a vector in ``robot.joint_names`` order.

    Accepts a JSON/YAML file or an already-loaded object holding ``{name: radians}``, a list
    of radians in URDF order, DREAM's ``sim_state.joints`` list of ``{name, position}``, or a
    whole DREAM frame JSON. Values far outside the URDF limits are rejected because they
    almost always mean degrees were given.
    """
    if isinstance(path_or_obj, (str, Path)):
        path = Path(path_or_obj)
        source = str(path)
        obj = _read_structured(path, "joints")
    else:
        source, obj = "joints", path_or_obj
    if obj is None:
        raise Monose3Error(f"{source}: no joint values found (empty file); give {{name: radians}} for {robot.name}")
    joints = _joints_from_obj(obj, source)
    named = joints.items() if isinstance(joints, dict) else ((f"#{i}", v) for i, v in enumerate(joints))
    for name, v in named:
        if not is_number(v):
            raise Monose3Error(f"{source}: joint {name} must be a number in radians, got {v!r}")
    vec = robot.joint_vector(joints)  # checks names, count and NaN with its own one-line errors
    limits = robot.joint_limits()
    for name, value, (lo, hi) in zip(robot.joint_names, vec, limits, strict=True):
        if (math.isfinite(lo) and value < lo - JOINT_LIMIT_SLACK_RAD) or (
            math.isfinite(hi) and value > hi + JOINT_LIMIT_SLACK_RAD
        ):
            raise Monose3Error(
                f"{source}: joint {name} = {value:g} is far outside its limits [{lo:g}, {hi:g}] rad; "
                "joint angles must be radians (convert degrees with math.radians)"
            )
    return vec


# ---- cameras --------------------------------------------------------------------------------


def _require(mapping: Mapping[str, Any], keys: tuple[str, ...], source: str, layout: str) -> None:
    missing = [k for k in keys if k not in mapping]
    if missing:
        raise Monose3Error(f"{source}: missing key(s) {missing} for {layout}; add them")


def _matrix9(value: Any, key: str, source: str) -> np.ndarray:
    if isinstance(value, Mapping):  # camera_calibration: {rows: 3, cols: 3, data: [...]}
        if "data" not in value:
            raise Monose3Error(f"{source}: '{key}' has no 'data' list; give its 9 numbers as data: [...]")
        value = value["data"]
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise Monose3Error(f"{source}: '{key}' must be 9 numbers (row-major 3x3), got {value!r}") from None
    if arr.size != 9:
        raise Monose3Error(f"{source}: '{key}' must hold 9 numbers (row-major 3x3), got {arr.size}")
    return arr.reshape(3, 3)


def camera_from_obj(obj: Any, source: str = "camera") -> Intrinsics:
    """Intrinsics from an already-parsed file of any supported layout (see ``load_camera``)."""
    if not isinstance(obj, Mapping):
        raise Monose3Error(
            f"{source}: expected a mapping with fx, fy, cx, cy, width, height (or DREAM / ROS CameraInfo layout), "
            f"got {type(obj).__name__}"
        )
    cam_data = obj.get("camera_data")
    if isinstance(cam_data, Mapping) and isinstance(cam_data.get("intrinsics"), Mapping):  # a DREAM frame JSON
        intr = cam_data["intrinsics"]
        _require(intr, ("fx", "fy", "cx", "cy", "width", "height"), source, "a DREAM frame's camera_data.intrinsics")
        return Intrinsics.checked(intr["fx"], intr["fy"], intr["cx"], intr["cy"], intr["width"], intr["height"], source)
    if "camera_settings" in obj:  # DREAM / NDDS _camera_settings.json
        settings = obj["camera_settings"]
        if not isinstance(settings, list) or not settings or not isinstance(settings[0], Mapping):
            raise Monose3Error(f"{source}: 'camera_settings' must be a non-empty list of cameras as NDDS writes it")
        cam = settings[0]
        _require(cam, ("intrinsic_settings",), source, "a DREAM camera_settings entry")
        intr = cam["intrinsic_settings"]
        _require(intr, ("fx", "fy", "cx", "cy"), source, "DREAM intrinsic_settings")
        size = cam.get("captured_image_size")
        if isinstance(size, Mapping) and "width" in size and "height" in size:
            w, h = size["width"], size["height"]
        elif "resX" in intr and "resY" in intr:
            w, h = intr["resX"], intr["resY"]
        else:
            raise Monose3Error(
                f"{source}: missing captured_image_size (width, height) in camera_settings[0]; add the image size"
            )
        if is_number(intr.get("s")) and abs(intr["s"]) > 1e-6:
            raise Monose3Error(f"{source}: camera has non-zero skew s={intr['s']}; give a zero-skew calibration")
        return Intrinsics.checked(intr["fx"], intr["fy"], intr["cx"], intr["cy"], w, h, source)
    matrix_key = next((k for k in ("K", "k", "camera_matrix") if k in obj), None)
    if matrix_key is not None and not any(k in obj for k in ("fx", "fy")):  # ROS CameraInfo style
        w = obj.get("width", obj.get("image_width"))
        h = obj.get("height", obj.get("image_height"))
        if w is None or h is None:
            raise Monose3Error(
                f"{source}: missing 'width'/'height' (or image_width/image_height) next to '{matrix_key}'; "
                "add the image size the camera was calibrated at"
            )
        return Intrinsics.from_K(_matrix9(obj[matrix_key], matrix_key, source), w, h, source)
    _require(
        obj,
        ("fx", "fy", "cx", "cy", "width", "height"),
        source,
        "camera intrinsics {fx, fy, cx, cy, width, height} (or a DREAM _camera_settings.json / ROS CameraInfo YAML)",
    )
    return Intrinsics.checked(obj["fx"], obj["fy"], obj["cx"], obj["cy"], obj["width"], obj["height"], source)


def load_camera(path: str | Path) -> Intrinsics:
    """Camera intrinsics from a JSON or YAML file.

    Accepted layouts: ours ``{fx, fy, cx, cy, width, height}``; DREAM's
    ``_camera_settings.json`` (``camera_settings[0].intrinsic_settings`` and
    ``captured_image_size``); ROS CameraInfo YAML (``width``/``height`` or
    ``image_width``/``image_height`` with ``K``, ``k`` or ``camera_matrix.data``).
    """
    p = Path(path)
    obj = _read_structured(p, "camera")
    camera = camera_from_obj(obj, str(p))
    if isinstance(obj, Mapping) and "camera_settings" in obj:
        _refuse_nominal_settings(p, camera)
    return camera


def read_camera_settings(path: str | Path) -> tuple[np.ndarray, tuple[int, int]]:
    """K and (width, height) from a DREAM ``_camera_settings.json``, by the same parser as
    :func:`load_camera` (without its refusal of a nominal camera: dataset readers take the
    frames' own intrinsics first)."""
    p = Path(path)
    try:
        camera = camera_from_obj(_read_structured(p, "camera settings"), str(p))
    except Monose3Error as err:
        raise Monose3Error(
            f"malformed camera settings {err}; expected camera_settings[0].intrinsic_settings "
            "{fx, fy, cx, cy} and captured_image_size {width, height}"
        ) from None
    return camera.K, camera.size


def _refuse_nominal_settings(path: Path, camera: Intrinsics) -> None:
    """A DREAM folder whose frames carry their own intrinsics (``camera_data.intrinsics``, as
    ``monose3 generate`` writes them) has only a nominal camera in ``_camera_settings.json``:
    refuse it when the first frame's own intrinsics differ."""
    frame = next((f for f in sorted(path.parent.glob("*.json")) if not f.name.startswith("_")), None)
    if frame is None:
        return
    try:
        own = json.loads(frame.read_text(encoding="utf-8")).get("camera_data", {}).get("intrinsics")
    except (OSError, ValueError, AttributeError):
        return
    if not isinstance(own, Mapping):
        return
    given = (camera.fx, camera.fy, camera.cx, camera.cy)
    try:
        theirs = tuple(float(own[k]) for k in ("fx", "fy", "cx", "cy"))
    except (KeyError, TypeError, ValueError):
        return
    if not np.allclose(given, theirs, rtol=1e-6, atol=1e-6):
        raise Monose3Error(
            f"{path} holds a nominal camera, but the frames of {path.parent} carry their own intrinsics "
            f"(e.g. {frame.name}: fx={theirs[0]:g}); pass the frame's JSON as the camera instead"
        )


def check_image_camera(image: np.ndarray, camera: Intrinsics) -> None:
    """Refuse an image whose size differs from the one the intrinsics were calibrated at.

    Mismatched intrinsics give a plausible-looking but wrong pose, so nothing is rescaled
    silently; ``scale_camera`` exists for users who know their image was only resized.
    """
    h, w = np.asarray(image).shape[:2]
    if (w, h) == (camera.width, camera.height):
        return
    hint = ""
    if abs(w / h - camera.width / camera.height) < 1e-3:
        hint = f" (if the image was only resized, use monose3.geometry.camera.scale_camera(camera, {w}, {h}))"
    raise Monose3Error(
        f"image is {w}x{h} but the camera intrinsics are for {camera.width}x{camera.height}; "
        f"give intrinsics calibrated at {w}x{h}{hint}"
    )


# ---- poses ----------------------------------------------------------------------------------


def pose_from_obj(obj: Any, source: str = "pose") -> np.ndarray:
    """A camera-from-base 4x4 (metres) from ``{camera_from_base: 4x4}`` (the ``pose.json`` /
    ``calibration.json`` that monose3 writes), ``{base_from_camera: 4x4}`` or a bare 4x4 list."""
    value, inverse = obj, False
    if isinstance(obj, Mapping):
        if "camera_from_base" in obj:
            value = obj["camera_from_base"]
        elif "base_from_camera" in obj:
            value, inverse = obj["base_from_camera"], True
        else:
            raise Monose3Error(
                f"{source} has no camera_from_base or base_from_camera key; give the pose.json written by "
                "monose3 estimate or calibrate, or a 4x4 list"
            )
    try:
        pose = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        pose = np.empty(0)
    if pose.shape != (4, 4):
        raise Monose3Error(f"{source}: the pose must be a 4x4 matrix (4 rows of 4 numbers, metres)")
    if not np.isfinite(pose).all():
        raise Monose3Error(f"{source}: the pose contains NaN or infinity; give finite numbers")
    rot = pose[:3, :3]
    rigid = np.allclose(pose[3], [0, 0, 0, 1], atol=1e-6) and np.allclose(rot @ rot.T, np.eye(3), atol=1e-3)
    if not rigid or np.linalg.det(rot) < 0:
        raise Monose3Error(
            f"{source}: the pose is not a rigid transform (orthonormal rotation with det +1, last row 0 0 0 1)"
        )
    return np.linalg.inv(pose) if inverse else pose


def load_pose(path: str | Path) -> np.ndarray:
    """An approximate camera-from-base from a JSON or YAML file (see :func:`pose_from_obj`)."""
    p = Path(path)
    return pose_from_obj(_read_structured(p, "pose"), str(p))


IMAGE_EXTS = (".jpg", ".jpeg", ".png", ".bmp", ".webp")


def list_backgrounds(folder: str | Path | None) -> list[Path]:
    """The images of a backgrounds folder (searched recursively); none without a folder."""
    if folder is None:
        return []
    folder = Path(folder)
    if not folder.is_dir():
        raise Monose3Error(f"backgrounds folder not found: {folder} (pass a folder of .jpg/.png images)")
    files = sorted(p for p in folder.rglob("*") if p.suffix.lower() in IMAGE_EXTS and p.is_file())
    if not files:
        raise Monose3Error(f"no images ({', '.join(IMAGE_EXTS)}) in backgrounds folder {folder}")
    return files
