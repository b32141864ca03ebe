"""``monose3 train``: the command around :func:`monose3.training.loop.train` (Alg. 1), on DREAM
folders, on scenes synthesised on the fly, or both; for a wall-clock budget or a step count;
multi-GPU / multi-node through ``torchrun`` (DistributedDataParallel)."""

from __future__ import annotations

import argparse

from monose3.data.datasets import load_datasets
from monose3.method.config import Config, get_preset, with_section
from monose3.robot import robot_reference


def config_from_args(args: argparse.Namespace) -> Config:
    config = get_preset(args.preset, robot=robot_reference(args.robot))
    train_over = {
        "max_steps": args.steps,
        "batch_size": args.batch_size,
        "lr": args.lr,
        "num_workers": args.workers,
        "checkpoint_every": args.checkpoint_every,
        "seed": args.seed,
        "rot_weight": args.rot_weight,
        "t_max": args.t_max,
        "t_curriculum_steps": args.t_curriculum_steps,
        "flow_weight": args.flow_weight,
        "crop_jitter": args.crop_jitter,
    }
    if args.minutes is not None and args.steps is None:
        train_over["max_steps"] = 10**12  # the clock decides
    config = with_section(config, "train", **{k: v for k, v in train_over.items() if v is not None})
    if args.design:
        config = with_section(config, "network", design=args.design)
    for name in ("rotation_output", "field_stride"):
        if getattr(args, name, None):
            config = with_section(config, "network", **{name: getattr(args, name)})
    diff_over = {"noise": args.noise, "gamma": args.gamma}
    return with_section(config, "diffusion", **{k: v for k, v in diff_over.items() if v is not None})


def run_train(args: argparse.Namespace) -> int:
    config = config_from_args(args)
    import torch

    from monose3.training.loop import Sources, train

    if args.threads:
        torch.set_num_threads(args.threads)
    checked = getattr(args, "checked_inputs", None)
    frames = checked.frames if checked else (load_datasets(args.data, config.robot) if args.data else [])
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
