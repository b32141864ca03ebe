"""The robot parser's masks on held-out sets, and how the default fit's accuracy depends on them.

Per frame: the IoU of the mask the default pipeline fits to (``views.parse_image``: the whole
image, then zoomed on a small robot; mirror-averaged) with the robot's silhouette at the true
pose, rendered in the same view and compared inside the image, as ``silhouette.mask_ious``
compares a fit's. The silhouette is the whole robot: where an occluder hides part of it, the
parser is right to leave that part out, so on occluded frames the IoU is lower than the mask's
own quality (a lower bound). With ``--fit``, the default fit on each frame too, its ADD per
band of mask IoU (how much of the error is the parser's), and, where the mask is fair, how
often the true pose fits the mask better than the estimate (how much is the fit's).

    python benchmarks/parser_masks.py --data data/reallike_tiny data/hard_tiny --fit --json parser_masks.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from monose3 import atomic
from monose3.api import load_estimator
from monose3.data.datasets import open_dataset
from monose3.errors import run_reporting_errors
from monose3.perception.fitting import fit_pose
from monose3.perception.silhouette import mask_ious, render_silhouettes
from monose3.perception.views import MIN_MASK_FRACTION, parse_image
from monose3.report.metrics import add_per_frame

BANDS = ((0.0, 0.8), (0.8, 0.9), (0.9, 1.01))  # mask IoU bands the ADD is split by
FAIR_MASK_IOU = 0.8
TRUTH_BETTER_IOU = 0.01  # the true pose's IoU with the mask over the estimate's by more than this


def frame_rows(estimator, frames, name: str, limit: int, fit: bool) -> list[dict]:
    """Per frame of ``frames`` (a dataset, the first ``limit``; ``name`` for the progress bar):
    the mask's IoU with the true silhouette (0 where the parser finds no robot) and, with
    ``fit``, the default fit's ADD (m) and IoU."""
    rows = []
    for i in tqdm(range(min(limit, len(frames))), desc=name):
        frame = frames[i]
        image = frame.load_image()
        view = parse_image(estimator.parser, image, frame.K)
        true = render_silhouettes(estimator.renderer, frame.joints, frame.pose[None], view, view.size)
        found = view.robot_fraction >= MIN_MASK_FRACTION
        row = {"mask_iou": float(mask_ious(true, view)[0]) if found else 0.0}
        if fit:
            estimate = fit_pose(estimator.parser, estimator.renderer, estimator.robot, image, frame.K, frame.joints)
            pred = estimator.robot.keypoints(frame.joints[None], estimate.pose[None])  # NaN when not found: ADD inf
            row["add"] = float(add_per_frame(pred, frame.keypoints_3d[None])[0])
            row["fit_iou"] = estimate.iou  # in the same view: the fit parses the image as above
        rows.append(row)
    return rows


def summary(rows: list[dict], bad_mm: float) -> dict:
    """The mask IoU's mean, median and shares; with the fits, their ADD per mask IoU band."""
    iou = np.array([r["mask_iou"] for r in rows])
    out = {"frames": len(rows), "mean": float(iou.mean()), "median": float(np.median(iou)),
           "share_at_least_0.9": float(np.mean(iou >= 0.9)), "share_below_0.8": float(np.mean(iou < 0.8))}  # fmt: skip
    if "add" in rows[0]:
        add = np.array([r["add"] for r in rows]) * 1000
        out["bands"] = [band(iou, add, lo, hi, bad_mm) for lo, hi in BANDS]
        # Where the mask is fair, does the true pose fit it better than the estimate? Then the
        # estimate is not the mask's best fit: the search or the edges held it elsewhere.
        fair, bad = iou >= FAIR_MASK_IOU, add > bad_mm
        truth_better = iou > np.array([r["fit_iou"] for r in rows]) + TRUTH_BETTER_IOU
        out["truth_fits_better"] = {name: [int((truth_better & fair & m).sum()), int((fair & m).sum())]
                                    for name, m in (("bad", bad), ("good", ~bad))}  # fmt: skip
    return out


def band(iou: np.ndarray, add_mm: np.ndarray, lo: float, hi: float, bad_mm: float) -> dict:
    m = (iou >= lo) & (iou < hi)
    median = atomic.json_number(float(np.median(add_mm[m]))) if m.any() else None
    return {"mask_iou": [lo, min(hi, 1.0)], "frames": int(m.sum()), "bad": int((add_mm[m] > bad_mm).sum()),
            "median_add_mm": median}  # fmt: skip


def print_summary(name: str, s: dict, bad_mm: float) -> None:
    print(f"{name}: {s['frames']} frames; mask IoU with the true silhouette: mean {s['mean']:.3f}, median "
          f"{s['median']:.3f}, {100 * s['share_at_least_0.9']:.0f} % at 0.9 or more, "
          f"{100 * s['share_below_0.8']:.0f} % below 0.8")  # fmt: skip
    for band in s.get("bands", []):
        lo, hi = band["mask_iou"]
        median = "-" if band["median_add_mm"] is None else f"{band['median_add_mm']:.1f} mm"
        print(f"  mask IoU {lo:.1f}-{hi:.1f}: {band['frames']} frames, {band['bad']} with ADD > {bad_mm:g} mm, "
              f"median ADD {median}")  # fmt: skip
    if "truth_fits_better" in s:
        (bad_hits, bad_n), (good_hits, good_n) = s["truth_fits_better"]["bad"], s["truth_fits_better"]["good"]
        print(f"  mask IoU {FAIR_MASK_IOU} or more: the true pose fits the mask better than the estimate"
              f" (IoU over {TRUTH_BETTER_IOU} higher) for {bad_hits} of {bad_n} bad estimates,"
              f" {good_hits} of {good_n} good ones")  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", nargs="+", default=["data/reallike_tiny", "data/hard_tiny"])
    p.add_argument("--limit", type=int, default=60)
    p.add_argument("--fit", action="store_true", help="fit each frame too: ADD per band of mask IoU")
    p.add_argument("--bad-mm", type=float, default=30.0)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--json", help="write the summaries and each frame's figures here")
    args = p.parse_args(argv)

    def run() -> int:
        torch.set_num_threads(args.threads)
        estimator = load_estimator(device="cpu")
        # every folder opened first: a bad one is refused before any frame is parsed
        datasets = {Path(folder).name: open_dataset(folder, estimator.robot) for folder in args.data}
        results = {}
        for name, frames in datasets.items():
            rows = frame_rows(estimator, frames, name, args.limit, args.fit)
            strict = [{k: atomic.json_number(v) for k, v in row.items()} for row in rows]  # ADD inf: null
            results[name] = {"summary": summary(rows, args.bad_mm), "frames": strict}
            print_summary(name, results[name]["summary"], args.bad_mm)
        if args.json:
            atomic.write_text(args.json, json.dumps(results, indent=1))
            print(f"wrote {args.json}")
        return 0

    return run_reporting_errors(run, "parser_masks")


if __name__ == "__main__":
    sys.exit(main())
