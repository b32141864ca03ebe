"""Training throughput per preset and source of samples: where does a training step's time go?

For each preset ('cpu', 'paper'), each source ('synthetic': scenes made on the training
device; 'frames': DREAM frames decoded by the data loader) and each device (the CPU, and the
GPU when there is one), the loop's own pieces are timed over ``--steps`` steps:

* batch: ``BatchMaker.batch`` (scene drawing or frame decoding, the forward process, the crop,
  the synthetic image, the render at H_t), split into its render and the rest;
* network: one optimiser step as in the loop (bf16 autocast, channels_last on a GPU);
* end to end: both, one after the other, as ``monose3 train`` runs them.

    python benchmarks/train_speed.py [--steps 3] [--presets cpu paper] [--sources synthetic frames]
                                     [--batch-size B] [--profile]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from contextlib import nullcontext
from pathlib import Path

import numpy as np
import torch

from monose3.data.datasets import open_dataset
from monose3.data.scenes.writer import generate_dataset
from monose3.errors import run_reporting_errors
from monose3.method.config import DESIGNS, Config, get_preset, with_section
from monose3.method.designs import build_denoiser
from monose3.training.loop import BatchMaker, Sources
from monose3.training.objective import train_step

GPU_GOAL = {"paper": 3000.0}  # samples/s on one H100 (the goal: training that fills a GPU)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


class TimedRender:
    """Wraps a renderer's ``render`` and adds up its seconds."""

    def __init__(self, renderer, device: torch.device):
        self.inner, self.device, self.seconds = renderer.render, device, 0.0
        renderer.render = self

    def __call__(self, *args, **kwargs):
        _sync(self.device)
        tick = time.perf_counter()
        out = self.inner(*args, **kwargs)
        _sync(self.device)
        self.seconds += time.perf_counter() - tick
        return out


def measure(config: Config, source: str, frames: list, device: torch.device, steps: int, profile: bool) -> dict:
    sources = Sources([], synthetic=True) if source == "synthetic" else Sources(frames)
    maker = BatchMaker(config, sources, device, 0, 0, 1)
    timer = TimedRender(maker.renderer, device)
    model = build_denoiser(config.network).to(device)
    if device.type == "cuda":
        model = model.to(memory_format=torch.channels_last)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.train.lr)
    amp = (lambda: torch.autocast("cuda", dtype=torch.bfloat16)) if device.type == "cuda" else nullcontext
    _, batch = maker.batch(0)  # warm-up: workers, allocations, cuDNN autotuning
    train_step(model, optimizer, batch, config, 1e-4, amp)
    timer.seconds = 0.0
    batch_s = net_s = 0.0
    ctx = torch.profiler.profile() if profile else nullcontext()
    with ctx as prof:
        for step in range(1, steps + 1):
            _sync(device)
            tick = time.perf_counter()
            _, batch = maker.batch(step)
            _sync(device)
            batch_s += time.perf_counter() - tick
            tick = time.perf_counter()
            train_step(model, optimizer, batch, config, 1e-4, amp)
            _sync(device)
            net_s += time.perf_counter() - tick
    n = steps * config.train.batch_size
    row = {
        "batch": n / batch_s,
        "render": n / max(timer.seconds, 1e-9),
        "network": n / net_s,
        "end_to_end": n / (batch_s + net_s),
        "render_share": timer.seconds / batch_s,
    }
    if profile:
        row["profile"] = prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=15)
    return row


def run(
    presets: list[str],
    sources: list[str],
    steps: int,
    batch_size: int | None,
    workers: int,
    profile: bool,
    design: str | None = None,
    flow_weight: float = 0.0,
):
    devices = [torch.device("cpu")] + ([torch.device("cuda")] if torch.cuda.is_available() else [])
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        frames = list(open_dataset(generate_dataset(Path(tmp) / "f", 8, seed=0, workers=0, progress=False), "panda"))
        for name in presets:
            for device in devices:
                config = get_preset(name)
                bs = batch_size or (config.train.batch_size if device.type == "cpu" else 128)
                config = with_section(config, "train", batch_size=bs, num_workers=workers, flow_weight=flow_weight)
                if design:
                    config = with_section(config, "network", design=design)
                for source in sources:
                    r = measure(config, source, frames, device, steps, profile)
                    rows.append({"preset": name, "device": device.type, "source": source, "bs": bs, **r})
    return rows


def report(rows: list[dict]) -> str:
    try:
        load = f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"
    except OSError:  # pragma: no cover
        load = "unknown"
    lines = [
        f"Training throughput in samples/s (torch threads {torch.get_num_threads()}, load average {load})",
        f"{'preset':<6} {'dev':<4} {'source':<9} {'batch':>5} {'make':>8} {'render':>8} {'network':>8} "
        f"{'end2end':>8} {'render%':>7}",
    ]
    for r in rows:
        goal = GPU_GOAL.get(r["preset"]) if r["device"] == "cuda" else None
        lines.append(
            f"{r['preset']:<6} {r['device']:<4} {r['source']:<9} {r['bs']:>5} {r['batch']:>8.1f} {r['render']:>8.1f} "
            f"{r['network']:>8.1f} {r['end_to_end']:>8.1f} {100 * r['render_share']:>6.0f}%"
            + (f"  ({r['end_to_end'] / goal:.2f}x of the {goal:.0f}/s goal)" if goal else "")
        )
    lines.append(
        "make = the batch (data + forward process + synthetic image + render at H_t); end2end = make + network"
    )
    for r in rows:
        if "profile" in r:
            lines += [f"\n{r['preset']} {r['device']} {r['source']}:", r["profile"]]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--presets", nargs="+", default=["cpu", "paper"])
    p.add_argument("--sources", nargs="+", default=["synthetic", "frames"], choices=["synthetic", "frames"])
    p.add_argument("--steps", type=int, default=3, help="timed steps per row")
    p.add_argument("--batch-size", type=int, help="batch size (default: the preset's on the CPU, 128 on a GPU)")
    p.add_argument("--workers", type=int, default=0, help="data-loader workers")
    p.add_argument("--threads", type=int, help="torch CPU threads")
    p.add_argument("--profile", action="store_true", help="print the top operators of each row")
    p.add_argument("--design", choices=list(DESIGNS), help="denoiser design (default: the preset's)")
    p.add_argument("--flow-weight", type=float, default=0.0, help="the field designs' auxiliary loss weight [0]")
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    tick = time.perf_counter()
    rows = run(
        args.presets,
        args.sources,
        args.steps,
        args.batch_size,
        args.workers,
        args.profile,
        args.design,
        args.flow_weight,
    )
    print(report(rows))
    print(f"({time.perf_counter() - tick:.1f} s, torch {torch.__version__}, numpy {np.__version__})")
    return 0


if __name__ == "__main__":
    sys.exit(run_reporting_errors(main, "train_speed.py"))
