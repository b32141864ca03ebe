"""Opening a dataset folder by its layout: DREAM or RoboKeyGen."""

from __future__ import annotations

import os
from pathlib import Path

from monose3.data.annotations import FrameSequence
from monose3.data.dream import FRAME_JSON, DreamDataset
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
