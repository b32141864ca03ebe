"""The estimate command and Python API: outputs, and a one-line error for each bad input."""

import json

import numpy as np
import pytest
import yaml
from conftest import save_tiny_checkpoint

from monose3.api import estimate_pose, load_estimator
from monose3.apps.cli import main
from monose3.data.datasets import open_dataset
from monose3.robot import RobotModel


@pytest.fixture(scope="module")
def scene(tiny_dream, tmp_path_factory):
    """An image, joints and camera files written the way a user would have them."""
    d = tmp_path_factory.mktemp("scene")
    frame = open_dataset(tiny_dream, "panda")[0]
    (d / "image.jpg").write_bytes(frame.image_path.read_bytes())
    (d / "joints.json").write_text(json.dumps(RobotModel("panda").joint_dict(frame.joints)))
    K = frame.K
    cam = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "width": 160, "height": 120}
    (d / "camera.json").write_text(json.dumps(cam))
    save_tiny_checkpoint(d / "panda.pt")
    save_tiny_checkpoint(d / "kuka.pt", robot="kuka")
    save_tiny_checkpoint(d / "wild.pt", xy_bias=20.0)
    return d, frame


def _estimate(d, *extra, image="image.jpg", joints="joints.json", camera="camera.json", ck="panda.pt"):
    return main(
        [
            "estimate",
            "--image",
            str(d / image),
            "--joints",
            str(d / joints),
            "--camera",
            str(d / camera),
            "--checkpoint",
            str(d / ck),
            "--out",
            str(d / "out"),
            "--chains",
            "2",
            "--sampler",  # the tiny checkpoints exercise the paper's sampler; test_fit_* the default
            "revdiff",
            *extra,
        ]
    )


def test_estimate_writes_pose_files_and_overlay(scene, capsys):
    d, _ = scene
    assert _estimate(d) == 0
    data = json.loads((d / "out" / "pose.json").read_text())
    pose, inv = np.asarray(data["camera_from_base"]), np.asarray(data["base_from_camera"])
    assert np.allclose(pose @ inv, np.eye(4), atol=1e-9) and data["units"] == "meters"
    assert yaml.safe_load((d / "out" / "pose.yaml").read_text())["chains"] == 2
    assert (d / "out" / "overlay.png").stat().st_size > 1000
    assert "camera_from_base" in capsys.readouterr().out


def test_python_api_mirrors_the_cli(scene, tmp_path):
    """``estimate_pose`` on the frame's own arrays gives what ``monose3 estimate`` writes from the
    user's files (image, joints.json, camera.json) for the same checkpoint and chains."""
    d, frame = scene
    est = load_estimator(d / "panda.pt")
    try:
        result = estimate_pose(est, frame.load_image(), frame.joints, frame.K, chains=2, sampler="revdiff")
    finally:
        est.close()
    assert result.camera_from_base.shape == (4, 4) and 0 <= result.confidence <= 1
    assert result.estimate.hypotheses.shape == (1, 2, 4, 4)
    assert _estimate(d, "--chains", "2", "--out", str(tmp_path)) == 0
    cli = json.loads((tmp_path / "pose.json").read_text())
    api = result.to_dict()
    assert set(cli) == set(api)
    np.testing.assert_allclose(cli["camera_from_base"], result.camera_from_base, rtol=0, atol=1e-9)
    np.testing.assert_allclose(cli["base_from_camera"], result.base_from_camera, rtol=0, atol=1e-9)
    for key in sorted(set(api) - {"camera_from_base", "base_from_camera"}):
        same = cli[key] == pytest.approx(api[key], rel=1e-9) if isinstance(api[key], float) else cli[key] == api[key]
        assert same, (key, cli[key], api[key])


def _write(d, name, content):
    (d / name).write_text(content if isinstance(content, str) else json.dumps(content))
    return name


@pytest.mark.parametrize(
    ("kind", "needle"),
    [
        ("missing_image", "image not found"),
        ("unreadable_image", "could not read"),
        ("missing_joint", "missing joint"),
        ("unknown_joint", "unknown joint"),
        ("nan_joint", "nan"),
        ("wrong_count", "joint values"),
        ("missing_camera", "not found"),
        ("negative_focal", "positive"),
        ("camera_size_mismatch", "160x120"),
        ("unknown_robot", "unknown robot"),
        ("other_robot_checkpoint", "kuka"),
        ("leaves_image", "outside the image"),
    ],
)
def test_bad_input_gives_one_line_error(scene, kind, needle, capsys):
    d, frame = scene
    joints = RobotModel("panda").joint_dict(frame.joints)
    kw, extra = {}, []
    if kind == "missing_image":
        kw["image"] = "nope.jpg"
    elif kind == "unreadable_image":
        kw["image"] = _write(d, "text.png", "not an image")
    elif kind == "missing_joint":
        kw["joints"] = _write(d, "j1.json", {k: v for k, v in joints.items() if k != "panda_joint3"})
    elif kind == "unknown_joint":
        kw["joints"] = _write(d, "j2.json", {**joints, "elbow": 0.1})
    elif kind == "nan_joint":
        kw["joints"] = _write(d, "j3.json", json.dumps({**joints, "panda_joint2": float("nan")}))
    elif kind == "wrong_count":
        kw["joints"] = _write(d, "j4.json", [0.0, 0.1, 0.2])
    elif kind == "missing_camera":
        kw["camera"] = "nocam.json"
    elif kind == "negative_focal":
        kw["camera"] = _write(d, "c1.json", {"fx": -1, "fy": 100, "cx": 80, "cy": 60, "width": 160, "height": 120})
    elif kind == "camera_size_mismatch":
        kw["camera"] = _write(d, "c2.json", {"fx": 400, "fy": 400, "cx": 320, "cy": 240, "width": 640, "height": 480})
    elif kind == "unknown_robot":
        extra = ["--robot", "ur5"]
    elif kind == "other_robot_checkpoint":
        kw["ck"], extra = "kuka.pt", ["--robot", "panda"]
    elif kind == "leaves_image":
        kw["ck"] = "wild.pt"
    assert _estimate(d, *extra, **kw) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle.lower() in err.lower(), err


def _add(frame, pose):
    kps = RobotModel("panda").keypoints(frame.joints[None], pose[None])[0]
    return float(np.linalg.norm(kps - frame.keypoints_3d, axis=1).mean())


def test_prior_is_refined_instead_of_robopose_start(scene):
    """The tiny model barely moves a pose, so a good prior must give a good estimate and no prior a bad one."""
    d, frame = scene
    est = load_estimator(d / "panda.pt")
    try:
        image = frame.load_image()
        with_prior = estimate_pose(est, image, frame.joints, frame.K, chains=1, prior=frame.pose, sampler="revdiff")
        without = estimate_pose(est, image, frame.joints, frame.K, chains=1, sampler="revdiff")
    finally:
        est.close()
    assert np.allclose(with_prior.estimate.history[0][0, 0], frame.pose)
    assert _add(frame, with_prior.camera_from_base) < 0.02 < _add(frame, without.camera_from_base)


def test_estimate_cli_takes_a_previous_pose_file_as_prior(scene):
    d, frame = scene
    (d / "prior.json").write_text(json.dumps({"camera_from_base": frame.pose.tolist()}))
    assert _estimate(d, "--prior", str(d / "prior.json"), "--chains", "1") == 0
    pose = np.asarray(json.loads((d / "out" / "pose.json").read_text())["camera_from_base"])
    assert _add(frame, pose) < 0.02


def test_inverted_prior_is_refused(scene, capsys):
    d, frame = scene
    (d / "inv.json").write_text(json.dumps({"camera_from_base": np.linalg.inv(frame.pose).tolist()}))
    assert _estimate(d, "--prior", str(d / "inv.json")) == 2
    assert "prior pose puts the robot outside the image" in capsys.readouterr().err
