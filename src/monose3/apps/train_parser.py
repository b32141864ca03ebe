"""``monose3 train-parser``: the command around :func:`monose3.training.parser_loop.train_parser`."""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from monose3.apps.arguments import (
    check_non_negative,
)
from monose3.data import validation as v
from monose3.data.inputs import list_backgrounds
from monose3.errors import Monose3Error
from monose3.perception.config import PARSER_PRESETS


def add_train_parser_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", required=True, help="run folder: weights.json + shards (written every minute), log.csv")
    p.add_argument("--preset", default="cpu", help="cpu (batch 16) or gpu (batch 96) [cpu]")
    p.add_argument("--minutes", type=float, help="stop cleanly after this much wall-clock time")
    p.add_argument("--steps", type=int, help="stop at this optimiser step")
    p.add_argument("--init", help="continue from a parser's shards or file (a fresh optimiser and warm-up)")
    p.add_argument("--anneal", action="store_true", help="cosine learning-rate decay to zero over the budget")
    p.add_argument("--lr", type=float, help="peak learning rate (default: the preset's; lower it to fine-tune)")
    p.add_argument("--workers", type=int, default=0, help="data-loader workers per scene profile (default 0)")
    p.add_argument(
        "--backgrounds", help="folder of photographs for backgrounds (default: scikit-image's, if installed)"
    )
    p.add_argument("--threads", type=int, help="torch CPU threads (default: torch's)")


def check_train_parser(args: argparse.Namespace) -> None:
    if args.preset not in PARSER_PRESETS:
        raise Monose3Error(f"unknown parser preset {args.preset!r}; choose one of {sorted(PARSER_PRESETS)}")
    if args.minutes is None and args.steps is None:
        raise Monose3Error("give the parser's training a budget: --minutes M and/or --steps N")
    if args.minutes is not None and not args.minutes > 0:
        raise Monose3Error(f"--minutes must be positive, got {args.minutes}")
    if args.steps is not None:
        v.check_count(args.steps, "--steps")
    if args.lr is not None and not args.lr > 0:
        raise Monose3Error(f"--lr must be positive, got {args.lr}")
    check_non_negative(args.workers, "--workers")
    if args.threads is not None:
        v.check_count(args.threads, "--threads")
    v.check_output_dir(args.out, "--out")
    if args.init is not None and not Path(args.init).exists():
        raise Monose3Error(f"--init {args.init} not found; pass a parser's run folder or weights file")
    if args.backgrounds:
        list_backgrounds(args.backgrounds)


def run_train_parser(args: argparse.Namespace) -> int:

    import torch

    from monose3.training.parser_loop import train_parser

    if args.threads:
        torch.set_num_threads(args.threads)
    meta = train_parser(
        replace(PARSER_PRESETS[args.preset], **({"lr": args.lr} if args.lr else {})),
        args.out,
        minutes=args.minutes,
        steps=args.steps,
        init=args.init,
        workers=args.workers,
        backgrounds=args.backgrounds,
        anneal=args.anneal,
    )
    print(f"trained the parser to step {meta.get('step', 0)} ({meta.get('samples', 0)} samples); weights in {args.out}")
    return 0
