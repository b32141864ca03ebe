"""Training: the network learns (overfits a fixed batch), checkpoints resume exactly, the CLI
wires it, and DistributedDataParallel runs on CPU with gloo."""

import os
import subprocess
import sys

import pytest
import torch
from conftest import TINY_NET
from torch.utils.data import default_collate

from monose3.checkpoint import read_checkpoint
from monose3.cli import main
from monose3.config import get_preset, with_section
from monose3.dream import open_dataset
from monose3.network import Denoiser
from monose3.train import learning_rate, train, train_step
from monose3.training_data import DenoisingSamples, GlobalSampleSampler


def tiny_config(**train):
    config = get_preset("cpu", network=TINY_NET)
    defaults = dict(batch_size=4, num_workers=0, warmup_steps=1, log_every=1, checkpoint_every=3, max_steps=6)
    return with_section(config, "train", **{**defaults, **train})


@pytest.fixture(scope="module")
def frames(tiny_dream):
    return open_dataset(tiny_dream, "panda")


def test_samples_are_a_pure_function_of_the_sample_number(frames):
    ds = DenoisingSamples(frames, tiny_config())
    a, b = ds[7], DenoisingSamples(frames, tiny_config())[7]
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not torch.equal(ds[8]["pose_ref_t"], a["pose_ref_t"])
    assert a["render"].shape == (3, 48, 64) and a["crop"].shape == (3, 48, 64)
    assert a["render"].amax() > 0  # the robot is in the render


def test_sampler_splits_global_batches_over_ranks():
    one = GlobalSampleSampler(8, 4, 0, 1)
    ranks = [GlobalSampleSampler(8, 2, r, 2) for r in range(2)]
    it = iter(one)
    first = [next(it) for _ in range(8)]
    per_rank = [[next(i) for _ in range(4)] for i in map(iter, ranks)]
    # rank 0 takes the first half of each global batch, rank 1 the second.
    assert per_rank[0] == first[0:2] + first[4:6] and per_rank[1] == first[2:4] + first[6:8]


def test_overfits_a_fixed_batch(frames):
    torch.manual_seed(0)
    config = tiny_config()
    ds = DenoisingSamples(frames, config)
    batch = default_collate([ds[i] for i in range(4)])
    model = Denoiser(config.network)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    losses = [train_step(model, opt, batch, config, 1e-3)[0] for _ in range(60)]
    assert losses[-1] < losses[0] / 5, losses[::10]


def test_resume_reproduces_the_uninterrupted_run(frames, tmp_path):
    torch.manual_seed(0)
    full = train(tiny_config(), [], tmp_path / "full", progress=False, frames=frames)
    # An interrupted run: stops at step 3 (its last checkpoint), then resumes to step 6.
    train(tiny_config(max_steps=3), [], tmp_path / "cut", progress=False, frames=frames)
    resumed = train(tiny_config(), [], tmp_path / "cut", resume=True, progress=False, frames=frames)
    assert len(full) == 6 and len(resumed) == 3
    assert resumed == pytest.approx(full[3:], rel=1e-4, abs=1e-6)
    state = read_checkpoint(tmp_path / "cut" / "checkpoint.pt")
    assert state["step"] == 6 and state["config"]["robot"] == "panda"
    rows = (tmp_path / "cut" / "log.csv").read_text().strip().splitlines()
    assert [int(r.split(",")[0]) for r in rows[1:]] == [1, 2, 3, 4, 5, 6]


def test_warmup_reaches_the_paper_rate():
    config = get_preset("paper")
    assert learning_rate(0, config) < learning_rate(100, config) < learning_rate(10_000, config) == 3e-4


def test_cli_refuses_to_overwrite_and_resumes(tiny_dream, tmp_path, capsys):
    args = [
        "train",
        "--data",
        str(tiny_dream),
        "--out",
        str(tmp_path),
        "--steps",
        "2",
        "--batch-size",
        "2",
        "--workers",
        "0",
        "--checkpoint-every",
        "1",
    ]
    assert main(args) == 0
    assert main(args) == 2
    assert "--resume" in capsys.readouterr().err
    assert main([*args[:6], "3", *args[7:], "--resume"]) == 0
    assert read_checkpoint(tmp_path / "checkpoint.pt")["step"] == 3


@pytest.mark.slow
def test_torchrun_two_processes_gloo(tiny_dream, tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--nproc_per_node",
        "2",
        "--master_port",
        "29517",
        "-m",
        "monose3.cli",
        "train",
        "--data",
        str(tiny_dream),
        "--out",
        str(tmp_path),
        "--steps",
        "2",
        "--batch-size",
        "2",
        "--workers",
        "0",
    ]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert read_checkpoint(tmp_path / "checkpoint.pt")["step"] == 2
