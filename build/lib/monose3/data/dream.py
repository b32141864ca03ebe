"""DREAM (NDDS) datasets: reading real and synthetic frames (the writer is
:mod:`monose3.data.dream_writer`).

A DREAM folder holds ``NNNNNN.rgb.jpg`` + ``NNNNNN.json`` per frame and a
``_camera_settings.json``. Two flavours exist and are told apart per frame:

* real frames (no ``quaternion_xyzw``): keypoints in meters; the camera-from-base pose is not
  stored, so it is recovered by a rigid fit of the robot's forward-kinematics keypoints to the
  annotated ones (the RMS residual is kept: it says how well the annotation fits the model);
* synthetic frames (``objects[0].quaternion_xyzw``): centimetres, and a rotation in Unreal's
  axes that is converted to OpenCV axes the way RoboPose does.

Every frame is turned into a :class:`~monose3.data.frame.Frame` in the project's conventions
(meters, OpenCV camera axes, camera-from-base 4x4). The dataset indexes all annotations once at
construction (compact arrays, never images), so bad frames are found and reported up front
instead of stopping a long job half-way.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from monose3.data.annotations import (
    FrameError,
    FrameSequence,
    ParsedFrame,
    build_index,
    check_units,
    finite_array,
    match_keypoints,
    parse_joints,
    progress,
)
from monose3.data.inputs import CAMERA_SETTINGS, camera_from_obj, read_camera_settings
from monose3.errors import Monose3Error
from monose3.geometry.rotations import quat_xyzw_to_matrix
from monose3.robot import RobotModel, RobotSpec

# Synthetic DREAM rotations are in Unreal's axes; right-multiplying gives OpenCV camera axes.
UNREAL_TO_OPENCV = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
IMAGE_SUFFIXES = (".rgb.jpg", ".rgb.png", ".jpg", ".png", ".jpeg")
FRAME_JSON = re.compile(r"^(?!_).+\.json$")


class _NoIntrinsics(FrameError):
    """The frame has no intrinsics and the folder has no camera settings."""


def frame_intrinsics(data: Mapping) -> tuple[np.ndarray, tuple[int, int]] | None:
    """Per-frame intrinsics ``camera_data.intrinsics`` {fx, fy, cx, cy, width, height}, if any."""
    cam = data.get("camera_data")
    intr = cam.get("intrinsics") if isinstance(cam, Mapping) else None
    if intr is None:
        return None
    if not isinstance(intr, Mapping):
        raise FrameError("camera_data.intrinsics is not an object")
    try:
        camera = camera_from_obj(data, "camera_data.intrinsics")
    except Monose3Error as err:
        raise FrameError(str(err)) from None
    return camera.K, camera.size


def unreal_quat_to_rotation(q_xyzw: object) -> np.ndarray:
    q = finite_array(q_xyzw, (4,), "quaternion_xyzw")
    if np.linalg.norm(q) < 1e-6:
        raise FrameError("quaternion_xyzw is zero")
    return quat_xyzw_to_matrix(q) @ UNREAL_TO_OPENCV


def find_image(stem: str, files: set[str], folder: Path) -> Path | None:
    for suffix in IMAGE_SUFFIXES:
        if stem + suffix in files:
            return folder / (stem + suffix)
    return None


class DreamDataset(FrameSequence):
    """A DREAM folder as a sequence of :class:`~monose3.data.frame.Frame` (``len``, indexing, iteration).

    ``units``: 'auto' (synthetic frames are cm; real frames are checked against the robot's
    size), 'm' or 'cm' to force. Frames whose annotation cannot be used are listed in
    ``skipped`` as ``(file name, reason)`` and one warning summarises them.
    """

    def __init__(self, folder: str | Path, robot: RobotModel | RobotSpec | str = "panda", units: str = "auto"):
        self.folder = Path(folder)
        self.robot = robot if isinstance(robot, RobotModel) else RobotModel(robot)
        self.units = check_units(units)
        if not self.folder.is_dir():
            raise Monose3Error(f"dataset folder not found: {self.folder} (check the path)")
        files = {e.name for e in os.scandir(self.folder) if e.is_file()}
        json_files = sorted(f for f in files if FRAME_JSON.match(f))
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
        for fname in progress(json_files, f"indexing {self.folder.name}"):
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
        self.packed = build_index(parsed, self.robot, units, self.skipped)
        self.report_skipped(len(json_files))
        if len(self) == 0:
            first = self.skipped[0] if self.skipped else ("-", "-")
            raise Monose3Error(
                f"none of the {len(json_files)} frames in {self.folder} could be read "
                f"(e.g. {first[0]}: {first[1]}); check the robot ({self.robot.name}) and the files"
            )

    def _parse(self, fname: str, files: set[str]) -> ParsedFrame:
        path = self.folder / fname
        stem = fname[: -len(".json")]
        try:
            data = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, ValueError) as err:
            raise FrameError(f"unreadable JSON ({type(err).__name__}: {err})") from None
        if not isinstance(data, Mapping):
            raise FrameError("not a DREAM frame (top level is not an object)")
        image = find_image(stem, files, self.folder)
        if image is None:
            raise FrameError(f"no image file {stem}.rgb.jpg")
        intr = frame_intrinsics(data)
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
            translation = finite_array(obj["location"], (3,), "objects[0].location")
        K, size = intr
        return ParsedFrame(stem, image, K, size, joints, locs, entries, synthetic, rotation, translation, fname)
