"""Robust SE(3) averaging against the plain mean, the calibration pipeline's rejections on a
scripted estimator, ``monose3 calibrate`` end to end with a tiny random model on DREAM and
plain folders, and each bad-input error."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from conftest import look_at

from monose3.apps.calibrate import write_calibration_files
from monose3.apps.cli import main
from monose3.calibration import REASON_CONSENSUS, REASON_OUT_OF_VIEW, REASON_UNRELIABLE, calibrate
from monose3.data.dream_writer import write_frame
from monose3.data.frames import load_frames
from monose3.errors import Monose3Error
from monose3.estimator import Estimate, PoseEstimator
from monose3.geometry.averaging import (
    geometric_median,
    mean_pose,
    pose_residuals,
    quaternion_mean,
    robust_consensus,
    robust_pose_average,
    rotation_l1_median,
)
from monose3.geometry.poses import make_pose
from monose3.geometry.rotations import matrix_to_rotvec, rotation_angle, rotvec_to_matrix
from monose3.robot.jobs import RenderJob

SIZE = (160, 120)
K = np.array([[150.0, 0.0, 79.5], [0.0, 150.0, 59.5], [0.0, 0.0, 1.0]])
N_FRAMES = 8


# ---- robust averaging -------------------------------------------------------------------------


def noisy_poses(rng, true, n, trans_std, rot_std_deg, outlier_fraction=0.0):
    """``n`` poses around ``true``; the first ``outlier_fraction`` of them are gross errors
    (any rotation, translation 0.3-1 m off)."""
    rots = true[:3, :3] @ rotvec_to_matrix(rng.normal(size=(n, 3)) * np.radians(rot_std_deg))
    trans = true[:3, 3] + rng.normal(size=(n, 3)) * trans_std
    poses = np.stack([make_pose(r, t) for r, t in zip(rots, trans, strict=True)])
    k = int(round(outlier_fraction * n))
    for i in range(k):
        axis = rng.normal(size=3)
        angle = rng.uniform(np.radians(30), np.pi)
        offset = rng.normal(size=3)
        offset *= rng.uniform(0.3, 1.0) / np.linalg.norm(offset)
        poses[i] = make_pose(true[:3, :3] @ rotvec_to_matrix(axis / np.linalg.norm(axis) * angle), true[:3, 3] + offset)
    return poses


TRUE = make_pose(rotvec_to_matrix(np.array([2.0, -0.5, 0.7])), np.array([0.1, -0.2, 1.6]))


def test_so3_log_exp_round_trip_including_near_pi():
    rng = np.random.default_rng(0)
    w = rng.normal(size=(200, 3))
    w = w / np.linalg.norm(w, axis=1, keepdims=True) * rng.uniform(0, np.pi - 1e-6, size=(200, 1))
    assert np.allclose(matrix_to_rotvec(rotvec_to_matrix(w)), w, atol=1e-6)
    r = rotvec_to_matrix(w)
    assert np.allclose(r @ np.swapaxes(r, 1, 2), np.eye(3), atol=1e-12)
    assert np.allclose(np.degrees(rotation_angle(np.eye(3), r)), np.degrees(np.linalg.norm(w, axis=1)), atol=1e-6)


def test_robust_average_ignores_30_percent_gross_outliers():
    rng = np.random.default_rng(1)
    poses = noisy_poses(rng, TRUE, 60, trans_std=0.005, rot_std_deg=1.0, outlier_fraction=0.3)
    robust_mm, robust_deg = pose_residuals(robust_pose_average(poses)[None], TRUE)
    mean_mm, mean_deg = pose_residuals(mean_pose(poses)[None], TRUE)
    # 42 inliers with 5 mm / 1 deg noise: the robust average is within a few mm / tenths of a degree...
    assert robust_mm[0] < 6.0 and robust_deg[0] < 0.6
    # ... while 18 gross errors drag the mean by centimetres and degrees.
    assert mean_mm[0] > 20.0 and mean_deg[0] > 5.0
    assert mean_mm[0] > 10 * robust_mm[0] and mean_deg[0] > 10 * robust_deg[0]
    consensus = robust_consensus(poses)
    assert not consensus.inliers[:18].any()  # every gross outlier rejected
    assert consensus.inliers[18:].mean() > 0.9  # and (nearly) no inlier
    fused_mm, fused_deg = pose_residuals(consensus.pose[None], TRUE)
    assert fused_mm[0] < 4.0 and fused_deg[0] < 0.5


def test_fusing_noisy_estimates_beats_the_median_single_frame():
    rng = np.random.default_rng(2)
    poses = noisy_poses(rng, TRUE, 40, trans_std=0.02, rot_std_deg=3.0, outlier_fraction=0.1)
    single_mm, single_deg = pose_residuals(poses, TRUE)
    fused = robust_consensus(poses).pose
    fused_mm, fused_deg = pose_residuals(fused[None], TRUE)
    assert fused_mm[0] < np.median(single_mm) / 2.5
    assert fused_deg[0] < np.median(single_deg) / 2.5


def test_rotation_average_across_the_quaternion_sign_flip():
    # Rotations around 179.5 deg: half of them have quaternions on the other side of w = 0.
    rng = np.random.default_rng(3)
    axis = np.array([0.0, 0.6, 0.8])
    centre = rotvec_to_matrix(axis * np.radians(179.5))
    rots = centre @ rotvec_to_matrix(rng.normal(size=(30, 3)) * np.radians(1.0))
    for average in (quaternion_mean, rotation_l1_median):
        assert np.degrees(rotation_angle(average(rots), centre)) < 0.5


def test_geometric_median_and_small_sets():
    pts = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0], [100, 0, 0]])
    assert np.allclose(geometric_median(pts), [2, 0, 0], atol=1e-6)
    assert np.allclose(geometric_median(pts[:1]), pts[0])
    one = robust_consensus(TRUE[None])
    assert one.inliers.all() and np.allclose(one.pose, TRUE)
    two = robust_consensus(np.stack([TRUE, make_pose(TRUE[:3, :3], TRUE[:3, 3] + 1.0)]))
    assert two.inliers.all()  # nothing can be called an outlier among two
    with pytest.raises(Monose3Error, match="NaN"):
        robust_pose_average(np.full((3, 4, 4), np.nan))


# ---- scenes ---------------------------------------------------------------------------------


# A static camera about 1.9 m in front of the Panda, looking at its middle.
POSE = look_at(np.array([1.7, 0.6, 0.8]), np.array([0.0, 0.0, 0.45]))


@pytest.fixture(scope="module")
def scene(models, renderers):
    """``N_FRAMES`` configurations of the Panda seen by one static camera: (joints [N, n], images)."""
    rng = np.random.default_rng(7)
    model = models["panda"]
    joints = model.random_joints(rng, N_FRAMES)
    images = [renderers["panda"].render_jobs([RenderJob(q, POSE, K, SIZE)])[0][0] for q in joints]
    return joints, images


@pytest.fixture(scope="module")
def dream_dir(tmp_path_factory, scene):
    folder = tmp_path_factory.mktemp("dream_static")
    for i, (q, rgb) in enumerate(zip(*scene, strict=True)):
        write_frame(folder, i, rgb, K, q, POSE)
    return folder


def write_plain(folder: Path, scene, models) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    joints, images = scene
    for i, (q, rgb) in enumerate(zip(joints, images, strict=True)):
        cv2.imwrite(str(folder / f"{i:04d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        (folder / f"{i:04d}.joints.json").write_text(json.dumps(models["panda"].joint_dict(q)))
    cam = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "width": SIZE[0], "height": SIZE[1]}
    (folder / "camera.json").write_text(json.dumps(cam))
    return folder


class ScriptedEstimator(PoseEstimator):
    """The real estimator's robot and renderer, with estimates scripted per frame (matched by
    joints): the true pose plus noise, or a chosen failure."""

    def __init__(self, base: PoseEstimator, joints: np.ndarray, script: dict[int, str], seed: int = 0):
        self.__dict__.update(base.__dict__)
        self.frame_joints = joints
        self.script = script
        self.rng = np.random.default_rng(seed)

    def estimate(self, images, Ks, joints, hypotheses=1, stochastic=False, seed=0, **kw) -> Estimate:
        poses, in_view, spread = [], [], []
        for q in joints:
            i = int(np.argmin(np.abs(self.frame_joints - q).sum(1)))
            what = self.script.get(i, "good")
            pose = noisy_poses(self.rng, POSE, 1, trans_std=0.004, rot_std_deg=0.5)[0]
            if what == "outlier":
                pose = make_pose(POSE[:3, :3] @ rotvec_to_matrix(np.array([0.0, 0.0, 0.6])), POSE[:3, 3] + 0.3)
            poses.append(pose)
            in_view.append(what != "out")
            spread.append(120.0 if what == "unreliable" else 3.0)
        poses = np.stack(poses)
        return Estimate(
            poses=poses,
            hypotheses=np.repeat(poses[:, None], hypotheses, 1),
            in_view=np.array(in_view),
            spread_mm=np.array(spread),
            spread_deg=np.array(spread) / 20,
        )


# ---- calibrate ------------------------------------------------------------------------------


def test_calibrate_rejects_each_kind_of_bad_frame(tiny, dream_dir, scene):
    frames = load_frames(dream_dir, tiny.robot)
    script = {1: "out", 3: "outlier", 5: "unreliable"}
    est = ScriptedEstimator(tiny, scene[0], script)
    result = calibrate(est, frames, chains=2, batch_size=3)
    reasons = [f.reason for f in result.frames]
    assert reasons[1] == REASON_OUT_OF_VIEW
    assert reasons[3] == REASON_CONSENSUS
    assert reasons[5] == REASON_UNRELIABLE
    assert [f.used for f in result.frames] == [i not in script for i in range(N_FRAMES)]
    assert result.rejected == {REASON_OUT_OF_VIEW: 1, REASON_CONSENSUS: 1, REASON_UNRELIABLE: 1}
    mm, deg = pose_residuals(result.camera_from_base[None], POSE)
    assert mm[0] < 8.0 and deg[0] < 0.8  # 5 good frames of 4 mm / 0.5 deg noise
    gt = result.ground_truth
    assert gt is not None and gt["static_camera"]
    assert gt["fused_error_mm"] == pytest.approx(mm[0], abs=1e-6)
    assert result.frames[3].residual_mm > 250  # the outlier is 0.3 m off on every axis
    assert all(f.residual_mm < result.threshold_mm for f in result.used)


def test_calibrate_all_frames_rejected(tiny, dream_dir, scene):
    frames = load_frames(dream_dir, tiny.robot)
    est = ScriptedEstimator(tiny, scene[0], {i: "out" for i in range(N_FRAMES)})
    with pytest.raises(Monose3Error, match=f"all {N_FRAMES} frames were rejected .*{N_FRAMES} out of view"):
        calibrate(est, frames)


def test_calibrate_cli_end_to_end_on_dream(dream_dir, checkpoint, tmp_path, capsys):
    out = tmp_path / "out"
    rc = main(["calibrate", "--frames", str(dream_dir), "--checkpoint", str(checkpoint), "--out", str(out)])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "vs ground truth" in printed and "camera_from_base" in printed
    data = json.loads((out / "calibration.json").read_text())
    fused = np.array(data["camera_from_base"])
    assert np.allclose(fused[:3, :3] @ fused[:3, :3].T, np.eye(3), atol=1e-9)
    assert np.allclose(np.array(data["base_from_camera"]) @ fused, np.eye(4), atol=1e-9)
    assert data["frames_total"] == N_FRAMES and len(data["frames"]) == N_FRAMES
    assert data["frames_used"] == sum(f["used"] for f in data["frames"]) >= 1
    # The per-frame residuals are those of the written single-frame poses to the fused one.
    singles = np.array([f["camera_from_base"] for f in data["frames"]])
    mm, deg = pose_residuals(singles, fused)
    assert np.allclose(mm, [f["residual_mm"] for f in data["frames"]], atol=1e-6)
    assert np.allclose(deg, [f["residual_deg"] for f in data["frames"]], atol=1e-6)
    # The reported error against ground truth is that of the written pose.
    assert data["ground_truth"]["fused_error_mm"] == pytest.approx(pose_residuals(fused[None], POSE)[0][0], abs=1e-6)
    summary = yaml.safe_load((out / "calibration.yaml").read_text())
    assert np.allclose(summary["camera_from_base"], fused) and "frames" not in summary
    grid = cv2.imread(str(out / "calibration_overlay.png"))
    assert grid.shape == (2 * SIZE[1] + 4, 3 * SIZE[0] + 8, 3)  # 6 frames, 3 columns


def test_calibrate_plain_folder(tiny, scene, models, tmp_path):
    folder = write_plain(tmp_path / "plain", scene, models)
    frames = load_frames(folder, tiny.robot)
    assert [f.name for f in frames] == [f"{i:04d}" for i in range(N_FRAMES)]
    assert np.allclose(frames[2].joints, scene[0][2])
    est = ScriptedEstimator(tiny, scene[0], {0: "outlier"})
    result = calibrate(est, frames)
    assert result.ground_truth is None  # the plain layout has no ground truth
    assert result.frames[0].reason == REASON_CONSENSUS and len(result.used) == N_FRAMES - 1
    json_path, yaml_path = write_calibration_files(result, tmp_path / "out")
    data = yaml.safe_load(yaml_path.read_text())
    assert np.allclose(np.array(data["base_from_camera"]), np.linalg.inv(result.camera_from_base))
    xyzq = data["camera_from_base_xyz_quat_xyzw"]
    assert np.allclose(xyzq[:3], result.camera_from_base[:3, 3])
    assert json.loads(json_path.read_text())["frames"][0]["rejected_because"] == REASON_CONSENSUS


# ---- bad inputs -------------------------------------------------------------------------------


def test_empty_folder(tiny, tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(Monose3Error, match="is empty"):
        load_frames(tmp_path / "empty", tiny.robot)
    with pytest.raises(Monose3Error, match="not found"):
        load_frames(tmp_path / "missing", tiny.robot)


def test_missing_joints_file(tiny, scene, models, tmp_path):
    folder = write_plain(tmp_path / "plain", scene, models)
    (folder / "0003.joints.json").unlink()
    with pytest.raises(Monose3Error, match=r"no joints file for image 0003\.png.*add 0003\.joints\.json"):
        load_frames(folder, tiny.robot)
    # Images alone (no joints files, no camera.json) get the same advice.
    only = tmp_path / "only_images"
    only.mkdir()
    cv2.imwrite(str(only / "0000.png"), np.zeros((SIZE[1], SIZE[0], 3), np.uint8))
    with pytest.raises(Monose3Error, match=r"no joints file for image 0000\.png"):
        load_frames(only, tiny.robot)


def test_missing_camera_and_wrong_image_size(tiny, scene, models, tmp_path):
    folder = write_plain(tmp_path / "plain", scene, models)
    (folder / "camera.json").unlink()
    with pytest.raises(Monose3Error, match="no camera.json"):
        load_frames(folder, tiny.robot)
    cam = {"fx": 300.0, "fy": 300.0, "cx": 159.5, "cy": 119.5, "width": 320, "height": 240}
    (folder / "camera.json").write_text(json.dumps(cam))
    frames = load_frames(folder, tiny.robot)
    with pytest.raises(Monose3Error, match="0000.png is 160x120 but the camera intrinsics are for 320x240"):
        frames[0].load_image()


def test_cli_error_is_one_line(checkpoint, tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    rc = main(["calibrate", "--frames", str(tmp_path / "empty"), "--checkpoint", str(checkpoint)])
    assert rc == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("monose3 calibrate: error:") and "is empty" in err and "\n" not in err
