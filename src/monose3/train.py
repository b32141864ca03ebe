"""``monose3 train``: Alg. 1 with checkpoints that resume exactly, TensorBoard/CSV logs and
multi-GPU / multi-node training through ``torchrun`` (DistributedDataParallel)."""

from __future__ import annotations

import argparse
import csv
import os
import time
from contextlib import nullcontext
from pathlib import Path

import torch
import torch.distributed as dist
from torch.utils.data import DataLoader
from tqdm import tqdm

from monose3.checkpoint import read_checkpoint, save_checkpoint
from monose3.config import Config, get_preset, with_section
from monose3.errors import Monose3Error
from monose3.network import Denoiser, disentangled_loss
from monose3.training_data import DenoisingSamples, GlobalSampleSampler

CHECKPOINT = "checkpoint.pt"
LOG_FIELDS = ["step", "loss", "loss_xy", "loss_rot", "loss_z", "lr", "samples_per_s"]


def learning_rate(step: int, config: Config) -> float:
    """Linear warm-up to the paper's 3e-4, then constant."""
    tc = config.train
    return tc.lr * min(1.0, (step + 1) / max(1, tc.warmup_steps))


def _distributed() -> tuple[int, int, int]:
    """(rank, local_rank, world_size); initialises the process group under torchrun."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
    return int(os.environ.get("RANK", "0")), int(os.environ.get("LOCAL_RANK", "0")), world


def load_frames(data_dirs: list[str | Path], robot: str) -> list:
    from monose3.dream import open_dataset

    frames: list = []
    for d in data_dirs:
        frames.extend(open_dataset(d, robot))
    if not frames:
        raise Monose3Error(
            f"no usable frames in {', '.join(map(str, data_dirs))}; generate some with `monose3 generate`"
        )
    return frames


class _Log:
    """CSV (always) and TensorBoard (rank 0) logs; on resume, rows after the checkpoint are dropped."""

    def __init__(self, out: Path, start_step: int):
        self.path = out / "log.csv"
        rows = []
        if self.path.is_file() and start_step > 0:
            with open(self.path) as fh:
                rows = [r for r in csv.DictReader(fh) if int(r["step"]) <= start_step]
        with open(self.path, "w", newline="") as fh:
            writer = csv.DictWriter(fh, LOG_FIELDS)
            writer.writeheader()
            writer.writerows(rows)
        from torch.utils.tensorboard import SummaryWriter

        self.tb = SummaryWriter(str(out / "tensorboard"), purge_step=start_step + 1 if start_step else None)

    def write(self, row: dict[str, float]) -> None:
        with open(self.path, "a", newline="") as fh:
            csv.DictWriter(fh, LOG_FIELDS).writerow(row)
        for key, value in row.items():
            if key != "step":
                self.tb.add_scalar(f"train/{key}", value, row["step"])

    def close(self) -> None:
        self.tb.close()


def train_step(
    model: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    batch: dict[str, torch.Tensor],
    config: Config,
    lr: float,
    amp=nullcontext,
    device: torch.device | str = "cpu",
) -> tuple[float, dict[str, float]]:
    """One optimiser step of Alg. 1 on a batch from :class:`DenoisingSamples`; returns the loss."""
    batch = {k: v.to(device, non_blocking=True) for k, v in batch.items()}
    for group in optimizer.param_groups:
        group["lr"] = lr
    with amp():
        raw = model(batch["render"], batch["crop"], batch["t"])
    loss, parts = disentangled_loss(
        raw.float(),
        batch["pose_ref_t"],
        batch["pose_ref_0"],
        batch["K_crop"],
        batch["points_ref"],
        config.network.render_size[0],
    )
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(model.parameters(), config.train.grad_clip)
    optimizer.step()
    return loss.item(), {k: v.item() for k, v in parts.items()}


def train(
    config: Config,
    data_dirs: list[str | Path],
    out_dir: str | Path,
    resume: bool = False,
    progress: bool = True,
    frames: list | None = None,
) -> list[float]:
    """Train until ``config.train.max_steps``; returns the losses of the steps run here."""
    rank, local_rank, world = _distributed()
    device = torch.device(f"cuda:{local_rank}" if torch.cuda.is_available() else "cpu")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tc = config.train
    torch.manual_seed(tc.seed)
    model = Denoiser(config.network).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=tc.lr)
    step = 0
    ckpt_path = out / CHECKPOINT
    if resume and ckpt_path.is_file():
        state = read_checkpoint(ckpt_path)
        saved = Config.from_dict(state["config"])
        if (saved.robot, saved.preset, saved.network) != (config.robot, config.preset, config.network):
            raise Monose3Error(f"{ckpt_path} was trained with another robot/preset/network; use a new --out")
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        step = int(state["step"])
    ddp_model = torch.nn.parallel.DistributedDataParallel(model) if world > 1 else model
    frames = frames if frames is not None else load_frames(data_dirs, config.robot)
    dataset = DenoisingSamples(frames, config, seed=tc.seed)
    sampler = GlobalSampleSampler(step * tc.batch_size * world, tc.batch_size, rank, world)
    loader = DataLoader(
        dataset,
        batch_size=tc.batch_size,
        sampler=sampler,
        num_workers=tc.num_workers,
        persistent_workers=tc.num_workers > 0,
        prefetch_factor=4 if tc.num_workers > 0 else None,
    )
    log = _Log(out, step) if rank == 0 else None
    amp = (lambda: torch.autocast("cuda", dtype=torch.bfloat16)) if device.type == "cuda" else nullcontext
    bar = tqdm(total=tc.max_steps, initial=step, desc="train", unit="step", disable=not progress or rank != 0)
    losses: list[float] = []
    tick, seen, window = time.perf_counter(), 0, []
    for batch in loader:
        if step >= tc.max_steps:
            break
        lr = learning_rate(step, config)
        loss, parts = train_step(ddp_model, optimizer, batch, config, lr, amp, device)
        step += 1
        seen += tc.batch_size * world
        losses.append(loss)
        window.append((loss, parts))
        bar.update(1)
        if log is not None and (step % tc.log_every == 0 or step == tc.max_steps):
            rate = seen / (time.perf_counter() - tick)
            # Logged losses are means over the logging window: single batches are too noisy to read.
            mean = {k: sum(p[k] for _, p in window) / len(window) for k in ("xy", "rot", "z")}
            row = {"step": step, "loss": sum(v for v, _ in window) / len(window), "lr": lr, "samples_per_s": rate}
            row.update({f"loss_{k}": v for k, v in mean.items()})
            tick, seen, window = time.perf_counter(), 0, []
            bar.set_postfix(loss=f"{row['loss']:.4f}", samples_s=f"{rate:.1f}")
            log.write(row)
        if rank == 0 and (step % tc.checkpoint_every == 0 or step == tc.max_steps):
            save_checkpoint(
                ckpt_path,
                {
                    "model": model.state_dict(),
                    "optimizer": optimizer.state_dict(),
                    "step": step,
                    "config": config.to_dict(),
                    "robot": config.robot,
                },
            )
    bar.close()
    if log is not None:
        log.close()
        plot_training_logs(log.path, out / "loss.png")
    if world > 1:
        dist.barrier()
    return losses


def _running_mean(values: list[float], width: int) -> list[float]:
    return [
        sum(values[max(0, i - width + 1) : i + 1]) / len(values[max(0, i - width + 1) : i + 1])
        for i in range(len(values))
    ]


def plot_training_logs(log_csv: Path, path: Path, smooth: int = 10) -> Path:
    """The loss of a run (``log.csv``) and its three parts of Eq. 10, smoothed by a running mean."""
    from monose3.viz import plot_curves

    with open(log_csv) as fh:
        rows = list(csv.DictReader(fh))
    curves = {
        name: _running_mean([float(r[col]) for r in rows], smooth)
        for name, col in (("total", "loss"), ("v_xy", "loss_xy"), ("rotation", "loss_rot"), ("v_z", "loss_z"))
    }
    return plot_curves(
        [int(r["step"]) for r in rows],
        curves,
        path,
        xlabel="step",
        ylabel="loss (Eq. 10, m)",
        title=f"training loss, running mean of {smooth} log points",
        logy=True,
    )


# The options live in the torch-free monose3.commands (fast --help and input errors).
from monose3.commands import add_train_arguments  # noqa: E402, F401


def config_from_args(args: argparse.Namespace) -> Config:
    config = get_preset(args.preset, robot=args.robot)
    train_over = {
        "max_steps": args.steps,
        "batch_size": args.batch_size,
        "lr": args.lr,
        "num_workers": args.workers,
        "checkpoint_every": args.checkpoint_every,
        "seed": args.seed,
    }
    config = with_section(config, "train", **{k: v for k, v in train_over.items() if v is not None})
    diff_over = {"noise": args.noise, "gamma": args.gamma}
    return with_section(config, "diffusion", **{k: v for k, v in diff_over.items() if v is not None})


def run_train(args: argparse.Namespace) -> int:
    if args.threads:
        torch.set_num_threads(args.threads)
    config = config_from_args(args)
    ckpt = Path(args.out) / CHECKPOINT
    if ckpt.is_file() and not args.resume:
        raise Monose3Error(f"{ckpt} exists; pass --resume to continue it or choose another --out")
    losses = train(config, args.data, args.out, resume=args.resume)
    if losses:
        print(f"trained to step {config.train.max_steps}; last loss {losses[-1]:.4f}; checkpoint {ckpt}")
    return 0
