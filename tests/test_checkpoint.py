"""Checkpoints: atomic writes, robot/preset checks and the fp16 export."""

import pytest
import torch
from conftest import TINY_NET, slab_surface

from monose3.errors import Monose3Error
from monose3.method.config import get_preset
from monose3.method.designs import build_denoiser
from monose3.training.checkpoints import export_model, load_model, read_checkpoint, save_checkpoint


@pytest.fixture
def checkpoint(tmp_path):
    torch.manual_seed(0)
    config = get_preset("cpu", network=TINY_NET)
    model = build_denoiser(config.network)
    torch.nn.init.normal_(model.net.fc.weight, std=0.01)
    path = tmp_path / "ck.pt"
    save_checkpoint(path, {"model": model.state_dict(), "optimizer": {}, "config": config.to_dict(), "step": 7})
    return path, model


def test_save_leaves_no_temporary_files(checkpoint):
    path, _ = checkpoint
    assert [p.name for p in path.parent.iterdir()] == ["ck.pt"]
    assert read_checkpoint(path)["step"] == 7


def test_load_checks_robot_and_preset(checkpoint):
    path, _ = checkpoint
    with pytest.raises(Monose3Error, match="robot 'panda', not 'kuka'"):
        load_model(path, robot="kuka")
    with pytest.raises(Monose3Error, match="preset 'cpu', not 'paper'"):
        load_model(path, preset="paper")


def test_not_a_checkpoint_is_a_clear_error(tmp_path):
    bad = tmp_path / "bad.pt"
    bad.write_text("hello")
    with pytest.raises(Monose3Error, match="cannot read checkpoint"):
        read_checkpoint(bad)
    with pytest.raises(Monose3Error, match="not found"):
        read_checkpoint(tmp_path / "missing.pt")


def test_fp16_export_is_half_the_size_and_predicts_the_same(checkpoint, tmp_path):
    path, model = checkpoint
    out = export_model(path, tmp_path / "small.pt")
    assert out.stat().st_size < 0.6 * path.stat().st_size
    loaded, config = load_model(out)
    x, t = torch.rand(2, 3, 48, 64), torch.tensor([3, 50])
    model.eval()
    with torch.no_grad():
        surface = slab_surface((64, 48))
        assert torch.allclose(loaded(x, x, t, surface).raw, model(x, x, t, surface).raw, atol=2e-3)
    assert config.network == TINY_NET


@pytest.mark.parametrize(("design", "rotation_output"), [("siamese-pose", "6d"), ("concat-grid", "abs6d")])
def test_a_checkpoint_of_a_removed_design_is_a_clear_error(tmp_path, design, rotation_output):
    config = get_preset("cpu", network=TINY_NET).to_dict()
    config["network"].update(design=design, rotation_output=rotation_output)
    save_checkpoint(tmp_path / "old.pt", {"model": {}, "config": config, "step": 1})
    with pytest.raises(Monose3Error, match=f"holds a '{design}' denoiser .* no longer builds"):
        load_model(tmp_path / "old.pt")
