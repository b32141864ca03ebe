"""Writing DREAM frames in synthetic-DREAM style (centimetres, Unreal-axes quaternion,
per-frame intrinsics) and a folder's ``_camera_settings.json``."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import cv2
import numpy as np

from monose3.atomic import write_text
from monose3.data.dream import UNREAL_TO_OPENCV
from monose3.data.inputs import CAMERA_SETTINGS
from monose3.errors import Monose3Error
from monose3.geometry.camera import project
from monose3.geometry.poses import transform_points
from monose3.geometry.rotations import matrix_to_quat_xyzw
from monose3.robot import RobotModel, RobotSpec


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
    write_text(path, json.dumps(data, indent=1))
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
    kp_cam = transform_points(pose, np.asarray(keypoints_base, np.float64))
    uv = project(kp_cam, K)
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
        write_text(path, json.dumps(record, indent=1))  # a frame's JSON exists only once complete
    except OSError as err:
        raise Monose3Error(
            f"cannot write frame {stem} to {folder}: {err}; check free disk space and permissions"
        ) from None
    return path
