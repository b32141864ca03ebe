"""Alg. 1: the training loop, its sources of samples, logs, checkpoints and weight shards.

Samples come from DREAM folders, from scenes synthesised on the training device, or from both
at a ratio. The loop runs to a step count or a wall-clock budget (``minutes``), writes a full
checkpoint (exact resume) every ``checkpoint_every`` steps and half-precision weight shards
every ``shard_minutes``, and can start from another run's shards (``init``).
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch.utils.data import DataLoader

from monose3.data.scenes.appearance import load_photos
from monose3.data.scenes.profiles import get_profile
from monose3.errors import Monose3Error
from monose3.method.config import Config
from monose3.method.denoiser import Denoiser
from monose3.method.designs import build_denoiser, design_inputs
from monose3.method.scheduler import make_noiser
from monose3.robot import RobotModel
from monose3.robot.renderer import RobotRenderer
from monose3.training.checkpoints import read_checkpoint, read_weights, save_checkpoint
from monose3.training.evidence_cache import EvidenceCache, evidence_batch
from monose3.training.logs import LogWindow, plot_training_logs
from monose3.training.objective import train_step
from monose3.training.samples import (
    FrameDataset,
    GlobalSampleSampler,
    denoising_batch,
    frames_batch,
    max_timestep,
    noisy_views,
    step_generator,
)
from monose3.training.shards import write_shards
from monose3.training.synthetic import SceneDataset, synthesize_crops

CHECKPOINT = "checkpoint.pt"


@dataclass
class Sources:
    """Where samples come from: DREAM ``frames``, synthetic scenes, or both (``synthetic_ratio``
    of the steps synthetic). ``backgrounds``: a folder of photographs for synthetic scenes."""

    frames: list = field(default_factory=list)
    synthetic: bool = False
    synthetic_ratio: float = 1.0
    profile: str = "train"
    backgrounds: str | Path | None = None
    evidence: list = field(
        default_factory=list
    )  # evidence cache folders (training.evidence_cache): the evidence denoiser's

    def __post_init__(self) -> None:
        if not self.frames and not self.synthetic and not self.evidence:
            raise Monose3Error("no training data: pass --data DIR (DREAM folders) and/or --synthetic")
        if self.evidence and (self.frames or self.synthetic):
            raise Monose3Error("an evidence cache trains the evidence denoiser alone; drop --data/--synthetic")
        if not 0.0 <= self.synthetic_ratio <= 1.0:
            raise Monose3Error(f"--synthetic-ratio must lie in [0, 1], got {self.synthetic_ratio}")


@dataclass
class TrainResult:
    losses: list[float]
    step: int
    samples: int
    stopped_by: str  # "steps" or "minutes"


def learning_rate(step: int, config: Config) -> float:
    """Linear warm-up (over steps since the run's start) to the paper's 3e-4, then constant."""
    tc = config.train
    return tc.lr * min(1.0, (step + 1) / max(1, tc.warmup_steps))


def _distributed() -> tuple[int, int, int]:
    """(rank, local_rank, world_size); initialises the process group under torchrun."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
    return int(os.environ.get("RANK", "0")), int(os.environ.get("LOCAL_RANK", "0")), world


class BatchMaker:
    """Makes the batch of each step from the sources, on ``device``."""

    def __init__(
        self,
        config: Config,
        sources: Sources,
        device: torch.device,
        start: int,
        rank: int,
        world: int,
        curriculum_from: int = 0,
    ):
        tc = config.train
        self.config, self.sources, self.device = config, sources, device
        # The t curriculum, like the warm-up, counts from the run's first step (an --init run starts both afresh).
        self.curriculum_from = curriculum_from
        self.robot = RobotModel(config.robot)
        self.renderer = RobotRenderer(self.robot, device)
        self.noiser = make_noiser(config.diffusion)
        self.rank, self.world = rank, world
        self.photos = load_photos(sources.backgrounds, device) if sources.synthetic else None
        self.profile = get_profile(sources.profile)
        loader = lambda ds: DataLoader(  # noqa: E731
            ds,
            batch_size=tc.batch_size,
            sampler=GlobalSampleSampler(start * tc.batch_size * world, tc.batch_size, rank, world),
            num_workers=tc.num_workers,
            persistent_workers=tc.num_workers > 0,
            prefetch_factor=4 if tc.num_workers > 0 else None,
            pin_memory=device.type == "cuda",
        )
        self._frames: Iterator | None = (
            iter(loader(FrameDataset(sources.frames, config, tc.seed))) if sources.frames else None
        )
        scenes = SceneDataset(self.robot.spec, sources.profile, config.network.input_size, tc.seed)
        self._scenes: Iterator | None = iter(loader(scenes)) if sources.synthetic else None
        self.evidence = EvidenceCache(sources.evidence) if sources.evidence else None
        if (self.evidence is None) != (design_inputs(config.network) != "parser"):
            raise Monose3Error("the evidence denoiser trains on an evidence cache (--evidence DIR), and only it does")

    def next_scenes(self) -> dict[str, torch.Tensor]:
        """The next batch of synthetic scenes (joints, pose, K, lighting...), as :meth:`batch` draws them."""
        if self._scenes is None:
            raise Monose3Error("this batch maker has no synthetic source; make it with Sources(synthetic=True)")
        return next(self._scenes)

    def source_of(self, step: int) -> str:
        if self._frames is None:
            return "synthetic"
        if self._scenes is None:
            return "frames"
        draw = np.random.default_rng([self.config.train.seed, step, 7]).random()
        return "synthetic" if draw < self.sources.synthetic_ratio else "frames"

    def batch(self, step: int) -> tuple[str, dict[str, torch.Tensor]]:
        if self.evidence is not None:
            return "cache", self.evidence_batch(step)
        # Both streams advance every step, so which source a step uses does not shift the others.
        source = self.source_of(step)
        frames = next(self._frames) if self._frames is not None else None
        scenes = next(self._scenes) if self._scenes is not None else None
        seed = self.config.train.seed * 1000 + self.rank
        gen = step_generator(seed, step)
        t_max = max_timestep(step - self.curriculum_from, self.config)
        if source == "frames":
            batch = frames_batch(frames, self.robot, self.renderer, self.noiser, self.config, gen, self.device, t_max)
            return source, batch
        return source, self.synthetic_batch(scenes, gen, step_generator(seed, step, self.device), t_max)

    def evidence_batch(self, step: int) -> dict[str, torch.Tensor]:
        """A batch of cached parser evidence: the samples drawn by the step's generator (so a
        resumed run sees the same ones), through the forward process."""
        tc = self.config.train
        gen = step_generator(tc.seed * 1000 + self.rank, step)
        indices = torch.randint(len(self.evidence), (tc.batch_size,), generator=gen)
        t_max = max_timestep(step - self.curriculum_from, self.config)
        samples = self.evidence.take(indices)
        return evidence_batch(samples, self.robot, self.renderer, self.noiser, self.config, gen, self.device, t_max)

    def synthetic_batch(
        self, scenes, gen: torch.Generator, device_gen: torch.Generator, t_max: int | None = None
    ) -> dict[str, torch.Tensor]:
        net = self.config.network
        joints = scenes["joints"].numpy()
        views = noisy_views(self.robot, self.noiser, self.config, scenes["pose"], joints, scenes["K"], gen, t_max)
        crops = synthesize_crops(
            self.renderer,
            scenes,
            views,
            net.render_size,
            net.input_size,
            self.profile,
            self.photos,
            device_gen,
            self.device,
        )
        return denoising_batch(views, crops, joints, self.renderer)


def _init_weights(model: Denoiser, init: str | Path, config: Config) -> tuple[int, int]:
    """Load ``init`` (shards or checkpoint) into ``model``; returns its (step, samples seen)."""
    state = read_weights(init)
    saved = Config.from_dict(state["config"])
    if (saved.robot, saved.network) != (config.robot, config.network):
        raise Monose3Error(f"--init {init} holds another network: pass {_flags_of(saved, config)} or another --init")
    try:
        model.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in state["model"].items()})
    except RuntimeError as err:
        raise Monose3Error(f"--init {init}: weights do not fit the network ({str(err)[:120]})") from None
    step = int(state.get("step", 0))
    return step, int(state.get("samples", step * saved.train.batch_size))


# The train flags that set each NetworkConfig field (the others come with --preset).
_NETWORK_FLAGS = {
    "design": "--design",
    "backbone": "--backbone",
    "rotation_output": "--rotation-output",
    "field_stride": "--field-stride",
}


def _flags_of(saved: Config, config: Config) -> str:
    """The train flags that would rebuild ``saved``'s robot and network from ``config``'s."""
    flags = [] if saved.robot == config.robot else [f"--robot {saved.robot}"]
    for name, value in vars(saved.network).items():
        if value != getattr(config.network, name):
            flag = _NETWORK_FLAGS.get(name, "--preset")
            flags.append(f"{flag} {saved.preset if flag == '--preset' else value}")
    return " ".join(dict.fromkeys(flags))


@dataclass
class RunState:
    """What a run carries from step to step (and through a checkpoint)."""

    model: Denoiser
    optimizer: torch.optim.Optimizer
    step: int = 0
    samples: int = 0
    warm_from: int = 0  # the learning rate warms up again from this step (a fresh optimiser)


def start_run(config: Config, out: Path, device: torch.device, resume: bool, init: str | Path | None) -> RunState:
    """The model and optimiser: resumed from ``out``'s checkpoint, started from ``init``, or new."""
    torch.manual_seed(config.train.seed)
    model = build_denoiser(config.network).to(device)
    if device.type == "cuda":
        model = model.to(memory_format=torch.channels_last)
    run = RunState(model, torch.optim.Adam(model.parameters(), lr=config.train.lr))
    ckpt_path = out / CHECKPOINT
    if resume and ckpt_path.is_file():
        state = read_checkpoint(ckpt_path)
        saved = Config.from_dict(state["config"])
        if (saved.robot, saved.preset, saved.network) != (config.robot, config.preset, config.network):
            raise Monose3Error(f"{ckpt_path} was trained with another robot/preset/network; use a new --out")
        model.load_state_dict(state["model"])
        run.optimizer.load_state_dict(state["optimizer"])
        run.step, run.samples = int(state["step"]), int(state.get("samples", 0))
        run.warm_from = int(state.get("warm_from", 0))
    elif init is not None:
        run.step, run.samples = _init_weights(model, init, config)
        run.warm_from = run.step
    return run


def save_run(run: RunState, out: Path, config: Config, loss: dict[str, float], final: bool = False) -> None:
    """Weight shards always; the exact-resume checkpoint every ``checkpoint_every`` steps and at the end."""
    meta = {"config": config.to_dict(), "step": run.step, "samples": run.samples, "loss": loss}
    write_shards(out, run.model.state_dict(), meta)
    if final or run.step % config.train.checkpoint_every == 0:
        state = {
            "model": run.model.state_dict(),
            "optimizer": run.optimizer.state_dict(),
            "step": run.step,
            "samples": run.samples,
            "warm_from": run.warm_from,
            "config": config.to_dict(),
            "robot": config.robot,
        }
        save_checkpoint(out / CHECKPOINT, state)


def train(
    config: Config,
    out_dir: str | Path,
    sources: Sources,
    resume: bool = False,
    init: str | Path | None = None,
    minutes: float | None = None,
    shard_minutes: float = 1.0,
    progress: bool = True,
    compile_model: bool = False,
) -> TrainResult:
    """Train until ``config.train.max_steps`` or ``minutes`` of wall clock, whichever comes first."""
    started = time.perf_counter()
    rank, local_rank, world = _distributed()
    device = torch.device(f"cuda:{local_rank}" if torch.cuda.is_available() else "cpu")
    out, tc = Path(out_dir), config.train
    run = start_run(config, out, device, resume, init)
    maker = BatchMaker(config, sources, device, run.step, rank, world, curriculum_from=run.warm_from)
    out.mkdir(parents=True, exist_ok=True)
    net = torch.nn.parallel.DistributedDataParallel(run.model) if world > 1 else run.model
    net = torch.compile(net) if compile_model else net
    amp = (lambda: torch.autocast("cuda", dtype=torch.bfloat16)) if device.type == "cuda" else nullcontext
    # With a clock budget the number of steps is not known in advance: count them, no total.
    window = LogWindow(out, run.step, None if minutes is not None else tc.max_steps, progress, rank)
    budget = None if minutes is None else minutes * 60.0
    losses: list[float] = []
    last_shard, stopped_by, step_time, source = time.perf_counter(), "steps", 0.0, ""
    while run.step < tc.max_steps:
        if budget is not None and time.perf_counter() - started + 1.5 * step_time > budget:
            stopped_by = "minutes"
            break
        begin = time.perf_counter()
        source, batch = maker.batch(run.step)
        lr = learning_rate(run.step - run.warm_from, config)
        loss, parts = train_step(net, run.optimizer, batch, config, lr, amp)
        run.step += 1
        run.samples += tc.batch_size * world
        step_time = time.perf_counter() - begin
        losses.append(loss)
        window.add(loss, parts)
        if window.log is not None and (run.step % tc.log_every == 0 or run.step == tc.max_steps):
            _log_row(window, run, config, source, world)
        if rank == 0 and (run.step % tc.checkpoint_every == 0 or time.perf_counter() - last_shard > shard_minutes * 60):
            save_run(run, out, config, window.means())
            last_shard = time.perf_counter()
    _finish(run, out, config, window, losses, source, world, rank)
    return TrainResult(losses, run.step, run.samples, stopped_by)


def _log_row(window: LogWindow, run: RunState, config: Config, source: str, world: int) -> None:
    lr = learning_rate(run.step - 1 - run.warm_from, config)
    window.write_row(run.step, run.samples, lr, source, config.train.batch_size * world)


def _finish(run, out: Path, config: Config, window: LogWindow, losses, source: str, world: int, rank: int) -> None:
    """The last log row (a clock stop mid-window), the final weights, the loss plot."""
    if window.log is not None and window.items:
        _log_row(window, run, config, source, world)
    window.bar.close()
    if rank == 0 and losses:
        save_run(run, out, config, window.means(), final=True)
    if window.log is not None:
        window.log.close()
        plot_training_logs(window.log.path, out / "loss.png")
    if world > 1:
        dist.barrier()
