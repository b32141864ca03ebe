"""What the torch-free option modules share: help texts and small argument checks."""

from __future__ import annotations

import argparse

from monose3.data import validation as v

CHECKPOINT_HELP = "model checkpoint file (.pt; default: the bundled Panda model)"
ROBOT_HELP = "robot the checkpoint must be for: panda, kuka or a robot file robot.json (checked before loading)"
ROBOT_FILE_HELP = 'a robot file: {"urdf": "arm.urdf", "keypoints": [{"name", "link", "offset"}]}'
DEVICE_HELP = "where the network runs: cpu, cuda or auto (the default: cuda when available)"
PLOT_SUFFIXES = (".png", ".jpg", ".jpeg", ".pdf", ".svg")


def robot_model(name: str | None):
    """The robot to check joints against before the model loads (None: known only after loading)."""
    if name is None:
        return None
    from monose3.robot import RobotModel

    return RobotModel(name)


def check_non_negative(value: int | None, name: str) -> None:
    if value is not None:
        v.check_count(value, name, 0)


def parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 640x480, got {text!r}") from None
    return w, h


def add_model_arguments(p: argparse.ArgumentParser, chains: int, chains_help: str) -> None:
    """``--checkpoint``, ``--robot`` and ``--chains``, as every command that estimates takes them."""
    p.add_argument("--checkpoint", help=CHECKPOINT_HELP)
    p.add_argument("--robot", help=ROBOT_HELP)
    p.add_argument("--chains", type=int, default=chains, help=f"{chains_help} (default {chains})")
