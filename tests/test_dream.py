"""DREAM reader and writer on hand-written frames (real: meters, keypoints only; synthetic:
centimetres and an Unreal-axes quaternion), malformed frames and bad inputs."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from monose3.data.datasets import detect_layout, frames_digest, open_dataset
from monose3.data.dream import UNREAL_TO_OPENCV, DreamDataset
from monose3.data.dream_writer import write_camera_settings, write_frame
from monose3.data.frame import Frame
from monose3.errors import Monose3Error
from monose3.robot import RobotModel

K_REAL = np.array([[615.52, 0.0, 328.26], [0.0, 615.22, 251.79], [0.0, 0.0, 1.0]])


def camera_pose(rng: np.random.Generator, model: RobotModel, joints: np.ndarray) -> np.ndarray:
    """A camera 1-2 m from the robot looking at it (plain numpy, independent of the generator)."""
    centre = model.centroid(model.surface_points(joints[None])[0])
    az, el = rng.uniform(0, 2 * np.pi), rng.uniform(0.0, 0.8)
    eye = centre + rng.uniform(1.0, 2.0) * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    z = (centre - eye) / np.linalg.norm(centre - eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, np.cross(z, x), z])
    pose[:3, 3] = -pose[:3, :3] @ eye
    return pose


def project(points: np.ndarray, K: np.ndarray) -> np.ndarray:
    return points[:, :2] / points[:, 2:3] * K[[0, 1], [0, 1]] + K[[0, 1], [2, 2]]


def write_image(path: Path, size: tuple[int, int] = (64, 48)) -> None:
    cv2.imwrite(str(path), np.full((size[1], size[0], 3), 127, np.uint8))


def real_record(model: RobotModel, joints: np.ndarray, kp_cam: np.ndarray, prefix: str = "panda/") -> dict:
    """A DREAM-real style frame: no orientation, keypoints in meters."""
    return {
        "objects": [
            {
                "class": "panda",
                "location": kp_cam[0].tolist(),
                "keypoints": [
                    {"name": n, "location": p.tolist(), "projected_location": q.tolist()}
                    for n, p, q in zip(model.keypoint_names, kp_cam, project(kp_cam, K_REAL), strict=True)
                ],
            }
        ],
        "sim_state": {
            "joints": [
                {"name": prefix + n, "position": float(v)} for n, v in zip(model.joint_names, joints, strict=True)
            ]
        },
    }


def camera_settings(folder: Path, K: np.ndarray = K_REAL, size: tuple[int, int] = (640, 480)) -> None:
    (folder / "_camera_settings.json").write_text(
        json.dumps(
            {
                "camera_settings": [
                    {
                        "name": "cam",
                        "intrinsic_settings": dict(
                            zip(("fx", "fy", "cx", "cy"), K[[0, 1, 0, 1], [0, 1, 2, 2]], strict=True)
                        ),
                        "captured_image_size": {"width": size[0], "height": size[1]},
                    }
                ]
            }
        )
    )


def write_real_set(folder: Path, model: RobotModel, n: int, noise: float, seed: int = 0):
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    camera_settings(folder)
    truth = []
    for i in range(n):
        q = model.random_joints(rng, 1)[0]
        pose = camera_pose(rng, model, q)
        kp = model.keypoints(q[None])[0] @ pose[:3, :3].T + pose[:3, 3]
        kp_noisy = kp + rng.normal(0, noise, kp.shape)
        (folder / f"{i:06d}.json").write_text(json.dumps(real_record(model, q, kp_noisy)))
        write_image(folder / f"{i:06d}.rgb.jpg")
        truth.append((q, pose, kp_noisy))
    return truth


def test_real_frames_pose_from_rigid_fit(tmp_path: Path, panda: RobotModel) -> None:
    truth = write_real_set(tmp_path / "exact", panda, 3, noise=0.0)
    ds = DreamDataset(tmp_path / "exact", panda)
    assert len(ds) == 3 and ds.skipped == []
    for frame, (q, pose, kp) in zip(ds, truth, strict=True):
        assert isinstance(frame, Frame)
        np.testing.assert_allclose(frame.joints, q, atol=1e-12)
        np.testing.assert_allclose(frame.pose, pose, atol=1e-9)
        np.testing.assert_allclose(frame.keypoints_3d, kp, atol=1e-12)
        np.testing.assert_allclose(frame.K, K_REAL)
        assert frame.image_size == (640, 480)
        assert frame.pose_residual < 1e-9
        assert frame.keypoint_names == panda.keypoint_names
        np.testing.assert_allclose(frame.keypoints_2d, project(kp, K_REAL), atol=1e-9)

    # With 5 mm annotation noise the fit stays close and the residual reports the noise level.
    truth = write_real_set(tmp_path / "noisy", panda, 4, noise=0.005, seed=1)
    for frame, (_, pose, _) in zip(DreamDataset(tmp_path / "noisy", panda), truth, strict=True):
        assert np.linalg.norm(frame.pose[:3, 3] - pose[:3, 3]) < 0.02
        assert 0.002 < frame.pose_residual < 0.015


def test_real_frames_stored_in_cm_are_detected(tmp_path: Path, panda: RobotModel) -> None:
    truth = write_real_set(tmp_path, panda, 1, noise=0.0)
    rec = json.loads((tmp_path / "000000.json").read_text())
    for kp in rec["objects"][0]["keypoints"]:
        kp["location"] = [100 * v for v in kp["location"]]
    (tmp_path / "000000.json").write_text(json.dumps(rec))
    frame = DreamDataset(tmp_path, panda)[0]
    np.testing.assert_allclose(frame.pose, truth[0][1], atol=1e-9)
    np.testing.assert_allclose(frame.keypoints_3d, truth[0][2], atol=1e-12)


def test_synthetic_frame_cm_and_unreal_quaternion(tmp_path: Path, panda: RobotModel) -> None:
    """Identity rotation in OpenCV axes is (x, y, z, w) = (-0.5, 0.5, -0.5, 0.5) in Unreal's axes
    (the rotation M^T with M = [[0,-1,0],[0,0,-1],[1,0,0]]), written by hand here."""
    q = np.array([0.3, -0.5, 0.1, -1.2, 0.4, 1.5, 0.2, 0.03])
    t = np.array([0.1, 0.2, 1.5])
    kp_cm = (panda.keypoints(q[None])[0] + t) * 100
    rec = {
        "objects": [
            {
                "class": "panda",
                "location": (t * 100).tolist(),
                "quaternion_xyzw": [-0.5, 0.5, -0.5, 0.5],
                "keypoints": [
                    {"name": n, "location": p.tolist()} for n, p in zip(panda.keypoint_names, kp_cm, strict=True)
                ],
            }
        ],
        "sim_state": {
            "joints": [{"name": f"panda/{n}", "position": v} for n, v in zip(panda.joint_names, q, strict=True)]
        },
    }
    (tmp_path / "000000.json").write_text(json.dumps(rec))
    write_image(tmp_path / "000000.rgb.jpg")
    camera_settings(tmp_path)
    frame = DreamDataset(tmp_path, "panda")[0]
    np.testing.assert_allclose(frame.pose[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(frame.pose[:3, 3], t, atol=1e-12)
    np.testing.assert_allclose(frame.keypoints_3d, kp_cm / 100, atol=1e-12)
    assert frame.pose_residual == 0.0
    # no projected_location in the file: projected with K
    np.testing.assert_allclose(frame.keypoints_2d, project(kp_cm / 100, K_REAL), atol=1e-9)
    np.testing.assert_allclose(UNREAL_TO_OPENCV @ UNREAL_TO_OPENCV.T, np.eye(3))


def test_write_read_roundtrip(tmp_path: Path, panda: RobotModel) -> None:
    rng = np.random.default_rng(3)
    poses, joints = [], []
    for i in range(5):
        q = panda.random_joints(rng, 1)[0]
        pose = camera_pose(rng, panda, q)
        K = np.array([[500 + 10 * i, 0, 320.5], [0, 505 + 10 * i, 240.2], [0, 0, 1]])
        img = rng.integers(0, 256, (480, 640, 3), dtype=np.uint8)
        write_frame(tmp_path, i, img, K, panda.joint_dict(q), pose, robot=panda, quality=90)
        poses.append((pose, K))
        joints.append(q)
    write_camera_settings(tmp_path, np.array([[500.0, 0, 319.5], [0, 500, 239.5], [0, 0, 1]]), 640, 480)
    ds = DreamDataset(tmp_path, panda)
    assert [f.name for f in ds] == [f"{i:06d}" for i in range(5)]
    for frame, (pose, K), q in zip(ds, poses, joints, strict=True):
        np.testing.assert_allclose(frame.pose, pose, atol=1e-9)
        np.testing.assert_allclose(frame.joints, q, atol=1e-12)
        np.testing.assert_allclose(frame.K, K)  # per-frame intrinsics override the folder's
        kp = panda.keypoints(q[None])[0] @ pose[:3, :3].T + pose[:3, 3]
        np.testing.assert_allclose(frame.keypoints_3d, kp, atol=1e-9)
        np.testing.assert_allclose(frame.keypoints_2d, project(kp, K), atol=1e-6)
        assert frame.load_image().shape == (480, 640, 3)
        assert frame.image_path.name == f"{frame.name}.rgb.jpg"
    assert ds[-1].name == "000004" and len(ds[1:3]) == 2
    with pytest.raises(IndexError):
        ds[5]
    # joints given as a vector and keypoints left to the writer's FK give the same file content
    write_frame(tmp_path / "b", 0, np.zeros((48, 64, 3), np.uint8), poses[0][1], joints[0], poses[0][0], robot="panda")
    a = json.loads((tmp_path / "000000.json").read_text())
    b = json.loads((tmp_path / "b" / "000000.json").read_text())
    assert a["objects"][0]["keypoints"] == b["objects"][0]["keypoints"]


def test_load_image_errors(tmp_path: Path, panda: RobotModel) -> None:
    write_real_set(tmp_path, panda, 1, noise=0.0)
    frame = DreamDataset(tmp_path, panda)[0]
    (tmp_path / "000000.rgb.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(Monose3Error, match="corrupt"):
        frame.load_image()
    (tmp_path / "000000.rgb.jpg").unlink()
    with pytest.raises(Monose3Error, match="not found"):
        frame.load_image()


def test_malformed_frames_are_skipped_and_reported(tmp_path: Path, panda: RobotModel, caplog) -> None:
    write_real_set(tmp_path, panda, 9, noise=0.0)

    def edit(i: int, fn) -> None:
        path = tmp_path / f"{i:06d}.json"
        rec = json.loads(path.read_text())
        fn(rec)
        path.write_text(json.dumps(rec))

    edit(1, lambda r: r["sim_state"]["joints"].pop(2))  # missing joint
    edit(2, lambda r: r["objects"][0]["keypoints"][3].update(location=[0.1, "x", 0.3]))  # non-numeric
    edit(3, lambda r: r["objects"][0]["keypoints"].pop(0))  # missing keypoint
    edit(4, lambda r: r["objects"][0]["keypoints"][1].update(location=[0.1, float("nan"), 0.3]))
    (tmp_path / "000005.json").write_text('{"objects": [')  # truncated JSON
    (tmp_path / "000006.rgb.jpg").unlink()  # image missing

    def decimetres(rec: dict) -> None:  # neither meters nor centimetres
        for kp in rec["objects"][0]["keypoints"]:
            kp["location"] = [10 * v for v in kp["location"]]

    edit(7, decimetres)
    with caplog.at_level(logging.WARNING, logger="monose3"):
        ds = DreamDataset(tmp_path, panda)
    assert [f.name for f in ds] == ["000000", "000008"]
    reasons = dict(ds.skipped)
    assert sorted(reasons) == [f"00000{i}.json" for i in range(1, 8)]
    assert "panda_joint3" in reasons["000001.json"]
    assert "not numeric" in reasons["000002.json"]
    assert "panda_link0" in reasons["000003.json"]
    assert "NaN" in reasons["000004.json"]
    assert "unreadable JSON" in reasons["000005.json"]
    assert "image" in reasons["000006.json"]
    assert "neither meters nor centimetres" in reasons["000007.json"]
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "skipped 7 of 9" in warnings[0].getMessage()


def test_bad_inputs_raise_with_fix(tmp_path: Path, panda: RobotModel) -> None:
    with pytest.raises(Monose3Error, match="not found"):
        DreamDataset(tmp_path / "missing", panda)
    (tmp_path / "empty").mkdir()
    with pytest.raises(Monose3Error, match="no DREAM frames"):
        DreamDataset(tmp_path / "empty", panda)
    with pytest.raises(Monose3Error, match="units"):
        DreamDataset(tmp_path / "empty", panda, units="mm")

    write_real_set(tmp_path / "nocam", panda, 2, noise=0.0)
    (tmp_path / "nocam" / "_camera_settings.json").unlink()
    with pytest.raises(Monose3Error, match="_camera_settings.json"):
        DreamDataset(tmp_path / "nocam", panda)

    write_real_set(tmp_path / "badcam", panda, 1, noise=0.0)
    (tmp_path / "badcam" / "_camera_settings.json").write_text('{"camera_settings": [{}]}')
    with pytest.raises(Monose3Error, match="malformed camera settings"):
        DreamDataset(tmp_path / "badcam", panda)

    # every frame unusable (here: the keypoints belong to another robot)
    write_real_set(tmp_path / "kuka", panda, 2, noise=0.0)
    with pytest.raises(Monose3Error, match="none of the 2 frames"):
        DreamDataset(tmp_path / "kuka", "kuka")


def test_open_dataset_detects_layout(tmp_path: Path, panda: RobotModel) -> None:
    write_real_set(tmp_path / "dream", panda, 2, noise=0.0)
    assert detect_layout(tmp_path / "dream") == "dream"
    assert isinstance(open_dataset(tmp_path / "dream", panda), DreamDataset)
    (tmp_path / "nothing").mkdir()
    (tmp_path / "nothing" / "readme.txt").write_text("hi")
    with pytest.raises(Monose3Error, match="neither DREAM"):
        open_dataset(tmp_path / "nothing", panda)
    with pytest.raises(Monose3Error, match="not found"):
        open_dataset(tmp_path / "gone", panda)


def test_frames_digest_names_the_frames_and_sees_a_changed_image_or_pose(tmp_path: Path, panda: RobotModel) -> None:
    import dataclasses
    import shutil

    write_real_set(tmp_path / "a", panda, 3, noise=0.0)
    shutil.copytree(tmp_path / "a", tmp_path / "b")
    a, b = open_dataset(tmp_path / "a", panda), open_dataset(tmp_path / "b", panda)
    digest = frames_digest([a[i] for i in range(3)])
    assert len(digest) == 16 and digest == frames_digest([b[i] for i in range(3)])  # a copy: the same frames
    assert frames_digest([a[i] for i in range(2)]) != digest
    moved = dataclasses.replace(a[2], pose=a[2].pose + np.eye(4) * 1e-9)
    assert frames_digest([a[0], a[1], moved]) != digest
    image = b[1].image_path
    image.write_bytes(image.read_bytes() + b"\0")
    assert frames_digest([b[i] for i in range(3)]) != digest
