"""``monose3 evaluate``: ADD / AUC on DREAM and RoboKeyGen data (Table I style), per-frame
JSON, the ADD distribution plot (Fig. 4) and denoising-step overlays (Fig. 3b).

Frames stream through in small batches, so memory stays flat however many frames there are.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from monose3.apps.arguments import (
    CHECKPOINT_HELP,
    PARSER_HELP,
    PLOT_SUFFIXES,
    SAMPLER_HELP,
    check_parser_file,
)
from monose3.data import validation as v
from monose3.data.datasets import open_dataset
from monose3.data.frames import format_skipped
from monose3.errors import Monose3Error
from monose3.report.metrics import format_table
from monose3.report.plots import plot_add_distribution
from monose3.training.formats import check_checkpoint


def add_evaluate_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", nargs="+", required=True, help="DREAM folders or RoboKeyGen sequences")
    p.add_argument("--checkpoint", help=CHECKPOINT_HELP)
    p.add_argument("--parser", help=PARSER_HELP)
    p.add_argument(
        "--sampler",
        choices=[*v.SAMPLERS, "tracking", "fit-tracking"],
        help=SAMPLER_HELP + "; tracking: revdiff on the first frame, then the paper's one step per frame from the "
        "previous estimate; fit-tracking: the same with fit and its refinement",
    )
    p.add_argument("--steps", type=int, nargs=2, metavar=("K", "M"), help="DDIM steps and direct steps (default 5 5)")
    p.add_argument("--batch-size", type=int, default=4, help="frames estimated together (default 4)")
    p.add_argument("--limit", type=int, help="evaluate only the first N frames of each dataset")
    p.add_argument("--json", help="write the summary, per-frame ADD and poses and the skipped frames here (JSON)")
    p.add_argument("--plot", help="write the ADD distribution plot here (PNG, PDF or SVG)")
    p.add_argument("--overlays", help="folder for denoising-step overlays of --overlay-frames")
    p.add_argument("--overlay-frames", type=int, nargs="*", default=[0], help="frame indices to draw (default 0)")


def check_evaluate(args: argparse.Namespace) -> SimpleNamespace:
    v.check_count(args.batch_size, "--batch-size")
    check_parser_file(args.parser)
    if args.limit is not None:
        v.check_count(args.limit, "--limit")
    if args.steps is not None:
        v.check_count(args.steps[0], "--steps K", 0)
        v.check_count(args.steps[1], "--steps M", 0)
        if sum(args.steps) == 0:
            raise Monose3Error("--steps K M must take at least one step (K + M >= 1)")
    if args.json:
        v.check_output_file(args.json, "--json")
    if args.plot:
        v.check_output_file(args.plot, "--plot", PLOT_SUFFIXES)
    if args.overlays:
        v.check_output_dir(args.overlays, "--overlays")
    robot = check_checkpoint(args.checkpoint)
    datasets = None
    for d in args.data:
        v.check_input_dir(d, "--data")
    if robot is not None:
        datasets = [open_dataset(d, robot) for d in args.data]
    return SimpleNamespace(datasets=datasets)


# evaluate --sampler tracking / fit-tracking: the sampler of their full estimates.
TRACKING_SAMPLERS = {"tracking": "revdiff", "fit-tracking": "fit"}


def run_evaluate(args: argparse.Namespace) -> int:
    from monose3.api import load_estimator
    from monose3.report.evaluation import evaluate_dataset, write_json

    checked = getattr(args, "checked_inputs", None) or check_evaluate(args)
    estimator = load_estimator(args.checkpoint, parser=args.parser)
    k, m = args.steps if args.steps else (None, None)
    results = []
    try:
        for n, d in enumerate(args.data):
            frames = checked.datasets[n] if checked.datasets is not None else open_dataset(d, estimator.robot)
            results.append(
                evaluate_dataset(
                    estimator,
                    frames,
                    Path(d).name,
                    sampler=TRACKING_SAMPLERS.get(args.sampler, args.sampler),
                    ddim_steps=k,
                    direct_steps=m,
                    batch_size=args.batch_size,
                    limit=args.limit,
                    overlay_frames=args.overlay_frames if args.overlays else (),
                    overlay_dir=Path(args.overlays) if args.overlays else None,
                    tracking=args.sampler in TRACKING_SAMPLERS,
                )
            )
    finally:
        estimator.close()
    print(format_table({r.name: r.summary() for r in results}))
    for r in results:
        line = format_skipped(r.name, r.skipped)
        if line:
            print(line)
    if args.json:
        write_json(
            results,
            Path(args.json),
            {"sampler": args.sampler, "steps": args.steps, "checkpoint": str(args.checkpoint or "bundled")},
        )
        print(f"wrote {args.json}")
    if args.plot:
        plot_add_distribution({r.name: np.asarray(r.adds) for r in results}, args.plot)
        print(f"wrote {args.plot}")
    return 0
