import json

import cv2
import numpy as np
import pytest
import yaml

from monose3.data.inputs import check_image_camera, load_camera, load_image, load_joints, load_pose
from monose3.errors import Monose3Error
from monose3.geometry.camera import Intrinsics, scale_camera

Q = [0.1, -0.5, 0.2, -2.0, 0.3, 1.5, 0.7]


def write(path, obj):
    if path.suffix == ".json":
        path.write_text(json.dumps(obj))
    else:
        path.write_text(yaml.safe_dump(obj))
    return path


# ---- images -----------------------------------------------------------------------------------


def test_load_image_rgb_order(tmp_path):
    rgb = np.zeros((6, 8, 3), np.uint8)
    rgb[..., 0] = 200  # red
    rgb[:, :2, 2] = 90
    cv2.imwrite(str(tmp_path / "a.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    out = load_image(tmp_path / "a.png")
    assert out.dtype == np.uint8 and out.shape == (6, 8, 3)
    np.testing.assert_array_equal(out, rgb)


def test_load_image_grey_becomes_rgb(tmp_path):
    cv2.imwrite(str(tmp_path / "g.png"), np.full((4, 5), 77, np.uint8))
    out = load_image(tmp_path / "g.png")
    assert out.shape == (4, 5, 3) and np.all(out == 77)


def test_load_image_errors(tmp_path):
    with pytest.raises(Monose3Error, match="not found"):
        load_image(tmp_path / "missing.png")
    (tmp_path / "junk.png").write_bytes(b"this is not a png")
    with pytest.raises(Monose3Error, match="could not read"):
        load_image(tmp_path / "junk.png")
    (tmp_path / "empty.jpg").write_bytes(b"")
    with pytest.raises(Monose3Error, match="could not read"):
        load_image(tmp_path / "empty.jpg")
    with pytest.raises(Monose3Error, match="not a file"):
        load_image(tmp_path)


# ---- joints -----------------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".json", ".yaml"])
def test_load_joints_mapping_file(tmp_path, panda, suffix):
    f = write(tmp_path / f"j{suffix}", {f"panda_joint{i + 1}": v for i, v in enumerate(Q)})
    vec = load_joints(f, panda)
    np.testing.assert_allclose(vec[:7], Q)
    assert vec[7] == pytest.approx(0.02)  # optional finger joint default


def test_load_joints_list_and_obj(tmp_path, panda):
    np.testing.assert_allclose(load_joints(write(tmp_path / "l.json", Q), panda)[:7], Q)
    np.testing.assert_allclose(load_joints(Q + [0.01], panda), Q + [0.01])


def test_load_joints_dream_styles(tmp_path, panda):
    entries = [{"name": f"panda/panda_joint{i + 1}", "position": v} for i, v in enumerate(Q)]
    entries.append({"name": "panda/panda_finger_joint1", "position": 0.03})
    np.testing.assert_allclose(load_joints(entries, panda), Q + [0.03])
    frame = {"objects": [{"class": "panda"}], "sim_state": {"joints": entries}}
    np.testing.assert_allclose(load_joints(write(tmp_path / "000001.json", frame), panda), Q + [0.03])


def test_load_joints_errors(tmp_path, panda):
    named = {f"panda_joint{i + 1}": v for i, v in enumerate(Q)}
    with pytest.raises(Monose3Error, match="missing joint"):
        load_joints({k: v for k, v in named.items() if k != "panda_joint3"}, panda)
    with pytest.raises(Monose3Error, match="unknown joint"):
        load_joints({**named, "elbow": 0.0}, panda)
    with pytest.raises(Monose3Error, match="NaN"):
        load_joints({**named, "panda_joint2": float("nan")}, panda)
    with pytest.raises(Monose3Error, match="got 5 joint values"):
        load_joints(Q[:5], panda)
    with pytest.raises(Monose3Error, match="must be a number"):
        load_joints({**named, "panda_joint2": "0.5"}, panda)
    with pytest.raises(Monose3Error, match="degrees"):
        load_joints({**named, "panda_joint1": 45.0}, panda)
    with pytest.raises(Monose3Error, match="twice"):
        load_joints([{"name": "panda_joint1", "position": 0.0}] * 2, panda)
    with pytest.raises(Monose3Error, match="not found"):
        load_joints(tmp_path / "nope.json", panda)
    (tmp_path / "bad.json").write_text("{panda_joint1: ")
    with pytest.raises(Monose3Error, match="not valid JSON"):
        load_joints(tmp_path / "bad.json", panda)
    (tmp_path / "empty.yaml").write_text("")
    with pytest.raises(Monose3Error, match="empty"):
        load_joints(tmp_path / "empty.yaml", panda)


# ---- cameras ----------------------------------------------------------------------------------

REALSENSE = dict(fx=615.52, fy=615.22, cx=328.26, cy=251.79, width=640, height=480)


@pytest.mark.parametrize("suffix", [".json", ".yaml"])
def test_load_camera_ours(tmp_path, suffix):
    cam = load_camera(write(tmp_path / f"cam{suffix}", REALSENSE))
    assert cam == Intrinsics(**REALSENSE)
    np.testing.assert_allclose(cam.K, [[615.52, 0, 328.26], [0, 615.22, 251.79], [0, 0, 1]])
    assert load_camera(write(tmp_path / "round.json", cam.to_dict())) == cam


def test_load_camera_dream(tmp_path):
    settings = {
        "camera_settings": [
            {
                "name": "Viewpoint",
                "horizontal_fov": 64,
                "intrinsic_settings": {"resX": 640, "resY": 480, "fx": 399.66, "fy": 399.50, "cx": 319.9, "cy": 244.06},
                "captured_image_size": {"width": 640, "height": 480},
            }
        ]
    }
    cam = load_camera(write(tmp_path / "_camera_settings.json", settings))
    assert cam == Intrinsics(399.66, 399.50, 319.9, 244.06, 640, 480)


def test_load_camera_ros_variants(tmp_path):
    K = [525.0, 0.0, 319.5, 0.0, 525.0, 239.5, 0.0, 0.0, 1.0]
    expected = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
    ros1 = {"header": {"frame_id": "cam"}, "height": 480, "width": 640, "distortion_model": "plumb_bob", "K": K}
    ros2 = {"height": 480, "width": 640, "k": K, "d": [0.0] * 5}
    calib = {
        "image_width": 640,
        "image_height": 480,
        "camera_name": "kinect",
        "camera_matrix": {"rows": 3, "cols": 3, "data": K},
    }
    for i, obj in enumerate((ros1, ros2, calib)):
        assert load_camera(write(tmp_path / f"ros{i}.yaml", obj)) == expected


def test_load_camera_errors(tmp_path):
    with pytest.raises(Monose3Error, match="not found"):
        load_camera(tmp_path / "none.yaml")
    with pytest.raises(Monose3Error, match=r"missing key\(s\) \['cy', 'height'\]"):
        load_camera(write(tmp_path / "a.json", {k: v for k, v in REALSENSE.items() if k not in ("cy", "height")}))
    with pytest.raises(Monose3Error, match="focal lengths must be positive"):
        load_camera(write(tmp_path / "b.json", {**REALSENSE, "fx": 0.0}))
    with pytest.raises(Monose3Error, match="principal point"):
        load_camera(write(tmp_path / "c.json", {**REALSENSE, "cx": 900.0}))
    with pytest.raises(Monose3Error, match="9 numbers"):
        load_camera(write(tmp_path / "d.yaml", {"width": 640, "height": 480, "K": [1, 2, 3]}))
    with pytest.raises(Monose3Error, match="width'/'height"):
        load_camera(write(tmp_path / "e.yaml", {"K": [525.0, 0, 319.5, 0, 525.0, 239.5, 0, 0, 1]}))
    with pytest.raises(Monose3Error, match="captured_image_size"):
        load_camera(
            write(
                tmp_path / "f.json",
                {"camera_settings": [{"intrinsic_settings": {"fx": 1.0, "fy": 1.0, "cx": 1.0, "cy": 1.0}}]},
            )
        )
    with pytest.raises(Monose3Error, match="must be a number"):
        load_camera(write(tmp_path / "g.json", {**REALSENSE, "fy": "615"}))


def test_check_image_camera_and_scale():
    cam = Intrinsics(**REALSENSE)
    check_image_camera(np.zeros((480, 640, 3), np.uint8), cam)
    with pytest.raises(Monose3Error, match=r"1280x960 .* 640x480.*scale_camera"):
        check_image_camera(np.zeros((960, 1280, 3), np.uint8), cam)
    with pytest.raises(Monose3Error, match="1280x720") as err:
        check_image_camera(np.zeros((720, 1280, 3), np.uint8), cam)
    assert "scale_camera" not in str(err.value)  # different aspect: rescaling would be wrong
    big = scale_camera(cam, 1280, 960)
    check_image_camera(np.zeros((960, 1280, 3), np.uint8), big)
    assert big.fx == pytest.approx(2 * cam.fx) and big.fy == pytest.approx(2 * cam.fy)
    # pixel-centre convention: the centre of pixel 0 is at 0, so cx' = (cx + 0.5) * 2 - 0.5
    assert big.cx == pytest.approx(2 * cam.cx + 0.5) and big.cy == pytest.approx(2 * cam.cy + 0.5)
    assert scale_camera(big, 640, 480).cx == pytest.approx(cam.cx)


# ---- poses ------------------------------------------------------------------------------------

POSE = np.array([[0.0, 1.0, 0.0, 0.1], [0.0, 0.0, -1.0, 0.2], [-1.0, 0.0, 0.0, 1.5], [0.0, 0.0, 0.0, 1.0]])


@pytest.mark.parametrize("suffix", [".json", ".yaml"])
def test_load_pose_layouts(tmp_path, suffix):
    assert np.allclose(load_pose(write(tmp_path / f"a{suffix}", {"camera_from_base": POSE.tolist()})), POSE)
    assert np.allclose(load_pose(write(tmp_path / f"b{suffix}", POSE.tolist())), POSE)
    inverse = {"base_from_camera": np.linalg.inv(POSE).tolist()}
    assert np.allclose(load_pose(write(tmp_path / f"c{suffix}", inverse)), POSE)


def test_load_pose_errors(tmp_path):
    with pytest.raises(Monose3Error, match="not found"):
        load_pose(tmp_path / "none.json")
    with pytest.raises(Monose3Error, match="no camera_from_base"):
        load_pose(write(tmp_path / "a.json", {"pose": POSE.tolist()}))
    with pytest.raises(Monose3Error, match="4x4"):
        load_pose(write(tmp_path / "b.json", POSE[:3].tolist()))
    with pytest.raises(Monose3Error, match="NaN"):
        load_pose(write(tmp_path / "c.yaml", [[float("nan")] * 4] * 4))
    mirrored = POSE.copy()
    mirrored[:3, 0] *= -1
    with pytest.raises(Monose3Error, match="not a rigid transform"):
        load_pose(write(tmp_path / "d.json", mirrored.tolist()))
    scaled = POSE.copy()
    scaled[:3, :3] *= 1000
    with pytest.raises(Monose3Error, match="not a rigid transform"):
        load_pose(write(tmp_path / "e.json", scaled.tolist()))
