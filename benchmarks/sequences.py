"""Tracking on sequences: does the policy hold a track, never trade it for a worse re-estimate,
flag its bad frames, and (``--static-camera``) converge to one camera pose?

Sequences are made for this run (``monose3 generate --sequence``) from seeds 51000 on, which
no choice of the policy looked at (its development used seeds 31000-31003, the tracked flag's
choice 41000-41007): by default one each of a static camera on a ``reallike`` and on a ``hard`` scene
and a slowly orbiting camera on each, ``--frames`` long. Each goes through

* ``track``: the default policy (``monose3 track``);
* ``static``: ``--static-camera --refine-at-end`` (static-camera sequences only);
* ``single``: the full estimate of every ``--single-every``-th frame alone (the reference;
  ``track``'s median on the same frames is given as a ratio to it).

Per run: median ADD, frames off by more than 50 mm (for ``static``: also after the fused pose
converged, and the frame it converged at), re-estimates that replaced the track and left the
frame worse than the track would have been (by more than ``WORSE_MM``), the per-frame flag's
recall of frames off by more than 30 mm and its false alarms, and the time: tracked frames per
second (frames that ran no full estimate) and where a frame's time goes (track, judge, full).

    python benchmarks/sequences.py --json docs/results/sequences.json
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

from monose3 import atomic
from monose3.api import load_estimator
from monose3.data.datasets import open_dataset
from monose3.data.scenes.sequences import SequenceConfig, write_sequence
from monose3.errors import run_reporting_errors
from monose3.report.metrics import add_per_frame
from monose3.tracking import MODE_FUSED, Tracker, TrackingPolicy

KINDS = (("static", "reallike"), ("static", "hard"), ("moving", "reallike"), ("moving", "hard"))
WORSE_MM = 5.0  # a re-estimate that leaves the frame this much further than the track "made it worse"
BAD_MM = 30.0  # what the flag should catch
FAILURE_MM = 50.0


def add_mm(estimator, frame, pose: np.ndarray | None) -> float:
    if pose is None or not np.isfinite(pose).all():
        return float("inf")
    pred = estimator.robot.keypoints(frame.joints[None], pose[None])
    return 1000.0 * float(add_per_frame(pred, frame.keypoints_3d[None])[0])


class Timed:
    """The estimator with the seconds of its track, judge and full-estimate calls counted per frame."""

    def __init__(self, estimator):
        self.inner, self.robot, self.seconds = estimator, estimator.robot, defaultdict(float)

    def _timed(self, name: str, *args, **kwargs):
        tick = time.perf_counter()
        try:
            return getattr(self.inner, name)(*args, **kwargs)
        finally:
            self.seconds[name] += time.perf_counter() - tick

    def estimate(self, *args, **kwargs):
        return self._timed("estimate", *args, **kwargs)

    def track(self, *args, **kwargs):
        return self._timed("track", *args, **kwargs)

    def judge(self, *args, **kwargs):
        return self._timed("judge", *args, **kwargs)


def run_tracking(estimator, frames: list, policy: TrackingPolicy) -> list[dict]:
    """Every frame through one :class:`Tracker`: its ADD, the not-chosen candidate's, the flag, the time."""
    timed = Timed(estimator)
    tracker = Tracker(timed, policy)
    rows = []
    for frame in frames:
        image = frame.load_image()
        timed.seconds.clear()
        tick = time.perf_counter()
        step = tracker.update(image, frame.K, frame.joints)
        rows.append({
            "add_mm": add_mm(estimator, frame, step.camera_from_base if step.in_view else None),
            "alternative_mm": None if step.alternative is None else add_mm(estimator, frame, step.alternative),
            "mode": step.mode, "reason": step.reason, "decision": step.decision, "reliable": step.reliable,
            "converged": step.converged, "seconds": time.perf_counter() - tick, "split": dict(timed.seconds),
        })  # fmt: skip
    if policy.static_camera and tracker.fusion.converged:  # --refine-at-end: earlier frames get the final fused pose
        for frame, row in zip(frames, rows, strict=True):
            if row["mode"] != MODE_FUSED:
                row["add_mm"], row["reliable"] = add_mm(estimator, frame, tracker.fusion.pose), True
    return rows


def run_single(estimator, frames: list, every: int) -> list[dict]:
    rows = []
    for frame in frames[::every]:
        tick = time.perf_counter()
        est = estimator.estimate([frame.load_image()], frame.K[None], frame.joints[None])
        pose = est.poses[0] if est.in_view[0] else None
        rows.append({"add_mm": add_mm(estimator, frame, pose), "reliable": bool(est.reliable[0]),
                     "seconds": time.perf_counter() - tick})  # fmt: skip
    return rows


def summarise(rows: list[dict]) -> dict:
    adds = np.array([r["add_mm"] for r in rows])
    flagged = np.array([r["reliable"] is False for r in rows])
    bad = ~(adds <= BAD_MM)
    out = {"frames": len(rows), "median_add_mm": float(np.median(adds)),
           "over_50mm": int((~(adds <= FAILURE_MM)).sum()), "bad": int(bad.sum()),
           "caught": int((bad & flagged).sum()), "false_alarms": int((~bad & flagged).sum()),
           "good": int((~bad).sum())}  # fmt: skip
    if rows and "mode" in rows[0]:
        replaced = [r for r in rows if r["reason"] is not None and r["decision"] is None and r["alternative_mm"]]
        out["reestimates"] = sum(r["reason"] is not None for r in rows)
        out["replaced_track"] = len(replaced)
        out["made_worse"] = sum(r["add_mm"] > r["alternative_mm"] + WORSE_MM for r in replaced)
        tracked = [r for r in rows if r["reason"] is None]
        out["tracked_fps"] = len(tracked) / max(sum(r["seconds"] for r in tracked), 1e-9)
        out["split_s"] = {
            k: float(np.mean([r["split"].get(k, 0.0) for r in rows])) for k in ("track", "judge", "estimate")
        }
        converged = [i for i, r in enumerate(rows) if r["converged"]]
        if converged:
            after = adds[converged[0] :]
            out["converged_at"] = converged[0]
            out["over_50mm_after_convergence"] = int((~(after <= FAILURE_MM)).sum())
    return out


def same_frames_ratio(track_rows: list[dict], single: dict, every: int) -> float:
    """The track's median ADD on the single-frame reference's frames over the reference's."""
    return float(np.median([r["add_mm"] for r in track_rows[::every]]) / single["median_add_mm"])


def fmt(s: dict) -> str:
    line = (f"median {s['median_add_mm']:6.1f} mm, >50 mm {s['over_50mm']:2d}/{s['frames']}, "
            f"flag {s['caught']}/{s['bad']} caught, {s['false_alarms']}/{s['good']} false alarms")  # fmt: skip
    if "reestimates" in s:
        line += (f", re-estimates {s['reestimates']} (replaced the track {s['replaced_track']}, made worse "
                 f"{s['made_worse']}), {s['tracked_fps']:.1f} tracked frames/s")  # fmt: skip
    if "ratio_to_single" in s:
        line += f", median {s['ratio_to_single']:.2f}x the single frames' on their frames"
    if "converged_at" in s:
        line += f", converged at frame {s['converged_at']} (>50 mm after: {s['over_50mm_after_convergence']})"
    return line


def main(argv: list[str] | None = None) -> int:
    return run_reporting_errors(lambda: run(argv), "sequences")


def run(argv: list[str] | None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sequences", type=int, default=len(KINDS), help="sequences (cycling through the kinds)")
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--seed", type=int, default=51000, help="first sequence's seed (the next ones count up)")
    p.add_argument("--single-every", type=int, default=3, help="the single-frame reference on every N-th frame")
    p.add_argument(
        "--renderer", default="torch", help="torch, or tiny for pybullet's (another renderer than training's)"
    )
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--json", type=Path, help="write the per-sequence figures here")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    estimator = load_estimator()
    results = {}
    with tempfile.TemporaryDirectory(prefix="monose3_sequences_") as tmp:
        for i in range(args.sequences):
            camera, profile = KINDS[i % len(KINDS)]
            seed = args.seed + i
            folder = write_sequence(Path(tmp) / f"seq{i}", SequenceConfig(args.frames, camera), seed,
                                    profile=profile, backend=args.renderer)  # fmt: skip
            low = json.loads((folder / "_sequence.json").read_text())["low_contrast"]
            frames = list(open_dataset(folder, estimator.robot))
            name = f"{camera} {profile} seed {seed}" + (" (low contrast)" if low else "")
            track_rows = run_tracking(estimator, frames, TrackingPolicy())
            runs = {"track": summarise(track_rows)}
            if camera == "static":
                runs["static"] = summarise(run_tracking(estimator, frames, TrackingPolicy(static_camera=True)))
            runs["single"] = summarise(run_single(estimator, frames, args.single_every))
            runs["track"]["ratio_to_single"] = same_frames_ratio(track_rows, runs["single"], args.single_every)
            results[name] = runs
            print(name)
            for run, s in runs.items():
                print(f"  {run:>6}: {fmt(s)}")
            sys.stdout.flush()
    estimator.close()
    if args.json:
        atomic.write_text(args.json, json.dumps(results, indent=1))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
