"""method.render_compare: the crop is centred on the reference point and its intrinsics map
points to the same crop pixels as the image followed by the crop."""

import numpy as np
import torch

from monose3.geometry.camera import intrinsics_matrix, project
from monose3.geometry.poses import make_pose, transform_points
from monose3.method.render_compare import crop_batch, crop_geometry, image_to_tensor

RENDER = (128, 96)


def scene():
    rot = torch.eye(3, dtype=torch.float64)[None]
    pose = make_pose(rot, torch.tensor([[0.1, -0.05, 1.2]], dtype=torch.float64))
    points = torch.tensor([[[-0.2, -0.3, 0.0], [0.25, 0.2, 0.1], [0.0, 0.1, -0.1]]], dtype=torch.float64)
    K = torch.as_tensor(intrinsics_matrix(500.0, 500.0, 319.5, 239.5))[None]
    return pose, points, K


def test_crop_is_centred_on_the_reference_point_with_the_render_aspect():
    pose, points, K = scene()
    boxes, _ = crop_geometry(pose, points, K, RENDER)
    centre_uv = project(pose[:, None, :3, 3], K)[0, 0]
    x1, y1, x2, y2 = boxes[0]
    torch.testing.assert_close(torch.stack([(x1 + x2) / 2, (y1 + y2) / 2]) - 0.5, centre_uv)
    assert float((x2 - x1) / (y2 - y1)) == np.float64(RENDER[0] / RENDER[1])
    uv = project(transform_points(pose, points), K)[0]
    assert (uv[:, 0] > x1).all() and (uv[:, 0] < x2).all() and (uv[:, 1] > y1).all() and (uv[:, 1] < y2).all()


def test_crop_intrinsics_agree_with_the_image_crop():
    pose, points, K = scene()
    boxes, K_crop = crop_geometry(pose, points, K, RENDER)
    # a one-pixel bright dot where a point projects in the image lands where K_crop projects it
    point = transform_points(pose, points)[:, :1]
    u, v = project(point, K)[0, 0].round().long().tolist()
    image = np.zeros((480, 640, 3), np.uint8)
    image[v - 2 : v + 3, u - 2 : u + 3] = 255
    crop = crop_batch(image_to_tensor(image)[None], boxes, RENDER)[0, 0]
    peak = np.unravel_index(int(crop.argmax()), crop.shape)
    fx, cx, cy = float(K[0, 0, 0]), float(K[0, 0, 2]), float(K[0, 1, 2])
    dot = torch.tensor([[[(u - cx) / fx, (v - cy) / fx, 1.0]]], dtype=torch.float64)  # the dot's ray
    expected = project(dot, K_crop)[0, 0]
    assert abs(peak[1] - float(expected[0])) <= 1.0 and abs(peak[0] - float(expected[1])) <= 1.0


def test_a_shifted_crop_moves_by_its_fraction_of_the_box_and_its_intrinsics_follow():
    pose, points, K = scene()
    boxes, K_crop = crop_geometry(pose, points, K, RENDER)
    shift = torch.tensor([[0.1, -0.05]], dtype=torch.float64)
    moved, K_moved = crop_geometry(pose, points, K, RENDER, shift)
    size = boxes[:, 2:] - boxes[:, :2]
    torch.testing.assert_close(moved, boxes + (shift * size).repeat(1, 2))
    cam = transform_points(pose, points)
    # every point lands 10 % of the render width to the left and 5 % of its height lower
    offset = project(cam, K_moved) - project(cam, K_crop)
    torch.testing.assert_close(offset, (-shift * torch.tensor(RENDER)).expand_as(offset).to(offset))
