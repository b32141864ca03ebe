"""Plots (matplotlib's Agg canvas, so no display is ever needed): ADD curves and training curves."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from monose3.atomic import atomic_path
from monose3.errors import Monose3Error
from monose3.report.metrics import auc as add_auc


def new_figure(size: tuple[float, float] = (6.4, 4.4)) -> Figure:
    """A figure outside pyplot (no global state, no backend to choose, nothing to close)."""
    fig = Figure(figsize=size, dpi=100)
    FigureCanvasAgg(fig)
    return fig


def save_figure(fig: Figure, path: str | Path, dpi: float | str = "figure") -> Path:
    p = Path(path)
    with atomic_path(p) as tmp:
        fig.savefig(tmp, bbox_inches="tight", dpi=dpi, format=(p.suffix[1:] or "png").lower())
    return p


def plot_add_distribution(adds_by_name: Mapping[str, np.ndarray], path: str | Path) -> Path:
    """Fig. 4 style: fraction of frames with ADD at most x, for x from 0 to 100 mm, one curve per method.

    Every frame is in the denominator (failures never reach the curve), so the area under
    each curve is the AUC shown in the legend.
    """
    if not adds_by_name:
        raise Monose3Error("plot_add_distribution needs at least one method's ADD values")
    fig = new_figure()
    ax = fig.add_subplot(1, 1, 1)
    thresholds_mm = np.linspace(0.0, 100.0, 1001)
    for name, adds in adds_by_name.items():
        arr = np.asarray(adds, dtype=np.float64).reshape(-1)
        score = add_auc(arr)  # also validates (empty, negative)
        arr = np.sort(np.where(np.isfinite(arr), arr, np.inf))
        frac = np.searchsorted(arr, thresholds_mm / 1000.0, side="right") / arr.size
        ax.plot(thresholds_mm, frac, label=f"{name} (AUC {score:.2f})")
    ax.set_xlim(0, 100)
    ax.set_ylim(0, 1.0)
    ax.set_xlabel("ADD threshold (mm)")
    ax.set_ylabel("fraction of frames")
    ax.set_title("ADD accuracy")
    ax.grid(True, alpha=0.4)
    ax.legend(loc="lower right")
    return save_figure(fig, path)


def plot_curves(
    x: Sequence[float] | np.ndarray,
    ys: Mapping[str, Sequence[float] | np.ndarray],
    path: str | Path,
    xlabel: str = "",
    ylabel: str = "",
    title: str = "",
    logy: bool = False,
) -> Path:
    """Generic line plot (e.g. loss curves): one line per entry of ``ys`` against the shared ``x``."""
    if not ys:
        raise Monose3Error("plot_curves needs at least one curve")
    xs = np.asarray(x, dtype=np.float64).reshape(-1)
    fig = new_figure()
    ax = fig.add_subplot(1, 1, 1)
    for name, y in ys.items():
        ya = np.asarray(y, dtype=np.float64).reshape(-1)
        if ya.size != xs.size:
            raise Monose3Error(f"curve {name!r} has {ya.size} values but x has {xs.size}; give one value per x")
        ax.plot(xs, ya, label=str(name))
    if logy:
        ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, alpha=0.4)
    ax.legend(loc="best")
    return save_figure(fig, path)
