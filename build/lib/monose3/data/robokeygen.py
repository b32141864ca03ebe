"""RoboKeyGen real sequences (RealSense-Franka, AzureKinect-Franka) as :class:`~monose3.data.frame.Frame`.

Layout, as RoboKeyGen's own loaders read it: one folder per sequence with ``NNNN_color.png``
and ``NNNN_meta.json`` per frame. The meta file is a JSON list whose element 0 holds

* ``keypoints``: ``[{"Name", "location_wrt_cam" (meters, OpenCV camera frame),
  "projected_location", ...}]`` (also ``R2C_mat`` per link, unused here);
* ``joints``: ``[{"Name", "position" (radians), ...}]``.

The intrinsics live in a DREAM-style ``_camera_settings.json``, which RoboKeyGen's loaders
read from the dataset folder; we look in the sequence folder, then its parent, and also
accept per-frame intrinsics (``camera_K`` / ``K`` as a 3x3 matrix, or ``intrinsics`` /
``camera_intrinsics`` as ``{fx, fy, cx, cy[, width, height]}``) in case an export stores
them there. Some of RoboKeyGen's scripts use ``NNNNNN.png`` + ``NNNNNN.json`` (same list
content) instead; that variant is read too. Key-name variants (``name``, ``location``,
``Angle``) are accepted.

The pose is not stored as camera-from-base; like real DREAM frames it is recovered by a rigid
fit of forward-kinematics keypoints to the annotated ones, and the residual is kept.
"""

from __future__ import annotations

import json
import os
import struct
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from monose3.data.annotations import (
    FrameError,
    FrameSequence,
    ParsedFrame,
    build_index,
    check_units,
    match_keypoints,
    parse_joints,
    progress,
)
from monose3.data.inputs import CAMERA_SETTINGS, read_camera_settings
from monose3.errors import Monose3Error
from monose3.geometry.camera import intrinsics_matrix
from monose3.robot import RobotModel, RobotSpec

META_SUFFIX = "_meta.json"
COLOR_SUFFIX = "_color.png"


def _frame_files(folder: Path) -> list[tuple[str, Path, Path]]:
    """(stem, meta path, image path) of a sequence folder, in either layout, sorted by stem."""
    try:
        names = {e.name for e in os.scandir(folder) if e.is_file()}
    except OSError:
        return []
    metas = sorted(n for n in names if n.endswith(META_SUFFIX))
    if metas:
        return [(m[: -len(META_SUFFIX)], folder / m, folder / (m[: -len(META_SUFFIX)] + COLOR_SUFFIX)) for m in metas]
    jsons = sorted(n for n in names if n.endswith(".json") and not n.startswith("_"))
    if not jsons or not _is_list_json(folder / jsons[0]):
        return []
    return [(j[:-5], folder / j, folder / (j[:-5] + ".png")) for j in jsons]


def _is_list_json(path: Path) -> bool:
    try:
        with open(path, "rb") as fh:
            head = fh.read(64).lstrip()
    except OSError:
        return False
    return head.startswith(b"[")


def find_sequences(path: str | Path) -> list[Path]:
    """Sequence folders under ``path``: ``path`` itself if it holds frames, else its sub-folders that do."""
    path = Path(path)
    if _frame_files(path):
        return [path]
    try:
        subdirs = sorted(e.path for e in os.scandir(path) if e.is_dir())
    except OSError:
        return []
    return [Path(d) for d in subdirs if _frame_files(Path(d))]


def _png_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from a PNG header, without decoding the image."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(24)
    except OSError:
        return None
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n":
        return None
    width, height = struct.unpack(">II", head[16:24])
    return int(width), int(height)


def _meta_intrinsics(entry: Mapping) -> tuple[np.ndarray, tuple[int, int] | None] | None:
    for key in ("camera_K", "K"):
        if key in entry:
            try:
                K = np.asarray(entry[key], np.float64).reshape(3, 3)
            except (TypeError, ValueError):
                raise FrameError(f"{key} is not a 3x3 matrix") from None
            return K, None
    for key in ("intrinsics", "camera_intrinsics"):
        if isinstance(entry.get(key), Mapping):
            d = entry[key]
            try:
                K = intrinsics_matrix(*(float(d[k]) for k in ("fx", "fy", "cx", "cy")))
            except (KeyError, TypeError, ValueError) as err:
                raise FrameError(f"{key} lacks {err}") from None
            size = (int(d["width"]), int(d["height"])) if "width" in d and "height" in d else None
            return K, size
    return None


def _pick_key(entries: list, candidates: tuple[str, ...]) -> str:
    first = entries[0] if entries and isinstance(entries[0], Mapping) else {}
    for key in candidates:
        if key in first:
            return key
    return candidates[0]


class RoboKeyGenDataset(FrameSequence):
    """RoboKeyGen sequence folder(s) as a sequence of :class:`~monose3.data.frame.Frame`.

    ``folder`` is one sequence (``NNNN_color.png`` + ``NNNN_meta.json``) or a folder of
    sequences; with several sequences frame names are ``sequence/NNNN``. Unusable frames are
    listed in ``skipped`` as (file name, reason).
    """

    def __init__(self, folder: str | Path, robot: RobotModel | RobotSpec | str = "panda", units: str = "auto"):
        self.folder = Path(folder)
        self.robot = robot if isinstance(robot, RobotModel) else RobotModel(robot)
        check_units(units)
        if not self.folder.is_dir():
            raise Monose3Error(f"dataset folder not found: {self.folder} (check the path)")
        self.sequences = find_sequences(self.folder)
        if not self.sequences:
            raise Monose3Error(
                f"no RoboKeyGen frames (NNNN_color.png + NNNN_meta.json) in {self.folder} or its sub-folders; "
                "point to a sequence folder or the folder that holds the sequences"
            )
        multi = len(self.sequences) > 1
        self.skipped: list[tuple[str, str]] = []
        parsed, total = [], 0
        for seq in self.sequences:
            camera = self._sequence_camera(seq)
            files = _frame_files(seq)
            total += len(files)
            for stem, meta, image in progress(files, f"indexing {seq.name}"):
                name = f"{seq.name}/{stem}" if multi else stem
                source = f"{seq.name}/{meta.name}" if multi else meta.name
                try:
                    parsed.append(self._parse(name, meta, image, camera, source))
                except FrameError as err:
                    self.skipped.append((source, str(err)))
        self.packed = build_index(parsed, self.robot, units, self.skipped)
        self.report_skipped(total)
        if len(self) == 0:
            first = self.skipped[0] if self.skipped else ("-", "-")
            raise Monose3Error(
                f"none of the {total} frames in {self.folder} could be read (e.g. {first[0]}: {first[1]}); "
                f"check the robot ({self.robot.name}), the intrinsics ({CAMERA_SETTINGS}) and the files"
            )

    @staticmethod
    def _sequence_camera(seq: Path) -> tuple[np.ndarray, tuple[int, int]] | None:
        for cand in (seq / CAMERA_SETTINGS, seq.parent / CAMERA_SETTINGS):
            if cand.is_file():
                return read_camera_settings(cand)
        return None

    def _parse(self, name: str, meta: Path, image: Path, camera, source: str) -> ParsedFrame:
        try:
            data = json.loads(meta.read_text())
        except (OSError, UnicodeDecodeError, ValueError) as err:
            raise FrameError(f"unreadable JSON ({type(err).__name__}: {err})") from None
        entry = data[0] if isinstance(data, list) and data else data
        if not isinstance(entry, Mapping):
            raise FrameError("meta is not a list whose first element is an object")
        if not image.is_file():
            raise FrameError(f"no image file {image.name}")
        intr = _meta_intrinsics(entry)
        if intr is None and camera is None:
            raise FrameError(f"no intrinsics (no {CAMERA_SETTINGS} in the sequence or its parent, none in the meta)")
        K, size = intr if intr is not None else camera
        if size is None:
            size = camera[1] if camera is not None else _png_size(image)
        if size is None:
            raise FrameError("image size unknown (add captured_image_size to the camera settings)")
        if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise FrameError("intrinsics are not finite positive focal lengths")
        kp_entries = entry.get("keypoints")
        kp_name = _pick_key(kp_entries if isinstance(kp_entries, list) else [], ("Name", "name"))
        kp_loc = _pick_key(kp_entries if isinstance(kp_entries, list) else [], ("location_wrt_cam", "location"))
        locs, chosen = match_keypoints(kp_entries, self.robot, kp_name, kp_loc)
        joint_entries = entry.get("joints")
        jl = joint_entries if isinstance(joint_entries, list) else []
        joints = parse_joints(
            joint_entries, self.robot, _pick_key(jl, ("Name", "name")), _pick_key(jl, ("position", "Angle", "angle"))
        )
        return ParsedFrame(name, image, K, size, joints, locs, chosen, synthetic=False, source=source)
