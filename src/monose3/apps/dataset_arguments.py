"""Options and input checks of the commands that make and use datasets: generate, train, evaluate
(torch-free, like :mod:`monose3.apps.arguments`)."""

from __future__ import annotations

import argparse
from pathlib import Path
from types import SimpleNamespace

from monose3.apps.options import (
    CHECKPOINT_HELP,
    PARSER_HELP,
    PLOT_SUFFIXES,
    ROBOT_FILE_HELP,
    SAMPLER_HELP,
    check_non_negative,
    check_parser_file,
    parse_size,
)
from monose3.data import validation as v
from monose3.data.scenes.profiles import PROFILES
from monose3.errors import Monose3Error
from monose3.method.config import DESIGNS, FIELD_STRIDES, MAX_CROP_JITTER, ROTATION_OUTPUTS, TRAIN_PRESET
from monose3.robot.jobs import RENDERERS
from monose3.training.formats import check_checkpoint

# ---- generate -----------------------------------------------------------------------------------


def add_generate_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, type=Path, help="output folder (DREAM layout)")
    parser.add_argument("--num", required=True, type=int, help="number of frames")
    parser.add_argument("--seed", type=int, default=0, help="random seed (same seed = same data) [0]")
    parser.add_argument("--robot", default="panda", help=f"panda, kuka or {ROBOT_FILE_HELP} [panda]")
    parser.add_argument("--urdf", type=Path, help="custom robot: URDF file (with --keypoints)")
    parser.add_argument("--keypoints", type=Path, help='custom robot: {"keypoints": [{"name", "link", "offset"}]}')
    parser.add_argument("--workers", type=int, default=None, help="processes [one per CPU core]; 0 = no subprocess")
    parser.add_argument("--profile", choices=sorted(PROFILES), default="train", help="scene randomisation [train]")
    parser.add_argument("--backgrounds", type=Path, help="folder of images to use as some of the backgrounds")
    parser.add_argument("--size", type=parse_size, default=(640, 480), help="image size WxH [640x480]")
    parser.add_argument("--resume", action="store_true", help="keep the frames already in --out, make the rest")
    parser.add_argument("--preview", type=Path, help="also save a grid of the first 12 frames with keypoints here")
    parser.add_argument(
        "--renderer",
        choices=RENDERERS,
        default="torch",
        help="torch: monose3's renderer [default]; tiny/egl: pybullet's (needs pybullet), for cross-renderer test sets",
    )


def check_generate(args: argparse.Namespace) -> None:
    v.check_count(args.num, "--num")
    check_non_negative(args.workers, "--workers")
    v.check_output_dir(args.out, "--out")
    if bool(args.urdf) != bool(args.keypoints):
        raise Monose3Error("a custom robot needs both --urdf and --keypoints")
    if not args.urdf:
        from monose3.robot import get_spec

        get_spec(args.robot)
    if args.backgrounds is not None:
        v.check_input_dir(args.backgrounds, "--backgrounds")
    if args.preview is not None:
        v.check_output_file(args.preview, "--preview", (".png", ".jpg", ".jpeg"))


# ---- train --------------------------------------------------------------------------------------


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
    p.add_argument("--preset", default=TRAIN_PRESET, help=f"configuration preset: cpu or paper [{TRAIN_PRESET}]")
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
    from monose3.data.scenes.profiles import get_profile
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
    from monose3.method.config import get_preset

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
    if args.design == "flow-solve" and args.rotation_output not in (None, "6d"):
        raise Monose3Error("--design flow-solve solves its rotation from the field; drop --rotation-output")
    for d in args.data:
        v.check_input_dir(d, "--data")
    if args.backgrounds:
        from monose3.data.scenes.appearance import list_backgrounds

        list_backgrounds(args.backgrounds)
    from monose3.data.datasets import load_datasets

    return SimpleNamespace(frames=load_datasets(args.data, args.robot) if args.data else [])


# ---- train-parser -------------------------------------------------------------------------------


def add_train_parser_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", required=True, help="run folder: weights.json + shards (written every minute), log.csv")
    p.add_argument("--preset", default="cpu", help="cpu (batch 16) or gpu (batch 96) [cpu]")
    p.add_argument("--minutes", type=float, help="stop cleanly after this much wall-clock time")
    p.add_argument("--steps", type=int, help="stop at this optimiser step")
    p.add_argument("--init", help="continue from a parser's shards or file (a fresh optimiser and warm-up)")
    p.add_argument("--anneal", action="store_true", help="cosine learning-rate decay to zero over the budget")
    p.add_argument("--workers", type=int, default=0, help="data-loader workers per scene profile (default 0)")
    p.add_argument(
        "--backgrounds", help="folder of photographs for backgrounds (default: scikit-image's, if installed)"
    )
    p.add_argument("--threads", type=int, help="torch CPU threads (default: torch's)")


def check_train_parser(args: argparse.Namespace) -> None:
    from monose3.data.scenes.appearance import list_backgrounds
    from monose3.perception.config import PARSER_PRESETS

    if args.preset not in PARSER_PRESETS:
        raise Monose3Error(f"unknown parser preset {args.preset!r}; choose one of {sorted(PARSER_PRESETS)}")
    if args.minutes is None and args.steps is None:
        raise Monose3Error("give the parser's training a budget: --minutes M and/or --steps N")
    if args.minutes is not None and not args.minutes > 0:
        raise Monose3Error(f"--minutes must be positive, got {args.minutes}")
    if args.steps is not None:
        v.check_count(args.steps, "--steps")
    check_non_negative(args.workers, "--workers")
    if args.threads is not None:
        v.check_count(args.threads, "--threads")
    v.check_output_dir(args.out, "--out")
    if args.init is not None and not Path(args.init).exists():
        raise Monose3Error(f"--init {args.init} not found; pass a parser's run folder or weights file")
    if args.backgrounds:
        list_backgrounds(args.backgrounds)


# ---- evaluate -----------------------------------------------------------------------------------


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
        from monose3.data.datasets import open_dataset

        datasets = [open_dataset(d, robot) for d in args.data]
    return SimpleNamespace(datasets=datasets)
