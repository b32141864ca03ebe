"""Does the chains' spread tell a wrong estimate from a good one? (the ``reliable`` flag of
``monose3 estimate`` / :class:`monose3.api.PoseResult`).

For every frame, ``--chains`` stochastic reverse chains run from perturbed initialisations (as
``api.estimate_pose`` does: ``PoseEstimator.estimate(hypotheses=chains, stochastic=True)``); the
chosen pose is the chains' medoid and its spread is the mean keypoint distance (mm) and rotation
angle (deg) of the chains to it. Each frame's ADD is measured for the chosen pose against the
annotated keypoints (``metrics.add_per_frame``).

* failure: ADD > 5 cm, or the estimate puts the robot out of view (``api.estimate_pose`` raises
  then, so an out-of-view frame never reaches the user as a pose: it is "caught" by the error);
* flagged: in view and ``spread_mm > threshold`` (``api.UNRELIABLE_MM`` is the shipped threshold);
* recall: the fraction of failures caught (flag, or flag + out-of-view error); false-alarm rate:
  the fraction of good frames (in view, ADD <= 5 cm) that are flagged;
* kept: in view and not flagged -- the frames a user would trust; their AUC (metrics.auc, over the
  kept frames only) and mean ADD against those of all frames say what trusting the flag buys.

``--prior M DEG`` measures the flag where the estimator starts from a user's approximate pose
(``monose3 estimate --prior``): each frame's prior is its ground truth moved by Gaussian noise
of M metres and DEG degrees per axis (``se3.perturb_poses_np``), and the chains refine it from
``InferenceConfig.prior_t``. A model that gets no frame right from RoboPose's start still gets
some right from a prior, so this is where false alarms can be counted.

The same numbers over a sweep of thresholds give the table and the recall / false-alarm curve;
the recommended threshold is the one with the highest recall whose false-alarm rate stays at or
under ``--max-false-alarm`` (a flag that fires on many good frames gets ignored), and the
threshold maximising recall - false-alarm (Youden's J) is printed next to it.

    python benchmarks/uncertainty.py --checkpoint CK --data data/test_reallike data/test_hard \
        [--limit 60] [--chains 4] [--prior 0.03 6] [--plot docs/results/uncertainty.png]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

from monose3.api import UNRELIABLE_MM, load_estimator, prior_arguments
from monose3.data.datasets import open_dataset
from monose3.errors import run_reporting_errors
from monose3.geometry.poses import perturb_poses
from monose3.report.metrics import add_per_frame, auc
from monose3.report.plots import new_figure, save_figure
from monose3.training.checkpoints import read_checkpoint

ROOT = Path(__file__).resolve().parents[1]
FAILURE_M = 0.05
SWEEP_MM = (5, 10, 15, 20, 25, 30, 40, 50, 60, 80, 100, 150, 200, 300)
MAX_FALSE_ALARM = 0.10


# ---- measuring --------------------------------------------------------------------------------


def measure(
    estimator,
    folder: str | Path,
    limit: int | None,
    chains: int,
    batch_size: int,
    seed: int,
    prior_error: tuple[float, float] | None = None,
) -> dict:
    """Per-frame ADD (m; inf when out of view), chain spread (mm, deg) and in-view flag of one
    set; with ``prior_error`` (m, deg per axis) also the ADD of each frame's prior."""
    ds = open_dataset(folder, estimator.robot)
    n = len(ds) if limit is None else min(limit, len(ds))
    rng = np.random.default_rng(seed)
    adds, prior_adds, spread_mm, spread_deg, in_view, names = [], [], [], [], [], []
    for b, start in enumerate(range(0, n, batch_size)):
        frames = [ds[i] for i in range(start, min(start + batch_size, n))]
        joints = np.stack([f.joints for f in frames])
        truth = np.stack([f.keypoints_3d for f in frames])
        priors = None
        if prior_error is not None:
            priors = perturb_poses(np.stack([f.pose for f in frames]), rng, *prior_error)
            prior_adds.append(add_per_frame(estimator.robot.keypoints(joints, priors), truth))
        est = estimator.estimate(
            [f.load_image() for f in frames],
            np.stack([f.K for f in frames]),
            joints,
            sampler="revdiff",  # the chains' spread is this benchmark's subject (the fit's flag: accuracy.py)
            hypotheses=chains,
            stochastic=chains > 1,
            seed=seed + b,
            **prior_arguments(estimator, priors),
        )
        pred = estimator.robot.keypoints(joints, est.poses)
        pred[~est.in_view] = np.nan  # out of view: a failed estimate (infinite ADD)
        adds.append(add_per_frame(pred, truth))
        spread_mm.append(est.spread_mm)
        spread_deg.append(est.spread_deg)
        in_view.append(est.in_view.astype(bool))
        names += [f.name for f in frames]
        done = start + len(frames)
        print(f"  {Path(folder).name}: {done}/{n} frames", file=sys.stderr, end="\r" if done < n else "\n")
    return {
        "names": names,
        "add": np.concatenate(adds),
        "spread_mm": np.concatenate(spread_mm),
        "spread_deg": np.concatenate(spread_deg),
        "in_view": np.concatenate(in_view),
        "prior_add": np.concatenate(prior_adds) if prior_adds else None,
    }


def pool(sets: dict[str, dict]) -> dict:
    first = next(iter(sets.values()))
    keys = [k for k in first if k != "names"]
    return {k: None if first[k] is None else np.concatenate([s[k] for s in sets.values()]) for k in keys}


# ---- statistics -------------------------------------------------------------------------------


def flag_stats(data: dict, threshold_mm: float) -> dict:
    """Recall, false alarms and what the kept frames score for one threshold."""
    add, spread, view = data["add"], data["spread_mm"], data["in_view"]
    fail = ~(add <= FAILURE_M)  # inf (out of view) counts as a failure
    flagged = view & (spread > threshold_mm)
    caught = flagged | ~view
    good = ~fail
    kept = view & ~flagged
    n_fail, n_good, n_fail_view = int(fail.sum()), int(good.sum()), int((fail & view).sum())
    kept_add = add[kept]
    return {
        "threshold_mm": float(threshold_mm),
        "failures": n_fail,
        "good": n_good,
        "flagged": int(flagged.sum()),
        "recall_flag": _ratio((flagged & fail).sum(), n_fail),
        "recall_flag_in_view": _ratio((flagged & fail).sum(), n_fail_view),
        "recall_caught": _ratio((caught & fail).sum(), n_fail),
        "false_alarm": _ratio((flagged & good).sum(), n_good),
        "precision": _ratio((flagged & fail).sum(), flagged.sum()),
        "kept": int(kept.sum()),
        "kept_fraction": _ratio(kept.sum(), len(add)),
        "kept_failures": int((kept & fail).sum()),
        "kept_auc": auc(kept_add) if kept_add.size else float("nan"),
        "kept_mean_mm": 1000 * float(kept_add[np.isfinite(kept_add)].mean()) if kept_add.size else float("nan"),
    }


def overall(data: dict) -> dict:
    add = data["add"]
    finite = add[np.isfinite(add)]
    return {
        "n": len(add),
        "out_of_view": int((~data["in_view"]).sum()),
        "failures": int((~(add <= FAILURE_M)).sum()),
        "auc": auc(add),
        "mean_mm": 1000 * float(finite.mean()) if finite.size else float("nan"),
        "median_mm": 1000 * float(np.median(finite)) if finite.size else float("nan"),
        "auroc_mm": auroc(data["spread_mm"][data["in_view"]], ~(add[data["in_view"]] <= FAILURE_M)),
        "auroc_deg": auroc(data["spread_deg"][data["in_view"]], ~(add[data["in_view"]] <= FAILURE_M)),
        "spearman": spearman(data["spread_mm"][data["in_view"]], add[data["in_view"]]),
    }


def auroc(score: np.ndarray, positive: np.ndarray) -> float:
    """Probability that a failure has a larger spread than a good frame (ties count half):
    how well the spread ranks failures above good frames whatever the threshold (0.5 = chance)."""
    pos, neg = score[positive], score[~positive]
    if not len(pos) or not len(neg):
        return float("nan")
    greater = (pos[:, None] > neg[None, :]).sum() + 0.5 * (pos[:, None] == neg[None, :]).sum()
    return float(greater / (len(pos) * len(neg)))


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    """Rank correlation of spread and ADD over the in-view frames."""
    if len(a) < 3:
        return float("nan")
    ra, rb = np.argsort(np.argsort(a)), np.argsort(np.argsort(b))
    return float(np.corrcoef(ra, rb)[0, 1])


def _ratio(num: float, den: float) -> float:
    return float(num) / float(den) if den else float("nan")


def recommend(rows: list[dict], max_false_alarm: float) -> tuple[dict | None, dict | None]:
    """(highest-recall threshold with false alarms <= the limit, Youden-optimal threshold)."""
    ok = [r for r in rows if np.isfinite(r["false_alarm"]) and r["false_alarm"] <= max_false_alarm]
    # ties: the fewest false alarms, then the lowest threshold reaching them
    best = max(ok, key=lambda r: (r["recall_flag"], -r["false_alarm"], -r["threshold_mm"])) if ok else None
    scored = [r for r in rows if np.isfinite(r["recall_flag"]) and np.isfinite(r["false_alarm"])]
    youden = max(scored, key=lambda r: (r["recall_flag"] - r["false_alarm"], r["threshold_mm"])) if scored else None
    return best, youden


# ---- report -----------------------------------------------------------------------------------


def _pct(v: float) -> str:
    return "   -" if not np.isfinite(v) else f"{100 * v:5.1f}"


def _num(v: float, spec: str = "6.1f") -> str:
    width = spec.split(".")[0]
    return format(v, spec) if np.isfinite(v) else "-".rjust(int(width) if width else 1)


def _prior_line(data: dict) -> list[str]:
    if data.get("prior_add") is None:
        return []
    prior = data["prior_add"]
    return [
        f"the priors themselves: AUC {auc(prior):.2f}, mean ADD {1000 * prior.mean():.1f} mm, "
        f"{int((prior <= FAILURE_M).sum())} within {1000 * FAILURE_M:.0f} mm"
    ]


def table(data: dict, thresholds: list[float]) -> list[str]:
    lines = [
        f"{'thr mm':>7} {'flagged':>7} {'recall':>7} {'rec(inview)':>11} {'+oov err':>8} {'false al':>8} "
        f"{'precis':>7} {'kept':>5} {'kept fail':>9} {'kept AUC':>8} {'kept mean mm':>12}"
    ]
    for thr in thresholds:
        r = flag_stats(data, thr)
        mark = " <- api.UNRELIABLE_MM" if thr == UNRELIABLE_MM else ""
        lines.append(
            f"{thr:>7.0f} {r['flagged']:>7} {_pct(r['recall_flag']):>7} {_pct(r['recall_flag_in_view']):>11} "
            f"{_pct(r['recall_caught']):>8} {_pct(r['false_alarm']):>8} {_pct(r['precision']):>7} {r['kept']:>5} "
            f"{r['kept_failures']:>9} {_num(r['kept_auc'], '8.2f')} {_num(r['kept_mean_mm'], '12.1f')}{mark}"
        )
    return lines


def start_label(prior_error: tuple[float, float] | None, prior_t: int) -> str:
    if prior_error is None:
        return "start: RoboPose's initialisation"
    m, deg = prior_error
    return (
        f"start: a prior = ground truth moved by {1000 * m:.0f} mm and {deg:g} deg per axis, refined from t = {prior_t}"
    )


def report(
    sets: dict[str, dict], chains: int, checkpoint: str, step: int | None, max_false_alarm: float, start: str
) -> str:
    thresholds = sorted({*SWEEP_MM, UNRELIABLE_MM})
    groups = dict(sets)
    if len(sets) > 1:
        groups["all"] = pool(sets)
    lines = [
        f"Uncertainty flag: {chains} stochastic chains per frame, checkpoint {checkpoint}"
        + (f" (step {step})" if step is not None else ""),
        start,
        f"failure = ADD > {1000 * FAILURE_M:.0f} mm or out of view; flagged = in view and spread > threshold; "
        "recall = failures flagged / failures (rec(inview): over in-view failures; +oov err: flag or the "
        "out-of-view error of api.estimate_pose); false al = good frames flagged / good frames; "
        "kept = in view and not flagged",
        "",
    ]
    for name, data in groups.items():
        o = overall(data)
        s = flag_stats(data, UNRELIABLE_MM)
        lines += [
            f"== {name}: {o['n']} frames, {o['failures']} failures ({o['out_of_view']} out of view), "
            f"{o['n'] - o['failures']} good",
            f"all frames: AUC {o['auc']:.2f}, mean ADD {_num(o['mean_mm'], '.1f')} mm, median "
            f"{_num(o['median_mm'], '.1f')} mm (over in-view frames)",
            *_prior_line(data),
            f"at api.UNRELIABLE_MM = {UNRELIABLE_MM:.0f} mm: recall {_pct(s['recall_flag']).strip()} % "
            f"({_pct(s['recall_caught']).strip()} % with the out-of-view error), false alarms "
            f"{_pct(s['false_alarm']).strip()} %; kept {s['kept']} frames: AUC {_num(s['kept_auc'], '.2f')} "
            f"(all: {o['auc']:.2f}), mean ADD {_num(s['kept_mean_mm'], '.1f')} mm (all: {_num(o['mean_mm'], '.1f')})",
            f"spread as a failure score (in-view frames): AUROC {_num(o['auroc_mm'], '.3f')} (mm), "
            f"{_num(o['auroc_deg'], '.3f')} (deg); Spearman(spread mm, ADD) {_num(o['spearman'], '.3f')}",
            *table(data, thresholds),
            "",
        ]
    pooled = groups["all"] if "all" in groups else next(iter(groups.values()))
    best, youden = recommend([flag_stats(pooled, t) for t in thresholds], max_false_alarm)
    where = "all sets pooled" if len(sets) > 1 else next(iter(sets))
    n_good = int((pooled["add"] <= FAILURE_M).sum())
    n_fail = len(pooled["add"]) - n_good
    if n_good == 0 or n_fail == 0:
        lines.append(
            f"Recommendation ({where}): none possible -- {n_good} good and {n_fail} failed frames; the flag can "
            "only be tuned on a model that gets some frames right and some wrong (keep UNRELIABLE_MM as it is)"
        )
    elif best is not None:
        lines.append(
            f"Recommendation ({where}): UNRELIABLE_MM = {best['threshold_mm']:.0f} mm -- the highest recall "
            f"({_pct(best['recall_flag']).strip()} %) with false alarms <= {100 * max_false_alarm:.0f} % "
            f"({_pct(best['false_alarm']).strip()} %); kept AUC {_num(best['kept_auc'], '.2f')} "
            f"(current {UNRELIABLE_MM:.0f} mm: recall {_pct(flag_stats(pooled, UNRELIABLE_MM)['recall_flag']).strip()}"
            f" %, false alarms {_pct(flag_stats(pooled, UNRELIABLE_MM)['false_alarm']).strip()} %)"
        )
    else:
        lines.append(f"Recommendation ({where}): no threshold keeps false alarms <= {100 * max_false_alarm:.0f} %")
    if youden is not None and n_good and n_fail:
        lines.append(
            f"Youden-optimal (max recall - false alarms): {youden['threshold_mm']:.0f} mm "
            f"(recall {_pct(youden['recall_flag']).strip()} %, false alarms {_pct(youden['false_alarm']).strip()} %)"
        )
    if n_good < 20 or n_fail < 20:
        lines.append(
            f"caution: only {n_good} good and {n_fail} failed frames; the rates above are "
            "coarse (one frame moves them by several %)"
        )
    return "\n".join(lines)


def threshold_grid(data: dict) -> np.ndarray:
    """Thresholds for the curve: log-spaced over the observed spreads."""
    s = data["spread_mm"][data["in_view"] & np.isfinite(data["spread_mm"])]
    lo = min(SWEEP_MM[0], max(1.0, float(s.min()) * 0.8)) if s.size else 1.0
    hi = max(lo * 2, float(s.max()) * 1.2) if s.size else 1000.0
    return np.round(np.geomspace(lo, hi, 60), 1)


# ---- plot -------------------------------------------------------------------------------------


def plot(
    sets: dict[str, dict], path: Path, chains: int, step: int | None, recommended: float | None, start: str
) -> Path:
    from matplotlib.ticker import FuncFormatter, NullFormatter

    fig = new_figure((12, 5))
    ax1, ax2 = fig.subplots(1, 2)
    colors = ["tab:blue", "tab:orange", "tab:green", "tab:purple"]
    finite = np.concatenate([d["add"][np.isfinite(d["add"])] for d in sets.values()])
    top = 1000 * 1.6 * max(float(finite.max()) if finite.size else FAILURE_M, 2 * FAILURE_M)
    for (name, data), c in zip(sets.items(), colors, strict=False):
        view = data["in_view"]
        add_mm = 1000 * data["add"][view]
        spread = np.maximum(data["spread_mm"][view], 0.1)
        ax1.scatter(spread, np.maximum(add_mm, 0.1), s=14, alpha=0.7, color=c, label=f"{name} ({view.sum()} in view)")
        oov = ~view
        if oov.any():  # out-of-view frames have no ADD: drawn along the top at their spread
            ax1.scatter(
                np.maximum(data["spread_mm"][oov], 0.1),
                np.full(oov.sum(), top),
                marker="x",
                color=c,
                s=24,
                label=f"{name}: out of view ({oov.sum()}, drawn at top)",
            )
    ax1.set_xscale("log")
    ax1.set_yscale("log")
    ax1.axvline(UNRELIABLE_MM, color="k", ls="--", lw=1, label=f"api.UNRELIABLE_MM = {UNRELIABLE_MM:.0f} mm")
    if recommended is not None and recommended != UNRELIABLE_MM:
        ax1.axvline(recommended, color="tab:red", ls=":", lw=1.2, label=f"recommended {recommended:.0f} mm")
    ax1.axhline(1000 * FAILURE_M, color="gray", ls="-.", lw=1, label="failure: ADD 50 mm")
    ax1.set_xlabel("chains' spread (mm, mean keypoint distance to the chosen chain)")
    ax1.set_ylabel("ADD of the chosen pose (mm)")
    ax1.set_title("Spread vs error (top left / bottom right = flag wrong)")
    ax1.legend(fontsize=7, loc="best")
    ax1.grid(alpha=0.3, which="both")

    pooled = pool(sets)
    grid = np.unique(np.concatenate([threshold_grid(pooled), SWEEP_MM, [UNRELIABLE_MM]]))
    rows = [flag_stats(pooled, t) for t in grid]
    ax2.plot(grid, [r["recall_flag"] for r in rows], "-", color="tab:red", label="recall (failures flagged)")
    ax2.plot(
        grid, [r["recall_caught"] for r in rows], "--", color="tab:red", alpha=0.6, label="recall incl. out-of-view"
    )
    ax2.plot(grid, [r["false_alarm"] for r in rows], "-", color="tab:blue", label="false alarms (good frames flagged)")
    ax2.plot(grid, [r["kept_fraction"] for r in rows], ":", color="tab:gray", label="frames kept")
    ax2.axvline(UNRELIABLE_MM, color="k", ls="--", lw=1)
    if recommended is not None and recommended != UNRELIABLE_MM:
        ax2.axvline(recommended, color="tab:red", ls=":", lw=1.2)
    ax2.set_xscale("log")
    ax2.set_ylim(-0.02, 1.02)
    ax2.set_xlabel("threshold on the spread (mm)")
    ax2.set_ylabel("fraction")
    ax2.set_title(f"Flag over thresholds ({', '.join(sets)} pooled)")
    ax2.legend(fontsize=8)
    ax2.grid(alpha=0.3, which="both")
    plain = FuncFormatter(lambda v, _: f"{v:g}")
    for ax in (ax1, ax2):
        ax.xaxis.set_major_formatter(plain)
        ax.xaxis.set_minor_formatter(NullFormatter())
    ax1.yaxis.set_major_formatter(plain)
    ax1.yaxis.set_minor_formatter(NullFormatter())
    n = sum(len(d["add"]) for d in sets.values())
    title = f"Chain spread as an uncertainty: {n} frames, {chains} chains" + (f", step {step}" if step else "")
    fig.suptitle(f"{title}\n{start}", fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path, dpi=110)


# ---- main -------------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", required=True, help="model checkpoint")
    p.add_argument("--data", nargs="+", required=True, help="DREAM folders (held-out test sets)")
    p.add_argument("--limit", type=int, help="first N frames of each set")
    p.add_argument("--chains", type=int, default=4, help="stochastic reverse chains per frame")
    p.add_argument("--batch-size", type=int, default=4, help="frames estimated together")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-false-alarm", type=float, default=MAX_FALSE_ALARM, help="for the recommendation")
    p.add_argument("--device", default="cpu", help="cpu, cuda or auto")
    p.add_argument(
        "--plot", default=str(ROOT / "docs" / "results" / "uncertainty.png"), help="output figure ('' for none)"
    )
    p.add_argument("--json", help="also write the per-frame numbers here")
    p.add_argument(
        "--prior", type=float, nargs=2, metavar=("M", "DEG"), help="start from ground truth moved by this much per axis"
    )
    args = p.parse_args(argv)
    if args.chains < 2:
        p.error("--chains must be at least 2 (the spread needs several chains)")
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    tick = time.perf_counter()
    step = read_checkpoint(args.checkpoint).get("step")
    estimator = load_estimator(args.checkpoint, device=args.device)
    try:
        sets = {
            Path(d).name: measure(estimator, d, args.limit, args.chains, args.batch_size, args.seed, args.prior)
            for d in args.data
        }
    finally:
        estimator.close()
    start = start_label(args.prior, estimator.config.inference.prior_t)
    print(report(sets, args.chains, args.checkpoint, step, args.max_false_alarm, start))
    pooled = pool(sets)
    best, _ = recommend([flag_stats(pooled, t) for t in sorted({*SWEEP_MM, UNRELIABLE_MM})], args.max_false_alarm)
    if args.plot:
        print(f"plot: {plot(sets, Path(args.plot), args.chains, step, best['threshold_mm'] if best else None, start)}")
    if args.json:
        out = {
            name: {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in d.items()}
            for name, d in sets.items()
        }
        for d in out.values():
            d["add"] = [x if np.isfinite(x) else None for x in d["add"]]
        Path(args.json).write_text(
            json.dumps({"chains": args.chains, "step": step, "start": start, "sets": out}, indent=1)
        )
        print(f"per-frame numbers: {args.json}")
    print(f"({time.perf_counter() - tick:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(run_reporting_errors(main, "uncertainty.py"))
