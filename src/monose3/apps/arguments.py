"""The shell every command shares: help texts and small argument checks (torch-free).

Each command module ``apps/<command>.py`` holds ``add_<name>_arguments(parser)`` (its options),
``check_<name>(args)`` (its input checks, through :mod:`monose3.data.validation`) and
``run_<name>(args)``; its module-level imports stay free of torch and pybullet (the heavy ones
are inside ``run_<name>``), so ``--help`` and a bad input answer in well under a second."""

from __future__ import annotations

import argparse
from pathlib import Path

from monose3.data import validation as v
from monose3.errors import Monose3Error
from monose3.robot import RobotModel

CHECKPOINT_HELP = "model checkpoint file (.pt; default: the bundled Panda model)"
ROBOT_HELP = "robot the checkpoint must be for: panda, kuka or a robot file robot.json (checked before loading)"
ROBOT_FILE_HELP = 'a robot file: {"urdf": "arm.urdf", "keypoints": [{"name", "link", "offset"}]}'
PARSER_HELP = "robot parser weights (.pt; default: the bundled Panda parser for the Panda, none for other robots)"
SAMPLER_HELP = (
    "fit: the robot parser's mask and keypoints, PnP, silhouette search and refinement (the default where there is "
    "a parser); revdiff: DDIM reverse diffusion then direct steps (the paper); directreg: direct steps only"
)
CHAINS_HELP = "stochastic reverse chains whose spread is the uncertainty (1 = one chain, no confidence)"
DEVICE_HELP = "where the network runs: cpu, cuda or auto (the default: cuda when available)"
PLOT_SUFFIXES = (".png", ".jpg", ".jpeg", ".pdf", ".svg")


def robot_model(name: str | None):
    """The robot to check joints against before the model loads (None: known only after loading)."""
    if name is None:
        return None
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
    """The options every estimating command takes: checkpoint, parser, robot, sampler, chains."""
    p.add_argument("--checkpoint", help=CHECKPOINT_HELP)
    p.add_argument("--parser", help=PARSER_HELP)
    p.add_argument("--robot", help=ROBOT_HELP)
    p.add_argument("--sampler", choices=list(v.SAMPLERS), help=SAMPLER_HELP)
    p.add_argument(
        "--chains", type=int, default=chains, help=f"{chains_help}; revdiff/directreg only (default {chains})"
    )


def check_parser_file(path: str | None) -> None:
    """A ``--parser`` that does not exist is refused before any model loads."""
    if path is not None and not Path(path).exists():
        raise Monose3Error(f"robot parser weights not found: {path}; pass an existing file or omit --parser")
