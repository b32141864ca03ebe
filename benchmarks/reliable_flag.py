"""How the ``reliable`` flag of the default pipeline is chosen: its thresholds (silhouette IoU,
the RMS distance of the outline to the image's own edges, the share of the outline on them) on
frames of their own, for a target recall of bad estimates (ADD > ``--bad-mm``) at the fewest
false alarms. The refined hypotheses' spread is offered too; the search here sets it to "never
doubt", and it set the edge support so too until the local search came (2026-12-05).

Prints the best thresholds found on ``--data`` and how the flag with the thresholds in
``perception/fitting.py`` does there. The frames must not be the held-out sets the README
reports on (``benchmarks/accuracy.py`` measures the flag there):

    monose3 generate --out data/calib_hard_tiny --num 80 --seed 3003 --profile hard --renderer tiny
    monose3 generate --out data/calib_reallike_tiny --num 40 --seed 4004 --profile reallike --renderer tiny
    monose3 generate --out data/calib2_hard_tiny --num 200 --seed 5005 --profile hard --renderer tiny
    monose3 generate --out data/calib2_reallike_tiny --num 100 --seed 6006 --profile reallike --renderer tiny
    python benchmarks/reliable_flag.py --data data/calib*_tiny
"""

from __future__ import annotations

import argparse
import itertools
import sys

import numpy as np
import torch
from tqdm import tqdm

from monose3.api import load_estimator
from monose3.data.datasets import open_dataset
from monose3.errors import run_reporting_errors
from monose3.perception import fitting
from monose3.report.metrics import add_per_frame

IOUS = np.round(np.arange(0.5, 0.951, 0.05), 2)
EDGE_DISTANCES_PX = np.round(np.arange(0.5, 1.51, 0.05), 2)
SUPPORTS = (0.0, 0.2, 0.3, 0.4, 0.45, 0.5)
SPREADS_MM = (2.0, 5.0, 10.0, 20.0, np.inf)


def frame_features(estimator, folder: str) -> list[dict]:
    """Per frame: the default fit's ADD (m), IoU, edge distance (px), edge support, hypotheses'
    spread (mm), robot share in the image."""
    frames = open_dataset(folder, estimator.robot)
    rows = []
    for i in tqdm(range(len(frames)), desc=folder):
        frame = frames[i]
        image = frame.load_image()
        fit = fitting.fit_pose(estimator.parser, estimator.renderer, estimator.robot, image, frame.K, frame.joints)
        pred = estimator.robot.keypoints(frame.joints[None], fit.pose[None])  # NaN when not found: ADD inf
        inside = fitting.inside_fraction(estimator.robot, fit.pose, frame.joints, frame.K, image.shape)  # 0 then
        rows.append({"add": float(add_per_frame(pred, frame.keypoints_3d[None])[0]), "iou": fit.iou,
                     "edge_distance": fit.edge_distance_px, "support": fit.edge_support, "spread": fit.spread_mm,
                     "inside": inside})  # fmt: skip
    return rows


def flag(f: dict, iou: float, edge_px: float, support: float = 0.0, spread_mm: float = np.inf) -> np.ndarray:
    """Unreliable, as ``fitting.fit_doubts`` decides it (the first three thresholds), for thresholds given."""
    return ((f["iou"] < iou) | ~(f["edge_distance"] <= edge_px) | (f["inside"] < fitting.MIN_INSIDE)
            | (f["support"] < support) | (f["spread"] > spread_mm))  # fmt: skip


def rates(flagged: np.ndarray, bad: np.ndarray) -> tuple[float, float]:
    return float(flagged[bad].mean()) if bad.any() else float("nan"), float(flagged[~bad].mean())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", nargs="+", required=True, help="frame folders not among the held-out sets")
    p.add_argument("--bad-mm", type=float, default=30.0)
    p.add_argument("--recall", type=float, default=0.9, help="target share of bad estimates flagged")
    p.add_argument("--threads", type=int, default=2)

    def run() -> int:
        torch.set_num_threads(args.threads)
        estimator = load_estimator(device="cpu")
        rows = [row for folder in args.data for row in frame_features(estimator, folder)]
        f = {k: np.array([r[k] for r in rows], float) for k in rows[0]}
        bad = f["add"] > args.bad_mm / 1000
        print(f"{len(rows)} frames, {bad.sum()} with ADD > {args.bad_mm:g} mm")
        found = []
        for thresholds in itertools.product(IOUS, EDGE_DISTANCES_PX, SUPPORTS, SPREADS_MM):
            recall, false_alarms = rates(flag(f, *thresholds), bad)
            if recall >= args.recall:
                found.append((false_alarms, -recall, *thresholds))
        for false_alarms, recall, iou, edge_px, support, spread in sorted(found)[:5]:
            rule = f"IoU >= {iou:.2f}, edge distance <= {edge_px:.2f} px, support >= {support:.2f}"
            rule += f", spread <= {spread:g} mm"
            print(f"  {rule}: recall {-100 * recall:.1f} %, false alarms {100 * false_alarms:.1f} %")
        current = (fitting.RELIABLE_IOU, fitting.RELIABLE_EDGE_DISTANCE_PX, fitting.RELIABLE_EDGE_SUPPORT)
        recall, false_alarms = rates(flag(f, *current), bad)
        print(f"the flag as shipped {current}: recall {100 * recall:.1f} %, false alarms {100 * false_alarms:.1f} %")
        return 0

    args = p.parse_args(argv)
    return run_reporting_errors(run, "reliable_flag")


if __name__ == "__main__":
    sys.exit(main())
