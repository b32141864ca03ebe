"""RobotModel: forward kinematics against pybullet, joint validation, keypoints, surface points."""

from __future__ import annotations

import json

import numpy as np
import pytest

from monose3.errors import Monose3Error
from monose3.geometry.poses import rigid_fit
from monose3.robot import NUM_SURFACE_POINTS, RobotModel, get_spec, spec_from_files

ROBOTS = ("panda", "kuka")


def _rotation_angle(a: np.ndarray, b: np.ndarray) -> float:
    cos = (np.trace(a.T @ b) - 1.0) / 2.0
    # arccos is ill-conditioned near 1; the chordal distance bounds the angle just as well there.
    return float(max(np.arccos(np.clip(cos, -1.0, 1.0)), np.linalg.norm(a - b) / np.sqrt(2.0)))


def _posed_triangles(model: RobotModel, q: np.ndarray) -> np.ndarray:
    """``[F, 3, 3]`` triangles of the robot's mesh, posed by the model's FK (base frame)."""
    mesh = model.mesh
    poses = model.link_poses(q[None])[0][mesh.vertex_link]
    verts = np.einsum("vij,vj->vi", poses[:, :3, :3], mesh.vertices) + poses[:, :3, 3]
    return verts[mesh.faces]


def _on_some_triangle(points: np.ndarray, tris: np.ndarray, tol: float = 1e-7) -> np.ndarray:
    """For each point: does it lie (within ``tol`` m) inside one of the triangles?"""
    lo, hi = tris.min(1) - tol, tris.max(1) + tol
    e1, e2 = tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
    normal = np.cross(e1, e2)
    area2 = np.linalg.norm(normal, axis=1)
    ok = np.zeros(len(points), bool)
    for i, p in enumerate(points):
        cand = np.nonzero(np.all((lo <= p) & (hi >= p), axis=1) & (area2 > 1e-14))[0]
        if len(cand) == 0:
            continue
        d = p - tris[cand, 0]
        n = normal[cand] / area2[cand, None]
        plane = np.abs((d * n).sum(1))
        # barycentric coordinates of p's projection in the triangle plane
        c1 = (np.cross(d, e2[cand]) * normal[cand]).sum(1) / area2[cand] ** 2
        c2 = (np.cross(e1[cand], d) * normal[cand]).sum(1) / area2[cand] ** 2
        eps = 1e-6
        ok[i] = bool(np.any((plane < tol) & (c1 >= -eps) & (c2 >= -eps) & (c1 + c2 <= 1 + eps)))
    return ok


# ---- forward kinematics ---------------------------------------------------------------------


@pytest.mark.parametrize("robot", ROBOTS)
def test_fk_matches_pybullet_link_states(robot, models, pybullet_renderers):
    model, renderer = models[robot], pybullet_renderers[robot]
    rng = np.random.default_rng(0)
    q = model.random_joints(rng, 150)
    # also the joint limits themselves
    q = np.concatenate([q, model.joint_limits().T])
    ours = model.link_poses(q)
    assert ours.shape == (len(q), len(model.links), 4, 4)
    worst_t = worst_r = 0.0
    for b in range(len(q)):
        renderer.set_joints(q[b])
        theirs = renderer.link_world_poses()
        assert set(theirs) == set(model.links)
        for link, pose in theirs.items():
            mine = ours[b, model.link_index[link]]
            worst_t = max(worst_t, float(np.abs(mine[:3, 3] - pose[:3, 3]).max()))
            worst_r = max(worst_r, _rotation_angle(mine[:3, :3], pose[:3, :3]))
    assert worst_t < 1e-6, f"FK translation differs from pybullet by {worst_t} m"
    assert worst_r < 1e-6, f"FK rotation differs from pybullet by {worst_r} rad"


def test_fk_is_not_trivially_constant(models):
    """Guards the pybullet comparison: the links really move with the joints."""
    model = models["panda"]
    q = model.random_joints(np.random.default_rng(1), 2)
    poses = model.link_poses(q)
    hand = model.link_index["panda_hand"]
    assert np.linalg.norm(poses[0, hand, :3, 3] - poses[1, hand, :3, 3]) > 1e-2
    np.testing.assert_allclose(poses[:, model.link_index[model.root]], np.broadcast_to(np.eye(4), (2, 4, 4)))


def test_fk_of_repeated_and_alternating_rows(models):
    """Kinematics solve each distinct row once and keep the last call's answer: a batch of
    repeated rows, or calls that alternate between configurations, still get their own poses."""
    model = models["panda"]
    q = model.random_joints(np.random.default_rng(2), 2)
    each = [model.link_poses(q[i : i + 1])[0] for i in range(2)]
    mixed = model.link_poses(q[[1, 0, 1, 1, 0]])
    for got, i in zip(mixed, [1, 0, 1, 1, 0], strict=True):
        np.testing.assert_array_equal(got, each[i])
    mixed[0] += 1.0  # the caller's copy: the kept answer is not changed
    np.testing.assert_array_equal(model.link_poses(q[1:2])[0], each[1])
    np.testing.assert_array_equal(model.link_poses(q[0:1])[0], each[0])


def test_panda_finger_mimic_follows_first_finger(models):
    model = models["panda"]
    q = model.joint_vector([0.0] * 7)
    for opening in (0.0, 0.01, 0.04):
        q[-1] = opening
        poses = model.link_poses(q[None])[0]
        left = poses[model.link_index["panda_leftfinger"], :3, 3]
        right = poses[model.link_index["panda_rightfinger"], :3, 3]
        assert np.linalg.norm(left - right) == pytest.approx(2 * opening, abs=1e-9)


# ---- joint configurations -------------------------------------------------------------------


def test_joint_names_and_required(models):
    panda, kuka = models["panda"], models["kuka"]
    assert panda.required_joints == [f"panda_joint{i}" for i in range(1, 8)]
    assert "panda_finger_joint1" in panda.joint_names
    assert kuka.required_joints == kuka.joint_names and len(kuka.joint_names) == 7


def test_joint_vector_accepts_prefixed_names(models):
    model = models["panda"]
    rng = np.random.default_rng(2)
    q = model.random_joints(rng, 1)[0]
    plain = model.joint_dict(q)
    prefixed = {f"panda/{k}": v for k, v in plain.items()}
    deep = {f"world/robot/{k}": v for k, v in plain.items()}
    np.testing.assert_array_equal(model.joint_vector(plain), q)
    np.testing.assert_array_equal(model.joint_vector(prefixed), q)
    np.testing.assert_array_equal(model.joint_vector(deep), q)


def test_joint_vector_fills_optional_joints(models):
    model = models["panda"]
    required = {f"panda_joint{i}": 0.1 * i for i in range(1, 8)}
    from_dict = model.joint_vector(required)
    from_list = model.joint_vector([0.1 * i for i in range(1, 8)])
    expected = [0.1 * i for i in range(1, 8)] + [0.02]
    np.testing.assert_allclose(from_dict, expected)
    np.testing.assert_allclose(from_list, expected)
    # a full list (optional joints included) is taken as given
    np.testing.assert_allclose(model.joint_vector([*expected[:7], 0.035]), [*expected[:7], 0.035])
    # a mimic joint may be present in the dict (DREAM writes it) and is ignored
    np.testing.assert_allclose(model.joint_vector({**required, "panda_finger_joint2": 0.3}), expected)


@pytest.mark.parametrize(
    ("joints", "words"),
    [
        ({f"panda_joint{i}": 0.0 for i in range(1, 7)}, ["missing", "panda_joint7"]),
        ({**{f"panda_joint{i}": 0.0 for i in range(1, 8)}, "elbow": 0.0}, ["unknown", "elbow"]),
        ({**{f"panda_joint{i}": 0.0 for i in range(1, 8)}, "panda_joint3": float("nan")}, ["panda_joint3", "nan"]),
        ({**{f"panda_joint{i}": 0.0 for i in range(1, 8)}, "panda_joint2": np.inf}, ["panda_joint2", "infinite"]),
        ({**{f"panda_joint{i}": 0.0 for i in range(1, 8)}, "panda_joint2": "fast"}, ["numbers"]),
        ([0.0] * 6, ["6 joint values", "panda_joint1"]),
        ([0.0] * 10, ["10 joint values"]),
        ([0.0] * 6 + [float("nan")], ["panda_joint7", "nan"]),
        (["a"] * 7, ["numbers"]),
    ],
)
def test_joint_vector_errors_are_helpful(models, joints, words):
    with pytest.raises(Monose3Error) as info:
        models["panda"].joint_vector(joints)
    msg = str(info.value)
    assert "\n" not in msg
    for word in words:
        assert word.lower() in msg.lower(), msg


def test_random_joints_within_limits(models):
    for model in models.values():
        q = model.random_joints(np.random.default_rng(3), 500)
        lim = model.joint_limits()
        assert q.shape == (500, len(model.joint_names))
        assert np.all(q >= lim[:, 0]) and np.all(q <= lim[:, 1])
        assert np.all(q.std(0) > 0.2 * (lim[:, 1] - lim[:, 0]) / np.sqrt(12))


def test_unknown_robot_name():
    with pytest.raises(Monose3Error, match="unknown robot 'ur5'.*panda"):
        RobotModel("ur5")
    assert get_spec("kuka").name == "kuka"


# ---- keypoints ------------------------------------------------------------------------------


@pytest.mark.parametrize("robot", ROBOTS)
def test_keypoints_are_link_origins(robot, models, pybullet_renderers):
    model, renderer = models[robot], pybullet_renderers[robot]
    q = model.random_joints(np.random.default_rng(4), 5)
    kp = model.keypoints(q)
    assert kp.shape == (5, len(model.keypoint_names), 3)
    for b in range(5):
        renderer.set_joints(q[b])
        links = renderer.link_world_poses()
        for k, spec in enumerate(model.spec.keypoints):
            np.testing.assert_allclose(kp[b, k], links[spec.link][:3, 3], atol=1e-6)


def test_dream_keypoint_names(models):
    assert models["panda"].keypoint_names == [
        "panda_link0",
        "panda_link2",
        "panda_link3",
        "panda_link4",
        "panda_link6",
        "panda_link7",
        "panda_hand",
    ]
    assert models["kuka"].keypoint_names == [f"iiwa7_link_{i}" for i in range(8)]  # DREAM's names


def test_custom_spec_keypoint_offsets(tmp_path, models):
    panda = models["panda"]
    offsets = {"hand_tip": ("panda_hand", [0.0, 0.0, 0.1]), "elbow": ("panda_link4", [0.05, -0.02, 0.01])}
    kp_file = tmp_path / "kp.json"
    kp_file.write_text(
        json.dumps(
            {
                "keypoints": [{"name": "base", "link": "panda_link0"}]
                + [{"name": n, "link": link, "offset": off} for n, (link, off) in offsets.items()]
            }
        )
    )
    spec = spec_from_files(panda.spec.urdf, kp_file, name="mypanda")
    model = RobotModel(spec)
    assert model.name == "mypanda" and model.keypoint_names == ["base", "hand_tip", "elbow"]
    q = model.random_joints(np.random.default_rng(5), 4)
    kp = model.keypoints(q)
    poses = model.link_poses(q)
    np.testing.assert_allclose(kp[:, 0], poses[:, model.link_index["panda_link0"], :3, 3], atol=1e-12)
    for k, (link, off) in enumerate(offsets.values(), start=1):
        expected = poses[:, model.link_index[link]] @ np.array([*off, 1.0])
        np.testing.assert_allclose(kp[:, k], expected[:, :3], atol=1e-12)
        # the offset is in the link frame: its length is kept, its direction turns with the link
        dist = np.linalg.norm(kp[:, k] - poses[:, model.link_index[link], :3, 3], axis=1)
        np.testing.assert_allclose(dist, np.linalg.norm(off), atol=1e-12)


def test_spec_from_files_errors(tmp_path, models):
    urdf = models["panda"].spec.urdf
    with pytest.raises(Monose3Error, match="not found"):
        spec_from_files(tmp_path / "nope.urdf", tmp_path / "kp.json")
    bad = tmp_path / "bad.json"
    bad.write_text('{"points": []}')
    with pytest.raises(Monose3Error, match="malformed keypoint spec"):
        spec_from_files(urdf, bad)
    bad.write_text("{not json")
    with pytest.raises(Monose3Error, match="malformed keypoint spec"):
        spec_from_files(urdf, bad)
    unknown = tmp_path / "unknown.json"
    unknown.write_text(json.dumps({"keypoints": [{"name": "x", "link": "panda_link99"}]}))
    with pytest.raises(Monose3Error, match="panda_link99"):
        RobotModel(spec_from_files(urdf, unknown))


# ---- surface points and centroid ------------------------------------------------------------


def test_surface_points_shape_and_determinism(models):
    for name, model in models.items():
        q = model.random_joints(np.random.default_rng(6), 3)
        pts = model.surface_points(q)
        assert pts.shape == (3, NUM_SURFACE_POINTS, 3)
        again = RobotModel(name).surface_points(q)
        np.testing.assert_array_equal(pts, again)
        # not degenerate: distinct points spread over the robot
        assert len(np.unique(pts[0].round(6), axis=0)) == NUM_SURFACE_POINTS
        extent = pts[0].max(0) - pts[0].min(0)
        assert extent.max() > 0.4


@pytest.mark.parametrize("robot", ROBOTS)
def test_surface_points_lie_on_posed_meshes(robot, models):
    model = models[robot]
    q = model.random_joints(np.random.default_rng(7), 1)[0]
    pts = model.surface_points(q[None])[0]
    tris = _posed_triangles(model, q)
    verts = tris.reshape(-1, 3)
    assert np.all(pts >= verts.min(0) - 1e-9) and np.all(pts <= verts.max(0) + 1e-9)
    sub = pts[np.random.default_rng(0).choice(len(pts), 300, replace=False)]
    on = _on_some_triangle(sub, tris)
    assert on.all(), f"{(~on).sum()} of {len(sub)} points are off the meshes"
    # and the check is able to fail: points pushed 5 mm off are not on the surface
    assert _on_some_triangle(sub[:50] + np.array([0.0, 0.0, 0.005]), tris).mean() < 0.2


@pytest.mark.parametrize(("robot", "joint"), [("panda", "panda_joint7"), ("panda", "panda_joint4"), ("kuka", 5)])
def test_surface_points_move_rigidly_with_their_links(robot, joint, models):
    model = models[robot]
    name = joint if isinstance(joint, str) else model.joint_names[joint]
    j = model.joint_names.index(name)
    q0 = model.random_joints(np.random.default_rng(8), 1)[0]
    q1 = q0.copy()
    q1[j] += 0.5
    p0, p1 = model.surface_points(np.stack([q0, q1]))
    moved = np.linalg.norm(p1 - p0, axis=1) > 1e-9
    assert 0 < moved.sum() < len(p0)
    # points of the links before the joint stay put (exactly); the rest turn as one rigid body
    child = model._joint_by_name[name].child
    pose, resid = rigid_fit(p0[moved], p1[moved])
    assert resid < 1e-9
    l0, l1 = model.link_poses(np.stack([q0, q1]))[:, model.link_index[child]]
    np.testing.assert_allclose(pose, l1 @ np.linalg.inv(l0), atol=1e-9)


def test_centroid_is_bounding_box_centre():
    rng = np.random.default_rng(9)
    pts = rng.exponential(size=(4, 500, 3))  # skewed: the mean is far from the box centre
    c = RobotModel.centroid(pts)
    assert c.shape == (4, 3)
    np.testing.assert_allclose(c, (pts.min(1) + pts.max(1)) / 2)
    assert np.abs(c - pts.mean(1)).min() > 0.5
    np.testing.assert_allclose(RobotModel.centroid(pts[0]), c[0])


def test_keypoints_in_the_camera_frame(models):
    model = models["panda"]
    q = model.random_joints(np.random.default_rng(5), 3)
    poses = np.stack([np.eye(4)] * 3)
    poses[:, :3, 3] = [[0.1, -0.2, 1.5], [0.0, 0.0, 2.0], [0.3, 0.1, 0.9]]
    poses[1, :3, :3] = [[0, 1, 0], [0, 0, -1], [-1, 0, 0]]
    base = model.keypoints(q)
    expected = np.stack([base[i] @ poses[i, :3, :3].T + poses[i, :3, 3] for i in range(3)])
    np.testing.assert_allclose(model.keypoints(q, poses), expected, atol=1e-12)
