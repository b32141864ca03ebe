"""The ``monose3`` command. Each subcommand lives in its own module, which provides
``add_arguments(parser)`` and ``run(args) -> int``; user errors print on one line."""

from __future__ import annotations

import argparse
import importlib
import sys

from monose3.errors import run_reporting_errors

COMMANDS = {
    "demo": ("monose3.demo", "estimate the pose on the bundled sample scene and show the error"),
    "estimate": ("monose3.api", "estimate camera-from-base from one image, joints and intrinsics"),
    "calibrate": ("monose3.calibrate", "fuse estimates over many frames from a static camera"),
    "track": ("monose3.track", "track the pose over a sequence of frames or a video"),
    "generate": ("monose3.generate", "generate domain-randomised synthetic data in DREAM format"),
    "train": ("monose3.train", "train the denoising network on DREAM folders"),
    "evaluate": ("monose3.evaluate", "evaluate a checkpoint on DREAM / RoboKeyGen data (ADD, AUC)"),
}


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser; only ``command``'s module is imported (torch makes imports slow)."""
    parser = argparse.ArgumentParser(prog="monose3", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name == command:
            mod = importlib.import_module(module)
            getattr(mod, f"add_{name}_arguments")(p)
            p.set_defaults(_run=getattr(mod, f"run_{name}"))
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    command = next((a for a in argv if not a.startswith("-")), None)
    args = build_parser(command).parse_args(argv)
    return run_reporting_errors(lambda: args._run(args), f"monose3 {args.command}")


if __name__ == "__main__":
    sys.exit(main())
