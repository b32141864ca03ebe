"""Renderer: the render agrees with the model's geometry and K (pixel-centre convention), and the
pool returns what a single process would."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from monose3.render import Lighting, RendererPool, RenderJob, projection_matrix
from monose3.robot import load_obj

ROBOTS = ("panda", "kuka")
VIEWS_PER_ROBOT = 20


_VERTS: dict[str, tuple[np.ndarray, np.ndarray]] = {}


def _mesh_vertices(model, q: np.ndarray) -> np.ndarray:
    """Every visual mesh vertex, posed (base frame): the silhouette's extremes are among them."""
    if model.name not in _VERTS:
        verts, links = [], []
        for vis in model._visuals:
            v, _ = load_obj(vis.mesh)
            verts.append(v * vis.scale @ vis.origin[:3, :3].T + vis.origin[:3, 3])
            links.append(np.full(len(v), model.link_index[vis.link]))
        _VERTS[model.name] = (np.concatenate(verts), np.concatenate(links))
    local, links = _VERTS[model.name]
    poses = model.link_poses(q[None])[0][links]
    return np.einsum("nij,nj->ni", poses[:, :3, :3], local) + poses[:, :3, 3]


def _on_mask_fraction(mask: np.ndarray, uv: np.ndarray) -> tuple[float, int]:
    """Fraction of the in-image projected points that hit the mask dilated by one pixel."""
    h, w = mask.shape
    grown = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    px = np.round(uv).astype(int)
    inside = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
    if not inside.any():
        return 1.0, 0
    return float(grown[px[inside, 1], px[inside, 0]].mean()), int(inside.sum())


def _mask_box(mask: np.ndarray) -> np.ndarray:
    ys, xs = np.nonzero(mask)
    return np.array([xs.min(), ys.min(), xs.max(), ys.max()], float)


@pytest.fixture(scope="module", params=ROBOTS)
def rendered_views(request, models, renderers, sample_view):
    """20 random views per robot (320x240) and their renders."""
    model, renderer = models[request.param], renderers[request.param]
    rng = np.random.default_rng(10 if request.param == "panda" else 11)
    out = []
    for _ in range(VIEWS_PER_ROBOT):
        view = sample_view(model, rng)
        rgb, mask = renderer.render(RenderJob(view.joints, view.pose, view.K, view.size))
        out.append((view, rgb, mask))
    return model, out


def test_render_outputs(rendered_views):
    _, views = rendered_views
    for _, rgb, mask in views:
        assert rgb.shape == (240, 320, 3) and rgb.dtype == np.uint8
        assert mask.shape == (240, 320) and mask.dtype == bool
        assert mask.any()
        assert not rgb[~mask].any(), "background must be black"
        assert rgb[mask].max() > 30, "the robot must be lit"


def test_projected_points_land_on_mask(rendered_views):
    _, views = rendered_views
    kp_hits = kp_total = 0
    for view, _, mask in views:
        frac, n = _on_mask_fraction(mask, view.uv())
        assert n == 0 or frac >= 0.95, f"only {frac:.1%} of {n} surface points on the mask"
        # the mask is not simply everything: most of the image is background
        assert mask.mean() < 0.6
        kfrac, kn = _on_mask_fraction(mask, view.uv(view.keypoints))
        kp_hits += kfrac * kn
        kp_total += kn
    # keypoints are link origins; some (panda_link3) sit just beside the shell in some views
    assert kp_total > 0 and kp_hits / kp_total >= 0.95


def test_mask_box_matches_projected_geometry(rendered_views):
    model, views = rendered_views
    checked = 0
    for view, _, mask in views:
        verts = _mesh_vertices(model, view.joints)
        if not view.fully_in_view(verts, margin=1.0):
            continue
        checked += 1
        mbox = _mask_box(mask)
        vuv = view.uv(verts)
        vbox = np.r_[vuv.min(0), vuv.max(0)]
        # A pixel is on the mask when its centre is inside the silhouette, whose extremes are mesh
        # vertices: first/last mask pixel lies within one pixel inside the vertex extremes. A
        # half-pixel shift of the renderer breaks this.
        gap = (mbox - vbox) * np.array([1, 1, -1, -1])
        assert np.all(gap >= -0.1) and np.all(gap <= 1.5), f"mask box {mbox} vs mesh box {vbox}"
        # the 2000 surface points span the same box (they undersample thin extremities a little)
        puv = view.uv()
        pbox = np.r_[puv.min(0), puv.max(0)]
        pgap = (pbox - mbox) * np.array([1, 1, -1, -1])
        assert np.all(pgap >= -1.0), f"surface points outside the mask box: {pbox} vs {mbox}"
        assert np.median(np.abs(pbox - mbox)) <= 2.0 and np.all(np.abs(pbox - mbox) <= 6.0), (pbox, mbox)
    assert checked >= VIEWS_PER_ROBOT // 3, f"only {checked} views had the robot fully in view"


def test_principal_point_shift_moves_the_mask(models, renderers, sample_view):
    model, renderer = models["panda"], renderers["panda"]
    rng = np.random.default_rng(12)
    for _ in range(20):
        view = sample_view(model, rng, dist=(1.5, 2.5))
        if view.fully_in_view(margin=40):
            break
    else:
        pytest.fail("no view with the robot well inside the image")
    _, base = renderer.render(RenderJob(view.joints, view.pose, view.K, view.size))
    for dx, dy in [(25, 0), (0, -17), (-31, 12)]:
        K = view.K.copy()
        K[0, 2] += dx
        K[1, 2] += dy
        _, moved = renderer.render(RenderJob(view.joints, view.pose, K, view.size))
        expected = np.roll(base, (dy, dx), axis=(0, 1))
        assert (moved != expected).mean() < 2e-3, f"shift ({dx}, {dy}) not reproduced"
        assert (moved != base).mean() > 1e-2


def test_lighting_changes_colour_not_mask(models, renderers, sample_view):
    model, renderer = models["kuka"], renderers["kuka"]
    view = sample_view(model, np.random.default_rng(13), dist=(1.5, 2.0))
    rgb1, m1 = renderer.render(RenderJob(view.joints, view.pose, view.K, view.size))
    dim = Lighting(ambient=0.1, diffuse=0.2, specular=0.0)
    rgb2, m2 = renderer.render(RenderJob(view.joints, view.pose, view.K, view.size, dim))
    np.testing.assert_array_equal(m1, m2)
    assert rgb2[m2].mean() < rgb1[m1].mean() - 10


def test_projection_matrix_maps_pixel_centres():
    K = np.array([[400.0, 0, 170.3], [0, 390.0, 110.7], [0, 0, 1]])
    w, h = 320, 240
    P = projection_matrix(K, w, h)
    rng = np.random.default_rng(14)
    cam = np.c_[rng.uniform(-0.5, 0.5, (50, 2)), rng.uniform(0.5, 3.0, 50)]
    uv = cam[:, :2] / cam[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]
    gl = np.c_[cam[:, 0], -cam[:, 1], -cam[:, 2], np.ones(50)]
    clip = gl @ P.T
    ndc = clip[:, :3] / clip[:, 3:]
    # OpenGL: pixel u spans NDC [2u/W - 1, 2(u+1)/W - 1]; image row 0 is the top (NDC y = 1)
    np.testing.assert_allclose((ndc[:, 0] + 1) * w / 2 - 0.5, uv[:, 0], atol=1e-9)
    np.testing.assert_allclose((1 - ndc[:, 1]) * h / 2 - 0.5, uv[:, 1], atol=1e-9)
    assert np.all(np.abs(ndc[:, 2]) < 1)


def test_pool_matches_single_process(models, sample_view):
    model = models["panda"]
    rng = np.random.default_rng(15)
    jobs = []
    for i in range(6):
        v = sample_view(model, rng, dist=(1.0, 2.0))
        jobs.append(RenderJob(v.joints, v.pose, v.K, (320, 240) if i % 2 else (160, 120)))
    with RendererPool("panda", workers=0) as local:
        assert local.workers == 0
        expected = local.render(jobs)
    with RendererPool(model, workers=2) as pool:
        got = pool.render(jobs)
        streamed = list(pool.imap(jobs))
    assert len(got) == len(streamed) == len(jobs)
    for (rgb_e, m_e), (rgb_g, m_g), (rgb_s, m_s) in zip(expected, got, streamed, strict=True):
        np.testing.assert_array_equal(m_e, m_g)
        np.testing.assert_array_equal(rgb_e, rgb_g)
        np.testing.assert_array_equal(m_e, m_s)
        np.testing.assert_array_equal(rgb_e, rgb_s)
    # the jobs differ, so an order mix-up would show
    assert not np.array_equal(expected[1][1], expected[3][1])


def test_a_pool_worker_stays_without_torch(models):
    """Workers import only the renderer and robot model (the pool resolves the backend in the
    parent): torch would cost each worker about 500 MB and a second of start-up."""
    pool = RendererPool(models["panda"].spec, workers=1)
    try:
        loaded = pool._pool.apply(_torch_loaded)
    finally:
        pool.close()
    assert loaded is False


def _torch_loaded() -> bool:
    import sys

    return "torch" in sys.modules
