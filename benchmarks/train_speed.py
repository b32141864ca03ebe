"""Training throughput per preset, split by stage: where does a training sample's time go?

For each preset ('cpu', 'paper') on this machine's CPU, and on the GPU when one is available:

* render: ``Renderer.render`` at the preset's render size, as called inside
  ``DenoisingSamples.__getitem__`` (timed by wrapping the dataset's renderer);
* data: the rest of ``__getitem__`` (image decode, standardisation, forward kinematics and
  surface points, the forward-process noise, crop geometry and the image crop), i.e. the whole
  ``__getitem__`` minus its render time. Measured with one torch thread, as in a data-loader
  worker;
* network: one optimiser step as in ``train.py`` (forward, Eq. 10 loss, backward, gradient
  clipping, Adam) on a batch of the preset's batch size (bf16 autocast on the GPU).

The end-to-end rates are implied from these: 'overlapped' assumes the preset's W data-loader
workers run beside the network on spare cores (min of the network rate and W x the sample
rate); 'serial' is no overlap at all; 'shared cores' bounds that by the machine's C cores when
workers and the network compete for them (C / (sample CPU-seconds + network threads x network
seconds), at most the network rate).

Uses a few synthetic 640x480 frames made with ``monose3.generate.generate_dataset`` in a
temporary folder.

    python benchmarks/train_speed.py [--samples 8] [--steps 3] [--presets cpu paper]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import default_collate

from monose3.config import Config, get_preset
from monose3.dream import open_dataset
from monose3.errors import run_reporting_errors
from monose3.generate import generate_dataset
from monose3.network import Denoiser, disentangled_loss
from monose3.render import Renderer, RenderJob
from monose3.training_data import DenoisingSamples


class TimedRenderer:
    """Delegates to a :class:`Renderer` and adds up the seconds spent in ``render``."""

    def __init__(self, renderer: Renderer):
        self.renderer = renderer
        self.seconds = 0.0
        self.calls = 0

    def render(self, job: RenderJob) -> tuple[np.ndarray, np.ndarray]:
        tick = time.perf_counter()
        out = self.renderer.render(job)
        self.seconds += time.perf_counter() - tick
        self.calls += 1
        return out

    def close(self) -> None:
        self.renderer.close()


def measure_data(frames: list, config: Config, samples: int, warmup: int = 2) -> dict:
    """Seconds per sample of the whole ``__getitem__`` and of its render, with one torch thread."""
    dataset = DenoisingSamples(frames, config, seed=0)
    timed = TimedRenderer(Renderer(dataset.robot))
    dataset._renderer = timed  # the dataset renders through this wrapper from now on
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # what a DataLoader worker runs with
    try:
        items = [dataset[i] for i in range(warmup)]
        timed.seconds, timed.calls = 0.0, 0
        tick = time.perf_counter()
        items = [dataset[warmup + i] for i in range(samples)]
        total = time.perf_counter() - tick
    finally:
        torch.set_num_threads(threads)
        timed.close()
    return {"getitem_s": total / samples, "render_s": timed.seconds / samples, "items": items}


def measure_network(items: list[dict], config: Config, device: torch.device, steps: int) -> float:
    """Seconds per optimiser step (forward + loss + backward + clip + Adam) at the preset's batch size."""
    torch.manual_seed(0)
    bs = config.train.batch_size
    batch = default_collate([items[i % len(items)] for i in range(bs)])
    batch = {k: v.to(device) for k, v in batch.items()}
    model = Denoiser(config.network).to(device).train()
    optimizer = torch.optim.Adam(model.parameters(), lr=config.train.lr)
    render_width = config.network.render_size[0]

    def step() -> None:
        with torch.autocast("cuda", dtype=torch.bfloat16, enabled=device.type == "cuda"):
            raw = model(batch["render"], batch["crop"], batch["t"])
        loss, _ = disentangled_loss(
            raw.float(), batch["pose_ref_t"], batch["pose_ref_0"], batch["K_crop"], batch["points_ref"], render_width
        )
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), config.train.grad_clip)
        optimizer.step()
        loss.item()  # synchronises, as train.py's logging does

    step()  # warm-up: allocations, cuDNN autotuning
    times = []
    for _ in range(steps):
        tick = time.perf_counter()
        step()
        times.append(time.perf_counter() - tick)
    return float(np.median(times))


def rates(data: dict, net_step_s: float, batch_size: int, workers: int, cores: int, device: str) -> dict:
    """Samples/s per stage and the implied end-to-end rates."""
    net_s = net_step_s / batch_size
    getitem, render = data["getitem_s"], data["render_s"]
    out = {
        "render": 1.0 / render,
        "data": 1.0 / max(getitem - render, 1e-9),
        "sample": 1.0 / getitem,
        "network": 1.0 / net_s,
        "overlapped": min(1.0 / net_s, max(workers, 1) / getitem),
        "serial": 1.0 / (getitem + net_s),
    }
    # On the CPU the network keeps min(threads, cores) cores busy for net_s per sample; on a GPU
    # it costs the CPU (almost) nothing, so only the loaders' CPU time counts.
    busy = min(torch.get_num_threads(), cores) * net_s if device == "cpu" else 0.0
    out["shared"] = min(out["overlapped"], cores / (getitem + busy))
    return out


def run(presets: list[str], samples: int, steps: int, frames_dir: Path | None = None) -> list[dict]:
    """One result row per (preset, device)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    devices = [torch.device("cpu")] + ([torch.device("cuda")] if torch.cuda.is_available() else [])
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = frames_dir or generate_dataset(Path(tmp) / "frames", 4, seed=0, workers=0, progress=False)
        frames = open_dataset(folder, "panda")
        for name in presets:
            config = get_preset(name)
            data = measure_data(list(frames), config, samples)
            for device in devices:
                net_step_s = measure_network(data["items"], config, device, steps)
                r = rates(data, net_step_s, config.train.batch_size, config.train.num_workers, cores, device.type)
                rows.append(
                    {
                        "preset": name,
                        "device": device.type,
                        "render_size": config.network.render_size,
                        "input_size": config.network.input_size,
                        "batch": config.train.batch_size,
                        "workers": config.train.num_workers,
                        "cores": cores,
                        "getitem_ms": 1000 * data["getitem_s"],
                        "render_ms": 1000 * data["render_s"],
                        "step_s": net_step_s,
                        **r,
                    }
                )
    return rows


def load_average() -> str:
    """The 1-minute load average and core count: timings on a shared machine need both."""
    try:
        return f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"
    except OSError:  # pragma: no cover - not on every platform
        return "unknown"


def report(rows: list[dict]) -> str:
    lines = [
        "Training throughput (samples/s; data stages with 1 torch thread as in a data-loader worker; "
        f"load average {load_average()})",
        f"{'preset':<6} {'dev':<4} {'render':>9} {'data':>8} {'sample':>8} {'network':>8} {'step s':>7} "
        f"{'W':>2} {'overlap':>8} {'serial':>7} {'shared':>7}",
    ]
    for r in rows:
        lines.append(
            f"{r['preset']:<6} {r['device']:<4} {r['render']:>9.1f} {r['data']:>8.1f} {r['sample']:>8.1f} "
            f"{r['network']:>8.1f} {r['step_s']:>7.2f} {r['workers']:>2} {r['overlapped']:>8.1f} "
            f"{r['serial']:>7.1f} {r['shared']:>7.1f}"
        )
    lines.append("")
    for r in rows:
        w, h = r["render_size"]
        iw, ih = r["input_size"]
        share = r["render_ms"] / r["getitem_ms"]
        bottleneck = "network" if r["network"] < r["workers"] * r["sample"] else "data loading"
        lines.append(
            f"{r['preset']}/{r['device']}: render {w}x{h}, input {iw}x{ih}, batch {r['batch']}; one sample "
            f"{r['getitem_ms']:.1f} ms of which render {r['render_ms']:.1f} ms ({100 * share:.0f}%); "
            f"with {r['workers']} worker(s) the {bottleneck} limits"
        )
    lines.append(
        f"'overlap' = min(network, W x sample); 'serial' = no overlap; 'shared' = 'overlap' limited by the "
        f"{rows[0]['cores'] if rows else '?'} core(s) the workers and the network share."
    )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--presets", nargs="+", default=["cpu", "paper"])
    p.add_argument("--samples", type=int, default=8, help="timed __getitem__ calls per preset")
    p.add_argument("--steps", type=int, default=3, help="timed optimiser steps per preset and device")
    p.add_argument("--threads", type=int, help="torch threads for the network step (default: torch's own)")
    p.add_argument("--frames", help="an existing DREAM folder to load from (default: 4 generated frames)")
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    tick = time.perf_counter()
    rows = run(args.presets, args.samples, args.steps, Path(args.frames) if args.frames else None)
    print(report(rows))
    print(f"({time.perf_counter() - tick:.1f} s, torch {torch.__version__}, torch threads {torch.get_num_threads()})")
    return 0


if __name__ == "__main__":
    sys.exit(run_reporting_errors(main, "train_speed.py"))
