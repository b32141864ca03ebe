"""Does adapting the parser to a user's scene help? (``monose3 calibrate --adapt``)

Each scene is a static camera 2-3 m from the robot, the hard profile's occluders, blur and
noise, and always low contrast (the background drawn near the robot's colours), 40 frames of
the robot moving (``monose3 generate --sequence static``), rendered by pybullet's TinyRenderer
with pybullet's own Panda model: another renderer and another model than the parser learnt on.
Seeds from 62000 on; the adaptation's settings were chosen on seeds 61000-61003.

Per scene, with ground truth used only to score: every frame estimated alone and the frames
fused (``calibrate``) with the bundled parser, the adaptation (``adapt_parser``, static camera:
the fused pose labels every frame; its guard's verdict on the held-out frames), and the same
again with the adapted parser (the one the guard kept, and the fine-tuned one whatever the
guard said). Reported: per-frame AUC and median ADD, frames off by more than 50 mm, the fused
pose's translation error and its part along the line of sight, and the adaptation's seconds.

    python benchmarks/adaptation.py --json docs/results/adaptation.json [--scenes 4] [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from monose3 import atomic
from monose3.adaptation import AdaptConfig, adapt_parser
from monose3.api import load_estimator
from monose3.atomic import json_number
from monose3.calibration import calibrate
from monose3.data.datasets import open_dataset
from monose3.data.scenes.profiles import get_profile
from monose3.data.scenes.sequences import SequenceConfig, write_sequence
from monose3.errors import run_reporting_errors
from monose3.report.metrics import auc

FIRST_SEED = 62000
FAILURE_MM = 50.0
FAR_LOW_CONTRAST = replace(get_profile("hard"), name="hard-far-low-contrast", distance=(2.0, 3.0),
                           low_contrast_prob=1.0)  # fmt: skip


def scene(folder: Path, seed: int, frames: int) -> Path:
    out = folder / f"scene{seed}"
    if not (out / "_sequence.json").exists():
        write_sequence(out, SequenceConfig(frames=frames, camera="static"), seed, profile=FAR_LOW_CONTRAST,
                       backend="tiny")  # fmt: skip
    return out


def scores(estimator, frames) -> dict:
    """Every frame alone and the fused pose, against ground truth."""
    result = calibrate(estimator, frames)
    adds = np.array([r.add_single_mm for r in result.frames], float)
    truth = np.asarray(frames[0].pose)  # a static camera: one true pose
    error = result.camera_from_base[:3, 3] - truth[:3, 3]
    sight = truth[:3, 3] / np.linalg.norm(truth[:3, 3])
    return {
        "auc": round(auc(adds / 1000.0), 2),
        "median_add_mm": round(float(np.median(adds)), 2),
        "over_50mm": int(np.sum(adds > FAILURE_MM)),
        "reliable": int(sum(bool(r.fit_reliable) for r in result.frames)),
        "fused_error_mm": round(1000 * float(np.linalg.norm(error)), 2),
        "fused_along_sight_mm": round(1000 * float(error @ sight), 2),
        "distance_m": round(float(np.linalg.norm(truth[:3, 3])), 3),
        "add_mm": [json_number(round(float(a), 2)) for a in adds],  # null: no estimate in view
    }


def run_scene(folder: Path, config: AdaptConfig) -> dict:
    estimator = load_estimator()
    frames = list(open_dataset(folder, estimator.robot))
    row = {"scene": folder.name, "frames": len(frames), "before": scores(estimator, frames)}
    start = time.perf_counter()
    adapted = adapt_parser(estimator, frames, config, static_camera=True, progress=True)
    row["adaptation"] = {**adapted.to_dict(), "seconds_total": round(time.perf_counter() - start, 1)}
    estimator.parser = adapted.candidate
    row["fine_tuned"] = scores(estimator, frames)
    row["kept"] = row["fine_tuned"] if adapted.adapted else row["before"]
    brief = {k: {n: v for n, v in row[k].items() if n != "add_mm"} for k in ("before", "fine_tuned")}
    print(json.dumps({"scene": row["scene"], **brief}), flush=True)
    print(f"  {adapted.verdict}; {row['adaptation']['seconds_total']:.0f} s", flush=True)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=int, default=4)
    ap.add_argument("--seed", type=int, default=FIRST_SEED)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--keep", type=Path, help="folder for the scenes (reused when present)")
    ap.add_argument("--json", type=Path, help="write the results here")
    args = ap.parse_args()
    torch.set_num_threads(2)
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.keep or Path(tmp)
        rows = [run_scene(scene(folder, args.seed + i, args.frames), AdaptConfig()) for i in range(args.scenes)]
    summary = {
        which: {
            "auc_mean": round(float(np.mean([r[which]["auc"] for r in rows])), 2),
            "over_50mm": int(sum(r[which]["over_50mm"] for r in rows)),
            "fused_error_mm_median": round(float(np.median([r[which]["fused_error_mm"] for r in rows])), 2),
        }
        for which in ("before", "fine_tuned", "kept")
    }
    summary["adaptation_seconds_max"] = max(r["adaptation"]["seconds_total"] for r in rows)
    print(json.dumps(summary, indent=1))
    if args.json:
        atomic.write_text(args.json, json.dumps({"summary": summary, "scenes": rows}, indent=1))


if __name__ == "__main__":
    sys.exit(run_reporting_errors(main, "benchmarks/adaptation.py"))
