import numpy as np
import pytest
import torch

from monose3.geometry.camera import project
from monose3.geometry.poses import make_pose, transform_points
from monose3.geometry.rotations import euler_xyz_to_matrix, rotation_angle
from monose3.method.flow_pose import (
    field_targets,
    pose_from_field,
    render_surface,
)
from monose3.method.loss import flow_loss
from monose3.method.pose_space import MIN_DEPTH, base_frame, centroid_frame

SIZE = (128, 96)


def _rendered_view(renderers, models, sample_view, seed: int):
    """H_t (camera-from-centroid), K, and the depth of a real render of the Panda at H_t."""
    model = models["panda"]
    view = sample_view(model, np.random.default_rng(seed), SIZE, (1.2, 1.8))
    centroid = torch.from_numpy(model.centroid(view.points))[None]
    pose_ref = centroid_frame(torch.from_numpy(view.pose)[None], centroid)
    K = torch.from_numpy(view.K)[None]
    depth = renderers["panda"].render(view.joints[None], base_frame(pose_ref, centroid), K, SIZE).depth
    return pose_ref, K, depth


def _nudged(pose: torch.Tensor, angles=(0.03, -0.04, 0.05), shift=(0.01, -0.02, 0.04)) -> torch.Tensor:
    """``pose`` rotated about its origin and shifted (a small-t forward-process step)."""
    rot = euler_xyz_to_matrix(torch.tensor([angles], dtype=pose.dtype)) @ pose[:, :3, :3]
    return make_pose(rot, pose[:, :3, 3] + torch.tensor([shift], dtype=pose.dtype))


def test_render_surface_points_project_back_onto_their_pixels(renderers, models, sample_view):
    pose_ref, K, depth = _rendered_view(renderers, models, sample_view, 0)
    surface = render_surface(depth, pose_ref, K, stride=2)
    assert surface.points_ref.shape == (1, 64 * 48, 3) and surface.valid.sum() > 50
    uv = project(transform_points(pose_ref, surface.points_ref), K)
    assert torch.allclose(uv[surface.valid], surface.uv[surface.valid].to(uv), atol=1e-6)
    rows, cols = surface.uv[0, :, 1].long(), surface.uv[0, :, 0].long()
    assert torch.equal(surface.valid[0], depth[0, rows, cols] > 0)  # valid exactly where the render shows robot


def test_field_targets_are_zero_without_motion_and_the_image_shift_of_a_sideways_move(renderers, models, sample_view):
    pose_ref, K, depth = _rendered_view(renderers, models, sample_view, 1)
    surface = render_surface(depth.float(), pose_ref.float(), K.float())
    field, mask = field_targets(surface, pose_ref.float(), SIZE, (12, 16))
    assert field.shape == (1, 2, 12, 16) and mask.any() and torch.allclose(field, torch.zeros_like(field), atol=1e-6)
    moved = pose_ref.float().clone()
    moved[:, 0, 3] += 0.01 * moved[:, 2, 3]  # 1 % of the depth along x
    field, mask = field_targets(surface, moved, SIZE, (12, 16))
    shift_px = field[:, 0][mask[:, 0]] * SIZE[0]
    expected = K[0, 0, 0].item() * 0.01  # fx * dx / z at the centroid's depth; the surface spans some depth
    assert shift_px.mean().item() == pytest.approx(expected, rel=0.15)
    assert field[:, 1][mask[:, 0]].abs().max() < 0.2 * shift_px.mean()
    assert flow_loss(field, field, mask) == 0 and flow_loss(torch.zeros_like(field), field, mask) > 0


def test_the_true_field_gives_back_most_of_a_small_rotation(renderers, models, sample_view):
    # What the flow-solve denoiser can reach when its field is right: cell means of the true
    # field at stride 8 bring the pose far closer to H_0 than H_t is, in rotation and depth.
    pose_t, K, depth = _rendered_view(renderers, models, sample_view, 2)
    pose_t, K = pose_t.float(), K.float()
    pose_0 = _nudged(pose_t)
    surface = render_surface(depth.float(), pose_t, K)
    field, mask = field_targets(surface, pose_0, SIZE, (12, 16))
    solved = pose_from_field(field, mask.float(), surface, SIZE)
    before = rotation_angle(pose_t[:, :3, :3], pose_0[:, :3, :3]).item()
    assert rotation_angle(solved[:, :3, :3], pose_0[:, :3, :3]).item() < 0.3 * before
    assert (solved[:, :3, 3] - pose_0[:, :3, 3]).norm() < 0.3 * (pose_t[:, :3, 3] - pose_0[:, :3, 3]).norm()
    unchanged = pose_from_field(torch.zeros_like(field), mask.float(), surface, SIZE)
    assert torch.allclose(unchanged, pose_t, atol=1e-5)  # a zero field is the identity update


def test_pose_from_field_keeps_the_depth_floor(renderers, models, sample_view, monkeypatch):
    pose_t, K, depth = _rendered_view(renderers, models, sample_view, 3)
    surface = render_surface(depth.float(), pose_t.float(), K.float())
    field = torch.zeros(1, 2, 12, 16)
    field[:, 0, :, :8], field[:, 0, :, 8:] = -5.0, 5.0  # every part flies out of the crop: "at the lens"
    field[:, 1, :6], field[:, 1, 6:] = -5.0, 5.0
    solved = pose_from_field(field, torch.ones(1, 1, 12, 16), surface, SIZE)
    assert torch.isfinite(solved).all() and solved[0, 2, 3] == pytest.approx(MIN_DEPTH)
    monkeypatch.setattr("monose3.method.flow_pose.MIN_DEPTH", -np.inf)
    assert pose_from_field(field, torch.ones(1, 1, 12, 16), surface, SIZE)[0, 2, 3] < MIN_DEPTH  # the floor acted
