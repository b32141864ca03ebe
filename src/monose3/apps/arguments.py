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


# ---- adapting the parser to the user's frames (adapt, calibrate --adapt, track --adapt) ----------

ADAPTED_PARSER_FILE = "adapted_parser.pt"


def add_adapt_budget(p: argparse.ArgumentParser) -> None:
    """How long the parser's adaptation trains: steps, capped by minutes (AdaptConfig's defaults)."""
    p.add_argument("--adapt-steps", type=int, help="the adaptation's fine-tuning steps (default 90: ~3 min on 2 cores)")
    p.add_argument("--adapt-minutes", type=float, help="stop the fine-tuning after this many minutes (default 4)")


def add_adapt_option(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument(
        "--adapt",
        action="store_true",
        help=f"first adapt the parser to these frames (a few minutes; kept only when it fits held-out frames better, "
        f"then saved as {ADAPTED_PARSER_FILE} in --out) and {what} with it",
    )
    add_adapt_budget(p)


def check_adapt_budget(args: argparse.Namespace) -> None:
    if args.adapt_steps is not None:
        v.check_count(args.adapt_steps, "--adapt-steps")
    if args.adapt_minutes is not None and not args.adapt_minutes > 0:
        raise Monose3Error(f"--adapt-minutes must be positive, got {args.adapt_minutes}")


def adapt_config(args: argparse.Namespace):
    """The adaptation's configuration with the command line's budget."""
    from monose3.adaptation import AdaptConfig

    budget = {k: getattr(args, f"adapt_{k}") for k in ("steps", "minutes") if getattr(args, f"adapt_{k}") is not None}
    return AdaptConfig(**budget)


def adapt_and_save(estimator, frames: list, static_camera: bool, args: argparse.Namespace, path: Path) -> list[Path]:
    """Adapt ``estimator``'s parser to ``frames`` in place (when the guard keeps it) and save it
    to ``path``, with the picture of the guard's check beside it (``.png``); the files written
    (none when the parser stayed as it was)."""
    from monose3.adaptation import adapt_parser, save_adapted_parser
    from monose3.report.overlays import save_image

    print(f"adapting the parser to {len(frames)} frames")
    result = adapt_parser(estimator, frames, adapt_config(args), static_camera, progress=True)
    print(result.verdict)
    if not result.adapted:
        return []
    written = [save_adapted_parser(result, path)]
    if result.picture is not None:
        written.append(save_image(path.with_suffix(".png"), result.picture))
    return written
