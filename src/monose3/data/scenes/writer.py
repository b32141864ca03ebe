"""Writing a synthetic DREAM dataset (``generate_dataset``): frames made by worker processes,
resumable, and a preview grid of the result.

Each frame: joints uniform within the limits, a camera around the robot (distance,
azimuth, elevation, roll, intrinsics and where the robot lands in the image all random),
the robot rendered (monose3's renderer, or pybullet's for cross-renderer sets) under random
lighting, composited over a random background with distractor shapes behind and occluders
in front, then colour jitter, blur, noise and a random JPEG quality. The annotation is exact by construction: the
keypoints written are the forward kinematics of the written joints under the written pose.

Frame ``i`` draws all its randomness from ``np.random.SeedSequence([seed, i])``, so a
dataset is byte-identical whatever the number of worker processes, and an interrupted job
can be resumed (``--resume``) without changing a single frame.
"""

from __future__ import annotations

import json
import math
import multiprocessing as mp
import os
import queue
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from monose3 import atomic
from monose3.data.dream import DreamDataset
from monose3.data.dream_writer import write_camera_settings, write_frame
from monose3.data.inputs import list_backgrounds
from monose3.data.scenes.appearance import compose_frame, load_photos
from monose3.data.scenes.profiles import SceneProfile, get_profile
from monose3.data.scenes.sampling import Scene, frame_rng, sample_scene
from monose3.errors import Monose3Error
from monose3.geometry.camera import intrinsics_matrix
from monose3.robot import RobotModel, RobotSpec, get_spec
from monose3.robot.jobs import RENDERERS, RenderJob

GENERATION_FILE = "_generation.json"
NOMINAL_HFOV_DEG = 60.0  # the field of view of the folder's nominal _camera_settings.json


@dataclass(frozen=True)
class _Job:
    out: str
    seed: int
    size: tuple[int, int]
    profile: SceneProfile
    spec: RobotSpec
    backgrounds: tuple[str, ...]
    backend: str


def make_renderer(model: RobotModel, backend: str):
    """monose3's own renderer ('torch'), or pybullet's TinyRenderer/EGL as an independent one."""
    if backend == "torch":
        from monose3.robot.renderer import RobotRenderer

        return _TorchJobs(RobotRenderer(model))
    from monose3.robot.reference import Renderer

    return Renderer(model, backend)


class _TorchJobs:
    """The batched renderer behind the one-job ``render`` / ``close`` interface of pybullet's."""

    def __init__(self, renderer):
        self.renderer = renderer

    def render(self, job: RenderJob) -> tuple[np.ndarray, np.ndarray]:
        return self.renderer.render_jobs([job])[0]

    def close(self) -> None:
        self.renderer.release()


class FrameMaker:
    """Renders and writes frames of one job (one per process: a pybullet client is not shareable)."""

    def __init__(self, job: _Job):
        self.job = job
        self.model = RobotModel(job.spec)
        self.renderer = make_renderer(self.model, job.backend)
        # The user's photographs only (never scikit-image's): a folder's frames depend on its arguments alone.
        self.photos = load_photos(job.backgrounds, torch.device("cpu")) if job.backgrounds else None

    def make(self, index: int) -> tuple[np.ndarray, Scene, dict]:
        rng = frame_rng(self.job.seed, index)
        scene = sample_scene(rng, self.model, self.job.profile, self.job.size)
        robot_rgb, mask = self.renderer.render(
            RenderJob(scene.joints, scene.pose, scene.K, self.job.size, scene.lighting)
        )
        img, occluded = compose_frame(rng, robot_rgb, mask, self.job.profile, self.photos)
        quality = int(rng.integers(self.job.profile.jpeg_quality[0], self.job.profile.jpeg_quality[1] + 1))
        return img, scene, {"occluded": occluded, "quality": quality}

    def write(self, index: int) -> int:
        img, scene, info = self.make(index)
        write_frame(
            self.job.out,
            index,
            img,
            scene.K,
            self.model.joint_dict(scene.joints),
            scene.pose,
            robot=self.model,
            quality=info["quality"],
            visibility=round(scene.visible_fraction * (1.0 - info["occluded"]), 4),
        )
        return index

    def close(self) -> None:
        self.renderer.close()


def _worker_main(job: _Job, tasks: mp.Queue, results: mp.Queue) -> None:
    """A worker process: one pybullet client, frames taken from ``tasks`` until ``None``.

    Every outcome is reported on ``results`` (index, or an error text), so the parent never
    waits on a worker that failed.
    """
    cv2.setNumThreads(1)
    if job.backend == "torch":  # one process per core: more threads each would only contend
        import torch

        torch.set_num_threads(1)
    try:
        maker = FrameMaker(job)
    except BaseException as err:  # noqa: BLE001 - reported to the parent, which raises
        results.put(("error", None, f"{type(err).__name__}: {err}"))
        return
    try:
        while (index := tasks.get()) is not None:
            try:
                maker.write(index)
            except BaseException as err:  # noqa: BLE001
                results.put(("error", index, f"{type(err).__name__}: {err}"))
                return
            results.put(("done", index, ""))
    finally:
        maker.close()


def _run_workers(job: _Job, todo: list[int], workers: int, bar) -> None:
    """Make ``todo`` over ``workers`` spawned processes; raise if one fails or dies."""
    ctx = mp.get_context("spawn")
    tasks, results = ctx.Queue(), ctx.Queue()
    for i in todo:
        tasks.put(i)
    for _ in range(workers):
        tasks.put(None)
    procs = [ctx.Process(target=_worker_main, args=(job, tasks, results), daemon=True) for _ in range(workers)]
    for p in procs:
        p.start()
    remaining = len(todo)
    try:
        while remaining:
            try:
                kind, index, text = results.get(timeout=1.0)
            except queue.Empty:
                dead = [p for p in procs if p.exitcode not in (None, 0)]
                if dead or all(p.exitcode is not None for p in procs):
                    raise Monose3Error(
                        f"a generate worker process exited (code {dead[0].exitcode if dead else 0}) before finishing; "
                        "when calling generate_dataset from a script, put the call under "
                        "`if __name__ == '__main__':` (worker processes re-import the script), or pass workers=0"
                    ) from None
                continue
            if kind == "error":
                where = f"frame {index}" if index is not None else "start-up"
                raise Monose3Error(f"generate worker failed at {where}: {text}")
            remaining -= 1
            bar.update()
    finally:
        for p in procs:
            if remaining:
                p.terminate()
            p.join(timeout=10)
        tasks.close()
        results.close()


def _existing_frames(out: Path) -> set[int]:
    if not out.is_dir():
        return set()
    done = set()
    for e in os.scandir(out):
        stem = e.name[:-5] if e.name.endswith(".json") else ""
        if stem.isdigit() and (out / f"{stem}.rgb.jpg").is_file():
            done.add(int(stem))
    return done


def generate_dataset(
    out: str | Path,
    num: int,
    seed: int = 0,
    robot: str | RobotSpec = "panda",
    workers: int | None = None,
    profile: str | SceneProfile = "train",
    backgrounds: str | Path | None = None,
    size: tuple[int, int] = (640, 480),
    *,
    resume: bool = False,
    backend: str = "torch",
    progress: bool = True,
) -> Path:
    """Generate ``num`` frames into ``out`` (DREAM layout, per-frame intrinsics); returns ``out``.

    ``workers``: processes (None = one per CPU core, 0 = in this process). The output does not
    depend on it. ``resume=True`` keeps the complete frames already in ``out`` and makes the
    rest (the result is identical to an uninterrupted run with the same settings).
    """
    out = Path(out)
    spec = get_spec(robot)
    prof = get_profile(profile)
    w, h = _check_request(out, num, size, workers, backend)
    bg_files = list_backgrounds(backgrounds)
    settings = {
        "num": int(num),
        "seed": int(seed),
        "robot": spec.name,
        "profile": asdict(prof),
        "size": [w, h],
        "backgrounds": [str(p) for p in bg_files],
        "renderer": backend,
    }
    done = _existing_frames(out)
    _check_resume(out, settings, done, resume)
    out.mkdir(parents=True, exist_ok=True)
    nominal_f = (w / 2.0) / math.tan(math.radians(NOMINAL_HFOV_DEG) / 2.0)
    write_camera_settings(out, intrinsics_matrix(nominal_f, nominal_f, (w - 1) / 2, (h - 1) / 2), w, h)
    atomic.write_text(out / GENERATION_FILE, json.dumps(settings, indent=1))
    todo = [i for i in range(int(num)) if i not in done]
    job = _Job(str(out), int(seed), (w, h), prof, spec, tuple(str(p) for p in bg_files), backend)
    _make_frames(job, todo, (os.cpu_count() or 1) if workers is None else int(workers), progress)
    return out


def _check_request(out: Path, num: int, size: tuple[int, int], workers: int | None, backend: str) -> tuple[int, int]:
    """Refuse what cannot be generated before any work; returns the image size."""
    if int(num) < 1:
        raise Monose3Error(f"--num must be at least 1, got {num}")
    w, h = (int(v) for v in size)
    if w < 64 or h < 64:
        raise Monose3Error(f"image size {w}x{h} is too small; use at least 64x64 (e.g. 640x480)")
    if workers is not None and workers < 0:
        raise Monose3Error(f"--workers must be >= 0, got {workers}")
    if out.exists() and not out.is_dir():
        raise Monose3Error(f"--out {out} is a file; give a folder path")
    if backend not in RENDERERS:
        raise Monose3Error(f"unknown renderer {backend!r}; choose one of {', '.join(RENDERERS)}")
    if backend != "torch":
        from monose3.robot.reference import resolve_backend

        resolve_backend(backend)  # a missing pybullet fails here, before any work
    return w, h


def _check_resume(out: Path, settings: dict, done: set[int], resume: bool) -> None:
    """Frames already in ``out`` need ``resume``, and a resumed run the same settings."""
    if done and not resume:
        raise Monose3Error(
            f"{out} already holds {len(done)} frames; choose a new --out folder, delete it, "
            "or pass --resume to finish an interrupted run"
        )
    if resume and (out / GENERATION_FILE).is_file():
        previous = json.loads((out / GENERATION_FILE).read_text())
        current = json.loads(json.dumps(settings))
        if {k: v for k, v in previous.items() if k != "num"} != {k: v for k, v in current.items() if k != "num"}:
            raise Monose3Error(
                f"--resume: {out} was generated with different settings ({out / GENERATION_FILE}); "
                "rerun with the same --seed/--robot/--profile/--size/--backgrounds or use a new folder"
            )


def _make_frames(job: _Job, todo: list[int], workers: int, progress: bool) -> None:
    """Frames ``todo`` in this process (``workers`` 0) or in worker processes, with a progress bar."""
    from tqdm import tqdm

    bar = tqdm(total=len(todo), desc=f"generate {Path(job.out).name}", unit="frame", disable=not progress or not todo)
    workers = min(workers, len(todo))
    if todo and workers == 0:
        maker = FrameMaker(job)
        try:
            for i in todo:
                maker.write(i)
                bar.update()
        finally:
            maker.close()
    elif todo:
        _run_workers(job, todo, workers, bar)
    bar.close()


# ---- preview --------------------------------------------------------------------------------


def draw_keypoints(img: np.ndarray, uv: np.ndarray, color: tuple[int, int, int] = (0, 255, 0)) -> np.ndarray:
    """Keypoints joined in chain order (base to hand) on a copy of an RGB image."""
    out = img.copy()
    scale = max(1, round(max(img.shape[:2]) / 320))
    pts = [(int(round(u)), int(round(v))) for u, v in uv]
    for a, b in zip(pts[:-1], pts[1:], strict=True):
        cv2.line(out, a, b, (255, 255, 0), scale, cv2.LINE_AA)
    for k, p in enumerate(pts):
        cv2.circle(out, p, 3 * scale, (255, 0, 0) if k == 0 else color, -1, cv2.LINE_AA)
    return out


def save_preview_grid(
    folder: str | Path,
    path: str | Path,
    rows: int = 3,
    cols: int = 4,
    robot: str | RobotSpec = "panda",
    tile_width: int = 320,
) -> Path:
    """A ``rows`` x ``cols`` grid of the first frames of a DREAM folder with their keypoints drawn."""
    ds = DreamDataset(folder, robot)
    n = min(len(ds), rows * cols)
    tiles = []
    for i in range(n):
        frame = ds[i]
        img = draw_keypoints(frame.load_image(), frame.keypoints_2d)
        s = tile_width / img.shape[1]
        img = cv2.resize(img, (tile_width, int(round(img.shape[0] * s))), interpolation=cv2.INTER_AREA)
        cv2.putText(img, frame.name, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(img)
    th = max(t.shape[0] for t in tiles)
    grid = np.zeros((rows * th + (rows - 1) * 4, cols * tile_width + (cols - 1) * 4, 3), np.uint8)
    for k, tile in enumerate(tiles):
        r, c = divmod(k, cols)
        grid[r * (th + 4) : r * (th + 4) + tile.shape[0], c * (tile_width + 4) : c * (tile_width + 4) + tile_width] = (
            tile
        )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), cv2.cvtColor(grid, cv2.COLOR_RGB2BGR)):
        raise Monose3Error(f"could not write {path}; check the folder is writable and the suffix is .png/.jpg")
    return path
