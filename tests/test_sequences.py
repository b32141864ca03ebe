"""Synthetic sequences (data/scenes/sequences.py, ``monose3 generate --sequence``): a static
camera keeps one pose and intrinsics, a moving one orbits, the joints move smoothly, the ground
truth is exact, and the command refuses what it cannot make."""

from __future__ import annotations

import json

import numpy as np
import pytest

from monose3.apps import cli
from monose3.data.dream import DreamDataset
from monose3.data.scenes.profiles import get_profile
from monose3.data.scenes.sampling import frame_rng
from monose3.data.scenes.sequences import (
    SEQUENCE_FILE,
    SequenceConfig,
    frame_in_view,
    in_view_fraction,
    sample_sequence,
    smooth_trajectory,
    write_sequence,
)
from monose3.errors import Monose3Error
from monose3.geometry.rotations import rotation_angle

SIZE = (160, 120)


def test_smooth_trajectory_passes_its_keyframes_without_a_velocity_jump():
    keys = np.array([[0.0], [1.0], [3.0]])
    path = smooth_trajectory(keys, 21, 10)
    assert path[0, 0] == 0.0 and path[10, 0] == pytest.approx(1.0) and path[20, 0] == pytest.approx(3.0)
    steps = np.diff(path[:, 0])
    assert steps[9] < 0.05 and steps[10] < 0.2 and steps[4] > steps[9]  # slows into a keyframe, starts slowly


@pytest.mark.parametrize("camera", ["static", "moving"])
def test_a_sequence_keeps_its_camera_and_moves_the_robot_smoothly(tmp_path, panda, camera):
    out = write_sequence(tmp_path / camera, SequenceConfig(frames=8, camera=camera, keyframe_every=4), seed=3,
                         profile="reallike", size=SIZE)  # fmt: skip
    frames = list(DreamDataset(out, panda))
    assert len(frames) == 8 and json.loads((out / SEQUENCE_FILE).read_text())["camera"] == camera
    assert all(np.allclose(f.K, frames[0].K) for f in frames)
    poses = np.stack([f.pose for f in frames])
    turned = np.degrees(rotation_angle(poses[0, :3, :3], poses[-1, :3, :3]))
    assert turned == pytest.approx(0.0 if camera == "static" else 7 * 0.4, abs=1e-6)
    joints = np.stack([f.joints for f in frames])
    assert np.abs(np.diff(joints, axis=0)).max() < 1.5 and not np.allclose(joints[0], joints[-1])
    for f in frames:  # the annotation is the forward kinematics under the written pose
        assert np.allclose(panda.keypoints(f.joints[None], f.pose[None])[0], f.keypoints_3d, atol=1e-5)
    assert (out / "000000.rgb.jpg").stat().st_size > 1000


def test_every_frame_keeps_the_robot_in_view_not_only_the_joint_targets(panda):
    """Off-centre hard scenes with an orbiting camera: the way between two targets and the
    orbit can carry the robot's centroid out of the picture, where any estimate counts as out of
    view; the sampler draws a target again until every frame keeps the robot in view."""
    hard, size = get_profile("hard"), (320, 240)
    for seed in range(3):
        path = sample_sequence(frame_rng(seed, 0), panda, hard, size, SequenceConfig(frames=40, camera="moving"))
        for q, pose in zip(path["joints"], path["poses"], strict=True):
            assert frame_in_view(panda, q, pose, path["K"], size, hard)
    # the check is not vacuous: the robot turned away from this camera leaves the picture
    q, pose = path["joints"][0], path["poses"][0].copy()
    pose[0, 3] += 5.0
    assert in_view_fraction(panda, q, pose, path["K"], size) == 0.0 and not frame_in_view(
        panda, q, pose, path["K"], size, hard
    )


def test_generate_sequence_command_and_its_refusals(tmp_path, capsys):
    out = tmp_path / "seq"
    assert cli.main(["generate", "--out", str(out), "--num", "3", "--sequence", "static", "--size", "160x120"]) == 0
    assert len(list(out.glob("*.rgb.jpg"))) == 3 and (out / SEQUENCE_FILE).is_file()
    for extra, message in [(["--num", "1"], "needs --num 2"), (["--num", "3", "--resume"], "--resume")]:
        code = cli.main(["generate", "--out", str(tmp_path / "no"), "--sequence", "moving", *extra])
        err = capsys.readouterr().err.strip()
        assert code == 2 and message in err and "\n" not in err and not (tmp_path / "no").exists()
    with pytest.raises(Monose3Error, match="unknown sequence camera"):
        SequenceConfig(camera="handheld")
