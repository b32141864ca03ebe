"""The ``monose3`` commands' options and their input checks, kept free of torch and pybullet.

Each command has ``add_<name>_arguments(parser)`` (every option with its help text) and
``check_<name>(args)``, which checks and loads the inputs through :mod:`monose3.data.validation`
before the implementation module (and with it torch and pybullet) is imported, so ``--help``
and a bad input answer in well under a second. ``check_<name>`` returns what it loaded (an
image, frames, ...), which the implementation reuses instead of reading the files again.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from types import SimpleNamespace

from monose3.apps.dataset_arguments import (  # noqa: F401 - every command's options are found here
    add_evaluate_arguments,
    add_generate_arguments,
    add_train_arguments,
    add_train_parser_arguments,
    check_evaluate,
    check_generate,
    check_train,
    check_train_parser,
)
from monose3.apps.options import (
    CHECKPOINT_HELP,
    DEVICE_HELP,
    PARSER_HELP,
    ROBOT_HELP,
    add_model_arguments,
    check_non_negative,
    check_parser_file,
    robot_model,
)
from monose3.data import validation as v
from monose3.errors import Monose3Error
from monose3.method.tracking import MAX_STEP_DEG, MAX_STEP_MM
from monose3.training.formats import check_checkpoint

# ---- estimate -----------------------------------------------------------------------------------

CHAINS_HELP = "stochastic reverse chains whose spread is the uncertainty (1 = one chain, no confidence)"


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
    add_model_arguments(p, 4, CHAINS_HELP)
    p.add_argument(
        "--out",
        default="monose3_out",
        help="folder for pose.json, pose.yaml and overlay.png (default: monose3_out; created if missing)",
    )
    p.add_argument(
        "--prior",
        help="approximate camera-from-base to refine, in metres (pose.json/calibration.json written by monose3, "
        "or a 4x4 list)",
    )


def check_estimate(args: argparse.Namespace) -> SimpleNamespace:
    from monose3.data.inputs import load_camera, load_image, load_pose

    chains = v.check_chains(args.chains, "--chains")
    check_parser_file(args.parser)
    out = v.check_output_dir(args.out, "--out")
    robot = robot_model(check_checkpoint(args.checkpoint, args.robot))
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
    p.add_argument("--chains", type=int, default=4, help=f"{CHAINS_HELP} (default 4)")


def check_demo(args: argparse.Namespace) -> SimpleNamespace:
    chains = v.check_chains(args.chains, "--chains")
    out = v.check_output_dir(args.out, "--out")
    check_checkpoint(args.checkpoint, "panda")
    return SimpleNamespace(chains=chains, out=out)


# ---- calibrate ----------------------------------------------------------------------------------


def add_calibrate_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--frames",
        required=True,
        help="folder of NNNN.png|jpg + NNNN.joints.json + camera.json, or a DREAM folder (then the error vs ground "
        "truth is reported)",
    )
    add_model_arguments(p, 1, "stochastic chains per frame; >1 also rejects frames whose chains disagree")
    p.add_argument(
        "--out",
        default="monose3_calibration",
        help="folder for calibration.json/.yaml and the overlay (default: monose3_calibration)",
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
    from monose3.data.frames import load_frames

    chains = v.check_chains(args.chains, "--chains")
    check_parser_file(args.parser)
    v.check_count(args.batch_size, "--batch-size")
    if args.limit is not None:
        v.check_count(args.limit, "--limit")
    check_non_negative(args.overlay_frames, "--overlay-frames")
    if not args.consensus_k > 0:
        raise Monose3Error(f"--consensus-k must be positive, got {args.consensus_k}")
    v.check_input_dir(args.frames, "--frames")
    out = v.check_output_dir(args.out, "--out")
    robot = robot_model(check_checkpoint(args.checkpoint, args.robot))
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
    p.add_argument("--parser", help=PARSER_HELP)
    p.add_argument("--robot", help=ROBOT_HELP)
    p.add_argument(
        "--sampler",
        choices=["fit", "revdiff"],
        help="fit: refinement on the robot parser's mask and keypoints each frame (default where there is a parser); "
        "revdiff: the paper's one step at a small t",
    )
    p.add_argument(
        "--out",
        default="monose3_track",
        help="folder for poses.jsonl, poses.csv and track.gif (default: monose3_track)",
    )
    p.add_argument("--limit", type=int, help="track only the first N frames of --frames")
    p.add_argument("--reinit-every", type=int, help="run the full process every N frames as well")
    more = "re-initialise when one step"
    p.add_argument("--max-step-mm", type=float, default=MAX_STEP_MM, help=f"{more} moves more [{MAX_STEP_MM:g}]")
    p.add_argument("--max-step-deg", type=float, default=MAX_STEP_DEG, help=f"{more} rotates more [{MAX_STEP_DEG:g}]")
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
    check_parser_file(args.parser)
    out = v.check_output_dir(args.out, "--out")
    robot = check_checkpoint(args.checkpoint, args.robot)
    frames = video_joints = None
    if args.frames is not None:
        v.check_input_dir(args.frames, "--frames")
        if robot is not None:
            from monose3.data.frames import load_frames

            frames = load_frames(args.frames, robot_model(robot))
            frames = frames[: args.limit] if args.limit is not None else frames
    else:
        from monose3.data.frames import load_joints_csv, load_joints_dir
        from monose3.data.inputs import load_camera

        camera = load_camera(args.camera)
        v.check_K(camera.K, camera.size, args.camera)
        if robot is not None:
            model = robot_model(robot)
            if args.joints_csv:
                video_joints = load_joints_csv(args.joints_csv, model)
            else:
                video_joints = load_joints_dir(args.joints, model)
    return SimpleNamespace(out=out, frames=frames, video_joints=video_joints)


COMMANDS = {
    "demo": ("monose3.apps.demo", "estimate the pose on the bundled sample scene and show the error"),
    "estimate": ("monose3.apps.estimate", "estimate camera-from-base from one image, joints and intrinsics"),
    "calibrate": ("monose3.apps.calibrate", "fuse estimates over many frames from a static camera"),
    "track": ("monose3.apps.track", "track the pose over a sequence of frames or a video"),
    "generate": ("monose3.apps.generate", "generate domain-randomised synthetic data in DREAM format"),
    "train": ("monose3.apps.train", "train the denoising network on DREAM folders or scenes synthesised on the fly"),
    "train-parser": (
        "monose3.apps.train_parser",
        "train the robot parser (mask + keypoints) on scenes synthesised on the fly",
    ),
    "evaluate": ("monose3.apps.evaluate", "evaluate a checkpoint on DREAM / RoboKeyGen data (ADD, AUC)"),
}
