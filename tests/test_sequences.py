"""Synthetic sequences (data/scenes/sequences.py, ``monose3 generate --sequence``): a static
camera keeps one pose and intrinsics, a moving one orbits, the joints move smoothly, the ground
truth is exact, and the command refuses what it cannot make."""

from __future__ import annotations

import json

import numpy as np
import pytest

from monose3.apps import cli
from monose3.data.dream import DreamDataset
from monose3.data.scenes.sequences import SEQUENCE_FILE, SequenceConfig, smooth_trajectory, write_sequence
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
