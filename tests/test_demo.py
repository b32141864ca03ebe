"""The bundled model and sample scene: the README's main job works out of the box."""

import json

import numpy as np

from monose3.apps.cli import main
from monose3.training.checkpoints import load_model
from monose3.training.formats import BUNDLED_CHECKPOINT as DEFAULT_CHECKPOINT


def test_bundled_model_is_a_small_panda_checkpoint():
    assert DEFAULT_CHECKPOINT.stat().st_size < 50e6
    _, config = load_model(DEFAULT_CHECKPOINT, robot="panda", preset="cpu")
    assert config.diffusion.noise == "visdiff"


def test_demo_estimates_the_sample_and_reports_its_error(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path), "--chains", "2"]) == 0
    out = capsys.readouterr().out
    assert "error vs ground truth: ADD" in out
    pose = np.asarray(json.loads((tmp_path / "pose.json").read_text())["camera_from_base"])
    assert np.allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-6)
    assert (tmp_path / "overlay.png").stat().st_size > 10_000
