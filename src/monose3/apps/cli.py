"""The ``monose3`` command.

The options of every subcommand and the checks of its inputs live in :mod:`monose3.apps.arguments`,
which imports neither torch nor pybullet: ``--help``, ``--version`` and a bad input answer
before the implementation module (``run_<name>(args)`` in the module named in
``commands.COMMANDS``) is imported. User errors print on one line (exit code 2).
"""

from __future__ import annotations

import argparse
import importlib
import sys

from monose3 import __version__
from monose3.apps.arguments import COMMANDS
from monose3.errors import run_reporting_errors

DESCRIPTION = (
    "monose3 estimates the pose of a robot's base in the camera frame from one RGB image, the robot's "
    "joint angles and the camera intrinsics (MonoSE(3)-Diffusion), and calibrates, tracks, trains and "
    "evaluates with the same model."
)
EPILOG = "Run `monose3 COMMAND --help` for the options of a command; `monose3 demo` tries the bundled sample."


def build_parser() -> argparse.ArgumentParser:
    """The parser with every subcommand and option (cheap: nothing heavy is imported)."""
    from monose3.apps import arguments as commands

    parser = argparse.ArgumentParser(prog="monose3", description=DESCRIPTION, epilog=EPILOG)
    parser.add_argument("--version", action="version", version=f"monose3 {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (_, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text[0].upper() + help_text[1:] + ".")
        getattr(commands, f"add_{name.replace('-', '_')}_arguments")(p)
    return parser


def _run(args: argparse.Namespace) -> int:
    from monose3.apps import arguments as commands

    name = args.command.replace("-", "_")
    checked = getattr(commands, f"check_{name}")(args)  # before torch / pybullet are imported
    args.checked_inputs = checked
    module = importlib.import_module(COMMANDS[args.command][0])
    return getattr(module, f"run_{name}")(args)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser().parse_args(argv)
    return run_reporting_errors(lambda: _run(args), f"monose3 {args.command}")


if __name__ == "__main__":
    sys.exit(main())
