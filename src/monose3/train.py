"""``monose3 train``: the command around :func:`monose3.training.loop.train` (Alg. 1), on DREAM
folders, on scenes synthesised on the fly, or both; for a wall-clock budget or a step count;
multi-GPU / multi-node through ``torchrun`` (DistributedDataParallel)."""

from __future__ import annotations

import argparse
from pathlib import Path

from monose3.config import Config, get_preset, with_section
from monose3.errors import Monose3Error


def load_frames(data_dirs: list[str | Path], robot: str) -> list:
    from monose3.dream import open_dataset

    frames: list = []
    for d in data_dirs:
        frames.extend(open_dataset(d, robot))
    if not frames:
        raise Monose3Error(
            f"no usable frames in {', '.join(map(str, data_dirs))}; "
            "generate some with `monose3 generate` or use --synthetic"
        )
    return frames


def add_train_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", nargs="+", default=[], help="DREAM folder(s) to train on")
    p.add_argument(
        "--synthetic", action="store_true", help="synthesise training scenes on the fly on the training device"
    )
    p.add_argument("--synthetic-ratio", type=float, default=0.5, help="with --data too: share of synthetic steps [0.5]")
    p.add_argument(
        "--profile", default="train", help="scene profile of synthetic scenes: train, reallike or hard [train]"
    )
    p.add_argument(
        "--backgrounds", help="folder of photographs for synthetic backgrounds (default: scikit-image's, if installed)"
    )
    p.add_argument("--out", required=True, help="run folder: weights.json + shards, checkpoint.pt, log.csv, loss.png")
    p.add_argument("--preset", default="cpu", help="configuration preset: cpu (default) or paper")
    p.add_argument("--robot", default="panda", help="robot to train for: panda or kuka [panda]")
    p.add_argument("--steps", type=int, help="stop at this optimiser step (overrides the preset)")
    p.add_argument("--minutes", type=float, help="stop cleanly after this much wall-clock time")
    p.add_argument("--init", help="start from these weights (a shard folder / weights.json or a .pt checkpoint)")
    p.add_argument("--batch-size", type=int, help="samples per optimiser step (per process)")
    p.add_argument("--lr", type=float, help="peak learning rate [3e-4]")
    p.add_argument("--workers", type=int, help="data-loader worker processes (decode frames / draw scenes)")
    p.add_argument("--checkpoint-every", type=int, help="steps between full checkpoints (optimiser state included)")
    p.add_argument("--shard-minutes", type=float, default=1.0, help="minutes between weight-shard writes [1]")
    p.add_argument("--noise", choices=["visdiff", "fixper"], help="forward process (default visdiff)")
    p.add_argument("--gamma", type=float, help="translation noise divisor of VisDiff (default 3)")
    p.add_argument("--seed", type=int, help="seed of every random draw of the run [0]")
    p.add_argument("--resume", action="store_true", help="continue exactly from OUT/checkpoint.pt")
    p.add_argument("--compile", action="store_true", help="torch.compile the network (GPU)")
    p.add_argument("--threads", type=int, help="torch CPU threads for the network (default: all cores)")


def config_from_args(args: argparse.Namespace) -> Config:
    config = get_preset(args.preset, robot=args.robot)
    train_over = {
        "max_steps": args.steps,
        "batch_size": args.batch_size,
        "lr": args.lr,
        "num_workers": args.workers,
        "checkpoint_every": args.checkpoint_every,
        "seed": args.seed,
    }
    if args.minutes is not None and args.steps is None:
        train_over["max_steps"] = 10**12  # the clock decides
    config = with_section(config, "train", **{k: v for k, v in train_over.items() if v is not None})
    diff_over = {"noise": args.noise, "gamma": args.gamma}
    return with_section(config, "diffusion", **{k: v for k, v in diff_over.items() if v is not None})


def check_train_arguments(args: argparse.Namespace) -> None:
    """Every refusal that needs no model: before anything is built or written."""
    from monose3.generate import get_profile
    from monose3.robot import get_spec

    if args.minutes is not None and not args.minutes > 0:
        raise Monose3Error(f"--minutes must be > 0, got {args.minutes}")
    if args.shard_minutes <= 0:
        raise Monose3Error(f"--shard-minutes must be > 0, got {args.shard_minutes}")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise Monose3Error(f"--out {out} is a file; give a folder for the run")
    if (out / "checkpoint.pt").is_file() and not args.resume:
        raise Monose3Error(f"{out / 'checkpoint.pt'} exists; pass --resume to continue it or choose another --out")
    if args.init and args.resume:
        raise Monose3Error("--init starts a new run from weights, --resume continues one; pass only one")
    if not args.data and not args.synthetic:
        raise Monose3Error("no training data: pass --data DIR (DREAM folders) and/or --synthetic")
    get_spec(args.robot)
    get_profile(args.profile)
    if args.backgrounds:
        from monose3.generate import list_backgrounds

        list_backgrounds(args.backgrounds)


def run_train(args: argparse.Namespace) -> int:
    check_train_arguments(args)
    config = config_from_args(args)
    import torch

    from monose3.training.loop import Sources, train

    if args.init:
        from monose3.checkpoint import read_weights

        read_weights(args.init)  # a missing, partial or corrupt --init fails before any work
    if args.threads:
        torch.set_num_threads(args.threads)
    frames = load_frames(args.data, config.robot) if args.data else []
    sources = Sources(frames, args.synthetic, args.synthetic_ratio if frames else 1.0, args.profile, args.backgrounds)
    result = train(
        config,
        args.out,
        sources,
        resume=args.resume,
        init=args.init,
        minutes=args.minutes,
        shard_minutes=args.shard_minutes,
        compile_model=args.compile,
    )
    if result.losses:
        window = result.losses[-min(len(result.losses), config.train.log_every) :]
        print(
            f"trained to step {result.step} ({result.samples} samples seen, stopped by {result.stopped_by}); "
            f"mean loss of the last {len(window)} steps {sum(window) / len(window):.4f}; weights in {args.out}"
        )
    return 0
