"""RoboKeyGen reader on hand-written sequences laid out as RoboKeyGen's real sets are."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from monose3.data.datasets import detect_layout, open_dataset
from monose3.data.robokeygen import RoboKeyGenDataset, find_sequences
from monose3.errors import Monose3Error
from monose3.robot import RobotModel

K_D415 = np.array([[615.0, 0.0, 320.0], [0.0, 615.0, 180.0], [0.0, 0.0, 1.0]])
LINKS = [f"panda_link{i}" for i in range(8)] + ["panda_hand", "panda_leftfinger", "panda_rightfinger"]


def random_pose(rng: np.random.Generator) -> np.ndarray:
    """Camera-from-base: base 1-2 m in front of the camera, arbitrary orientation."""
    a = rng.normal(size=(3, 3))
    u, _, vt = np.linalg.svd(a)
    rot = u @ np.diag([1, 1, np.linalg.det(u @ vt)]) @ vt
    pose = np.eye(4)
    pose[:3, :3] = rot
    pose[:3, 3] = [rng.uniform(-0.3, 0.3), rng.uniform(-0.2, 0.2), rng.uniform(1.0, 2.0)]
    return pose


def meta_record(model: RobotModel, q: np.ndarray, pose: np.ndarray, K: np.ndarray = K_D415) -> list:
    """RoboKeyGen's ``NNNN_meta.json``: a list whose element 0 holds per-link keypoints
    (Name, location_wrt_cam, R2C_mat, projected_location) and joints (Name, position)."""
    links = model.link_poses(q[None])[0]
    keypoints = []
    for name in LINKS:
        link_cam = pose @ links[model.link_index[name]]
        p = link_cam[:3, 3]
        uv = (K @ p)[:2] / p[2]
        keypoints.append(
            {
                "Name": name,
                "location_wrt_cam": p.tolist(),
                "R2C_mat": link_cam[:3, :3].tolist(),
                "projected_location": uv.tolist(),
                "Part ID": LINKS.index(name),
            }
        )
    joints = [
        {"Name": n, "position": float(v), "location_wrt_cam": [0.0, 0.0, 1.0]}
        for n, v in zip(model.joint_names, q, strict=True)
    ]
    return [{"keypoints": keypoints, "joints": joints}]


def settings(folder: Path, K: np.ndarray = K_D415, size: tuple[int, int] = (640, 360)) -> None:
    intr = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}
    cam = {"intrinsic_settings": intr, "captured_image_size": {"width": size[0], "height": size[1]}}
    (folder / "_camera_settings.json").write_text(json.dumps({"camera_settings": [cam]}))


def write_sequence(folder: Path, model: RobotModel, n: int, seed: int, layout: str = "meta") -> list:
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    truth = []
    for i in range(n):
        q = model.random_joints(rng, 1)[0]
        pose = random_pose(rng)
        if layout == "meta":
            meta, image = folder / f"{i:04d}_meta.json", folder / f"{i:04d}_color.png"
        else:
            meta, image = folder / f"{i:06d}.json", folder / f"{i:06d}.png"
        meta.write_text(json.dumps(meta_record(model, q, pose)))
        cv2.imwrite(str(image), np.zeros((360, 640, 3), np.uint8))
        truth.append((q, pose))
    return truth


def test_sequences_read_with_pose_from_fit(tmp_path: Path, panda: RobotModel) -> None:
    settings(tmp_path)  # the intrinsics sit in the folder that holds the sequences
    t1 = write_sequence(tmp_path / "1_D415_front_0", panda, 3, seed=0)
    t2 = write_sequence(tmp_path / "2_D415_front_1", panda, 2, seed=1)
    assert detect_layout(tmp_path) == "robokeygen"
    ds = open_dataset(tmp_path, panda)
    assert isinstance(ds, RoboKeyGenDataset)
    assert [f.name for f in ds] == [f"1_D415_front_0/{i:04d}" for i in range(3)] + [
        f"2_D415_front_1/{i:04d}" for i in range(2)
    ]
    for frame, (q, pose) in zip(ds, t1 + t2, strict=True):
        np.testing.assert_allclose(frame.joints, q, atol=1e-12)
        np.testing.assert_allclose(frame.pose, pose, atol=1e-9)
        assert frame.pose_residual < 1e-9
        assert frame.image_size == (640, 360)
        np.testing.assert_allclose(frame.K, K_D415)
        kp = panda.keypoints(q[None])[0] @ pose[:3, :3].T + pose[:3, 3]
        np.testing.assert_allclose(frame.keypoints_3d, kp, atol=1e-12)
        np.testing.assert_allclose(frame.keypoints_2d, kp[:, :2] / kp[:, 2:] * 615.0 + [320.0, 180.0], atol=1e-9)
        assert frame.load_image().shape == (360, 640, 3)
        assert frame.image_path.name.endswith("_color.png")

    # one sequence on its own: names are the frame stems, intrinsics found in the parent
    single = RoboKeyGenDataset(tmp_path / "2_D415_front_1", panda)
    assert [f.name for f in single] == ["0000", "0001"]


def test_variant_layout_and_per_frame_intrinsics(tmp_path: Path, panda: RobotModel) -> None:
    truth = write_sequence(tmp_path / "seq", panda, 2, seed=2, layout="plain")
    for i in range(2):  # no _camera_settings.json: K and size in the meta; lower-case key variants
        path = tmp_path / "seq" / f"{i:06d}.json"
        rec = json.loads(path.read_text())
        rec[0]["camera_K"] = K_D415.tolist()
        for kp in rec[0]["keypoints"]:
            kp["name"] = kp.pop("Name")
        path.write_text(json.dumps(rec))
    assert find_sequences(tmp_path) == [tmp_path / "seq"]
    ds = open_dataset(tmp_path / "seq", panda)
    assert isinstance(ds, RoboKeyGenDataset)
    for frame, (_, pose) in zip(ds, truth, strict=True):
        np.testing.assert_allclose(frame.pose, pose, atol=1e-9)
        assert frame.image_size == (640, 360)  # from the PNG header


def test_noisy_annotation_residual(tmp_path: Path, panda: RobotModel) -> None:
    settings(tmp_path)
    truth = write_sequence(tmp_path / "s", panda, 1, seed=3)
    path = tmp_path / "s" / "0000_meta.json"
    rec = json.loads(path.read_text())
    rng = np.random.default_rng(0)
    for kp in rec[0]["keypoints"]:
        kp["location_wrt_cam"] = (np.array(kp["location_wrt_cam"]) + rng.normal(0, 0.004, 3)).tolist()
    path.write_text(json.dumps(rec))
    frame = RoboKeyGenDataset(tmp_path / "s", panda)[0]
    assert 0.001 < frame.pose_residual < 0.012
    assert np.linalg.norm(frame.pose[:3, 3] - truth[0][1][:3, 3]) < 0.02


def test_malformed_frames_skipped(tmp_path: Path, panda: RobotModel, caplog) -> None:
    settings(tmp_path)
    write_sequence(tmp_path / "s", panda, 5, seed=4)
    seq = tmp_path / "s"
    rec = json.loads((seq / "0001_meta.json").read_text())
    rec[0]["joints"] = rec[0]["joints"][:3]
    (seq / "0001_meta.json").write_text(json.dumps(rec))
    (seq / "0002_meta.json").write_text("[{")
    (seq / "0003_color.png").unlink()
    rec = json.loads((seq / "0004_meta.json").read_text())
    rec[0]["keypoints"] = [k for k in rec[0]["keypoints"] if k["Name"] != "panda_hand"]
    (seq / "0004_meta.json").write_text(json.dumps(rec))
    with caplog.at_level(logging.WARNING, logger="monose3"):
        ds = RoboKeyGenDataset(seq, panda)
    assert [f.name for f in ds] == ["0000"]
    reasons = dict(ds.skipped)
    assert "panda_joint4" in reasons["0001_meta.json"]
    assert "unreadable JSON" in reasons["0002_meta.json"]
    assert "0003_color.png" in reasons["0003_meta.json"]
    assert "panda_hand" in reasons["0004_meta.json"]
    assert sum("skipped 4 of 5" in r.getMessage() for r in caplog.records) == 1


def test_errors(tmp_path: Path, panda: RobotModel) -> None:
    with pytest.raises(Monose3Error, match="not found"):
        RoboKeyGenDataset(tmp_path / "nope", panda)
    (tmp_path / "empty").mkdir()
    with pytest.raises(Monose3Error, match="no RoboKeyGen frames"):
        RoboKeyGenDataset(tmp_path / "empty", panda)
    write_sequence(tmp_path / "nocam", panda, 2, seed=5)
    with pytest.raises(Monose3Error, match="_camera_settings.json"):
        RoboKeyGenDataset(tmp_path / "nocam", panda)
