"""Does VisDiff keep noisy training poses in view while spreading their rotations? (the paper's
first claim, Sec. III-B). Pure geometry, no rendering: runs in seconds.

Ground-truth poses are drawn like real scenes (Panda with random joints, a camera 0.8-2.5 m from
the robot's centroid looking at it, random intrinsics of a 640x480 image: ``monose3.data.scenes``'s
scene sampler). For each forward process and timestep t we draw noisy poses H_t from H_0 with
the training code's own noisers and measure

* in view: the robot's centroid projects inside the image and H_t's depth is above the 0.1 m
  floor both noisers clamp to (a sample that hit the floor was put behind or onto the camera);
* half visible: at least half of the robot's surface points are in front of the camera and
  project inside the image;
* the rotation angle between R_t and R_0 (mean and p10/p50/p90, degrees);
* the centroid's shift in the image (median pixels) and how that shift depends on the camera
  distance (median shift of the nearest third of scenes over that of the farthest third: 1 means
  the translation noise is the same in the image whatever the distance, Sec. III-B advantage ii).

Processes: VisDiff with gamma = 3 (our reading, see ``DiffusionConfig``), VisDiff with gamma = 1
(plain Eq. 5), FixPer (RoboPose's fixed perturbation about the reference point; t-independent),
FixPer with its rotation std rescaled so that its mean rotation angle matches VisDiff's at
each t ("matched rotation spread"), and, for reference, FixPer's perturbation applied about the
camera origin instead of the centroid (the paper's Fig. 2a).

    python benchmarks/visdiff.py [--scenes 400] [--reps 10] [--plot docs/results/visdiff.png]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from monose3.data.scenes.profiles import PROFILES
from monose3.data.scenes.sampling import sample_scene
from monose3.errors import run_reporting_errors
from monose3.geometry.poses import make_pose, transform_points
from monose3.geometry.rotations import euler_xyz_to_matrix, rotation_angle
from monose3.method.config import DiffusionConfig
from monose3.method.pose_space import MIN_DEPTH, centroid_frame
from monose3.method.scheduler import DDIMScheduler, FixPer
from monose3.report.plots import new_figure, save_figure
from monose3.robot import RobotModel

ROOT = Path(__file__).resolve().parents[1]
IMAGE_SIZE = (640, 480)
DEPTH_FLOOR = MIN_DEPTH  # both noisers clamp depth to this; a sample at the floor counts as out of view
TIMESTEPS = [1, *range(10, 101, 10)]
POINT_STRIDE = 4  # use every 4th of the 2000 surface points for the half-visible test


def sample_ground_truth(num: int, seed: int) -> dict[str, torch.Tensor]:
    """``num`` real-looking scenes: camera-from-centroid H_0, K and centroid-frame surface points."""
    model = RobotModel("panda")
    profile = replace(PROFILES["reallike"], name="visdiff", distance=(0.8, 2.5))
    rng = np.random.default_rng(seed)
    poses, Ks, points = [], [], []
    for _ in range(num):
        scene = sample_scene(rng, model, profile, IMAGE_SIZE)
        pts = model.surface_points(scene.joints[None])[0]
        centroid = model.centroid(pts)
        poses.append(centroid_frame(torch.from_numpy(scene.pose)[None], torch.from_numpy(centroid)[None])[0])
        Ks.append(torch.from_numpy(scene.K))
        points.append(torch.from_numpy(pts[::POINT_STRIDE] - centroid))
    return {"pose_ref": torch.stack(poses), "K": torch.stack(Ks), "points_ref": torch.stack(points)}


def fixper_about_camera(pose_ref: torch.Tensor, config: DiffusionConfig, gen: torch.Generator) -> torch.Tensor:
    """FixPer's perturbation with the rotation about the camera origin (Fig. 2a), not the centroid."""
    n = len(pose_ref)
    angles = torch.randn((n, 3), generator=gen, dtype=pose_ref.dtype) * math.radians(config.fixper_rot_std_deg)
    dt = torch.randn((n, 3), generator=gen, dtype=pose_ref.dtype) * config.fixper_trans_std
    rot = euler_xyz_to_matrix(angles)
    trans = (rot @ pose_ref[:, :3, 3:])[..., 0] + dt
    trans[:, 2] = trans[:, 2].clamp_min(DEPTH_FLOOR)
    return make_pose(rot @ pose_ref[:, :3, :3], trans)


def measure(pose_t: torch.Tensor, pose_0: torch.Tensor, K: torch.Tensor, points_ref: torch.Tensor) -> dict:
    """In-view, half-visible and depth-floor fractions and rotation-angle statistics of H_t."""
    w, h = IMAGE_SIZE
    t = pose_t[:, :3, 3]
    z = t[:, 2]
    u = K[:, 0, 0] * t[:, 0] / z + K[:, 0, 2]
    v = K[:, 1, 1] * t[:, 1] / z + K[:, 1, 2]
    floor = z <= DEPTH_FLOOR + 1e-9
    inside = (u >= -0.5) & (u <= w - 0.5) & (v >= -0.5) & (v <= h - 0.5)
    in_view = inside & ~floor
    cam = transform_points(pose_t.float(), points_ref.float())
    pz = cam[..., 2]
    pu = K[:, None, 0, 0].float() * cam[..., 0] / pz + K[:, None, 0, 2].float()
    pv = K[:, None, 1, 1].float() * cam[..., 1] / pz + K[:, None, 1, 2].float()
    vis = (pz > 0) & (pu >= -0.5) & (pu <= w - 0.5) & (pv >= -0.5) & (pv <= h - 0.5)
    half = vis.float().mean(1) >= 0.5
    ang = torch.rad2deg(rotation_angle(pose_t[:, :3, :3], pose_0[:, :3, :3])).numpy()
    p10, p50, p90 = np.percentile(ang, [10, 50, 90])
    t0 = pose_0[:, :3, 3]
    u0 = K[:, 0, 0] * t0[:, 0] / t0[:, 2] + K[:, 0, 2]
    v0 = K[:, 1, 1] * t0[:, 1] / t0[:, 2] + K[:, 1, 2]
    shift = torch.hypot(u - u0, v - v0)[~floor].numpy()
    z0 = t0[:, 2][~floor].numpy()
    near, far = z0 <= np.quantile(z0, 1 / 3), z0 >= np.quantile(z0, 2 / 3)
    near_far = float(np.median(shift[near]) / max(np.median(shift[far]), 1e-9)) if len(shift) >= 3 else float("nan")
    return {
        "in_view": float(in_view.double().mean()),
        "half_visible": float(half.double().mean()),
        "depth_floor": float(floor.double().mean()),
        "rot_mean": float(ang.mean()),
        "rot_p10": float(p10),
        "rot_p50": float(p50),
        "rot_p90": float(p90),
        "shift_px": float(np.median(shift)) if len(shift) else float("nan"),
        "near_far": near_far,
    }


def fixper_mean_angle_curve(seed: int, samples: int = 4000) -> tuple[np.ndarray, np.ndarray]:
    """Mean rotation angle (deg) of FixPer's Euler-angle noise as a function of its std (deg).

    The angle between R_t = dR R_0 and R_0 is the angle of dR, so it does not depend on R_0.
    Made monotone (it saturates near the uniform-SO(3) mean of ~126.5 deg).
    """
    gen = torch.Generator().manual_seed(seed)
    stds = np.arange(0.0, 181.0, 1.0)
    unit = torch.randn((samples, 3), generator=gen, dtype=torch.float64)
    means = []
    with one_thread():
        for s in stds:
            rot = euler_xyz_to_matrix(unit * math.radians(s))
            eye = torch.eye(3, dtype=torch.float64).expand_as(rot)
            means.append(float(torch.rad2deg(rotation_angle(rot, eye)).mean()))
    return stds, np.maximum.accumulate(np.asarray(means))


def std_for_mean_angle(target: float, stds: np.ndarray, means: np.ndarray) -> float:
    """FixPer rotation std (deg) whose mean angle is ``target`` (the largest std if out of reach)."""
    if target >= means[-1]:
        return float(stds[-1])
    first = int(np.argmax(means >= target))
    return float(np.interp(target, means[: first + 1], stds[: first + 1]))


def run(scenes: int = 400, reps: int = 10, seed: int = 0, timesteps: list[int] | None = None) -> dict:
    """All measurements; ``results[process][t]`` is :func:`measure`'s dict.

    Runs on one torch thread: the tensors are small, and on a busy shared machine a second
    OpenMP thread makes such work many times slower instead of faster.
    """
    with one_thread():
        return _run(scenes, reps, seed, TIMESTEPS if timesteps is None else timesteps)


@contextmanager
def one_thread() -> Iterator[None]:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def _run(scenes: int, reps: int, seed: int, timesteps: list[int]) -> dict:
    gt = sample_ground_truth(scenes, seed)
    pose_0 = gt["pose_ref"].repeat_interleave(reps, 0)
    K = gt["K"].repeat_interleave(reps, 0)
    points = gt["points_ref"].repeat_interleave(reps, 0)
    size = torch.tensor([IMAGE_SIZE], dtype=torch.float64).expand(len(K), 2)
    base = DiffusionConfig()
    stds, means = fixper_mean_angle_curve(seed)
    noisers = {
        "VisDiff g=3": DDIMScheduler(replace(base, gamma=3.0)),
        "VisDiff g=1": DDIMScheduler(replace(base, gamma=1.0)),
        "FixPer": FixPer(base),
    }
    results: dict[str, dict[int, dict]] = {name: {} for name in [*noisers, "FixPer matched", "FixPer@camera"]}
    matched_std: dict[int, float] = {}
    for k, t in enumerate(timesteps):
        tt = torch.full((len(K),), t, dtype=torch.long)
        for j, (name, noiser) in enumerate(noisers.items()):
            gen = torch.Generator().manual_seed(seed * 1_000_003 + 100 * k + j)
            results[name][t] = measure(noiser.add_noise(pose_0, tt, K, size, gen), pose_0, K, points)
        std = std_for_mean_angle(results["VisDiff g=3"][t]["rot_mean"], stds, means)
        matched_std[t] = std
        gen = torch.Generator().manual_seed(seed * 1_000_003 + 100 * k + 50)
        matched = FixPer(replace(base, fixper_rot_std_deg=std))
        results["FixPer matched"][t] = measure(matched.add_noise(pose_0, tt, K, size, gen), pose_0, K, points)
        gen = torch.Generator().manual_seed(seed * 1_000_003 + 100 * k + 60)
        results["FixPer@camera"][t] = measure(fixper_about_camera(pose_0, base, gen), pose_0, K, points)
    return {
        "timesteps": timesteps,
        "results": results,
        "matched_std": matched_std,
        "samples": len(K),
        "fixper_std": base.fixper_rot_std_deg,
    }


def crossing_t(timesteps: list[int], values: list[float], level: float) -> float | None:
    """First t (linearly interpolated) where ``values`` reaches ``level``; None if it never does."""
    for i in range(1, len(values)):
        lo, hi = values[i - 1], values[i]
        if (lo - level) * (hi - level) <= 0 and hi != lo:
            return timesteps[i - 1] + (level - lo) / (hi - lo) * (timesteps[i] - timesteps[i - 1])
    return None


def report(out: dict) -> str:
    ts, res = out["timesteps"], out["results"]
    lines = [f"VisDiff vs FixPer: {out['samples']} noisy poses per (process, t), 640x480 images, camera 0.8-2.5 m", ""]
    for name, per_t in res.items():
        note = " (rotation std matched to VisDiff g=3's mean angle)" if "matched" in name else ""
        lines.append(f"== {name}{note}")
        header = f"{'t':>4} {'in view':>8} {'half vis':>9} {'z floor':>8} {'rot mean':>9} {'p10':>7} {'p50':>7}"
        header += f" {'p90':>7} {'shift px':>9} {'near/far':>9}"
        if "matched" in name:
            header += f" {'std deg':>8}"
        lines.append(header)
        for t in ts:
            r = per_t[t]
            row = (
                f"{t:>4} {r['in_view']:>8.3f} {r['half_visible']:>9.3f} {r['depth_floor']:>8.3f} "
                f"{r['rot_mean']:>9.1f} {r['rot_p10']:>7.1f} {r['rot_p50']:>7.1f} {r['rot_p90']:>7.1f} "
                f"{r['shift_px']:>9.1f} {r['near_far']:>9.2f}"
            )
            if "matched" in name:
                row += f" {out['matched_std'][t]:>8.1f}"
            lines.append(row)
        lines.append("")
    v3, v1, fp, fm = (res[k] for k in ("VisDiff g=3", "VisDiff g=1", "FixPer", "FixPer matched"))
    lines.append("== ratios (in view / half visible)")
    lines.append(f"{'t':>4} {'g3/FixPer':>16} {'g3/matched':>16} {'g3/g1':>16} {'rot mean g3/g1':>15}")
    for t in ts:
        lines.append(
            f"{t:>4} {_ratio(v3[t], fp[t]):>16} {_ratio(v3[t], fm[t]):>16} {_ratio(v3[t], v1[t]):>16} "
            f"{v3[t]['rot_mean'] / max(v1[t]['rot_mean'], 1e-9):>15.2f}"
        )
    lines.append("")
    fixper_mean = float(np.mean([fp[t]["rot_mean"] for t in ts]))
    tx = crossing_t(ts, [v3[t]["rot_mean"] for t in ts], fixper_mean)
    if tx is None:
        lines.append(f"VisDiff g=3's mean rotation angle never reaches FixPer's {fixper_mean:.1f} deg in t <= {ts[-1]}")
    else:
        iv = float(np.interp(tx, ts, [v3[t]["in_view"] for t in ts]))
        hv = float(np.interp(tx, ts, [v3[t]["half_visible"] for t in ts]))
        fiv = float(np.mean([fp[t]["in_view"] for t in ts]))
        fhv = float(np.mean([fp[t]["half_visible"] for t in ts]))
        lines.append(
            f"At t = {tx:.1f} VisDiff g=3's mean rotation angle equals FixPer's ({fixper_mean:.1f} deg, std "
            f"{out['fixper_std']:.0f} deg): in view {iv:.3f} vs {fiv:.3f} (ratio {iv / max(fiv, 1e-9):.2f}), "
            f"half visible {hv:.3f} vs {fhv:.3f} (ratio {hv / max(fhv, 1e-9):.2f})"
        )
    last = ts[-1]
    lines.append(
        f"Effect of gamma at t = {last}: in view {v1[last]['in_view']:.3f} (g=1) -> {v3[last]['in_view']:.3f} (g=3), "
        f"half visible {v1[last]['half_visible']:.3f} -> {v3[last]['half_visible']:.3f}, depth floor hit "
        f"{v1[last]['depth_floor']:.3f} -> {v3[last]['depth_floor']:.3f}, mean rotation "
        f"{v1[last]['rot_mean']:.1f} -> {v3[last]['rot_mean']:.1f} deg (gamma scales translation noise only)"
    )
    lines.append(
        f"Centroid shift in the image at t = {last}: VisDiff g=3 median {v3[last]['shift_px']:.0f} px, near/far "
        f"{v3[last]['near_far']:.2f}; FixPer median {fp[last]['shift_px']:.0f} px, near/far {fp[last]['near_far']:.2f}"
    )
    cam = res["FixPer@camera"]
    lines.append(
        f"Rotation about the camera origin (Fig. 2a) instead of the centroid: FixPer in view "
        f"{np.mean([cam[t]['in_view'] for t in ts]):.3f} vs {np.mean([fp[t]['in_view'] for t in ts]):.3f}"
    )
    return "\n".join(lines)


def _ratio(a: dict, b: dict) -> str:
    return f"{a['in_view'] / max(b['in_view'], 1e-9):.2f}/{a['half_visible'] / max(b['half_visible'], 1e-9):.2f}"


def plot(out: dict, path: Path) -> Path:

    ts, res = out["timesteps"], out["results"]
    colors = {
        "VisDiff g=3": "tab:blue",
        "VisDiff g=1": "tab:orange",
        "FixPer": "tab:red",
        "FixPer matched": "tab:green",
        "FixPer@camera": "tab:gray",
    }
    fig = new_figure((12, 4.5))
    ax1, ax2 = fig.subplots(1, 2)
    markers = {"VisDiff g=3": "o", "VisDiff g=1": "o", "FixPer": "s", "FixPer matched": "^", "FixPer@camera": "o"}
    for name, per_t in res.items():
        c = colors[name]
        ax1.plot(
            ts,
            [per_t[t]["in_view"] for t in ts],
            "-",
            marker=markers[name],
            ms=4,
            mfc="none",
            color=c,
            label=f"{name}: centroid in view",
        )
        ax1.plot(ts, [per_t[t]["half_visible"] for t in ts], "--", color=c, label=f"{name}: >= half visible")
    ax1.set_xlabel("diffusion step t")
    ax1.set_ylabel("fraction of noisy poses")
    ax1.set_ylim(0, 1.02)
    ax1.set_title("Robot kept in view")
    ax1.legend(fontsize=7, loc="center left")
    ax1.grid(alpha=0.3)
    for name in ("VisDiff g=3", "VisDiff g=1", "FixPer", "FixPer matched"):
        per_t, c = res[name], colors[name]
        ax2.plot(ts, [per_t[t]["rot_p50"] for t in ts], "-", color=c, label=f"{name} (p10/p50/p90)")
        ax2.fill_between(ts, [per_t[t]["rot_p10"] for t in ts], [per_t[t]["rot_p90"] for t in ts], color=c, alpha=0.15)
    ax2.set_xlabel("diffusion step t")
    ax2.set_ylabel("angle between R_t and R_0 (deg)")
    ax2.set_title("Rotation spread")
    ax2.legend(fontsize=7, loc="upper left")
    ax2.grid(alpha=0.3)
    fig.suptitle(f"VisDiff vs FixPer ({out['samples']} noisy poses per point, 640x480, camera 0.8-2.5 m)")
    fig.tight_layout()
    return save_figure(fig, path, dpi=110)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", type=int, default=400, help="ground-truth scenes")
    p.add_argument("--reps", type=int, default=10, help="noisy poses per scene and t")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--timesteps", type=int, nargs="+", help=f"default {TIMESTEPS}")
    p.add_argument("--plot", default=str(ROOT / "docs" / "results" / "visdiff.png"), help="output figure ('' for none)")
    args = p.parse_args(argv)
    tick = time.perf_counter()
    out = run(args.scenes, args.reps, args.seed, args.timesteps)
    print(report(out))
    if args.plot:
        print(f"plot: {plot(out, Path(args.plot))}")
    print(f"({time.perf_counter() - tick:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(run_reporting_errors(main, "visdiff.py"))
