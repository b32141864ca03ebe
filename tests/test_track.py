"""Tracking: full process on the first frame and 1 step after, re-initialisation on loss,
jumps and periodically (scripted estimator), ``monose3 track`` end to end on a DREAM folder
and on a video with a joints CSV (tiny random model), and each bad-input error."""

from __future__ import annotations

import json

import imageio.v3 as iio
import numpy as np
import pytest
from conftest import look_at

from monose3.apps.cli import main
from monose3.apps.track import load_joints_csv, load_joints_dir
from monose3.data.dream_writer import write_frame
from monose3.data.frame import Frame
from monose3.data.video import read_video, video_frames
from monose3.errors import Monose3Error
from monose3.estimator import Estimate
from monose3.report.overlays import save_animation
from monose3.report.sequences import track_sequence
from monose3.robot.jobs import RenderJob
from monose3.tracking import MAX_STEP_DEG, MAX_STEP_MM, MODE_FULL, MODE_TRACK, Tracker, TrackingPolicy

SIZE = (160, 120)
K = np.array([[150.0, 0.0, 79.5], [0.0, 150.0, 59.5], [0.0, 0.0, 1.0]])
N = 4


# A static camera about 1.9 m in front of the Panda, looking at its middle.
POSE = look_at(np.array([1.7, -0.5, 0.9]), np.array([0.0, 0.0, 0.45]))


@pytest.fixture(scope="module")
def sequence(models, renderers):
    """A 4-frame sequence: the arm moving smoothly in front of a static camera."""
    model = models["panda"]
    start = model.random_joints(np.random.default_rng(3), 1)[0]
    joints = np.stack([start + 0.05 * i for i in range(N)])
    images = [renderers["panda"].render_jobs([RenderJob(q, POSE, K, SIZE)])[0][0] for q in joints]
    return joints, images


@pytest.fixture(scope="module")
def dream_dir(tmp_path_factory, sequence):
    folder = tmp_path_factory.mktemp("dream_seq")
    for i, (q, rgb) in enumerate(zip(*sequence, strict=True)):
        write_frame(folder, i, rgb, K, q, POSE)
    return folder


def frames_of(sequence) -> list[Frame]:
    return [Frame(f"{i:04d}", K, SIZE, q, image=img) for i, (q, img) in enumerate(zip(*sequence, strict=True))]


class ScriptedTracker:
    """Full estimates at the true pose; per frame index: "jump" (the update moves 200 mm), "out"
    (the update leaves the image), "lost" (the update and the full process leave the image)."""

    def __init__(self, robot, script: dict[int, str]):
        self.robot = robot
        self.script = script
        self.frame = -1
        self.calls: list[tuple[int, str]] = []

    def _estimate(self, pose: np.ndarray, in_view: bool = True) -> Estimate:
        return Estimate(pose[None], pose[None, None], np.array([in_view]), np.zeros(1), np.zeros(1))

    def estimate(self, images, Ks, joints, **kw) -> Estimate:
        self.calls.append((self.frame, "full"))
        return self._estimate(POSE, self.script.get(self.frame) != "lost")

    def track(self, images, Ks, joints, previous) -> Estimate:
        self.calls.append((self.frame, "track"))
        what = self.script.get(self.frame)
        pose = previous[0].copy()
        if what == "jump":
            pose[:3, 3] += [0.2, 0.0, 0.0]
        return self._estimate(pose, what not in ("out", "lost"))


def counting(frames, tracker):
    for i, f in enumerate(frames):
        tracker.frame = i
        yield f


# ---- track_sequence ----------------------------------------------------------------------------


def test_full_first_then_track_with_the_real_estimator(tiny, sequence):
    seen = []
    results = track_sequence(tiny, frames_of(sequence), on_frame=lambda f, img, r: seen.append((f.name, img.shape)))
    assert [r.mode for r in results] == [MODE_FULL] + [MODE_TRACK] * (N - 1)
    assert results[0].reason == "first" and all(r.reason is None for r in results[1:])
    assert seen == [(f"{i:04d}", (SIZE[1], SIZE[0], 3)) for i in range(N)]
    assert all(r.in_view for r in results)
    for r in results[1:]:  # the step size is measured and below the jump thresholds
        assert r.step_mm is not None and 0 <= r.step_mm < MAX_STEP_MM and r.step_deg < MAX_STEP_DEG


def test_reinitialises_on_jump_out_of_view_lost_and_periodically(models):
    frames = [Frame(f"{i}", K, SIZE, np.zeros(9), image=np.zeros((120, 160, 3), np.uint8)) for i in range(7)]
    tracker = ScriptedTracker(models["panda"], {2: "jump", 4: "out", 5: "lost"})
    results = track_sequence(tracker, counting(frames, tracker))
    assert [(r.mode, r.reason, r.in_view) for r in results] == [
        (MODE_FULL, "first", True),
        (MODE_TRACK, None, True),
        (MODE_FULL, "jump", True),  # the 1-step update moved the robot 200 mm
        (MODE_TRACK, None, True),
        (MODE_FULL, "out of view", True),  # the update lost the robot, the full process found it
        (MODE_FULL, "out of view", False),  # ... and here the full process failed too
        (MODE_FULL, "lost", True),  # so the next frame starts from scratch
    ]
    assert results[2].step_mm == pytest.approx(200.0, abs=1e-6) and results[2].step_deg == pytest.approx(0.0)
    assert tracker.calls == [
        (0, "full"),
        (1, "track"),
        (2, "track"),
        (2, "full"),
        (3, "track"),
        (4, "track"),
        (4, "full"),
        (5, "track"),
        (5, "full"),
        (6, "full"),
    ]
    periodic = ScriptedTracker(models["panda"], {})
    results = track_sequence(periodic, counting(frames[:5], periodic), TrackingPolicy(reinit_every=2))
    assert [r.mode for r in results] == [MODE_FULL, MODE_TRACK, MODE_FULL, MODE_TRACK, MODE_FULL]
    assert [r.reason for r in results if r.mode == MODE_FULL] == ["first", "periodic", "periodic"]
    # A looser jump threshold keeps the 200 mm step as tracking.
    loose = ScriptedTracker(models["panda"], {2: "jump"})
    results = track_sequence(loose, counting(frames[:3], loose), TrackingPolicy(max_step_mm=250.0))
    assert [r.mode for r in results] == [MODE_FULL, MODE_TRACK, MODE_TRACK]


def test_tracker_passes_full_estimate_options_and_refuses_a_bad_period(models):
    """The shared Tracker hands its full-estimate options to every full estimate only."""
    calls = []

    class Recorder(ScriptedTracker):
        def estimate(self, images, Ks, joints, **kw):
            calls.append(kw)
            return super().estimate(images, Ks, joints, **kw)

    frames = [np.zeros((120, 160, 3), np.uint8)] * 3
    rec = Recorder(models["panda"], {1: "jump"})
    tracker = Tracker(rec, ddim_steps=2, direct_steps=0)
    steps = []
    for i, img in enumerate(frames):
        rec.frame = i
        steps.append(tracker.update(img, K, np.zeros(9)))
    assert [(s.mode, s.reason) for s in steps] == [(MODE_FULL, "first"), (MODE_FULL, "jump"), (MODE_TRACK, None)]
    assert calls == [{"ddim_steps": 2, "direct_steps": 0}] * 2
    assert np.array_equal(steps[2].camera_from_base, steps[2].estimate.poses[0])
    with pytest.raises(Monose3Error, match="reinit_every must be at least 1"):
        TrackingPolicy(reinit_every=0)


# ---- command line ------------------------------------------------------------------------------


def test_track_cli_on_dream_folder(dream_dir, checkpoint, tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["track", "--frames", str(dream_dir), "--checkpoint", str(checkpoint), "--sampler", "revdiff"]
    rc = main([*argv, "--out", str(out)])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "ADD vs ground truth" in printed and f"frames: {N}; full estimates run: 1 (1 first)" in printed
    assert f"poses from full 1, track {N - 1}, fused 0" in printed
    lines = [json.loads(line) for line in (out / "poses.jsonl").read_text().splitlines()]
    assert [d["mode"] for d in lines] == ["full"] + ["track"] * (N - 1)
    assert [d["frame"] for d in lines] == [f"{i:06d}" for i in range(N)]
    for d in lines:
        pose = np.array(d["camera_from_base"]).reshape(4, 4)
        assert np.allclose(pose[3], [0, 0, 0, 1]) and np.allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-9)
        assert d["add_mm"] is not None and d["add_mm"] > 0
    csv_rows = (out / "poses.csv").read_text().splitlines()
    assert len(csv_rows) == N + 1 and csv_rows[0].startswith(
        "index,frame,mode,reason,in_view,confidence,reliable,doubts,m00"
    )
    gif = iio.imread(out / "track.gif", index=None)
    assert gif.shape[0] == N


def write_video_inputs(tmp_path, sequence, models, rows: int | None = None):
    joints, images = sequence
    video = save_animation(images, tmp_path / "seq.mp4", fps=5)
    names = models["panda"].required_joints
    lines = ["frame," + ",".join(names)]
    for i, q in enumerate(joints[: rows if rows is not None else len(joints)]):
        d = models["panda"].joint_dict(q)
        lines.append(f"f{i}," + ",".join(f"{d[n]:.9f}" for n in names))
    csv_path = tmp_path / "joints.csv"
    csv_path.write_text("\n".join(lines) + "\n")
    cam = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "width": SIZE[0], "height": SIZE[1]}
    (tmp_path / "camera.json").write_text(json.dumps(cam))
    return video, csv_path, tmp_path / "camera.json"


def test_track_cli_on_video_with_joints_csv(sequence, models, checkpoint, tmp_path):
    video, csv_path, camera = write_video_inputs(tmp_path, sequence, models)
    out = tmp_path / "out"
    argv = ["track", "--video", str(video), "--joints-csv", str(csv_path), "--camera", str(camera)]
    rc = main([*argv, "--checkpoint", str(checkpoint), "--sampler", "revdiff", "--out", str(out), "--gif-every", "2"])
    assert rc == 0
    lines = [json.loads(line) for line in (out / "poses.jsonl").read_text().splitlines()]
    assert [d["frame"] for d in lines] == [f"f{i}" for i in range(N)]
    assert [d["mode"] for d in lines] == ["full"] + ["track"] * (N - 1)
    assert all(d["add_mm"] is None for d in lines)  # no ground truth for a video
    assert iio.imread(out / "track.gif", index=None).shape[0] == N // 2


def test_joints_csv_reading_and_errors(models, tmp_path):
    robot = models["panda"]
    names = robot.required_joints
    q = [0.1, -0.3, 0.0, -2.0, 0.0, 1.8, 0.7][: len(names)]
    good = tmp_path / "good.csv"
    # any column order; time column ignored; no frame column
    good.write_text("time," + ",".join(reversed(names)) + "\n0.5," + ",".join(map(str, reversed(q))) + "\n")
    frame_names, joints = load_joints_csv(good, robot)
    assert frame_names is None and np.allclose(joints[0][: len(q)], q)
    bad = tmp_path / "bad.csv"
    bad.write_text(",".join(map(str, q)) + "\n" + ",".join(map(str, q)) + "\n")
    with pytest.raises(Monose3Error, match="no header row"):
        load_joints_csv(bad, robot)
    bad.write_text(",".join(names) + "\n" + ",".join(["x"] + list(map(str, q[1:]))) + "\n")
    with pytest.raises(Monose3Error, match=f"row 2: {names[0]} = 'x' is not a number"):
        load_joints_csv(bad, robot)
    bad.write_text(",".join(names) + "\n" + ",".join(str(np.degrees(v) + 200) for v in q) + "\n")
    with pytest.raises(Monose3Error, match="row 2: .*radians"):
        load_joints_csv(bad, robot)
    bad.write_text(",".join(names[:-1]) + "\n" + ",".join(map(str, q[:-1])) + "\n")
    with pytest.raises(Monose3Error, match="missing joint"):
        load_joints_csv(bad, robot)


def test_joints_dir_and_video_reading(sequence, models, tmp_path):
    robot = models["panda"]
    folder = tmp_path / "joints"
    folder.mkdir()
    for i in (10, 2, 1):  # natural order: 1, 2, 10
        (folder / f"{i}.joints.json").write_text(json.dumps(robot.joint_dict(sequence[0][i % N])))
    names, joints = load_joints_dir(folder, robot)
    assert names == ["1", "2", "10"] and np.allclose(joints[2], sequence[0][10 % N])
    gif = save_animation(sequence[1][:3], tmp_path / "seq.gif")
    frames = list(read_video(gif))
    assert len(frames) == 3 and frames[0].shape == (SIZE[1], SIZE[0], 3) and frames[0].dtype == np.uint8
    video, csv_path, camera = write_video_inputs(tmp_path, sequence, models)
    with pytest.raises(Monose3Error, match=f"has {N} frames but 3 joint rows"):
        video_frames(video, camera, joints)  # checked before any frame is decoded for estimation
    frames = list(video_frames(video, camera, np.repeat(joints[:1], N, 0), ["a", "", "c", "d"]))
    assert [f.name for f in frames] == ["a", "000001", "c", "d"]
    assert frames[0].load_image().shape == (SIZE[1], SIZE[0], 3)


def test_video_input_errors(sequence, models, checkpoint, tmp_path, capsys):
    video, csv_path, camera = write_video_inputs(tmp_path, sequence, models, rows=N - 1)
    base = ["track", "--checkpoint", str(checkpoint), "--out", str(tmp_path / "out")]
    cases = [
        (
            ["--video", str(video), "--joints-csv", str(csv_path), "--camera", str(camera)],
            f"has {N} frames but {N - 1}",
        ),
        (["--video", str(video), "--joints-csv", str(csv_path)], "--video needs --camera"),
        (["--video", str(video), "--camera", str(camera)], "--joints-csv FILE or --joints DIR"),
        (["--video", str(tmp_path / "none.mp4"), "--joints-csv", str(csv_path), "--camera", str(camera)], "not found"),
        (["--frames", str(tmp_path), "--joints-csv", str(csv_path)], "go with --video"),
    ]
    for extra, message in cases:
        assert main(base + extra) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("monose3 track: error:") and message in err and "\n" not in err, err


def test_track_option_and_static_camera_errors_write_nothing(dream_dir, sequence, models, checkpoint, tmp_path, capsys):
    """--refine-at-end alone, a bad --recheck-every, an unreadable video, and under --static-camera a
    folder whose frames come from different cameras: one line each, exit 2, no output folder."""
    mixed, (joints, images) = tmp_path / "mixed", sequence
    for i in range(2):  # the second frame's camera zoomed by 10 %
        write_frame(mixed, i, images[i], K * [[1.0 + 0.1 * i], [1.0 + 0.1 * i], [1.0]], joints[i], POSE)
    broken = tmp_path / "broken.mp4"
    broken.write_bytes(b"not a video")
    names = models["panda"].required_joints
    csv_path = tmp_path / "joints.csv"
    csv_path.write_text("frame," + ",".join(names) + "\n0," + ",".join("0.0" for _ in names) + "\n")
    camera = tmp_path / "camera.json"
    camera.write_text(json.dumps({"fx": 150, "fy": 150, "cx": 79.5, "cy": 59.5, "width": 160, "height": 120}))
    out = tmp_path / "out"
    base = ["track", "--checkpoint", str(checkpoint), "--out", str(out)]
    cases = [
        (["--frames", str(dream_dir), "--refine-at-end"], "--refine-at-end goes with --static-camera"),
        (["--frames", str(dream_dir), "--recheck-every", "0"], "--recheck-every"),
        (["--frames", str(mixed), "--static-camera"], "another intrinsics than frame"),
        (["--video", str(broken), "--joints-csv", str(csv_path), "--camera", str(camera)], "video"),
    ]
    for extra, message in cases:
        assert main(base + extra) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("monose3 track: error:") and message in err and "\n" not in err, err
        assert not out.exists(), extra
