"""``monose3 evaluate``: ADD / AUC on DREAM and RoboKeyGen data (Table I style), per-frame
JSON, the ADD distribution plot (Fig. 4) and denoising-step overlays (Fig. 3b).

Frames stream through in small batches, so memory stays flat however many frames there are.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from monose3.estimator import PoseEstimator
from monose3.metrics import add_per_frame, format_table, summarize
from monose3.robot.renderer import RenderJob
from monose3.viz import denoising_strip, plot_add_distribution


@dataclass
class DatasetResult:
    name: str
    adds: list[float] = field(default_factory=list)
    frames: list[dict] = field(default_factory=list)
    seconds: float = 0.0

    def summary(self) -> dict:
        fps = len(self.adds) / self.seconds if self.seconds > 0 else None
        return summarize(np.asarray(self.adds), fps=fps)


def _batches(n: int, size: int, limit: int | None) -> list[range]:
    n = n if limit is None else min(n, limit)
    return [range(i, min(i + size, n)) for i in range(0, n, size)]


def evaluate_dataset(
    estimator: PoseEstimator,
    frames: Sequence,
    name: str,
    sampler: str = "revdiff",
    ddim_steps: int | None = None,
    direct_steps: int | None = None,
    batch_size: int = 4,
    limit: int | None = None,
    overlay_frames: Sequence[int] = (),
    overlay_dir: Path | None = None,
    tracking: bool = False,
    progress: bool = True,
) -> DatasetResult:
    """ADD of every frame; failures (estimate out of view) count as infinite ADD.

    ``tracking``: frames are a sequence; the first gets the full reverse process, each next
    one a single step from the previous estimate (batch size 1).
    """
    result = DatasetResult(name)
    previous = None
    batches = _batches(len(frames), 1 if tracking else batch_size, limit)
    for idx in tqdm(batches, desc=f"evaluate {name}", unit="batch", disable=not progress):
        batch = [frames[i] for i in idx]
        images = [f.load_image() for f in batch]
        Ks = np.stack([f.K for f in batch])
        joints = np.stack([f.joints for f in batch])
        tick = time.perf_counter()
        if tracking and previous is not None:
            est = estimator.track(images, Ks, joints, previous)
        else:
            est = estimator.estimate(
                images, Ks, joints, sampler=sampler, ddim_steps=ddim_steps, direct_steps=direct_steps
            )
        result.seconds += time.perf_counter() - tick
        previous = est.poses if est.in_view.all() else None
        pred = estimator.robot.keypoints(joints, est.poses)
        gt = np.stack([f.keypoints_3d for f in batch])
        adds = add_per_frame(pred, gt)
        adds[~est.in_view] = np.inf
        for j, frame in enumerate(batch):
            result.adds.append(float(adds[j]))
            result.frames.append(
                {
                    "frame": frame.name,
                    "add_m": float(adds[j]) if np.isfinite(adds[j]) else None,
                    "camera_from_base": est.poses[j].tolist(),
                    "in_view": bool(est.in_view[j]),
                }
            )
        for j, i in enumerate(idx):
            if i in overlay_frames and overlay_dir is not None:
                _denoising_overlay(
                    estimator,
                    images[j],
                    Ks[j],
                    joints[j],
                    [h[j, 0] for h in est.history],
                    overlay_dir / f"{name}_{frame_label(batch[j])}.png",
                )
    return result


def frame_label(frame) -> str:
    return str(frame.name).replace("/", "_")


def _denoising_overlay(estimator: PoseEstimator, image, K, joints, poses, path: Path) -> None:
    """Overlays of the render on the image at each denoising step (paper's Fig. 3b)."""
    h, w = image.shape[:2]
    masks = [mask for _, mask in estimator.renderer.render_jobs([RenderJob(joints, p, K, (w, h)) for p in poses])]
    labels = ["init"] + [f"step {i}" for i in range(1, len(poses))]
    denoising_strip(image, masks, labels, path)


def write_json(results: Sequence[DatasetResult], path: Path, meta: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    data = {"meta": meta, "datasets": {r.name: {"summary": r.summary(), "frames": r.frames} for r in results}}
    path.write_text(json.dumps(data, indent=1, default=float))


def add_evaluate_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", nargs="+", required=True, help="DREAM folders or RoboKeyGen sequences")
    p.add_argument("--checkpoint", help="model checkpoint (default: the bundled Panda model)")
    p.add_argument("--sampler", choices=["revdiff", "directreg", "tracking"], default="revdiff")
    p.add_argument("--steps", type=int, nargs=2, metavar=("K", "M"), help="DDIM steps and direct steps (default 5 5)")
    p.add_argument("--batch-size", type=int, default=4)
    p.add_argument("--limit", type=int, help="evaluate only the first N frames of each dataset")
    p.add_argument("--json", help="write per-frame ADD and poses here")
    p.add_argument("--plot", help="write the ADD distribution plot (PNG) here")
    p.add_argument("--overlays", help="folder for denoising-step overlays of --overlay-frames")
    p.add_argument("--overlay-frames", type=int, nargs="*", default=[0], help="frame indices to draw (default 0)")


def run_evaluate(args: argparse.Namespace) -> int:
    from monose3.api import load_estimator
    from monose3.dream import open_dataset

    estimator = load_estimator(args.checkpoint)
    k, m = args.steps if args.steps else (None, None)
    results = []
    try:
        for d in args.data:
            frames = open_dataset(d, estimator.robot)
            results.append(
                evaluate_dataset(
                    estimator,
                    frames,
                    Path(d).name,
                    sampler="revdiff" if args.sampler == "tracking" else args.sampler,
                    ddim_steps=k,
                    direct_steps=m,
                    batch_size=args.batch_size,
                    limit=args.limit,
                    overlay_frames=args.overlay_frames if args.overlays else (),
                    overlay_dir=Path(args.overlays) if args.overlays else None,
                    tracking=args.sampler == "tracking",
                )
            )
    finally:
        estimator.close()
    print(format_table({r.name: r.summary() for r in results}))
    if args.json:
        write_json(
            results,
            Path(args.json),
            {"sampler": args.sampler, "steps": args.steps, "checkpoint": str(args.checkpoint or "bundled")},
        )
        print(f"wrote {args.json}")
    if args.plot:
        plot_add_distribution({r.name: np.asarray(r.adds) for r in results}, args.plot)
        print(f"wrote {args.plot}")
    return 0
