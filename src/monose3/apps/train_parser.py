"""``monose3 train-parser``: the command around :func:`monose3.training.parser_loop.train_parser`."""

from __future__ import annotations

import argparse


def run_train_parser(args: argparse.Namespace) -> int:
    import torch

    from monose3.perception.config import PARSER_PRESETS
    from monose3.training.parser_loop import train_parser

    if args.threads:
        torch.set_num_threads(args.threads)
    meta = train_parser(
        PARSER_PRESETS[args.preset],
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
