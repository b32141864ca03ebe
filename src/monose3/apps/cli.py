"""The ``monose3`` command: one module per subcommand (:data:`COMMANDS`).

A command module holds its options (``add_<name>_arguments``), its input checks
(``check_<name>``) and ``run_<name>``; its module-level imports are free of torch and pybullet,
so ``--help``, ``--version`` and a bad input answer before anything heavy is imported (the
checks run first, then ``run_<name>`` imports what it needs). User errors print on one line
(exit code 2).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from types import ModuleType

from monose3 import __version__
from monose3.errors import run_reporting_errors

COMMANDS = {
    "demo": ("monose3.apps.demo", "estimate the pose on the bundled sample scene and show the error"),
    "estimate": ("monose3.apps.estimate", "estimate camera-from-base from one image, joints and intrinsics"),
    "calibrate": ("monose3.apps.calibrate", "fuse estimates over many frames from a static camera"),
    "track": ("monose3.apps.track", "track the pose over a sequence of frames or a video"),
    "adapt": ("monose3.apps.adapt", "fine-tune the robot parser on your own frames (no labels needed)"),
    "generate": ("monose3.apps.generate", "generate domain-randomised synthetic data in DREAM format"),
    "train": ("monose3.apps.train", "train the denoising network on DREAM folders or scenes synthesised on the fly"),
    "train-parser": (
        "monose3.apps.train_parser",
        "train the robot parser (mask + keypoints) on scenes synthesised on the fly",
    ),
    "evaluate": ("monose3.apps.evaluate", "evaluate a checkpoint on DREAM / RoboKeyGen data (ADD, AUC)"),
}

DESCRIPTION = (
    "monose3 estimates the pose of a robot's base in the camera frame from one RGB image, the robot's "
    "joint angles and the camera intrinsics (MonoSE(3)-Diffusion), and calibrates, tracks, trains and "
    "evaluates with the same model."
)
EPILOG = "Run `monose3 COMMAND --help` for the options of a command; `monose3 demo` tries the bundled sample."


def build_parser() -> argparse.ArgumentParser:
    """The parser with every subcommand and option (cheap: nothing heavy is imported)."""
    parser = argparse.ArgumentParser(prog="monose3", description=DESCRIPTION, epilog=EPILOG)
    parser.add_argument("--version", action="version", version=f"monose3 {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (_, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text[0].upper() + help_text[1:] + ".")
        getattr(command_module(name), f"add_{name.replace('-', '_')}_arguments")(p)
    return parser


def command_module(command: str) -> ModuleType:
    """The module of ``command`` (cheap to import: its heavy imports are inside ``run_<name>``)."""
    return importlib.import_module(COMMANDS[command][0])


def _run(args: argparse.Namespace) -> int:
    name, module = args.command.replace("-", "_"), command_module(args.command)
    args.checked_inputs = getattr(module, f"check_{name}")(args)  # before torch / pybullet are imported
    return getattr(module, f"run_{name}")(args)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser().parse_args(argv)
    return run_reporting_errors(lambda: _run(args), f"monose3 {args.command}")


if __name__ == "__main__":
    sys.exit(main())
