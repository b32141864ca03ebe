"""Render throughput of the panda at 320x240 and 640x480, in one process and over a pool.

Usage: ``python benchmarks/render.py [--seconds S] [--workers N] [--robot panda]``

Prints renders/s in one process (workers=0, one core) and with RendererPool over all cores,
the pool's speed-up and the per-core rate, each against its target as a PASS/MISS ratio.
Targets: >= 35 renders/s per core at 320x240; pool speed-up >= 0.9x per core (1.8x on 2).
The numbers depend on the machine and on what else runs on it; nothing is asserted.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

from monose3.errors import run_reporting_errors
from monose3.render import RendererPool, RenderJob
from monose3.robot import RobotModel

PER_CORE_TARGET = 35.0  # renders/s on one core at 320x240
SPEEDUP_PER_CORE = 0.9  # 1.8x on 2 cores
SIZES = ((320, 240), (640, 480))


def _look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, np.cross(z, x), z])
    pose[:3, 3] = -pose[:3, :3] @ eye
    return pose


def make_jobs(model: RobotModel, size: tuple[int, int], n: int, seed: int = 0) -> list[RenderJob]:
    """Typical RoboPose renders: random configurations, camera 1-2 m away, robot filling the view."""
    rng = np.random.default_rng(seed)
    w, h = size
    q = model.random_joints(rng, n)
    centres = model.centroid(model.surface_points(q))
    jobs = []
    for b in range(n):
        d = rng.normal(size=3)
        eye = centres[b] + rng.uniform(1.0, 2.0) * d / np.linalg.norm(d)
        pose = _look_at(eye, centres[b], np.array([0.0, 0.0, 1.0]) + rng.normal(scale=0.1, size=3))
        f = rng.uniform(0.9, 1.2) * w
        K = np.array([[f, 0.0, w / 2 - 0.5], [0.0, f, h / 2 - 0.5], [0.0, 0.0, 1.0]])
        jobs.append(RenderJob(q[b], pose, K, size))
    return jobs


def measure(pool: RendererPool, jobs: list[RenderJob], seconds: float, batch: int) -> float:
    """Renders per second over at least ``seconds`` of whole batches (after one warm-up batch)."""
    pool.render(jobs[:batch])
    done, i, start = 0, 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        chunk = [jobs[(i + k) % len(jobs)] for k in range(batch)]
        pool.render(chunk)
        done += batch
        i += batch
    return done / (time.perf_counter() - start)


def verdict(value: float, target: float) -> str:
    return f"{'PASS' if value >= target else 'MISS'} ({value / target:.2f}x of target {target:g})"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=3.0, help="time per measurement (default 3)")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="pool size (default: all cores)")
    parser.add_argument("--robot", default="panda")
    args = parser.parse_args()

    model = RobotModel(args.robot)
    cores = max(1, args.workers)
    jobs = {size: make_jobs(model, size, 64, seed=i) for i, size in enumerate(SIZES)}
    single, pooled = {}, {}
    with RendererPool(model, workers=0) as local:
        backend = "EGL (hardware)" if local._local.hardware else "TinyRenderer (CPU)"
        for size in SIZES:
            single[size] = measure(local, jobs[size], args.seconds, batch=8)
    with RendererPool(model, workers=cores) as pool:
        for size in SIZES:
            pooled[size] = measure(pool, jobs[size], args.seconds, batch=8 * cores)

    print(f"robot {model.name}, backend {backend}, pool of {cores} workers, {os.cpu_count()} cores visible")
    print(f"{'size':>9} | {'1 process':>12} | {'pool':>12} | {'speed-up':>8} | {'pool/core':>10}")
    for size in SIZES:
        w, h = size
        speedup = pooled[size] / single[size]
        print(
            f"{w:>4}x{h:<4} | {single[size]:>8.1f} r/s | {pooled[size]:>8.1f} r/s | {speedup:>7.2f}x | "
            f"{pooled[size] / cores:>6.1f} r/s"
        )
    small = SIZES[0]
    speedup = pooled[small] / single[small]
    print(f"per-core rate at 320x240 (1 process): {single[small]:.1f} r/s  {verdict(single[small], PER_CORE_TARGET)}")
    print(
        f"pool per-core rate at 320x240: {pooled[small] / cores:.1f} r/s  "
        f"{verdict(pooled[small] / cores, PER_CORE_TARGET)}"
    )
    print(f"pool speed-up at 320x240 on {cores} cores: {speedup:.2f}x  {verdict(speedup, SPEEDUP_PER_CORE * cores)}")
    return 0


if __name__ == "__main__":
    sys.exit(run_reporting_errors(main, "render.py"))
