"""Does fusing N frames of a static camera beat a single frame? (``monose3 calibrate``)

A static-camera DREAM set is synthesised the way ``monose3 generate`` makes frames, with one
camera for the whole set:

* camera: intrinsics and pose drawn once from the ``reallike`` profile's camera sampling
  (``generate.sample_scene``: 0.8-1.8 m from the robot, looking at it); same for every frame;
* robot: ``--frames`` configurations uniform within the joint limits, each kept only if the
  robot stays in view (the profile's ``min_visible`` share of its surface points inside the
  image, none closer than 10 cm to the lens); a camera that cannot keep the robot in view for
  random configurations is redrawn;
* pixels: one light and one domain-randomised background with its distractor shapes, drawn
  once (the scene does not change when the camera does not move); per frame only what a real
  static camera still sees change: occluders, colour jitter, blur, sensor noise and the JPEG
  quality (``appearance.compose_frame`` with the ``reallike`` settings);
* written with ``dream.write_frame`` (ground truth = forward kinematics under the camera pose).

The set is split into disjoint subsets of N frames for every N in ``--sizes`` and
``calibrate()`` runs on each. Reported per N: the fused extrinsic's error against ground truth
(ADD over the keypoints averaged over the subset's frames, translation mm, rotation deg; median
and range over the subsets) and the frames rejected (out of view / unreliable chains or fit / far from
consensus), next to the median single-frame error of the same frames.

    python benchmarks/calibration.py --checkpoint CK [--frames 40] [--sizes 5 10 20 40] [--seed 0] \
        [--chains 1] [--plot docs/results/calibration.png] [--keep DIR]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from collections import Counter
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from monose3.api import load_estimator
from monose3.calibration import REASON_CONSENSUS, REASON_OUT_OF_VIEW, REASON_POOR_FIT, REASON_UNRELIABLE, calibrate
from monose3.data.datasets import open_dataset
from monose3.data.dream_writer import write_camera_settings, write_frame
from monose3.data.scenes.appearance import compose_frame, scene_background
from monose3.data.scenes.profiles import PROFILES
from monose3.data.scenes.sampling import frame_rng, sample_scene
from monose3.data.scenes.sequences import in_view_fraction
from monose3.errors import Monose3Error, run_reporting_errors
from monose3.geometry.averaging import pose_residuals
from monose3.report.plots import new_figure, save_figure
from monose3.robot import RobotModel
from monose3.robot.renderer import RenderJob, RobotRenderer
from monose3.training.checkpoints import read_checkpoint

ROOT = Path(__file__).resolve().parents[1]
IMAGE_SIZE = (640, 480)
SIZES = (5, 10, 20, 40)
MAX_JOINT_TRIES = 200  # random configurations tried per frame before the camera is redrawn
MAX_CAMERAS = 20
REASONS = (REASON_OUT_OF_VIEW, REASON_UNRELIABLE, REASON_POOR_FIT, REASON_CONSENSUS)


# ---- the static-camera set ------------------------------------------------------------------


def sample_configurations(
    rng: np.random.Generator, model: RobotModel, pose: np.ndarray, K: np.ndarray, n: int, min_visible: float
) -> np.ndarray | None:
    """``n`` random joint vectors that keep the robot in view of this camera, or None if it cannot."""
    out = []
    for _ in range(n):
        for _ in range(MAX_JOINT_TRIES):
            q = model.random_joints(rng, 1)[0]
            if in_view_fraction(model, q, pose, K, IMAGE_SIZE) >= min_visible:
                out.append(q)
                break
        else:
            return None
    return np.stack(out)


def make_static_set(out: Path, frames: int, seed: int) -> dict:
    """Write the static-camera DREAM set to ``out``; returns what was drawn once (camera, tries)."""
    model = RobotModel("panda")
    profile = PROFILES["reallike"]
    # What varies per frame: occluders, augmentation, JPEG quality; the scene itself is fixed.
    per_frame = replace(profile, name="static", distractors=(0, 0), low_contrast_prob=0.0, user_background_prob=0.0)
    rng = frame_rng(seed, 0)  # the scene's generator; frame i uses frame_rng(seed, i + 1)
    for camera in range(MAX_CAMERAS):  # noqa: B007 - reported below
        scene = sample_scene(rng, model, profile, IMAGE_SIZE)
        joints = sample_configurations(rng, model, scene.pose, scene.K, frames, profile.min_visible)
        if joints is not None:
            break
    else:
        raise Monose3Error(f"no camera of profile reallike kept the robot in view for {frames} configurations")
    background = scene_background(torch.Generator().manual_seed(int(rng.integers(2**62))), 1, IMAGE_SIZE, profile,
                                  None, "cpu")  # fmt: skip
    renders = RobotRenderer(model).render_jobs(
        [RenderJob(q, scene.pose, scene.K, IMAGE_SIZE, scene.lighting) for q in joints]
    )
    for i, (q, (rgb, mask)) in enumerate(zip(joints, renders, strict=True)):
        frng = frame_rng(seed, i + 1)
        img, _ = compose_frame(frng, rgb, mask, per_frame, None, background)
        quality = int(frng.integers(profile.jpeg_quality[0], profile.jpeg_quality[1] + 1))
        write_frame(out, i, img, scene.K, model.joint_dict(q), scene.pose, robot=model, quality=quality)
    write_camera_settings(out, scene.K, *IMAGE_SIZE)
    centroid = model.centroid(model.surface_points(joints)).mean(0)
    distance = float(np.linalg.norm(scene.pose[:3, :3] @ centroid + scene.pose[:3, 3]))
    hfov = float(np.degrees(2 * np.arctan2(IMAGE_SIZE[0] / 2, scene.K[0, 0])))
    return {"cameras_tried": camera + 1, "distance_m": distance, "hfov_deg": hfov, "pose": scene.pose, "K": scene.K}


# ---- the experiment -------------------------------------------------------------------------


def run(estimator, frames: list, sizes: list[int], chains: int, seed: int) -> dict:
    """``calibrate()`` on disjoint subsets of every size; per run its fused errors and rejections."""
    runs: dict[int, list[dict]] = {}
    for n in sizes:
        runs[n] = []
        for k in range(len(frames) // n):
            subset = frames[k * n : (k + 1) * n]
            try:
                result = calibrate(estimator, subset, chains=chains, seed=seed + 1000 * n + k)
            except Monose3Error as err:  # every frame rejected: the calibration fails
                runs[n].append({"failed": str(err), "n": n, "rejected": {}, "singles": []})
                continue
            gt = result.ground_truth
            assert gt is not None, "the synthetic set carries ground truth"
            gt_pose = np.asarray(subset[0].pose, np.float64)
            singles = []
            for f, r in zip(subset, result.frames, strict=True):
                ok = r.in_view and np.all(np.isfinite(r.camera_from_base))
                mm, deg = pose_residuals(r.camera_from_base[None], gt_pose) if ok else ([np.inf], [np.inf])
                singles.append({"add": r.add_single_mm, "mm": float(mm[0]), "deg": float(deg[0]), "name": f.name})
            runs[n].append(
                {
                    "n": n,
                    "add": gt["fused_add_mean_mm"],
                    "mm": gt["fused_error_mm"],
                    "deg": gt["fused_error_deg"],
                    "used": len(result.used),
                    "rejected": result.rejected,
                    "singles": singles,
                    "static": gt["static_camera"],
                }
            )
            print(
                f"  N={n} subset {k + 1}: fused {gt['fused_error_mm']:.1f} mm / {gt['fused_error_deg']:.2f} deg, "
                f"{len(result.used)}/{n} used",
                file=sys.stderr,
            )
    return runs


def single_frame_errors(runs: dict[int, list[dict]]) -> dict[str, np.ndarray]:
    """Every frame's own estimate's errors (taken from the largest N's runs: each frame once)."""
    n = max(runs)
    singles = [s for r in runs[n] for s in r["singles"]]
    if not singles:  # the largest N failed entirely: fall back to any run that has frames
        singles = [s for rs in runs.values() for r in rs for s in r["singles"]]
    return {k: np.array([s[k] for s in singles], np.float64) for k in ("add", "mm", "deg")}


def _med(values: list[float]) -> float:
    v = np.asarray(values, np.float64)
    return float(np.median(v)) if v.size else float("nan")


def report(runs: dict[int, list[dict]], info: dict, total: int, chains: int, checkpoint: str, step) -> str:
    single = single_frame_errors(runs)
    fails = int(np.sum(~np.isfinite(single["add"])))
    lines = [
        f"Static-camera calibration: {total} frames of one reallike camera ({info['distance_m']:.2f} m from the "
        f"robot, hfov {info['hfov_deg']:.0f} deg, 640x480), {chains} chain(s) per frame, checkpoint {checkpoint}"
        + (f" (step {step})" if step is not None else ""),
        f"single frames ({len(single['add'])}): median ADD {_med(single['add']):.1f} mm, translation "
        f"{_med(single['mm']):.1f} mm, rotation {_med(single['deg']):.2f} deg; out of view {fails}",
        "",
        f"{'N':>3} {'subsets':>7} {'fused ADD mm':>20} {'fused trans mm':>20} {'fused rot deg':>20} "
        f"{'used':>9} {'out of view':>11} {'unreliable':>10} {'consensus':>9} {'failed':>6}",
    ]
    summary = {}
    for n, rs in runs.items():
        ok = [r for r in rs if "failed" not in r]
        rej = Counter()
        for r in rs:
            rej.update(r["rejected"])
        used = sum(r["used"] for r in ok)

        def cell(key: str, fmt: str, ok=ok) -> str:
            v = [r[key] for r in ok]
            if not v:
                return "-"
            if len(v) == 1:
                return format(v[0], fmt)
            return f"{format(np.median(v), fmt)} [{format(min(v), fmt)}-{format(max(v), fmt)}]"

        unreliable = rej.get(REASON_UNRELIABLE, 0) + rej.get(REASON_POOR_FIT, 0)
        lines.append(
            f"{n:>3} {len(rs):>7} {cell('add', '.1f'):>20} {cell('mm', '.1f'):>20} {cell('deg', '.2f'):>20} "
            f"{f'{used}/{n * len(rs)}':>9} {rej.get(REASON_OUT_OF_VIEW, 0):>11} {unreliable:>10} "
            f"{rej.get(REASON_CONSENSUS, 0):>9} {len(rs) - len(ok):>6}"
        )
        summary[n] = {k: _med([r[k] for r in ok]) for k in ("add", "mm", "deg")}
    lines.append("(fused columns: median [min-max] over the disjoint subsets; rejected frames summed over them)")
    lines.append("")
    n_max = max(runs)
    s = summary[n_max]
    if np.isfinite(s["add"]):
        verdict = lambda a, b: "beats" if a < b else "does NOT beat"  # noqa: E731
        lines.append(
            f"N={n_max}: fused ADD {s['add']:.1f} mm vs single-frame median {_med(single['add']):.1f} mm "
            f"({verdict(s['add'], _med(single['add']))}; x{_med(single['add']) / max(s['add'], 1e-9):.1f}), "
            f"translation {s['mm']:.1f} vs {_med(single['mm']):.1f} mm "
            f"({verdict(s['mm'], _med(single['mm']))}), rotation {s['deg']:.2f} vs {_med(single['deg']):.2f} deg "
            f"({verdict(s['deg'], _med(single['deg']))})"
        )
        beats = [n for n in runs if np.isfinite(summary[n]["add"]) and summary[n]["add"] < _med(single["add"])]
        lines.append(f"N whose median fused ADD beats the median single frame: {beats or 'none'}")
    else:
        lines.append(f"N={n_max}: the calibration failed (every frame rejected)")
    if not all(r.get("static", True) for rs in runs.values() for r in rs):
        lines.append("warning: the ground-truth poses differ between frames: the set is not static")
    return "\n".join(lines)


# ---- plot -------------------------------------------------------------------------------------


def plot(runs: dict[int, list[dict]], path: Path, total: int, chains: int, step) -> Path:

    single = single_frame_errors(runs)
    fig = new_figure((14, 4.3))
    axes = fig.subplots(1, 3)
    panels = [("add", "ADD of the pose (mm)"), ("mm", "translation error (mm)"), ("deg", "rotation error (deg)")]
    sizes = sorted(runs)
    for ax, (key, label) in zip(axes, panels, strict=True):
        for n in sizes:
            v = [r[key] for r in runs[n] if "failed" not in r]
            ax.scatter([n] * len(v), v, s=18, color="tab:blue", alpha=0.5)
        med = [_med([r[key] for r in runs[n] if "failed" not in r]) for n in sizes]
        ax.plot(sizes, med, "-o", color="tab:blue", label="fused (median over subsets; dots: each subset)")
        finite = single[key][np.isfinite(single[key])]
        ax.axhline(_med(single[key]), color="tab:red", ls="--", label="single frame: median")
        if finite.size >= 4:
            q1, q3 = np.percentile(finite, [25, 75])
            ax.axhspan(q1, q3, color="tab:red", alpha=0.08, label="single frame: 25-75 % (in view)")
        ax.set_xscale("log", base=2)
        ax.set_xticks(sizes)
        ax.set_xticklabels([str(n) for n in sizes])
        ax.set_xlabel("frames fused (N)")
        ax.set_ylabel(label)
        shown = [*finite, *(r[key] for rs in runs.values() for r in rs if "failed" not in r)]
        ax.set_ylim(0, 1.15 * max(shown) if shown and np.isfinite(max(shown)) else None)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle(
        f"Static-camera calibration: fused extrinsic vs single frames ({total} frames, {chains} chain(s)"
        + (f", step {step})" if step is not None else ")")
    )
    fig.tight_layout()
    return save_figure(fig, path, dpi=110)


# ---- main -------------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", required=True, help="model checkpoint")
    p.add_argument("--frames", type=int, default=40, help="frames in the static-camera set")
    p.add_argument("--sizes", type=int, nargs="+", default=list(SIZES), help="N frames fused (subsets)")
    p.add_argument("--seed", type=int, default=0, help="scene seed (camera, background, configurations)")
    p.add_argument("--chains", type=int, default=1, help="chains per frame (>1 also rejects unreliable frames)")
    p.add_argument("--device", default="cpu", help="cpu, cuda or auto")
    p.add_argument(
        "--plot", default=str(ROOT / "docs" / "results" / "calibration.png"), help="output figure ('' for none)"
    )
    p.add_argument("--keep", help="write the static set here (kept) instead of a temporary folder")
    args = p.parse_args(argv)
    sizes = sorted({n for n in args.sizes if 1 <= n <= args.frames})
    if not sizes:
        p.error(f"--sizes must hold at least one N between 1 and --frames ({args.frames})")
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    tick = time.perf_counter()
    step = read_checkpoint(args.checkpoint).get("step")
    with tempfile.TemporaryDirectory(prefix="monose3_static_") as tmp:
        folder = Path(args.keep) if args.keep else Path(tmp) / "static"
        info = make_static_set(folder, args.frames, args.seed)
        made = time.perf_counter() - tick
        print(f"static set: {args.frames} frames in {folder} ({made:.0f} s)", file=sys.stderr)
        estimator = load_estimator(args.checkpoint, device=args.device)
        try:
            ds = open_dataset(folder, estimator.robot)
            frames = [ds[i] for i in range(len(ds))]
            runs = run(estimator, frames, sizes, args.chains, args.seed)
        finally:
            estimator.close()
    print(report(runs, info, args.frames, args.chains, args.checkpoint, step))
    if args.plot:
        print(f"plot: {plot(runs, Path(args.plot), args.frames, args.chains, step)}")
    print(f"({time.perf_counter() - tick:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(run_reporting_errors(main, "calibration.py"))
