"""Where along the line of sight does the fit settle? The signed error of the robot centroid's
distance from the camera (estimate minus truth: positive is further), in mm and as a share of
the distance, per DREAM folder:

* ``fit``: the default fit from scratch (``fitting.fit_pose``);
* from the true pose, the refinement (``fitting.refine_coarse_to_fine``, no local search) on
  the parser's view around it, term by term: the mask and keypoints alone, with the image's
  outline edges, with the inner edges too (the default), and the outline edges alone (mask
  and keypoints weighted 0, at the view's resolution only): where each term's fixed point lies;
* the outline edges alone on views whose pixels are replaced by a render of the robot at the
  true pose before a grey background: rendered at the view's resolution (the image is the
  fit's own render), supersampled 2x and area-averaged (antialiased, as a camera sees an edge),
  and blurred by ``BLUR_PX`` (a soft lens): how the edges' localisation depends on the image's
  sharpness, with nothing else wrong.

A bias is systematic where its mean is many standard errors from 0 and has one sign across
folders. Frames: the first ``--limit`` of each folder. The figures in docs/ACCURACY.md: the
README's held-out sets and two made for this with the training renderer,

    monose3 generate --out data/bias_reallike --num 40 --seed 45045 --profile reallike
    monose3 generate --out data/bias_hard --num 40 --seed 46046 --profile hard
    python benchmarks/depth_bias.py --data data/bias_reallike data/bias_hard data/reallike_tiny \
        data/hard_tiny --limit 40 --json docs/results/depth_bias.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from monose3 import atomic
from monose3.api import load_estimator
from monose3.data.datasets import open_dataset
from monose3.errors import run_reporting_errors
from monose3.perception import fitting
from monose3.perception.from_pose import view_around
from monose3.perception.views import ViewEvidence

BLUR_PX = 0.7
BACKGROUND = 0.35  # the grey behind the synthetic views' robot
REFINEMENTS = {  # name: (edges, inner edges, mask and keypoints weighted)
    "from truth: mask + keypoints": (False, False, True),
    "from truth: + outline edges": (True, False, True),
    "from truth: + inner edges (default)": (True, True, True),
    "from truth: outline edges alone": (True, False, False),
}
SYNTHETIC = ("render at view resolution", "render 2x, area-averaged", f"render blurred {BLUR_PX} px")


def centroid_distance_mm(estimator, frame, pose: np.ndarray) -> float:
    """How far (mm) ``pose`` puts the robot's centroid from the camera."""
    centroid = estimator.robot.centroid(estimator.robot.surface_points(frame.joints[None])[0])
    return 1000.0 * float(np.linalg.norm(pose[:3, :3] @ centroid + pose[:3, 3]))


def line_of_sight_mm(estimator, frame, pose: np.ndarray) -> float:
    """Estimated minus true distance (mm) of the robot's centroid from the camera."""
    if not np.isfinite(pose).all():
        return float("nan")
    return centroid_distance_mm(estimator, frame, pose) - centroid_distance_mm(estimator, frame, frame.pose)


def refined(estimator, frame, view: ViewEvidence, edges: bool, inner: bool, weighted: bool) -> np.ndarray:
    """The refinement from the true pose; ``weighted`` False leaves the outline edges alone, at
    the view's resolution only (the coarse pass reads the mask)."""
    kp_base = estimator.robot.keypoints(frame.joints[None])[0]
    args = (estimator.renderer, frame.joints, frame.pose[None])
    if weighted:
        return fitting.refine_coarse_to_fine(*args, view, kp_base, edges=edges, inner_edges=inner)[0]
    alone = dataclasses.replace(view, confidence=view.confidence * 0)
    return fitting.refine_poses(*args, alone, kp_base, edges=True, mask_share=0.0)[0]


def synthetic_views(estimator, frame, view: ViewEvidence) -> dict[str, ViewEvidence]:
    """``view`` with its pixels replaced by renders at the true pose (:data:`SYNTHETIC`)."""
    w, h = view.size

    def composed(K: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        out = estimator.renderer.render(frame.joints[None], frame.pose[None], K[None], size)
        rgb = out.rgb[0].permute(1, 2, 0).numpy() if out.rgb.shape[1] == 3 else out.rgb[0].numpy()
        return np.where(out.mask[0].numpy()[..., None], rgb, BACKGROUND).astype(np.float32)

    sharp = composed(view.K, (w, h))
    K2 = view.K.copy()
    K2[:2, :2] *= 2
    K2[:2, 2] = 2 * view.K[:2, 2] + 0.5  # pixel centres: u' = 2u + 0.5
    antialiased = cv2.resize(composed(K2, (2 * w, 2 * h)), (w, h), interpolation=cv2.INTER_AREA)
    blurred = cv2.GaussianBlur(sharp, (0, 0), BLUR_PX)
    images = (sharp, antialiased, blurred)
    return {name: dataclasses.replace(view, image=img) for name, img in zip(SYNTHETIC, images, strict=True)}


def measure_folder(estimator, folder: str, limit: int) -> dict:
    frames = open_dataset(folder, estimator.robot)
    errors: dict[str, list[float]] = {name: [] for name in ("fit", *REFINEMENTS, *SYNTHETIC)}
    distances = []
    for i in tqdm(range(min(limit, len(frames))), desc=Path(folder).name):
        frame = frames[i]
        image = frame.load_image()
        distances.append(centroid_distance_mm(estimator, frame, frame.pose))
        fit = fitting.fit_pose(estimator.parser, estimator.renderer, estimator.robot, image, frame.K, frame.joints)
        errors["fit"].append(line_of_sight_mm(estimator, frame, fit.pose))
        view = view_around(estimator.parser, estimator.robot, image, frame.K, frame.joints, frame.pose)
        for name, (edges, inner, weighted) in REFINEMENTS.items():
            pose = refined(estimator, frame, view, edges, inner, weighted)
            errors[name].append(line_of_sight_mm(estimator, frame, pose))
        for name, synthetic in synthetic_views(estimator, frame, view).items():
            pose = refined(estimator, frame, synthetic, True, False, False)
            errors[name].append(line_of_sight_mm(estimator, frame, pose))
    return summarise(errors, np.array(distances))


def summarise(errors: dict[str, list[float]], distances: np.ndarray) -> dict:
    out = {"frames": len(distances), "median_distance_m": float(np.median(distances) / 1000)}
    for name, values in errors.items():
        v = np.array(values)
        ok = np.isfinite(v) & (np.abs(v) < 100.0)  # a fit off by 10 cm in depth is a failure, not a bias
        share = 100 * v[ok] / distances[ok]
        out[name] = {"median_mm": float(np.median(v[ok])), "mean_mm": float(v[ok].mean()),
                     "standard_error_mm": float(v[ok].std() / np.sqrt(ok.sum())),
                     "median_share_percent": float(np.median(share)), "frames": int(ok.sum())}  # fmt: skip
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", nargs="+", required=True, help="DREAM folders (monose3 generate)")
    p.add_argument("--limit", type=int, default=40)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--json")
    args = p.parse_args(argv)

    def run() -> int:
        torch.set_num_threads(args.threads)
        estimator = load_estimator(device="cpu")
        results = {Path(d).name: measure_folder(estimator, d, args.limit) for d in args.data}
        for folder, r in results.items():
            print(f"{folder}: {r['frames']} frames, median distance {r['median_distance_m']:.2f} m")
            for name, s in r.items():
                if isinstance(s, dict):
                    print(f"  {name:>38}: median {s['median_mm']:+6.2f} mm ({s['median_share_percent']:+.3f} %), "
                          f"mean {s['mean_mm']:+6.2f} +- {s['standard_error_mm']:.2f} mm "
                          f"({s['frames']} frames)")  # fmt: skip
        if args.json:
            atomic.write_text(args.json, json.dumps(results, indent=1))
            print(f"wrote {args.json}")
        return 0

    return run_reporting_errors(run, "depth_bias")


if __name__ == "__main__":
    sys.exit(main())
