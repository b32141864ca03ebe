"""Accuracy of the default pipeline ("fit") and its stages on held-out sets, and what it costs.

Rows (one per stage, each adding to the one above): the paper's reverse diffusion alone
(RevDiff, 5 DDIM + 5 direct steps); the robot parser with PnP (hypotheses scored by silhouette
IoU, no sphere search, no refinement); + the coarse search over the sphere; + the silhouette
and keypoint refinement on the mask alone; + the image's edges in its fine pass (for the
outline and for the robot's inner edges); + the local search on the silhouette's score
between the passes; + the restarts in depth from the best refined pose; + the second look
from a denser sphere when the fit is doubted (the default).
Per row and set: AUC of ADD (0-100 mm), median ADD, CPU seconds per image (with the stages'
split for the default). Then:

* refinement from the true pose moved by ``--start-deg`` / ``--start-cm`` (a random axis and
  direction): the default pipeline's refinement alone (``from_pose.refine_from``: no PnP start),
  the share of frames that end closer than they started, start and
  final medians;
* the ``reliable`` flag (``perception.reliability.fit_doubts``) against ADD > ``--bad-mm``: recall of
  the bad estimates and false alarms among the good ones;
* tracking: ``PoseEstimator.track`` from the true pose moved by 2 cm / 3 deg per axis (images/s,
  median ADD, the share flagged reliable); with ``--tracking-only``, that alone (the same starts).

The sets are the README's (``monose3 generate --renderer tiny``: rendered by pybullet, never
trained on):

    python benchmarks/accuracy.py --data data/reallike_tiny data/hard_tiny --limit 60 --json accuracy.json

Each set's line names its frames' digest (``datasets.frames_digest``): figures compare only
between runs on sets with the same digest (``docs/results/accuracy.json`` records the sets it
was measured on).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from monose3 import atomic
from monose3.api import load_estimator
from monose3.data.datasets import frames_digest, open_dataset
from monose3.errors import run_reporting_errors
from monose3.geometry.poses import perturb_poses
from monose3.geometry.rotations import axis_angle_to_matrix
from monose3.perception.fitting import fit_pose
from monose3.perception.from_pose import refine_from
from monose3.perception.reliability import fit_doubts
from monose3.report.metrics import add_per_frame, auc

STAGES = ("paper: revdiff 5+5", "parser + PnP", "+ sphere search", "+ mask refinement", "+ edges",
          "+ local search", "+ restarts in depth", "+ second look when doubtful (default)")  # fmt: skip


def frame_add(estimator, frame, pose: np.ndarray) -> float:
    if not np.isfinite(pose).all():
        return float("inf")
    pred = estimator.robot.keypoints(frame.joints[None], pose[None])
    return float(add_per_frame(pred, frame.keypoints_3d[None])[0])


def run_stage(estimator, frame, image, stage: str) -> tuple[np.ndarray, dict, bool]:
    """(pose, timings, whether the fit flags it unreliable) of one frame through one stage."""
    if stage == STAGES[0]:
        tick = time.perf_counter()
        est = estimator.estimate([image], frame.K[None], frame.joints[None], sampler="revdiff")
        pose = est.poses[0] if est.in_view[0] else np.full((4, 4), np.nan)
        return pose, {"total": time.perf_counter() - tick}, True
    # sphere, refine, edges, search, restart, second look: each stage turns on one more
    on = STAGES.index(stage) - 1
    sphere, refine, edges, search, restart, second_look = (i < on for i in range(6))
    args = (estimator.parser, estimator.renderer, estimator.robot, image, frame.K, frame.joints)
    fit = fit_pose(*args, sphere=sphere, refine=refine, edges=edges, search=search, restart=restart,
                   second_look=second_look)  # fmt: skip
    doubts = fit_doubts(fit, estimator.robot, frame.joints, frame.K, image.shape)
    return fit.pose, {**fit.timings, "total": sum(fit.timings.values())}, bool(doubts)


def moved(pose: np.ndarray, rng: np.random.Generator, deg: float, cm: float) -> np.ndarray:
    """``pose`` turned by exactly ``deg`` about a random axis (through the base origin, camera
    frame) and shifted by exactly ``cm`` in a random direction."""
    axis, shift = rng.normal(size=3), rng.normal(size=3)
    out = pose.copy()
    out[:3, :3] = axis_angle_to_matrix(axis / np.linalg.norm(axis), np.radians(deg)) @ pose[:3, :3]
    out[:3, 3] += shift / np.linalg.norm(shift) * cm / 100
    return out


def evaluate_set(estimator, folder: str, limit: int, args) -> dict:
    frames = open_dataset(folder, estimator.robot)
    n = min(limit, len(frames))
    rng = np.random.default_rng(0)
    adds, seconds, flagged = defaultdict(list), defaultdict(list), []
    refine = {"start": [], "final": []}
    tracking = {"seconds": [], "add": [], "reliable": []}
    for i in tqdm(range(n), desc=Path(folder).name):
        frame = frames[i]
        image = frame.load_image()
        start = moved(frame.pose, rng, args.start_deg, args.start_cm)  # drawn either way: tracking's starts stay
        if not args.tracking_only:
            for stage in STAGES:
                pose, timings, doubted = run_stage(estimator, frame, image, stage)
                adds[stage].append(frame_add(estimator, frame, pose))
                for key, value in timings.items():
                    seconds[f"{stage}/{key}"].append(value)
                if stage == STAGES[-1]:
                    flagged.append(doubted)
            parts = (estimator.parser, estimator.renderer, estimator.robot, image, frame.K, frame.joints)
            fit = refine_from(*parts, start)
            refine["start"].append(frame_add(estimator, frame, start))
            refine["final"].append(frame_add(estimator, frame, fit.pose))
        near = perturb_poses(frame.pose[None], rng, 0.02, 3.0)
        tick = time.perf_counter()
        tracked = estimator.track([image], frame.K[None], frame.joints[None], near)
        tracking["seconds"].append(time.perf_counter() - tick)
        tracking["add"].append(frame_add(estimator, frame, tracked.poses[0]))
        tracking["reliable"].append(bool(tracked.reliable[0]))
    summary = summarise(adds, seconds, flagged, refine, tracking, args.bad_mm / 1000)
    summary["frames"] = {"count": n, "digest": frames_digest([frames[i] for i in range(n)])}
    return summary


def summarise(adds, seconds, flagged, refine, tracking, bad_m: float) -> dict:
    tracked = {
        "images_per_s": float(1 / np.mean(tracking["seconds"])),
        "median_add_mm": float(np.median(tracking["add"]) * 1000),
        "reliable_share": float(np.mean(tracking["reliable"])),
    }
    if not adds:  # --tracking-only
        return {"tracking": tracked}
    rows = {}
    for stage in STAGES:
        a = np.asarray(adds[stage])
        # per image: a stage that ran on some frames only (the second look) counts 0 s on the others
        split = {k.split("/", 1)[1]: sum(v) / len(a) for k, v in seconds.items() if k.startswith(stage + "/")}
        rows[stage] = {"auc": auc(a), "median_add_mm": float(np.median(a) * 1000), "seconds": split}
    final = np.asarray(adds[STAGES[-1]])
    flagged = np.asarray(flagged)
    bad = final > bad_m
    start, end = np.asarray(refine["start"]), np.asarray(refine["final"])
    return {
        "stages": rows,
        "refinement": {
            "closer_share": float((end < start).mean()),
            "start_median_mm": float(np.median(start) * 1000),
            "final_median_mm": float(np.median(end) * 1000),
        },
        "reliable_flag": {
            "bad": int(bad.sum()),
            "good": int((~bad).sum()),
            "recall": float((flagged & bad).sum() / max(1, bad.sum())),
            "false_alarms": float((flagged & ~bad).sum() / max(1, (~bad).sum())),
        },
        "tracking": tracked,
    }


def print_report(results: dict[str, dict], args) -> None:
    if args.tracking_only:
        for name, r in results.items():
            print(f"{name} ({r['frames']['count']} frames, digest {r['frames']['digest']}):")
            print_tracking(r["tracking"])
        return
    names = list(results)
    width = max(map(len, STAGES)) + 1
    print(f"{'stage':<{width}}" + "".join(f"{n + ' AUC':>22}{'median mm':>11}{'s/img':>7}" for n in names))
    for stage in STAGES:
        cells = []
        for n in names:
            row = results[n]["stages"][stage]
            cells.append(f"{row['auc']:>22.2f}{row['median_add_mm']:>11.1f}{row['seconds']['total']:>7.2f}")
        print(f"{stage:<{width}}" + "".join(cells))
    for n in names:
        r = results[n]
        split = ", ".join(f"{k} {v:.2f}" for k, v in r["stages"][STAGES[-1]]["seconds"].items())
        ref, flag = r["refinement"], r["reliable_flag"]
        frames = f"{r['frames']['count']} frames, digest {r['frames']['digest']}"
        print(f"\n{n} ({frames}): default pipeline s/img split: {split}")
        print(
            f"  refinement from truth moved {args.start_deg:g} deg / {args.start_cm:g} cm: "
            f"{100 * ref['closer_share']:.0f} % end closer; median ADD {ref['start_median_mm']:.1f} -> "
            f"{ref['final_median_mm']:.1f} mm"
        )
        print(
            f"  reliable flag vs ADD > {args.bad_mm:g} mm: recall {100 * flag['recall']:.0f} % "
            f"of {flag['bad']} bad, false alarms {100 * flag['false_alarms']:.0f} % of {flag['good']} good"
        )
        print_tracking(r["tracking"])


def print_tracking(track: dict) -> None:
    print(
        f"  tracking from truth moved 2 cm / 3 deg per axis: {track['images_per_s']:.1f} images/s, "
        f"median ADD {track['median_add_mm']:.1f} mm, {100 * track['reliable_share']:.0f} % reliable"
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", nargs="+", default=["data/reallike_tiny", "data/hard_tiny"])
    p.add_argument("--limit", type=int, default=60)
    p.add_argument("--checkpoint", help="denoiser (default: bundled)")
    p.add_argument("--parser", help="robot parser weights (default: bundled)")
    p.add_argument("--start-deg", type=float, default=5.0)
    p.add_argument("--start-cm", type=float, default=3.0)
    p.add_argument("--bad-mm", type=float, default=30.0)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--tracking-only", action="store_true", help="measure tracking alone (minutes, not an hour)")
    p.add_argument("--json")
    args = p.parse_args(argv)

    def run() -> int:
        torch.set_num_threads(args.threads)
        estimator = load_estimator(args.checkpoint, parser=args.parser, device="cpu")
        results = {Path(d).name: evaluate_set(estimator, d, args.limit, args) for d in args.data}
        print_report(results, args)
        if args.json:
            atomic.write_text(args.json, json.dumps(results, indent=1))
            print(f"wrote {args.json}")
        return 0

    return run_reporting_errors(run, "accuracy")


if __name__ == "__main__":
    sys.exit(main())
