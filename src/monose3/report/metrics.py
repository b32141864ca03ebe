"""Pose-accuracy metrics computed the way DREAM and RoboPose compute them.

Numbers are only comparable with the published tables (the paper's Table I) if every
detail matches, so this module follows the reference evaluation code exactly:

* ADD of a frame is the mean over the keypoints of the 3D distance between the keypoints
  at the estimated pose and the annotated keypoints (meters).
* AUC uses the thresholds ``np.arange(0, 0.1, 1e-5)`` (10,000 values, 0.1 itself excluded),
  the fraction of *all* frames whose ADD is at most each threshold, the trapezoid integral
  with ``dx = 1e-5``, divided by 0.1 and reported x100. Because 0.1 is excluded, a perfect
  estimator scores 99.99, not 100 -- exactly as the reference code does.
* A failed estimate is an infinite ADD: it stays in the denominator of the AUC and of the
  "fraction under X mm" numbers, but is left out of the mean and median (and counted in
  ``out_of_view``), which is how DREAM reports mean/median over the frames it solved.
* ``failures`` are frames with ADD above ``FAILURE_MM`` (50 mm), out-of-view frames included:
  the meaning the README and the uncertainty study give the word.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from monose3.errors import Monose3Error

AUC_MAX_THRESHOLD = 0.1
AUC_STEP = 1e-5
UNDER_THRESHOLDS_MM = (10, 20, 40, 60)
# A frame whose ADD exceeds this (or that has no estimate in view) is a failure.
FAILURE_MM = 50.0


def add_per_frame(pred_keypoints: np.ndarray, gt_keypoints: np.ndarray) -> np.ndarray:
    """ADD of each frame: mean keypoint distance in meters, ``[N, K, 3] x [N, K, 3] -> [N]``.

    A frame whose prediction holds any NaN or infinite coordinate is a failed estimate and
    gets ``inf``, so it counts against the AUC instead of silently disappearing.
    """
    pred = np.asarray(pred_keypoints, dtype=np.float64)
    gt = np.asarray(gt_keypoints, dtype=np.float64)
    if pred.ndim == 2:
        pred = pred[None]
    if gt.ndim == 2:
        gt = gt[None]
    if pred.ndim != 3 or pred.shape[-1] != 3 or pred.shape != gt.shape:
        raise Monose3Error(
            "ADD needs predicted and ground-truth keypoints of the same shape [N, K, 3]; got "
            f"{tuple(np.shape(pred_keypoints))} and {tuple(np.shape(gt_keypoints))}: "
            "pass one row per frame and keypoint"
        )
    if pred.shape[1] == 0:
        raise Monose3Error("ADD needs at least one keypoint per frame; check the keypoint list of the robot")
    if not np.all(np.isfinite(gt)):
        raise Monose3Error(
            "ground-truth keypoints contain NaN or infinite values; fix or drop those frames of the dataset"
        )
    failed = ~np.all(np.isfinite(pred), axis=(1, 2))
    with np.errstate(invalid="ignore"):
        dist = np.linalg.norm(pred - gt, axis=-1).mean(axis=1)
    dist[failed] = np.inf
    return dist


def _as_adds(adds: Sequence[float] | np.ndarray) -> np.ndarray:
    """ADDs as a flat float array where every non-finite value (NaN, +-inf) is a failure (+inf)."""
    arr = np.asarray(adds, dtype=np.float64).reshape(-1)
    if arr.size == 0:
        raise Monose3Error("no ADD values to summarise: the evaluation produced no frames; check the dataset path")
    arr = np.where(np.isfinite(arr), arr, np.inf)
    if np.any(arr < 0):
        raise Monose3Error("ADD values must be non-negative distances in meters; got negative values")
    return arr


def auc(adds: Sequence[float] | np.ndarray, max_threshold: float = AUC_MAX_THRESHOLD, step: float = AUC_STEP) -> float:
    """Area under the ADD accuracy curve, x100, exactly as DREAM/RoboPose compute it.

    Thresholds are ``np.arange(0, max_threshold, step)``; at each the fraction of frames
    with ``ADD <= threshold`` (every frame in the denominator, failures never count); the
    trapezoid integral with ``dx = step`` is divided by ``max_threshold``.
    """
    if not (max_threshold > 0 and step > 0 and step < max_threshold):
        raise Monose3Error(f"AUC needs 0 < step < max_threshold, got step={step}, max_threshold={max_threshold}")
    arr = np.sort(_as_adds(adds))
    thresholds = np.arange(0.0, max_threshold, step)
    fraction = np.searchsorted(arr, thresholds, side="right") / arr.size
    return float(np.trapezoid(fraction, dx=step) / max_threshold * 100.0)


def auc_interval(adds: Sequence[float] | np.ndarray, level: float = 0.95, resamples: int = 2000,
                 seed: int = 0) -> tuple[float, float]:  # fmt: skip
    """A percentile bootstrap interval of :func:`auc` over the frames (resampled with
    replacement ``resamples`` times): how much the AUC of another draw of as many frames may differ."""
    arr = _as_adds(adds)
    rng = np.random.default_rng(seed)
    draws = [auc(arr[rng.integers(0, arr.size, arr.size)]) for _ in range(resamples)]
    tail = 100 * (1 - level) / 2
    return float(np.percentile(draws, tail)), float(np.percentile(draws, 100 - tail))


def summarize(adds: Sequence[float] | np.ndarray, fps: float | None = None) -> dict[str, float]:
    """The numbers of a results table for one dataset.

    Keys: ``n`` (frames), ``auc`` (x100), ``mean`` / ``median`` / ``std`` (meters, over the
    finite ADDs only; NaN if none), ``failures`` (ADD > ``FAILURE_MM`` or no estimate),
    ``out_of_view`` (frames with non-finite ADD, excluded from
    mean/median but counted everywhere else), ``under_10mm`` ... ``under_60mm`` (fraction of
    all frames with ADD <= that threshold) and ``fps`` when given.
    """
    arr = _as_adds(adds)
    finite = arr[np.isfinite(arr)]
    out: dict[str, float] = {
        "n": int(arr.size),
        "auc": auc(arr),
        "mean": float(finite.mean()) if finite.size else math.nan,
        "median": float(np.median(finite)) if finite.size else math.nan,
        "std": float(finite.std()) if finite.size else math.nan,
        "failures": int(np.sum(~(arr <= FAILURE_MM / 1000.0))),
        "out_of_view": int(arr.size - finite.size),
    }
    for mm in UNDER_THRESHOLDS_MM:
        out[f"under_{mm}mm"] = float(np.mean(arr <= mm / 1000.0))
    if fps is not None:
        out["fps"] = float(fps)
    return out


def _fmt(value: float | None, spec: str) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return format(value, spec)


def format_table(rows: Mapping[str, Mapping[str, float]]) -> str:
    """A Table-I-style plain-text table, one line per dataset (or method) from ``summarize``.

    Columns: frames, AUC, mean and median ADD in meters, percentage of frames under
    10/20/40/60 mm, failures (ADD > 50 mm), out-of-view frames, and FPS when any row has it.
    """
    with_fps = any("fps" in r for r in rows.values())
    header = ["dataset", "n", "AUC", "mean ADD (m)", "median (m)"]
    header += [f"<{mm}mm %" for mm in UNDER_THRESHOLDS_MM] + [f"failures >{FAILURE_MM:g}mm", "out of view"]
    if with_fps:
        header.append("FPS")
    lines = [header]
    for name, r in rows.items():
        line = [
            str(name),
            str(int(r.get("n", 0))),
            _fmt(r.get("auc"), ".2f"),
            _fmt(r.get("mean"), ".4f"),
            _fmt(r.get("median"), ".4f"),
        ]
        for mm in UNDER_THRESHOLDS_MM:
            frac = r.get(f"under_{mm}mm")
            line.append(_fmt(None if frac is None else 100.0 * frac, ".1f"))
        line.append(str(int(r.get("failures", 0))))
        line.append(str(int(r.get("out_of_view", 0))))
        if with_fps:
            line.append(_fmt(r.get("fps"), ".2f"))
        lines.append(line)
    widths = [max(len(row[i]) for row in lines) for i in range(len(header))]

    def render(row: list[str]) -> str:
        cells = [row[0].ljust(widths[0])] + [c.rjust(w) for c, w in zip(row[1:], widths[1:], strict=True)]
        return "  ".join(cells).rstrip()

    rule = "-" * len(render(header))
    return "\n".join([render(header), rule, *(render(row) for row in lines[1:])])
