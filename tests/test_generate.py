"""Synthetic data generation: exact ground truth, reproducibility across worker counts,
resume, scene profiles, and the command line."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from monose3.apps import cli
from monose3.data.dream import DreamDataset
from monose3.data.scenes.appearance import backgrounds, load_photos
from monose3.data.scenes.profiles import PROFILES
from monose3.data.scenes.sampling import frame_rng, sample_scene
from monose3.data.scenes.writer import generate_dataset, save_preview_grid
from monose3.errors import Monose3Error
from monose3.robot import RobotModel

SIZE = (320, 240)


@pytest.fixture(scope="module")
def small_set(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("gen") / "w0"
    generate_dataset(out, 6, seed=7, workers=0, size=SIZE, progress=False)
    return out


def files_of(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def check_ground_truth(ds: DreamDataset, model: RobotModel, seed: int, profile: str = "train") -> None:
    for i, frame in enumerate(ds):
        assert frame.name == f"{i:06d}"
        # the scene the generator drew for this frame (it is the first use of the frame's RNG)
        scene = sample_scene(frame_rng(seed, i), model, PROFILES[profile], frame.image_size)
        np.testing.assert_allclose(frame.pose, scene.pose, atol=1e-4)
        np.testing.assert_allclose(frame.joints, scene.joints, atol=1e-9)
        np.testing.assert_allclose(frame.K, scene.K, atol=1e-9)
        # annotated keypoints are exactly FK of the annotated joints under the annotated pose
        kp = model.keypoints(frame.joints[None])[0] @ frame.pose[:3, :3].T + frame.pose[:3, 3]
        np.testing.assert_allclose(frame.keypoints_3d, kp, atol=1e-4)
        assert np.abs(frame.keypoints_3d - kp).max() < 1e-9
        uv = kp[:, :2] / kp[:, 2:] * frame.K[[0, 1], [0, 1]] + frame.K[[0, 1], [2, 2]]
        np.testing.assert_allclose(frame.keypoints_2d, uv, atol=1e-6)


def test_generated_frames_have_exact_ground_truth(small_set: Path, panda: RobotModel) -> None:
    ds = DreamDataset(small_set, panda)
    assert len(ds) == 6 and ds.skipped == []
    check_ground_truth(ds, panda, seed=7)
    w, h = SIZE
    for frame in ds:
        img = frame.load_image()
        assert img.shape == (h, w, 3) and img.std() > 1.0
        pts = panda.surface_points(frame.joints[None])[0]
        cam = pts @ frame.pose[:3, :3].T + frame.pose[:3, 3]
        c = panda.centroid(pts) @ frame.pose[:3, :3].T + frame.pose[:3, 3]
        u, v = (frame.K @ c)[:2] / c[2]
        assert 0 <= u < w and 0 <= v < h  # the robot's centroid is in the image
        uv = cam[:, :2] / cam[:, 2:] * frame.K[[0, 1], [0, 1]] + frame.K[[0, 1], [2, 2]]
        inside = ((uv >= -0.5) & (uv < np.array([w, h]) - 0.5)).all(1)
        assert inside.mean() >= PROFILES["train"].min_visible
        assert cam[:, 2].min() > 0.1
    settings = json.loads((small_set / "_generation.json").read_text())
    assert settings["seed"] == 7 and settings["size"] == list(SIZE)


def test_worker_count_does_not_change_the_data(small_set: Path, tmp_path: Path) -> None:
    generate_dataset(tmp_path / "w2", 6, seed=7, workers=2, size=SIZE, progress=False)
    assert files_of(tmp_path / "w2") == files_of(small_set)
    generate_dataset(tmp_path / "s8", 2, seed=8, workers=0, size=SIZE, progress=False)
    assert (tmp_path / "s8" / "000000.rgb.jpg").read_bytes() != (small_set / "000000.rgb.jpg").read_bytes()


def test_worker_failure_is_reported(tmp_path: Path) -> None:
    for workers in (0, 1):
        out = tmp_path / f"w{workers}"
        (out / "000001.rgb.jpg").mkdir(parents=True)  # frame 1 cannot be written
        with pytest.raises(Monose3Error, match="cannot write frame 000001"):
            generate_dataset(out, 3, seed=7, workers=workers, size=SIZE, progress=False)


def test_resume_finishes_identically(small_set: Path, tmp_path: Path) -> None:
    out = tmp_path / "r"
    generate_dataset(out, 6, seed=7, workers=0, size=SIZE, progress=False)
    (out / "000002.json").unlink()  # an interrupted frame: image written, JSON not yet
    (out / "000004.json").unlink()
    (out / "000004.rgb.jpg").unlink()
    with pytest.raises(Monose3Error, match="--resume"):
        generate_dataset(out, 6, seed=7, workers=0, size=SIZE, progress=False)
    with pytest.raises(Monose3Error, match="different settings"):
        generate_dataset(out, 6, seed=8, workers=0, size=SIZE, progress=False, resume=True)
    generate_dataset(out, 6, seed=7, workers=0, size=SIZE, progress=False, resume=True)
    assert files_of(out) == files_of(small_set)


@pytest.mark.parametrize("name", ["train", "reallike", "hard"])
def test_profiles_shape_the_cameras(name: str, panda: RobotModel) -> None:
    prof = PROFILES[name]
    dists, offsets = [], []
    for i in range(25):
        scene = sample_scene(frame_rng(0, i), panda, prof, (640, 480))
        pts = panda.surface_points(scene.joints[None])[0]
        c = panda.centroid(pts) @ scene.pose[:3, :3].T + scene.pose[:3, 3]
        dists.append(np.linalg.norm(c))
        u, v = (scene.K @ c)[:2] / c[2]
        offsets.append(max(abs(u - scene.K[0, 2]) / 320, abs(v - scene.K[1, 2]) / 240))
        hfov = np.degrees(2 * np.arctan(320 / scene.K[0, 0]))
        assert prof.hfov[0] - 1e-6 <= hfov <= prof.hfov[1] + 1e-6
        assert abs(scene.K[1, 1] / scene.K[0, 0] - 1) < 0.05
        assert scene.visible_fraction >= prof.min_visible
    assert prof.distance[0] - 1e-6 <= min(dists) and max(dists) <= prof.distance[1] + 1e-6
    assert max(offsets) <= prof.offcenter + 1e-6
    if name == "reallike":
        assert max(offsets) < 0.3
    if name == "hard":
        assert max(offsets) > 0.3 and np.mean(dists) > 1.8


def test_backgrounds_from_user_folder(tmp_path: Path) -> None:
    folder = tmp_path / "bg"
    folder.mkdir()
    cv2.imwrite(str(folder / "a.png"), np.full((100, 200, 3), (10, 200, 30), np.uint8))  # BGR
    photos = load_photos(folder, torch.device("cpu"))
    assert photos.shape == (1, 3, 384, 512) and photos.dtype == torch.uint8
    img = backgrounds(torch.Generator().manual_seed(0), 2, (64, 48), photos, "cpu", photo_prob=1.0)
    assert img.shape == (2, 3, 48, 64)
    assert torch.allclose(img[:, :, 5:-5, 5:-5], torch.tensor([30, 200, 10]).view(1, 3, 1, 1) / 255, atol=1e-3)
    procedural = backgrounds(torch.Generator().manual_seed(1), 6, (64, 48), photos, "cpu")  # photo_prob 0
    assert len({im.numpy().tobytes() for im in procedural}) == 6
    generate_dataset(tmp_path / "out", 2, seed=1, workers=0, size=SIZE, backgrounds=folder, progress=False)
    assert len(DreamDataset(tmp_path / "out")) == 2


def test_bad_arguments(tmp_path: Path) -> None:
    with pytest.raises(Monose3Error, match="profile"):
        generate_dataset(tmp_path / "a", 1, profile="easy")
    with pytest.raises(Monose3Error, match="at least 1"):
        generate_dataset(tmp_path / "a", 0)
    with pytest.raises(Monose3Error, match="too small"):
        generate_dataset(tmp_path / "a", 1, size=(32, 24))
    with pytest.raises(Monose3Error, match="backgrounds folder not found"):
        generate_dataset(tmp_path / "a", 1, backgrounds=tmp_path / "none")
    (tmp_path / "emptybg").mkdir()
    with pytest.raises(Monose3Error, match="no images"):
        generate_dataset(tmp_path / "a", 1, backgrounds=tmp_path / "emptybg")
    with pytest.raises(Monose3Error, match="unknown robot"):
        generate_dataset(tmp_path / "a", 1, robot="ur5")
    assert not (tmp_path / "a").exists()


def test_preview_grid(small_set: Path, tmp_path: Path) -> None:
    path = save_preview_grid(small_set, tmp_path / "grid.png", rows=2, cols=3)
    grid = cv2.imread(str(path))
    assert grid.shape == (2 * 240 + 4, 3 * 320 + 8, 3)


def _generate_only(monkeypatch: pytest.MonkeyPatch) -> None:
    # build the parser with the generate command only, so this test does not depend on the others
    monkeypatch.setattr(cli, "COMMANDS", {"generate": cli.COMMANDS["generate"]})


def test_cli_errors(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    _generate_only(monkeypatch)
    rc = cli.main(["generate", "--out", str(tmp_path / "x"), "--num", "1", "--profile", "train", "--size", "10x10"])
    assert rc == 2 and "too small" in capsys.readouterr().err


@pytest.mark.slow
def test_cli_generates_200_frames(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, panda: RobotModel) -> None:
    _generate_only(monkeypatch)
    out = tmp_path / "d"
    assert cli.main(["generate", "--out", str(out), "--num", "200", "--seed", "0"]) == 0
    ds = DreamDataset(out, panda)
    assert len(ds) == 200 and ds.skipped == []
    check_ground_truth(ds, panda, seed=0)
