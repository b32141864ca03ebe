"""Render throughput of monose3's batched renderer, against pybullet's TinyRenderer.

Usage: ``python benchmarks/render.py [--seconds S] [--batch 16] [--robot panda] [--picture PNG]``

On the CPU: renders/s at 128x96 and 320x240 in batches of ``--batch`` (all torch threads),
and pybullet TinyRenderer's renders/s over a pool of one process per core on the same jobs,
in the same run; the ratio is the figure (goal >= 1.0x). Also the silhouettes alone
(``RobotRenderer.silhouettes``, the fit's comparisons) against unshaded renders (mask and
depth), and unshaded renders with the compiled rasteriser (``rasterize_cpu.py``, the CPU's
default) against the tensor code. On a GPU: renders/s in batches of 256 (goals 20,000/s at
128x96 and 5,000/s at 320x240). Nothing is asserted: the numbers depend on the machine and on
what else runs on it.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
import torch

from monose3.data.scenes.profiles import PROFILES
from monose3.data.scenes.sampling import sample_scene
from monose3.errors import run_reporting_errors
from monose3.robot import RobotModel
from monose3.robot import rasterize as rasterize_module
from monose3.robot.renderer import RenderJob, RobotRenderer

SIZES = ((128, 96), (320, 240))
GPU_BATCH = 256
GPU_TARGETS = {(128, 96): 20_000.0, (320, 240): 5_000.0}


def make_jobs(model: RobotModel, size: tuple[int, int], n: int, seed: int = 0) -> list[RenderJob]:
    """Training-like renders: cameras of the ``train`` profile, robot mostly in view."""
    rng = np.random.default_rng(seed)
    return [
        RenderJob(s.joints, s.pose, s.K, size)
        for s in (sample_scene(rng, model, PROFILES["train"], size) for _ in range(n))
    ]


def torch_rate(renderer: RobotRenderer, jobs: list[RenderJob], batch: int, seconds: float, device: str,
               what: str = "render") -> float:  # fmt: skip
    """Renders per second over whole batches (after a warm-up batch): shaded (``render``), or
    mask and depth (``unshaded``), or the mask alone (``silhouettes``)."""
    stacks = [
        tuple(
            torch.as_tensor(np.stack([getattr(j, f) for j in jobs[i : i + batch]]), device=device)
            for f in ("pose", "K")
        )
        + (np.stack([j.joints for j in jobs[i : i + batch]]),)
        for i in range(0, len(jobs) - batch + 1, batch)
    ]
    size = jobs[0].size

    def one(k: int) -> None:
        pose, K, q = stacks[k % len(stacks)]
        if what == "silhouettes":
            renderer.silhouettes(q, pose, K, size)
        else:
            renderer.render(q, pose, K, size, shade=what == "render")

    one(0)
    if device == "cuda":
        torch.cuda.synchronize()
    done, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        one(done)
        done += 1
    if device == "cuda":
        torch.cuda.synchronize()
    return done * batch / (time.perf_counter() - start)


def tensor_code_rate(renderer: RobotRenderer, jobs: list[RenderJob], batch: int, seconds: float) -> float:
    """:func:`torch_rate` of unshaded renders on the CPU with the tensor rasteriser (what runs without numba)."""
    compiled, rasterize_module.rasterize_cpu = rasterize_module.rasterize_cpu, None
    try:
        return torch_rate(renderer, jobs, batch, seconds, "cpu", "unshaded")
    finally:
        rasterize_module.rasterize_cpu = compiled


def pybullet_rate(model: RobotModel, jobs: list[RenderJob], seconds: float, workers: int) -> float | None:
    try:
        from monose3.robot.reference import RendererPool
    except ImportError:
        return None
    with RendererPool(model.spec, workers=workers, backend="tiny") as pool:
        pool.render(jobs[: 2 * workers])
        done, start = 0, time.perf_counter()
        while time.perf_counter() - start < seconds:
            pool.render(jobs)
            done += len(jobs)
        return done / (time.perf_counter() - start)


def save_comparison(model: RobotModel, renderer: RobotRenderer, path: str, size=(320, 240), n: int = 4) -> None:
    """Rows of (monose3, pybullet TinyRenderer, silhouette difference) for ``n`` training-like views."""
    from monose3.report.overlays import save_image
    from monose3.robot.reference import Renderer

    jobs = make_jobs(model, size, n, seed=5)
    ours = renderer.render_jobs(jobs)
    ref_renderer = Renderer(model, "tiny")
    rows = []
    for job, (rgb, mask) in zip(jobs, ours, strict=True):
        ref_rgb, ref_mask = ref_renderer.render(job)
        diff = np.zeros_like(rgb)
        diff[mask & ref_mask] = 90
        diff[mask & ~ref_mask] = (255, 60, 60)  # drawn only by monose3
        diff[~mask & ref_mask] = (60, 160, 255)  # drawn only by pybullet
        rows.append(np.concatenate([rgb, ref_rgb, diff], 1))
    ref_renderer.close()
    save_image(path, np.concatenate(rows, 0))
    print(f"wrote {path}: monose3 | pybullet TinyRenderer | red: only monose3, blue: only pybullet")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=4.0, help="time per measurement")
    parser.add_argument("--batch", type=int, default=16, help="CPU batch size")
    parser.add_argument("--robot", default="panda", help="panda or kuka")
    parser.add_argument("--picture", help="also save monose3 vs pybullet renders side by side here (PNG)")
    args = parser.parse_args()
    model = RobotModel(args.robot)
    renderer = RobotRenderer(model)
    if args.picture:
        save_comparison(model, renderer, args.picture)
    cores = os.cpu_count() or 1
    print(
        f"robot {model.name}, {len(model.mesh.faces)} triangles and {len(model.mesh.caps)} in caps, {cores} cores, "
        f"torch threads {torch.get_num_threads()}"
    )
    print(f"{'size':>8} {'device':>6} {'batch':>5} {'monose3/s':>9} {'pybullet/s':>11} {'ratio':>6}")
    for size in SIZES:
        jobs = make_jobs(model, size, 4 * args.batch)
        ours = torch_rate(renderer, jobs, args.batch, args.seconds, "cpu")
        ref = pybullet_rate(model, jobs, args.seconds, cores)
        ratio = f"{ours / ref:5.2f}x" if ref else "  n/a"
        ref_text = f"{ref:11.1f}" if ref else f"{'(no pybullet)':>11}"
        print(f"{size[0]:>4}x{size[1]:<3} {'cpu':>6} {args.batch:>5} {ours:9.1f} {ref_text} {ratio}  (goal >= 1.0x)")
    for size in SIZES:
        jobs = make_jobs(model, size, 4 * args.batch)
        unshaded = torch_rate(renderer, jobs, args.batch, args.seconds, "cpu", "unshaded")
        alone = torch_rate(renderer, jobs, args.batch, args.seconds, "cpu", "silhouettes")
        print(
            f"{size[0]:>4}x{size[1]:<3} silhouettes alone {alone:.1f}/s, unshaded renders {unshaded:.1f}/s:"
            f" {alone / unshaded:.2f}x"
        )
    for size in SIZES if rasterize_module.rasterize_cpu is not None else ():
        jobs = make_jobs(model, size, 4 * args.batch)
        compiled = torch_rate(renderer, jobs, args.batch, args.seconds, "cpu", "unshaded")
        tensor = tensor_code_rate(renderer, jobs, args.batch, args.seconds)
        print(
            f"{size[0]:>4}x{size[1]:<3} unshaded renders, compiled rasteriser {compiled:.1f}/s, tensor code"
            f" {tensor:.1f}/s: {compiled / tensor:.2f}x"
        )
    if torch.cuda.is_available():
        for size in SIZES:
            jobs = make_jobs(model, size, 4 * GPU_BATCH)
            rate = torch_rate(renderer, jobs, GPU_BATCH, args.seconds, "cuda")
            goal = GPU_TARGETS[size]
            head = f"{size[0]:>4}x{size[1]:<3} {'cuda':>6} {GPU_BATCH:>5}"
            print(f"{head} {rate:9.0f} {'':>11} {rate / goal:5.2f}x of {goal:.0f}/s")
    return 0


if __name__ == "__main__":
    sys.exit(run_reporting_errors(main, "benchmarks/render.py"))
