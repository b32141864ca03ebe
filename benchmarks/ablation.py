"""Table II and Table III on the held-out synthetic test sets.

Table II: {FixPer, VisDiff} training x {DirectReg, RevDiff} inference (AUC with its 95 %
bootstrap interval over the frames, mean ADD).
Table III: the VisDiff model with 10 steps (5 DDIM + 5 direct), 5 steps (5 DDIM) and
1-step tracking (AUC and FPS). The test sets are independent frames, so tracking starts
from the ground truth perturbed by an inter-frame motion (default 2 cm and 3 deg per axis,
about what a robot moves between frames at 30 Hz), not from a previous frame.

    python benchmarks/ablation.py --visdiff runs/visdiff/checkpoint.pt --fixper runs/fixper/checkpoint.pt \
        --data data/test_reallike data/test_hard --json docs/results/ablation.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from monose3.api import load_estimator
from monose3.data.datasets import open_dataset
from monose3.errors import run_reporting_errors
from monose3.geometry.poses import perturb_poses
from monose3.report.metrics import add_per_frame, auc_interval, summarize


def run(estimator, frames, mode: str, batch: int, limit: int | None, motion: tuple[float, float]) -> dict:
    """ADD of each frame and FPS for one inference mode."""
    n = len(frames) if limit is None else min(limit, len(frames))
    rng = np.random.default_rng(0)
    adds, start_adds, seconds = [], [], 0.0
    for start in tqdm(range(0, n, batch), desc=mode, leave=False):
        chunk = [frames[i] for i in range(start, min(start + batch, n))]
        images, Ks = [f.load_image() for f in chunk], np.stack([f.K for f in chunk])
        joints = np.stack([f.joints for f in chunk])
        tick = time.perf_counter()
        if mode == "tracking":
            start = perturb_poses(np.stack([f.pose for f in chunk]), rng, *motion)
            est = estimator.track(images, Ks, joints, start, sampler="revdiff")
        else:
            sampler, k, m = {
                "revdiff": ("revdiff", 5, 5),
                "directreg": ("directreg", 5, 5),
                "revdiff-5": ("revdiff", 5, 0),
            }[mode]
            est = estimator.estimate(images, Ks, joints, sampler=sampler, ddim_steps=k, direct_steps=m)
        seconds += time.perf_counter() - tick
        pred = estimator.robot.keypoints(joints, est.poses)
        gt = np.stack([f.keypoints_3d for f in chunk])
        a = add_per_frame(pred, gt)
        if mode == "tracking":  # what the step starts from, to judge what it adds
            start_adds.extend(add_per_frame(estimator.robot.keypoints(joints, start), gt).tolist())
        a[~est.in_view] = np.inf
        adds.extend(a.tolist())
    result = summarize(np.asarray(adds), fps=n / seconds)
    result["auc_interval"] = auc_interval(np.asarray(adds))
    if start_adds:
        result["start_auc"] = summarize(np.asarray(start_adds))["auc"]
    return result


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--visdiff", required=True)
    p.add_argument("--fixper", required=True)
    p.add_argument("--final", help="a longer-trained VisDiff model: extra Table II rows; Table III uses it")
    p.add_argument("--data", nargs="+", required=True)
    p.add_argument("--limit", type=int)
    p.add_argument("--batch-size", type=int, default=4, help="Table II batch; Table III times one image at a time")
    p.add_argument("--motion", type=float, nargs=2, default=(0.02, 3.0), metavar=("M", "DEG"))
    p.add_argument("--threads", type=int)
    p.add_argument("--json")
    args = p.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    results: dict = {"table2": {}, "table3": {}}
    models = [("FixPer", args.fixper), ("VisDiff", args.visdiff)] + (
        [("VisDiff-final", args.final)] if args.final else []
    )
    table3_model = models[-1][0]
    for name, ck in models:
        est = load_estimator(ck)
        for d in args.data:
            frames = open_dataset(d, est.robot)
            for sampler in ("directreg", "revdiff"):
                s = run(est, frames, sampler, args.batch_size, args.limit, args.motion)
                results["table2"][f"{name}+{sampler}|{Path(d).name}"] = s
            if name == table3_model:
                for mode in ("revdiff", "revdiff-5", "tracking"):
                    results["table3"][f"{mode}|{Path(d).name}"] = run(est, frames, mode, 1, args.limit, args.motion)
        est.close()
    sets = [Path(d).name for d in args.data]
    print("Table II: AUC / mean ADD (mm) per test set")
    print(f"{'method':26s}" + "".join(f"{s:>28s}" for s in sets))
    for name, _ in models:
        for sampler, label in (("directreg", "DirectReg"), ("revdiff", "RevDiff")):
            cells = [results["table2"][f"{name}+{sampler}|{s}"] for s in sets]
            print(
                f"{name + ' + ' + label:26s}"
                + "".join(
                    f"{c['auc']:>8.2f} [{c['auc_interval'][0]:5.1f}-{c['auc_interval'][1]:5.1f}] / "
                    f"{1000 * c['mean']:6.1f}"
                    for c in cells
                )  # fmt: skip
            )
    print(f"\nTable III ({table3_model}): AUC and FPS (one image per call)")
    print(f"{'steps':26s}" + "".join(f"{s:>28s}" for s in sets))
    for mode, label in (("revdiff", "10 (5 DDIM + 5 direct)"), ("revdiff-5", "5 (DDIM)"), ("tracking", "1 (tracking)")):
        cells = [results["table3"][f"{mode}|{s}"] for s in sets]
        print(f"{label:26s}" + "".join(f"{c['auc']:>16.2f} / {c['fps']:5.2f} FPS" for c in cells))
    cells = [results["table3"][f"tracking|{s}"] for s in sets]
    print(f"{'tracking start (no step)':26s}" + "".join(f"{c['start_auc']:>16.2f}" + " " * 12 for c in cells))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1, default=float))
        print(f"wrote {args.json}")


if __name__ == "__main__":
    sys.exit(run_reporting_errors(main, "ablation.py"))
