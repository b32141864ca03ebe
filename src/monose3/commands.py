"""The ``monose3`` commands' options and their input checks, kept free of torch and pybullet.

Each command has ``add_<name>_arguments(parser)`` (every option with its help text) and
``check_<name>(args)``, which checks and loads the inputs through :mod:`monose3.validation`
before the implementation module (and with it torch and pybullet) is imported, so ``--help``
and a bad input answer in well under a second. ``check_<name>`` returns what it loaded (an
image, frames, ...), which the implementation reuses instead of reading the files again.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from types import SimpleNamespace

from monose3 import validation as v
from monose3.errors import Monose3Error
from monose3.robot.jobs import RENDERERS

CHECKPOINT_HELP = "model checkpoint file (.pt; default: the bundled Panda model)"
ROBOT_HELP = "robot the checkpoint must be for: panda or kuka (checked before loading)"
DEVICE_HELP = "where the network runs: cpu, cuda or auto (the default: cuda when available)"
PLOT_SUFFIXES = (".png", ".jpg", ".jpeg", ".pdf", ".svg")


def _robot_model(name: str | None):
    """The robot to check joints against before the model loads (None: known only after loading)."""
    if name is None:
        return None
    from monose3.robot import RobotModel

    return RobotModel(name)


def _non_negative(value: int | None, name: str) -> None:
    if value is not None:
        v.check_count(value, name, 0)


# ---- estimate -----------------------------------------------------------------------------------


def add_estimate_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--image", required=True, help="RGB image (PNG/JPEG) of the robot")
    p.add_argument(
        "--joints",
        required=True,
        help="JSON/YAML: {name: radians}, a list in URDF order (7 for the Panda) or a DREAM frame JSON",
    )
    p.add_argument(
        "--camera",
        required=True,
        help="intrinsics of this image: JSON {fx, fy, cx, cy, width, height}, DREAM camera settings or ROS "
        "CameraInfo YAML",
    )
    p.add_argument("--checkpoint", help=CHECKPOINT_HELP)
    p.add_argument("--robot", help=ROBOT_HELP)
    p.add_argument(
        "--out",
        default="monose3_out",
        help="folder for pose.json, pose.yaml and overlay.png (default: monose3_out; created if missing)",
    )
    p.add_argument(
        "--chains",
        type=int,
        default=4,
        help="stochastic reverse chains whose spread is the uncertainty (default 4; 1 = one chain, no confidence)",
    )
    p.add_argument(
        "--sampler",
        choices=["revdiff", "directreg"],
        default="revdiff",
        help="revdiff: DDIM reverse diffusion then direct steps (the paper, default); directreg: direct "
        "regression steps only (the baseline)",
    )
    p.add_argument(
        "--prior",
        help="approximate camera-from-base to refine, in metres (pose.json/calibration.json written by monose3, "
        "or a 4x4 list)",
    )


def check_estimate(args: argparse.Namespace) -> SimpleNamespace:
    from monose3.inputs import load_camera, load_image, load_pose

    chains = v.check_chains(args.chains, "--chains")
    v.check_sampler(args.sampler)
    out = v.check_output_dir(args.out, "--out")
    robot = _robot_model(v.check_checkpoint(args.checkpoint, args.robot))
    image = v.check_image(load_image(args.image), args.image)
    camera = load_camera(args.camera)
    K = v.check_camera(camera, image, args.camera)
    joints = prior = None
    if robot is not None:
        joints = v.check_joints(args.joints, robot)
    if args.prior:
        prior = load_pose(args.prior)
        if robot is not None:
            prior = v.check_prior(prior, robot, joints, K, camera.size, f"prior {args.prior}")
    return SimpleNamespace(image=image, camera=camera, K=K, joints=joints, prior=prior, chains=chains, out=out)


# ---- demo ---------------------------------------------------------------------------------------


def add_demo_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--out",
        default="monose3_demo",
        help="folder for pose.json, pose.yaml and overlay.png (default: monose3_demo; created if missing)",
    )
    p.add_argument("--checkpoint", help=CHECKPOINT_HELP + "; it must be a Panda model")
    p.add_argument(
        "--chains",
        type=int,
        default=4,
        help="stochastic reverse chains whose spread is the uncertainty (default 4; 1 = one chain, no confidence)",
    )


def check_demo(args: argparse.Namespace) -> SimpleNamespace:
    chains = v.check_chains(args.chains, "--chains")
    out = v.check_output_dir(args.out, "--out")
    v.check_checkpoint(args.checkpoint, "panda")
    return SimpleNamespace(chains=chains, out=out)


# ---- calibrate ----------------------------------------------------------------------------------


def add_calibrate_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--frames",
        required=True,
        help="folder of NNNN.png|jpg + NNNN.joints.json + camera.json, or a DREAM folder (then the error vs ground "
        "truth is reported)",
    )
    p.add_argument("--checkpoint", help=CHECKPOINT_HELP)
    p.add_argument("--robot", help=ROBOT_HELP)
    p.add_argument(
        "--out",
        default="monose3_calibration",
        help="folder for calibration.json/.yaml and the overlay (default: monose3_calibration)",
    )
    p.add_argument(
        "--chains",
        type=int,
        default=1,
        help="stochastic chains per frame (default 1); >1 also rejects frames whose chains disagree",
    )
    p.add_argument("--batch-size", type=int, default=4, help="frames estimated together (default 4)")
    p.add_argument("--limit", type=int, help="use only the first N frames")
    p.add_argument("--device", default="auto", help=DEVICE_HELP)
    p.add_argument(
        "--consensus-k",
        type=float,
        default=3.0,
        help="reject frames beyond median + k * sigma_MAD of the residuals to the first robust fusion (default 3)",
    )
    p.add_argument("--overlay-frames", type=int, default=6, help="frames in the overlay grid (default 6; 0: none)")


def check_calibrate(args: argparse.Namespace) -> SimpleNamespace:
    from monose3.frames import load_frames

    chains = v.check_chains(args.chains, "--chains")
    v.check_count(args.batch_size, "--batch-size")
    if args.limit is not None:
        v.check_count(args.limit, "--limit")
    _non_negative(args.overlay_frames, "--overlay-frames")
    if not args.consensus_k > 0:
        raise Monose3Error(f"--consensus-k must be positive, got {args.consensus_k}")
    v.check_input_dir(args.frames, "--frames")
    out = v.check_output_dir(args.out, "--out")
    robot = _robot_model(v.check_checkpoint(args.checkpoint, args.robot))
    frames = None
    if robot is not None:
        frames = load_frames(args.frames, robot)
        if args.limit is not None:
            frames = frames[: args.limit]
    return SimpleNamespace(chains=chains, out=out, frames=frames)


# ---- track --------------------------------------------------------------------------------------


def add_track_arguments(p: argparse.ArgumentParser) -> None:
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--frames", help="DREAM folder or folder of NNNN.png + NNNN.joints.json + camera.json")
    src.add_argument("--video", help="video file (MP4, AVI, GIF...); needs --camera and --joints-csv or --joints")
    jsrc = p.add_mutually_exclusive_group()
    jsrc.add_argument("--joints-csv", help="with --video: CSV, header = joint names, one row per frame (radians)")
    jsrc.add_argument("--joints", help="with --video: folder with one joints JSON per frame (name order)")
    p.add_argument("--camera", help="with --video: intrinsics file (JSON {fx, fy, cx, cy, width, height}, ...)")
    p.add_argument("--checkpoint", help=CHECKPOINT_HELP)
    p.add_argument("--robot", help=ROBOT_HELP)
    p.add_argument(
        "--out",
        default="monose3_track",
        help="folder for poses.jsonl, poses.csv and track.gif (default: monose3_track)",
    )
    p.add_argument("--limit", type=int, help="track only the first N frames of --frames")
    p.add_argument("--reinit-every", type=int, help="run the full process every N frames as well")
    p.add_argument(
        "--max-step-mm", type=float, default=50.0, help="re-initialise when one step moves more (default 50)"
    )
    p.add_argument(
        "--max-step-deg", type=float, default=10.0, help="re-initialise when one step rotates more (default 10)"
    )
    p.add_argument("--gif-every", type=int, default=1, help="put every N-th frame in track.gif (default 1; 0: no GIF)")
    p.add_argument("--fps", type=float, default=10.0, help="frame rate of track.gif (default 10)")
    p.add_argument("--device", default="auto", help=DEVICE_HELP)


def check_track_args(args: argparse.Namespace) -> None:
    """Argument combinations, checked before the model is loaded."""
    if args.limit is not None and args.limit < 1:
        raise Monose3Error(f"--limit must be at least 1, got {args.limit}")
    if args.gif_every < 0:
        raise Monose3Error(f"--gif-every must be >= 0, got {args.gif_every}")
    if args.reinit_every is not None:
        v.check_count(args.reinit_every, "--reinit-every")
    if not args.fps > 0:
        raise Monose3Error(f"--fps must be positive, got {args.fps}")
    if args.frames is not None:
        if args.joints_csv or args.joints or args.camera:
            raise Monose3Error(
                "--joints-csv/--joints/--camera go with --video; a --frames folder holds its own joints and camera"
            )
        return
    if not Path(args.video).is_file():
        raise Monose3Error(f"video not found: {args.video}; check the path")
    if not args.camera:
        raise Monose3Error("--video needs --camera FILE with the intrinsics {fx, fy, cx, cy, width, height}")
    if not (args.joints_csv or args.joints):
        raise Monose3Error("--video needs the joints of every frame: --joints-csv FILE or --joints DIR")


def check_track(args: argparse.Namespace) -> SimpleNamespace:
    check_track_args(args)
    out = v.check_output_dir(args.out, "--out")
    robot = v.check_checkpoint(args.checkpoint, args.robot)
    frames = video_joints = None
    if args.frames is not None:
        v.check_input_dir(args.frames, "--frames")
        if robot is not None:
            from monose3.frames import load_frames

            frames = load_frames(args.frames, _robot_model(robot))
            frames = frames[: args.limit] if args.limit is not None else frames
    else:
        from monose3.frames import load_joints_csv, load_joints_dir
        from monose3.inputs import load_camera

        camera = load_camera(args.camera)
        v.check_K(camera.K, camera.size, args.camera)
        if robot is not None:
            model = _robot_model(robot)
            if args.joints_csv:
                video_joints = load_joints_csv(args.joints_csv, model)
            else:
                video_joints = load_joints_dir(args.joints, model)
    return SimpleNamespace(out=out, frames=frames, video_joints=video_joints)


# ---- generate -----------------------------------------------------------------------------------


def _parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 640x480, got {text!r}") from None
    return w, h


GENERATE_PROFILES = ("hard", "reallike", "train")


def add_generate_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, type=Path, help="output folder (DREAM layout)")
    parser.add_argument("--num", required=True, type=int, help="number of frames")
    parser.add_argument("--seed", type=int, default=0, help="random seed (same seed = same data) [0]")
    parser.add_argument("--robot", default="panda", help="robot name: panda or kuka [panda]")
    parser.add_argument("--urdf", type=Path, help="custom robot: URDF file (with --keypoints)")
    parser.add_argument("--keypoints", type=Path, help='custom robot: {"keypoints": [{"name", "link", "offset"}]}')
    parser.add_argument("--workers", type=int, default=None, help="processes [one per CPU core]; 0 = no subprocess")
    parser.add_argument("--profile", choices=GENERATE_PROFILES, default="train", help="scene randomisation [train]")
    parser.add_argument("--backgrounds", type=Path, help="folder of images to use as some of the backgrounds")
    parser.add_argument("--size", type=_parse_size, default=(640, 480), help="image size WxH [640x480]")
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
    _non_negative(args.workers, "--workers")
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
    p.add_argument(
        "--design",
        choices=["concat", "siamese", "siamese-corr", "siamese-pose", "concat-grid", "siamese-grid"],
        help="denoiser architecture (default: the preset's, concat = the paper's; see benchmarks/denoiser_designs.py)",
    )
    p.add_argument(
        "--rotation-output",
        choices=["6d", "so3", "abs6d"],
        help="how the denoiser's rotation outputs are read (default 6d, the paper's; see docs/DESIGNS.md)",
    )
    p.add_argument("--rot-weight", type=float, help="weight of Eq. 10's rotation part in the loss [1]")
    p.add_argument("--seed", type=int, help="seed of every random draw of the run [0]")
    p.add_argument("--resume", action="store_true", help="continue exactly from OUT/checkpoint.pt")
    p.add_argument("--compile", action="store_true", help="torch.compile the network (GPU)")
    p.add_argument("--threads", type=int, help="torch CPU threads for the network (default: all cores)")


def check_train(args: argparse.Namespace) -> SimpleNamespace:
    """Every refusal that needs no model, before anything is built or written; returns the frames."""
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
    from monose3.config import get_preset

    get_preset(args.preset)
    get_spec(args.robot)
    get_profile(args.profile)
    for name in ("steps", "batch_size", "checkpoint_every", "threads"):
        value = getattr(args, name)
        if value is not None:
            v.check_count(value, "--" + name.replace("_", "-"))
    _non_negative(args.workers, "--workers")
    for name in ("lr", "gamma", "rot_weight"):
        value = getattr(args, name)
        if value is not None and not value > 0:
            raise Monose3Error(f"--{name.replace('_', '-')} must be positive, got {value}")
    for d in args.data:
        v.check_input_dir(d, "--data")
    if args.backgrounds:
        from monose3.generate import list_backgrounds

        list_backgrounds(args.backgrounds)
    from monose3.train import load_frames

    return SimpleNamespace(frames=load_frames(args.data, args.robot) if args.data else [])


# ---- evaluate -----------------------------------------------------------------------------------


def add_evaluate_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", nargs="+", required=True, help="DREAM folders or RoboKeyGen sequences")
    p.add_argument("--checkpoint", help=CHECKPOINT_HELP)
    p.add_argument(
        "--sampler",
        choices=["revdiff", "directreg", "tracking"],
        default="revdiff",
        help="revdiff: DDIM reverse diffusion then direct steps (default); directreg: direct steps only; tracking: "
        "the full process on the first frame, then one step per frame from the previous estimate",
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
    robot = v.check_checkpoint(args.checkpoint)
    datasets = None
    for d in args.data:
        v.check_input_dir(d, "--data")
    if robot is not None:
        from monose3.dream import open_dataset

        datasets = [open_dataset(d, robot) for d in args.data]
    return SimpleNamespace(datasets=datasets)


COMMANDS = {
    "demo": ("monose3.demo", "estimate the pose on the bundled sample scene and show the error"),
    "estimate": ("monose3.api", "estimate camera-from-base from one image, joints and intrinsics"),
    "calibrate": ("monose3.calibrate", "fuse estimates over many frames from a static camera"),
    "track": ("monose3.track", "track the pose over a sequence of frames or a video"),
    "generate": ("monose3.generate", "generate domain-randomised synthetic data in DREAM format"),
    "train": ("monose3.train", "train the denoising network on DREAM folders or scenes synthesised on the fly"),
    "evaluate": ("monose3.evaluate", "evaluate a checkpoint on DREAM / RoboKeyGen data (ADD, AUC)"),
}
