"""One validation layer for the Python API and the commands: every bad input is
refused the same way (a one-line Monose3Error / exit code 2, before the model loads), every
documented joint layout is accepted, and a bad input never reaches torch."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import save_tiny_checkpoint

from monose3.api import estimate_pose, load_estimator
from monose3.apps.cli import main
from monose3.data import validation
from monose3.data.datasets import open_dataset
from monose3.errors import Monose3Error
from monose3.geometry.camera import intrinsics_matrix
from monose3.report.metrics import summarize
from monose3.robot import RobotModel

SRC = Path(__file__).resolve().parents[1] / "src"


@pytest.fixture(scope="module")
def base(tiny_dream, tmp_path_factory):
    """One generated 160x120 frame (image, joints, K, ground-truth pose) and a tiny checkpoint."""
    d = tmp_path_factory.mktemp("validation")
    frame = open_dataset(tiny_dream, "panda")[0]
    save_tiny_checkpoint(d / "panda.pt")
    return d, frame


@pytest.fixture(scope="module")
def estimator(base):
    est = load_estimator(base[0] / "panda.pt")
    yield est
    est.close()


def _inputs(frame, case: str) -> dict:
    """image, joints, K, prior, chains for one case (the good inputs, one of them spoiled)."""
    image, K = frame.load_image(), frame.K.copy()
    joints = RobotModel("panda").joint_dict(frame.joints)
    prior, chains = None, 2
    if case == "nan_joint":
        joints["panda_joint2"] = float("nan")
    elif case == "degrees":
        joints["panda_joint4"] = -120.0
    elif case == "negative_fx":
        K[0, 0] = -K[0, 0]
    elif case == "fx_huge":
        K[0, 0] = K[1, 1] = 583615.0
    elif case == "fx_tiny":
        K[0, 0] = K[1, 1] = 0.5
    elif case == "K_other_size":  # the K of the same camera at twice the resolution
        K[:2] *= 2
    elif case == "tiny_image":
        image = image[:1, :1]
        K = np.array([[1.0, 0, 0.5], [0, 1.0, 0.5], [0, 0, 1]])
    elif case == "black_image":
        image = np.zeros_like(image)
    elif case == "prior_mm":
        prior = frame.pose.copy()
        prior[:3, 3] *= 1000
    elif case == "prior_inverted":
        prior = np.linalg.inv(frame.pose)
    elif case == "chains_0":
        chains = 0
    elif case == "chains_negative":
        chains = -3
    return {"image": image, "joints": joints, "K": K, "prior": prior, "chains": chains}


def _write_cli_files(d: Path, inp: dict, tag: str) -> list[str]:
    image, K = inp["image"], inp["K"]
    h, w = image.shape[:2]
    cv2.imwrite(str(d / f"{tag}.png"), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    (d / f"{tag}.joints.json").write_text(json.dumps(inp["joints"]))
    cam = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "width": w, "height": h}
    (d / f"{tag}.camera.json").write_text(json.dumps(cam))
    args = ["--image", str(d / f"{tag}.png"), "--joints", str(d / f"{tag}.joints.json")]
    args += ["--camera", str(d / f"{tag}.camera.json"), "--chains", str(inp["chains"])]
    if inp["prior"] is not None:
        (d / f"{tag}.prior.json").write_text(json.dumps({"camera_from_base": inp["prior"].tolist()}))
        args += ["--prior", str(d / f"{tag}.prior.json")]
    return args


BAD = {
    "nan_joint": "nan",
    "degrees": "radians",
    "negative_fx": "positive",
    "fx_huge": "implausible",
    "fx_tiny": "implausible",
    "K_other_size": "principal point",
    "tiny_image": "1x1",
    "black_image": "uniform",
    "prior_mm": "millimetres",
    "prior_inverted": "outside the image",
    "chains_0": "at least 1",
    "chains_negative": "at least 1",
}


@pytest.mark.parametrize("via", ["api", "cli"])
@pytest.mark.parametrize(("case", "needle"), BAD.items())
def test_bad_input_is_refused_alike_by_api_and_cli(base, estimator, case, needle, via, capsys):
    d, frame = base
    inp = _inputs(frame, case)
    if via == "api":
        with pytest.raises(Monose3Error) as err:
            estimate_pose(estimator, inp["image"], inp["joints"], inp["K"], chains=inp["chains"], prior=inp["prior"])
        message = str(err.value)
    else:
        out = d / f"out_{case}"
        args = ["estimate", *_write_cli_files(d, inp, case), "--checkpoint", str(d / "panda.pt"), "--out", str(out)]
        assert main(args) == 2
        message = capsys.readouterr().err.strip()
        assert not out.exists()  # refused before any output
    assert len(message.splitlines()) == 1 and needle.lower() in message.lower(), message


JOINT_LAYOUTS = ["dict", "list7", "list8", "array8", "array1x8", "dream_frame"]


def _joints_as(frame, layout: str):
    q = frame.joints  # 8 values: the arm's 7 and the finger
    names = RobotModel("panda").joint_names
    return {
        "dict": dict(zip(names, map(float, q), strict=True)),
        "list7": [float(v) for v in q[:7]],
        "list8": [float(v) for v in q],
        "array8": q.copy(),
        "array1x8": q[None].copy(),
        "dream_frame": {
            "sim_state": {"joints": [{"name": n, "position": float(v)} for n, v in zip(names, q, strict=True)]}
        },
    }[layout]


# Through the CLI each case loads the model again (6 s): one case stays fast, the rest are slow.
VIA = ["api", "cli"]


@pytest.mark.parametrize("via", VIA)
@pytest.mark.parametrize(
    "layout", [layout if layout == "dict" else pytest.param(layout, marks=pytest.mark.slow) for layout in JOINT_LAYOUTS]
)
def test_every_documented_joint_layout_is_accepted(base, estimator, layout, via, tmp_path):
    d, frame = base
    joints = _joints_as(frame, layout)
    if via == "api":
        result = estimate_pose(estimator, frame.load_image(), joints, frame.K, chains=1, prior=frame.pose)
        pose = result.camera_from_base
    else:
        inp = _inputs(frame, "good")
        args = _write_cli_files(tmp_path, {**inp, "chains": 1}, "x")
        data = joints.tolist() if isinstance(joints, np.ndarray) else joints
        (tmp_path / "x.joints.json").write_text(json.dumps(data))
        (tmp_path / "prior.json").write_text(json.dumps({"camera_from_base": frame.pose.tolist()}))
        args += ["--prior", str(tmp_path / "prior.json")]
        argv = ["estimate", *args, "--checkpoint", str(d / "panda.pt"), "--sampler", "revdiff"]
        assert main([*argv, "--out", str(tmp_path / "o")]) == 0
        pose = np.asarray(json.loads((tmp_path / "o" / "pose.json").read_text())["camera_from_base"])
    assert pose.shape == (4, 4) and np.isfinite(pose).all()


@pytest.mark.parametrize(
    ("image", "needle"),
    [
        (np.full((120, 160), 90, np.uint8), "grayscale"),
        (np.full((120, 160, 1), 90, np.uint8), "grayscale"),
        (np.full((120, 160, 4), 90, np.uint8), "rgba"),
        (np.random.default_rng(0).random((120, 160, 3)), "float"),
        (np.full((120, 160, 3), 90, np.uint16), "uint16"),
        ("image.png", "array"),
    ],
)
def test_api_refuses_images_it_cannot_read_unambiguously(base, estimator, image, needle):
    _, frame = base
    with pytest.raises(Monose3Error, match=f"(?i){needle}"):
        estimate_pose(estimator, image, frame.joints, frame.K, chains=1)


def test_estimator_entry_points_refuse_nan_joints_instead_of_crashing(base, estimator):
    _, frame = base
    q = frame.joints.copy()
    q[1] = np.nan
    with pytest.raises(Monose3Error, match="NaN"):
        estimator.track([frame.load_image()], frame.K[None], q[None], frame.pose[None])
    with pytest.raises(Monose3Error, match="NaN"):
        estimator.estimate([frame.load_image()], frame.K[None], q[None])
    with pytest.raises(Monose3Error, match="Ks must be"):
        estimator.estimate([frame.load_image()], frame.K[None, :2], frame.joints[None])


@pytest.mark.parametrize("via", ["api", "cli"])
def test_one_chain_gives_null_confidence_never_nan(base, estimator, via, tmp_path, capsys):
    d, frame = base
    if via == "api":
        image = frame.load_image()
        result = estimate_pose(estimator, image, frame.joints, frame.K, chains=1, prior=frame.pose, sampler="revdiff")
        text = json.dumps(result.to_dict(), allow_nan=False)
    else:
        args = _write_cli_files(tmp_path, {**_inputs(frame, "good"), "chains": 1, "prior": frame.pose}, "x")
        argv = ["estimate", *args, "--checkpoint", str(d / "panda.pt"), "--sampler", "revdiff"]
        assert main([*argv, "--out", str(tmp_path / "o")]) == 0
        assert "nan" not in capsys.readouterr().out.lower()
        text = (tmp_path / "o" / "pose.json").read_text()

    def refuse(constant):
        raise ValueError(f"non-standard JSON constant {constant}")

    data = json.loads(text, parse_constant=refuse)
    assert data["confidence"] is None and data["reliable"] is None and data["chains"] == 1


@pytest.mark.parametrize("via", ["api", "cli"])
def test_checkpoint_folder_is_named_as_a_folder(base, via, capsys):
    d, _ = base
    if via == "api":
        with pytest.raises(Monose3Error, match="is a folder"):
            load_estimator(d)
    else:
        assert main(["demo", "--checkpoint", str(d), "--out", str(d / "demo")]) == 2
        assert "is a folder" in capsys.readouterr().err


# ---- the commands answer without torch -----------------------------------------------------------


def _run_without_torch(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    """``monose3 ARGS`` in a fresh interpreter that fails if torch or pybullet got imported."""
    code = (
        "import sys\nfrom monose3.apps.cli import main\n"
        "try:\n    rc = main(sys.argv[1:])\nexcept SystemExit as e:\n    rc = e.code or 0\n"
        "heavy = [m for m in ('torch', 'pybullet') if m in sys.modules]\n"
        "sys.exit(99 if heavy else rc)\n"
    )
    env = {"PYTHONPATH": str(SRC), "PATH": "/usr/bin:/bin", "OMP_NUM_THREADS": "1"}
    return subprocess.run(
        [sys.executable, "-c", code, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=120
    )


@pytest.fixture(scope="module")
def cli_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    (d / "a_file").write_text("x")
    (d / "empty").mkdir()
    (d / "folder").mkdir()
    (d / "no_header.csv").write_text("0.0,0.1\n0.2,0.3\n")
    return d


HELP = [["--help"], ["--version"]] + [
    [c, "--help"] for c in ("demo", "estimate", "calibrate", "track", "generate", "train", "evaluate")
]


@pytest.mark.parametrize("args", HELP, ids=" ".join)
def test_help_and_version_do_not_import_torch(args, cli_dir):
    res = _run_without_torch(args, cli_dir)
    assert res.returncode == 0 and res.stdout.strip(), res.stderr


S = "{sample}"
EXISTING_FILE_OUT = {
    "estimate": ["estimate", "--image", f"{S}/image.jpg", "--joints", f"{S}/joints.json", "--camera",
                 f"{S}/camera.json", "--out", "a_file"],
    "demo": ["demo", "--out", "a_file"],
    "calibrate": ["calibrate", "--frames", "folder", "--out", "a_file"],
    "track": ["track", "--frames", "folder", "--out", "a_file"],
    "generate": ["generate", "--out", "a_file", "--num", "1"],
    "train": ["train", "--data", "folder", "--out", "a_file"],
    "evaluate_json": ["evaluate", "--data", "folder", "--json", "folder"],
    "evaluate_json_parent": ["evaluate", "--data", "folder", "--json", "a_file/results.json"],
    "evaluate_overlays": ["evaluate", "--data", "folder", "--overlays", "a_file"],
    "evaluate_plot": ["evaluate", "--data", "folder", "--plot", "add.txt"],
}  # fmt: skip
INPUT_ERRORS = {
    "missing_image": (["estimate", "--image", "nope.png", "--joints", "j", "--camera", "c"], "not found"),
    "chains_0": (["demo", "--chains", "0"], "at least 1"),
    "batch_size_0": (["evaluate", "--data", "folder", "--batch-size", "0"], "at least 1"),
    "unknown_robot": (["track", "--frames", "folder", "--robot", "ur5"], "unknown robot"),
    "checkpoint_folder": (["demo", "--checkpoint", "folder"], "is a folder"),
    "other_robot": (["calibrate", "--frames", "folder", "--robot", "kuka"], "trained for robot 'panda'"),
    "train_no_data": (["train", "--data", "empty", "--out", "run"], "no"),
    "missing_data": (["evaluate", "--data", "nope"], "not found"),
    "video_joints_csv": (
        ["track", "--video", "a_file", "--camera", f"{S}/camera.json", "--joints-csv", "no_header.csv"],
        "no header row",
    ),
}


@pytest.mark.parametrize(("name", "args"), EXISTING_FILE_OUT.items())
def test_an_output_that_is_an_existing_file_is_refused_at_once(name, args, cli_dir):
    sample = SRC / "monose3" / "assets" / "sample"
    res = _run_without_torch([a.replace(S, str(sample)) for a in args], cli_dir)
    err = res.stderr.strip()
    assert res.returncode == 2 and len(err.splitlines()) == 1, err
    assert "a_file" in err or "folder" in err or "extension" in err


@pytest.mark.parametrize(("name", "case"), INPUT_ERRORS.items())
def test_input_errors_answer_in_one_line_without_torch(name, case, cli_dir):
    args, needle = case
    sample = SRC / "monose3" / "assets" / "sample"
    res = _run_without_torch([a.replace(S, str(sample)) for a in args], cli_dir)
    err = res.stderr.strip()
    assert res.returncode == 2 and len(err.splitlines()) == 1 and needle in err, (res.returncode, err)
    assert not (cli_dir / "run").exists()  # train with no data leaves no output folder


# ---- folders with unreadable frames ------------------------------------------------------------


@pytest.fixture
def broken_dream(tiny_dream, tmp_path):
    """The tiny DREAM folder with frame 000002's JPEG corrupted."""
    d = tmp_path / "dream"
    shutil.copytree(tiny_dream, d)
    jpg = sorted(d.glob("*.jpg"))[2]
    jpg.write_bytes(b"not a jpeg")
    return d, jpg.name.split(".")[0]


def _corrupt_all(d: Path) -> None:
    for jpg in d.glob("*.jpg"):
        jpg.write_bytes(b"")


@pytest.mark.parametrize("command", ["evaluate", "calibrate", "track"])
def test_unreadable_frames_are_skipped_named_and_fatal_only_when_none_is_left(
    command, broken_dream, base, tmp_path, capsys
):
    d, bad = broken_dream
    ck = str(base[0] / "panda.pt")
    out = tmp_path / "out"
    args = {
        "evaluate": ["evaluate", "--data", str(d), "--steps", "1", "0", "--json", str(out / "r.json")],
        "calibrate": ["calibrate", "--frames", str(d), "--out", str(out), "--overlay-frames", "2"],
        "track": ["track", "--frames", str(d), "--out", str(out), "--gif-every", "0"],
    }[command] + ["--checkpoint", ck, "--sampler", "revdiff"]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert f"skipped 1 unusable frame(s): {bad}" in printed
    listing = {"evaluate": "r.json", "calibrate": "calibration.json", "track": "skipped.json"}[command]
    data = json.loads((out / listing).read_text())
    skipped = data["datasets"][d.name]["skipped"] if command == "evaluate" else data["skipped"]
    assert [s["frame"] for s in skipped] == [bad] and "corrupt" in skipped[0]["reason"]
    if command == "track":
        assert len((out / "poses.jsonl").read_text().splitlines()) == 5

    _corrupt_all(d)
    shutil.rmtree(out)
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]  # after the progress bar
    assert err.startswith(f"monose3 {command}: error: no usable frame"), err
    assert not list(out.glob("poses.*")) and not list(out.glob("*.json"))  # nothing partial left behind


# ---- small pieces ------------------------------------------------------------------------------


def test_failures_mean_add_over_50mm_and_out_of_view_is_counted_apart():
    s = summarize([0.01, 0.05, 0.06, 0.3, np.inf])
    assert s["failures"] == 3 and s["out_of_view"] == 1


def test_plausibility_limits_are_documented_numbers():
    K = np.array([[500.0, 0, 319.5], [0, 500, 239.5], [0, 0, 1]])
    assert validation.check_K(K, (640, 480)) is not None
    for fx in (0.1 * 640 - 1, 10 * 640 + 1):
        with pytest.raises(Monose3Error, match="implausible"):
            validation.check_K(np.array([[fx, 0, 319.5], [0, fx, 239.5], [0, 0, 1]]), (640, 480))
    with pytest.raises(Monose3Error, match="existing file"):
        validation.check_output_dir(__file__)


@pytest.mark.parametrize("via", ["api", "cli"])
def test_generated_folders_nominal_camera_is_refused_and_the_frame_json_accepted(tiny_dream, base, via, capsys):
    from monose3.data.inputs import load_camera

    d, _ = base
    frame = open_dataset(tiny_dream, "panda")[0]
    settings, frame_json = tiny_dream / "_camera_settings.json", tiny_dream / f"{frame.name}.json"
    if via == "api":
        with pytest.raises(Monose3Error, match="nominal camera"):
            load_camera(settings)
        assert np.allclose(load_camera(frame_json).K, frame.K)
        return
    args = ["estimate", "--image", str(frame.image_path), "--joints", str(frame_json), "--chains", "1"]
    args += ["--checkpoint", str(d / "panda.pt"), "--out", str(d / "nominal")]
    assert main([*args, "--camera", str(settings)]) == 2
    assert "nominal camera" in capsys.readouterr().err
    assert main([*args, "--camera", str(frame_json)]) in (0, 2)  # accepted as a camera (the tiny model may miss)
    assert "camera" not in capsys.readouterr().err


# ---- check_K ---------------------------------------------------------------------------------


REAL_CAMERAS = [intrinsics_matrix(615.52, 615.22, 328.26, 251.79), intrinsics_matrix(399.66, 399.5, 319.9, 244.06)]


@pytest.mark.parametrize("K", REAL_CAMERAS)
def test_check_K_accepts_real_cameras(K):  # noqa: N802
    out = validation.check_K(K.tolist(), (640, 480))
    assert out.dtype == np.float64 and np.array_equal(out, K)


@pytest.mark.parametrize(
    ("K", "size", "pattern"),
    [
        (intrinsics_matrix(-600, 600, 320, 240), (640, 480), "focal lengths must be positive"),
        (intrinsics_matrix(600, 0, 320, 240), (640, 480), "focal lengths must be positive"),
        (intrinsics_matrix(600, 600, np.nan, 240), (640, 480), "finite"),
        (np.eye(4), (640, 480), "3x3 camera matrix"),
        (intrinsics_matrix(1200, 1200, 960, 540), (640, 480), "principal point .* outside the 640x480"),
        (intrinsics_matrix(600, 600, 320, -2), (640, 480), "calibrated at 640x480"),
    ],
)
def test_check_K_errors(K, size, pattern):  # noqa: N802
    with pytest.raises(Monose3Error, match=pattern) as info:
        validation.check_K(K, size, source="cam.json", plausible=False)
    assert str(info.value).startswith("cam.json")
