"""The compiled CPU rasteriser draws what the tensor code draws, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from monose3.robot import rasterize as rasterize_module
from monose3.robot.rasterize import rasterize, rasterize_coverage

pytest.importorskip("numba")


def _both(monkeypatch, draw):
    """``draw()`` by the compiled rasteriser, then by the tensor code."""
    compiled = draw()
    with monkeypatch.context() as m:
        m.setattr(rasterize_module, "rasterize_cpu", None)
        return compiled, draw()


def _assert_same(compiled, tensor) -> None:
    assert torch.equal(compiled.face, tensor.face) and torch.equal(compiled.depth, tensor.depth)
    assert (compiled.bary is None) == (tensor.bary is None)
    if compiled.bary is not None:
        assert torch.equal(compiled.bary, tensor.bary)


@pytest.mark.parametrize("robot", ["panda", "kuka"])
@pytest.mark.parametrize("size", [(160, 120), (320, 240)])
def test_robot_renders_are_the_tensor_codes_bit_for_bit(models, renderers, sample_view, robot, size, monkeypatch):
    """Near, far, and cut by the image's border; faces culled or drawn from both sides; with and
    without barycentrics; silhouettes too."""
    renderer = renderers[robot]
    rng = np.random.default_rng(7)
    views = [sample_view(models[robot], rng, size=size, dist=(0.3, 2.5)) for _ in range(5)]
    poses = torch.as_tensor(np.stack([v.pose for v in views]))
    poses[:2, 0, 3] += 0.5  # robots the image's right border cuts
    verts, _ = renderer.camera_vertices(renderer.camera_links(np.stack([v.joints for v in views]), poses))
    faces = torch.as_tensor(models[robot].mesh.drawn_faces)
    cullable = torch.as_tensor(models[robot].mesh.closed_faces())
    K = torch.as_tensor(np.stack([v.K for v in views]))
    for cull in (cullable, None):
        for bary in (True, False):
            compiled, tensor = _both(monkeypatch, lambda: rasterize(verts, faces, K, size, cull, bary))  # noqa: B023
            assert compiled.mask.sum() > 1000
            _assert_same(compiled, tensor)
        covered, tensor_covered = _both(monkeypatch, lambda: rasterize_coverage(verts, faces, K, size, cull))  # noqa: B023
        assert torch.equal(covered, tensor_covered) and torch.equal(covered, compiled.mask)


def test_slivers_flat_edges_and_points_behind_the_camera_as_the_tensor_code(monkeypatch):
    rng = np.random.default_rng(5)
    centre = rng.uniform([0, 0], [160, 120], size=(400, 1, 2))
    uv = centre + rng.normal(scale=rng.choice([0.5, 4.0, 40.0, 400.0], size=(400, 1, 1)), size=(400, 3, 2))
    uv[:100, 2] = uv[:100, 1] + rng.normal(scale=0.05, size=(100, 2))  # slivers
    uv[100:150, :, 1] = uv[100:150, :1, 1] + rng.normal(scale=[0, 1e-3, 30], size=(50, 3))  # a flat edge
    z = rng.uniform(1, 3, size=(400, 3, 1))
    z[350:, 0] = rng.uniform(-1, 0.02, size=(50, 1))  # a corner behind the camera or too near
    K = torch.tensor([[[100.0, 0, 0], [0, 100.0, 0], [0, 0, 1]]], dtype=torch.float64)
    verts = torch.as_tensor(np.concatenate([uv / 100 * z, z], -1).reshape(1, -1, 3))
    faces = torch.arange(1200).view(400, 3)
    compiled, tensor = _both(monkeypatch, lambda: rasterize(verts, faces, K, (160, 120)))
    assert compiled.mask.sum() > 1000
    _assert_same(compiled, tensor)
