"""``monose3 train``: the command around :func:`monose3.training.loop.train` (Alg. 1), on DREAM
folders, on scenes synthesised on the fly, or both; for a wall-clock budget or a step count;
multi-GPU / multi-node through ``torchrun`` (DistributedDataParallel)."""

from __future__ import annotations

import argparse
from pathlib import Path
from types import SimpleNamespace

from monose3.apps.arguments import (
    ROBOT_FILE_HELP,
    check_non_negative,
)
from monose3.data import validation as v
from monose3.data.datasets import load_datasets
from monose3.data.inputs import list_backgrounds
from monose3.data.scenes.profiles import get_profile
from monose3.errors import Monose3Error
from monose3.method.config import (
    BACKBONES,
    DESIGNS,
    FIELD_STRIDES,
    MAX_CROP_JITTER,
    PRETRAINED_TRUNK_DESIGNS,
    ROTATION_OUTPUTS,
    TRAIN_PRESET,
    Config,
    get_preset,
    with_section,
)
from monose3.robot import get_spec, robot_reference


def add_train_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", nargs="+", default=[], help="DREAM folder(s) to train on")
    p.add_argument(
        "--evidence",
        nargs="+",
        default=[],
        help="evidence cache folder(s): the robot parser's outputs on synthesised scenes (--preset evidence)",
    )
    p.add_argument(
        "--cache-samples",
        type=int,
        help="with --evidence: first make (or complete) the first folder's cache to this many samples",
    )
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
    p.add_argument(
        "--preset", default=TRAIN_PRESET, help=f"configuration preset: cpu, paper or evidence [{TRAIN_PRESET}]"
    )
    p.add_argument("--robot", default="panda", help=f"robot to train for: panda, kuka or {ROBOT_FILE_HELP} [panda]")
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
    p.add_argument(
        "--design",
        choices=list(DESIGNS),
        help="denoiser architecture (default: the preset's, concat = the paper's; see benchmarks/denoiser_designs.py)",
    )
    p.add_argument(
        "--backbone",
        choices=BACKBONES,
        help="the denoiser's trunk: a ResNet from scratch, or ImageNet-pretrained EfficientNet-Lite0 (cost-volume and "
        "flow-solve) [the preset's]",
    )
    p.add_argument(
        "--rotation-output",
        choices=list(ROTATION_OUTPUTS),
        help="how the denoiser's rotation outputs are read (default 6d, the paper's; see docs/DESIGNS.md)",
    )
    p.add_argument(
        "--field-stride",
        type=int,
        choices=list(FIELD_STRIDES),
        help="crop pixels per cell of the flow-solve design's displacement field [8]",
    )
    p.add_argument("--rot-weight", type=float, help="weight of Eq. 10's rotation part in the loss [1]")
    p.add_argument(
        "--flow-weight",
        type=float,
        help="weight of the auxiliary displacement-field loss of the designs that predict one "
        "(cost-volume, flow-solve) [0: off; see docs/DESIGNS.md]",
    )
    p.add_argument(
        "--crop-jitter",
        type=float,
        help="move each training crop off H_t by up to this fraction of its size [0: RoboPose's rule; docs/DESIGNS.md]",
    )
    p.add_argument("--t-max", type=int, help="curriculum: draw t <= T_MAX (default: T, the paper's U{1..T})")
    p.add_argument(
        "--t-curriculum-steps", type=int, help="raise --t-max linearly to T over this many steps [0: keep it]"
    )
    p.add_argument("--seed", type=int, help="seed of every random draw of the run [0]")
    p.add_argument("--resume", action="store_true", help="continue exactly from OUT/checkpoint.pt")
    p.add_argument("--compile", action="store_true", help="torch.compile the network (GPU)")
    p.add_argument("--threads", type=int, help="torch CPU threads for the network (default: all cores)")


def check_train(args: argparse.Namespace) -> SimpleNamespace:
    """Every refusal that needs no model, before anything is built or written; returns the frames."""
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
    if not args.data and not args.synthetic and not args.evidence:
        raise Monose3Error("no training data: pass --data DIR (DREAM folders) and/or --synthetic")
    design = args.design or get_preset(args.preset).network.design
    if bool(args.evidence) != design.startswith("evidence"):
        raise Monose3Error(
            "--evidence DIR trains the evidence denoiser (--preset evidence) and it trains on nothing else"
        )
    if args.evidence and (args.data or args.synthetic):
        raise Monose3Error("an evidence cache trains the evidence denoiser alone; drop --data/--synthetic")
    if args.cache_samples is not None:
        v.check_count(args.cache_samples, "--cache-samples")
        if not args.evidence:
            raise Monose3Error("--cache-samples makes an evidence cache: pass --evidence DIR")
    for folder in args.evidence[1:] if args.cache_samples else args.evidence:
        v.check_input_dir(folder, "--evidence")
    get_preset(args.preset)
    get_spec(args.robot)
    get_profile(args.profile)
    if args.t_max is not None:
        steps = get_preset(args.preset).diffusion.num_steps
        v.check_count(args.t_max, "--t-max", 1, f" (t runs from 1 to the preset's T = {steps})")
    check_non_negative(args.t_curriculum_steps, "--t-curriculum-steps")
    for name in ("steps", "batch_size", "checkpoint_every", "threads"):
        value = getattr(args, name)
        if value is not None:
            v.check_count(value, "--" + name.replace("_", "-"))
    check_non_negative(args.workers, "--workers")
    for name in ("lr", "gamma", "rot_weight"):
        value = getattr(args, name)
        if value is not None and not value > 0:
            raise Monose3Error(f"--{name.replace('_', '-')} must be positive, got {value}")
    if args.flow_weight is not None and not args.flow_weight >= 0:
        raise Monose3Error(f"--flow-weight must be 0 or more, got {args.flow_weight}")
    if args.crop_jitter is not None and not 0.0 <= args.crop_jitter <= MAX_CROP_JITTER:
        raise Monose3Error(
            f"--crop-jitter must lie in [0, {MAX_CROP_JITTER}] (a fraction of the crop; more cuts the robot off), "
            f"got {args.crop_jitter}"
        )
    if args.flow_weight:
        from monose3.method.designs import FIELD_DESIGNS  # torch: only where a field loss is asked for

        if args.design not in FIELD_DESIGNS:
            designs = " or ".join(FIELD_DESIGNS)
            raise Monose3Error(f"--flow-weight needs --design {designs}, the designs that predict a displacement field")
    if args.field_stride is not None and args.design != "flow-solve":
        raise Monose3Error("--field-stride sets the flow-solve design's field; pass --design flow-solve")
    if args.backbone == BACKBONES[2] and design not in PRETRAINED_TRUNK_DESIGNS:
        raise Monose3Error(f"--backbone {args.backbone} needs --design {' or '.join(PRETRAINED_TRUNK_DESIGNS)}")
    if args.design == "flow-solve" and args.rotation_output not in (None, "6d"):
        raise Monose3Error("--design flow-solve solves its rotation from the field; drop --rotation-output")
    for d in args.data:
        v.check_input_dir(d, "--data")
    if args.backgrounds:
        list_backgrounds(args.backgrounds)
    return SimpleNamespace(frames=load_datasets(args.data, args.robot) if args.data else [])


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
    for name in ("backbone", "rotation_output", "field_stride"):
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
    if args.cache_samples:
        from monose3.training.checkpoints import load_parser
        from monose3.training.evidence_cache import make_cache
        from monose3.training.formats import BUNDLED_PARSER

        make_cache(args.evidence[0], args.cache_samples, config.train.seed, load_parser(BUNDLED_PARSER), config.robot)
    ratio = args.synthetic_ratio if frames else 1.0
    sources = Sources(frames, args.synthetic, ratio, args.profile, args.backgrounds, args.evidence)
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
