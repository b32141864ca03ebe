"""Opening a dataset folder by its layout: DREAM or RoboKeyGen."""

from __future__ import annotations

import hashlib
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from monose3.data.annotations import FrameSequence
from monose3.data.dream import FRAME_JSON, DreamDataset
from monose3.data.frame import Frame
from monose3.data.robokeygen import RoboKeyGenDataset, find_sequences
from monose3.errors import Monose3Error
from monose3.robot import RobotModel, RobotSpec


def detect_layout(path: str | Path) -> str:
    """'dream' or 'robokeygen' for a dataset folder (RoboKeyGen: ``*_meta.json`` files in it or in
    its sequence sub-folders, or frame JSONs whose top level is a list)."""
    path = Path(path)
    if not path.is_dir():
        raise Monose3Error(f"dataset folder not found: {path} (check the path)")
    if find_sequences(path):
        return "robokeygen"
    names = sorted(e.name for e in os.scandir(path) if e.is_file() and FRAME_JSON.match(e.name))
    if names:
        return "dream"
    raise Monose3Error(
        f"{path} holds neither DREAM frames (NNNNNN.json) nor RoboKeyGen sequences (NNNN_meta.json); "
        "point to the dataset folder"
    )


def open_dataset(path: str | Path, robot: RobotModel | RobotSpec | str = "panda", units: str = "auto") -> FrameSequence:
    """Open a DREAM folder or a RoboKeyGen sequence (or folder of sequences) by its layout."""
    if detect_layout(path) == "robokeygen":
        return RoboKeyGenDataset(path, robot)
    return DreamDataset(path, robot, units)


def load_datasets(data_dirs: list[str | Path], robot: RobotModel | RobotSpec | str) -> list:
    """Every frame of the given dataset folders, in order; refuses when there is none."""
    frames: list = []
    for d in data_dirs:
        frames.extend(open_dataset(d, robot))
    if not frames:
        raise Monose3Error(
            f"no usable frames in {', '.join(map(str, data_dirs))}; "
            "generate some with `monose3 generate` or use --synthetic"
        )
    return frames


def frames_digest(frames: Sequence[Frame]) -> str:
    """A fingerprint (16 hex digits of SHA-256) of ``frames``: each one's image (its file's bytes,
    or its pixels), intrinsics, joints and true pose. Copies of a held-out set with the same
    digest hold the same frames, so their figures compare; a set generated again by another
    version of the generator can differ in a frame, and then the digest differs."""
    sha = hashlib.sha256()
    for frame in frames:
        sha.update(frame.image_path.read_bytes() if frame.image_path is not None else frame.load_image().tobytes())
        for values in (frame.K, frame.joints, frame.pose):
            if values is not None:
                sha.update(np.ascontiguousarray(values, np.float64).tobytes())
    return sha.hexdigest()[:16]
