"""The training run's logs: CSV and TensorBoard rows, the progress bar, the loss plot."""

from __future__ import annotations

import csv
import time
from pathlib import Path

from tqdm import tqdm

# loss_flow: the cost-volume design's auxiliary loss (TrainConfig.flow_weight), empty when off.
LOG_FIELDS = ["step", "samples", "loss", "loss_xy", "loss_rot", "loss_z", "loss_flow", "lr", "samples_per_s", "source"]


class CsvTensorBoardLog:
    """CSV (always) and TensorBoard (rank 0) logs; on resume, rows after the checkpoint are dropped."""

    def __init__(self, out: Path, start_step: int, fields: list[str] = LOG_FIELDS):
        self.path, self.fields = out / "log.csv", fields
        out.mkdir(parents=True, exist_ok=True)
        rows = []
        if self.path.is_file() and start_step > 0:
            with open(self.path) as fh:
                rows = [r for r in csv.DictReader(fh) if int(r["step"]) <= start_step]
        with open(self.path, "w", newline="") as fh:
            writer = csv.DictWriter(fh, fields, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(rows)
        from torch.utils.tensorboard import SummaryWriter

        self.tb = SummaryWriter(str(out / "tensorboard"), purge_step=start_step + 1 if start_step else None)

    def write(self, row: dict) -> None:
        with open(self.path, "a", newline="") as fh:
            csv.DictWriter(fh, self.fields, extrasaction="ignore").writerow(row)
        for key, value in row.items():
            if key not in ("step", "source"):
                self.tb.add_scalar(f"train/{key}", value, row["step"])

    def close(self) -> None:
        self.tb.close()


class LogWindow:
    """The losses since the last log row, the progress bar and the log (rank 0 only)."""

    def __init__(self, out: Path, start_step: int, total: int | None, progress: bool, rank: int):
        self.log = CsvTensorBoardLog(out, start_step) if rank == 0 else None
        self.bar = tqdm(total=total, initial=start_step, desc="train", unit="step", disable=not progress or rank != 0)
        self.tick, self.items, self.logged = time.perf_counter(), [], {}

    def add(self, loss: float, parts: dict[str, float]) -> None:
        self.items.append((loss, parts))
        self.bar.update(1)

    def means(self) -> dict[str, float]:
        """The window's mean losses, or the last row's when the window is empty."""
        return window_means(self.items) or self.logged

    def write_row(self, step: int, samples: int, lr: float, source: str, samples_per_step: int) -> None:
        """One row of the window's mean losses and its samples/s; the window starts again."""
        rate = len(self.items) * samples_per_step / (time.perf_counter() - self.tick)
        row = {"step": step, "samples": samples, "lr": lr}
        row.update({"samples_per_s": rate, "source": source, **window_means(self.items)})
        self.tick, self.logged, self.items = time.perf_counter(), window_means(self.items), []
        self.bar.set_postfix(loss=f"{row['loss']:.4f}", samples_s=f"{rate:.1f}")
        self.log.write(row)


def window_means(window: list[tuple[float, dict[str, float]]]) -> dict[str, float]:
    """Mean loss and Eq. 10 parts over the logging window (single batches are too noisy to read)."""
    if not window:
        return {}
    means = {f"loss_{k}": sum(p[k] for _, p in window) / len(window) for k in window[0][1]}
    return {"loss": sum(v for v, _ in window) / len(window), **means}


def _running_mean(values: list[float], width: int) -> list[float]:
    return [
        sum(values[max(0, i - width + 1) : i + 1]) / len(values[max(0, i - width + 1) : i + 1])
        for i in range(len(values))
    ]


def plot_training_logs(log_csv: Path, path: Path, smooth: int = 10) -> Path | None:
    """Eq. 10 of a run (``log.csv``) and its three parts against samples seen. The sum is of the
    unweighted parts, not the training objective: with ``rot_weight`` or a field's negative
    log-likelihood (which can be below zero) that is not Eq. 10 and would not fit a log axis."""
    from monose3.report.plots import plot_curves

    with open(log_csv) as fh:
        rows = list(csv.DictReader(fh))
    if not rows:
        return None
    parts = {"v_xy": "loss_xy", "rotation": "loss_rot", "v_z": "loss_z"}
    eq10 = [sum(float(r[col]) for col in parts.values()) for r in rows]
    curves = {"Eq. 10 (sum)": _running_mean(eq10, smooth)} | {
        name: _running_mean([float(r[col]) for r in rows], smooth) for name, col in parts.items()
    }
    return plot_curves(
        [int(r.get("samples") or 0) or int(r["step"]) for r in rows],
        curves,
        path,
        xlabel="samples seen",
        ylabel="loss (Eq. 10, m)",
        title=f"training loss, running mean of {smooth} log points",
        logy=True,
    )
