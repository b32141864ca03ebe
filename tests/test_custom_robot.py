"""A robot given as a URDF and a keypoint file (one robot.json) goes through every command:
generate, train, evaluate and estimate, the way a user with their own arm would run them."""

import json

import numpy as np
import pytest

from monose3.apps.cli import main
from monose3.errors import Monose3Error
from monose3.robot import RobotModel, get_spec, robot_reference


def box_obj(path, size, color):
    """A box mesh centred on its link's origin, with an MTL colour."""
    sx, sy, sz = (s / 2 for s in size)
    corners = [(x, y, z) for x in (-sx, sx) for y in (-sy, sy) for z in (0.0, 2 * sz)]
    faces = [(1, 3, 4, 2), (5, 6, 8, 7), (1, 2, 6, 5), (3, 7, 8, 4), (1, 5, 7, 3), (2, 4, 8, 6)]
    path.with_suffix(".mtl").write_text(f"newmtl m\nKd {color[0]} {color[1]} {color[2]}\n")
    text = f"mtllib {path.with_suffix('.mtl').name}\nusemtl m\n"
    text += "".join(f"v {x} {y} {z}\n" for x, y, z in corners)
    text += "".join(f"f {a} {b} {c}\nf {a} {c} {d}\n" for a, b, c, d in faces)
    path.write_text(text)


def link(name, mesh):
    return f'<link name="{name}"><visual><geometry><mesh filename="{mesh}"/></geometry></visual></link>'


def joint(name, parent, child, z):
    return (
        f'<joint name="{name}" type="revolute"><parent link="{parent}"/><child link="{child}"/>'
        f'<origin xyz="0 0 {z}" rpy="0 0 0"/><axis xyz="0 1 0"/><limit lower="-2" upper="2"/></joint>'
    )


@pytest.fixture
def robot_file(tmp_path):
    """A three-link arm (base, upper arm, forearm) of OBJ boxes, described by robot.json."""
    folder = tmp_path / "arm"
    folder.mkdir()
    box_obj(folder / "base.obj", (0.3, 0.3, 0.15), (0.2, 0.2, 0.8))
    box_obj(folder / "upper.obj", (0.1, 0.1, 0.5), (0.9, 0.5, 0.1))
    box_obj(folder / "fore.obj", (0.08, 0.08, 0.4), (0.1, 0.8, 0.2))
    urdf = (
        '<robot name="arm">'
        + link("base", "base.obj")
        + link("upper", "upper.obj")
        + link("fore", "fore.obj")
        + joint("shoulder", "base", "upper", 0.15)
        + joint("elbow", "upper", "fore", 0.5)
        + "</robot>"
    )
    (folder / "arm.urdf").write_text(urdf)
    keypoints = [
        {"name": "base", "link": "base"},
        {"name": "shoulder", "link": "upper"},
        {"name": "elbow", "link": "fore"},
        {"name": "tip", "link": "fore", "offset": [0, 0, 0.4]},
    ]
    path = folder / "robot.json"
    path.write_text(json.dumps({"name": "arm", "urdf": "arm.urdf", "keypoints": keypoints}))
    return path


def test_robot_file_resolves_to_its_urdf(robot_file):
    spec = get_spec(str(robot_file))
    assert spec.name == "arm" and [k.name for k in spec.keypoints] == ["base", "shoulder", "elbow", "tip"]
    model = RobotModel(str(robot_file))
    assert model.joint_names == ["shoulder", "elbow"]
    # straight up: the tip is 0.15 + 0.5 + 0.4 m above the base
    tip = model.keypoints(np.zeros((1, 2)), np.eye(4)[None])[0, 3]
    np.testing.assert_allclose(tip, [0, 0, 1.05], atol=1e-9)
    assert robot_reference(str(robot_file)) == str(robot_file.resolve())
    assert robot_reference("panda") == "panda"


def test_robot_file_errors_name_the_fix(tmp_path):
    (tmp_path / "r.json").write_text(json.dumps({"keypoints": []}))
    with pytest.raises(Monose3Error, match='add "urdf"'):
        get_spec(str(tmp_path / "r.json"))
    with pytest.raises(Monose3Error, match="robot file not found"):
        get_spec(str(tmp_path / "missing.json"))
    with pytest.raises(Monose3Error, match="robot file"):
        get_spec("ur5")


@pytest.mark.slow
def test_generate_train_evaluate_estimate_on_a_custom_robot(robot_file, tmp_path):
    robot = str(robot_file)
    data, run, out = tmp_path / "data", tmp_path / "run", tmp_path / "estimate"
    base = ["--robot", robot]
    assert main(["generate", "--out", str(data), "--num", "4", "--size", "160x120", "--workers", "0", *base]) == 0
    frame = json.loads((data / "000000.json").read_text())
    assert [k["name"] for k in frame["objects"][0]["keypoints"]] == ["base", "shoulder", "elbow", "tip"]
    train = ["train", "--data", str(data), "--out", str(run), "--preset", "cpu", "--steps", "2", "--batch-size", "2"]
    assert main([*train, "--workers", "0", *base]) == 0
    report = tmp_path / "evaluate.json"
    # evaluate and estimate find the robot in the checkpoint (its robot file's absolute path)
    assert main(["evaluate", "--data", str(data), "--checkpoint", str(run), "--limit", "2", "--json", str(report)]) == 0
    (result,) = json.loads(report.read_text())["datasets"].values()
    assert len(result["frames"]) == 2
    image, joints = data / "000000.rgb.jpg", data / "000000.json"
    estimate = ["estimate", "--image", str(image), "--joints", str(joints), "--camera", str(joints)]
    assert main([*estimate, "--checkpoint", str(run), "--out", str(out), "--chains", "1"]) == 0
    pose = np.array(json.loads((out / "pose.json").read_text())["camera_from_base"])
    assert pose.shape == (4, 4) and np.isfinite(pose).all()
    assert (out / "overlay.png").stat().st_size > 0
