"""The batched PyTorch renderer: its render agrees with the model's geometry and K (OpenCV
pixel centres), batches equal single renders, no holes at any size, clear errors, and a CUDA
out-of-memory error falls back to smaller chunks."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from monose3.errors import Monose3Error
from monose3.robot import RobotModel, spec_from_files
from monose3.robot import rasterize as rasterize_module
from monose3.robot.rasterize import rasterize
from monose3.robot.renderer import Lighting, RenderJob, RobotRenderer

ROBOTS = ("panda", "kuka")
VIEWS_PER_ROBOT = 20


def _mesh_vertices(model: RobotModel, q: np.ndarray) -> np.ndarray:
    """Every mesh vertex, posed (base frame): the silhouette's extremes are among them."""
    mesh = model.mesh
    poses = model.link_poses(q[None])[0][mesh.vertex_link]
    return np.einsum("nij,nj->ni", poses[:, :3, :3], mesh.vertices) + poses[:, :3, 3]


def _on_mask_fraction(mask: np.ndarray, uv: np.ndarray) -> tuple[float, int]:
    """Fraction of the in-image projected points that hit the mask dilated by one pixel."""
    h, w = mask.shape
    grown = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    px = np.round(uv).astype(int)
    inside = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
    if not inside.any():
        return 1.0, 0
    return float(grown[px[inside, 1], px[inside, 0]].mean()), int(inside.sum())


@pytest.fixture(scope="module", params=ROBOTS)
def rendered_views(request, models, renderers, sample_view):
    """20 random views per robot (320x240), rendered in one batch."""
    model = models[request.param]
    rng = np.random.default_rng(10 if request.param == "panda" else 11)
    views = [sample_view(model, rng) for _ in range(VIEWS_PER_ROBOT)]
    out = renderers[request.param].render_jobs([RenderJob(v.joints, v.pose, v.K, v.size) for v in views])
    return model, [(v, rgb, mask) for v, (rgb, mask) in zip(views, out, strict=True)]


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
        assert mask.mean() < 0.6
        kfrac, kn = _on_mask_fraction(mask, view.uv(view.keypoints))
        kp_hits += kfrac * kn
        kp_total += kn
    assert kp_total > 0 and kp_hits / kp_total >= 0.95


def test_mask_box_matches_projected_geometry(rendered_views):
    """A pixel is on the mask when its centre is inside the silhouette, whose extremes are mesh
    vertices: the first/last mask pixel lies within one pixel inside the vertex extremes. A
    half-pixel shift breaks this."""
    model, views = rendered_views
    checked = 0
    for view, _, mask in views:
        verts = _mesh_vertices(model, view.joints)
        if not view.fully_in_view(verts, margin=1.0):
            continue
        checked += 1
        ys, xs = np.nonzero(mask)
        mbox = np.array([xs.min(), ys.min(), xs.max(), ys.max()], float)
        vuv = view.uv(verts)
        gap = (mbox - np.r_[vuv.min(0), vuv.max(0)]) * np.array([1, 1, -1, -1])
        assert np.all(gap >= -1e-3) and np.all(gap <= 1.5), f"mask box {mbox} vs mesh box {vuv.min(0), vuv.max(0)}"
    assert checked >= VIEWS_PER_ROBOT // 3, f"only {checked} views had the robot fully in view"


def test_principal_point_shift_moves_the_mask(models, renderers, sample_view):
    model, renderer = models["panda"], renderers["panda"]
    rng = np.random.default_rng(12)
    view = next(v for v in (sample_view(model, rng, dist=(1.5, 2.5)) for _ in range(50)) if v.fully_in_view(margin=40))
    shifts = [(0, 0), (25, 0), (0, -17), (-31, 12)]
    Ks = []
    for dx, dy in shifts:
        K = view.K.copy()
        K[0, 2] += dx
        K[1, 2] += dy
        Ks.append(K)
    masks = renderer.render([view.joints] * 4, [view.pose] * 4, Ks, view.size).mask.numpy()
    for (dx, dy), moved in zip(shifts[1:], masks[1:], strict=True):
        expected = np.roll(masks[0], (dy, dx), axis=(0, 1))
        assert (moved != expected).mean() < 2e-3, f"shift ({dx}, {dy}) not reproduced"
        assert (moved != masks[0]).mean() > 1e-2


def test_a_batch_renders_as_its_images_one_by_one(models, renderers, sample_view):
    model, renderer = models["kuka"], renderers["kuka"]
    views = [sample_view(model, np.random.default_rng(30 + i)) for i in range(4)]
    batch = renderer.render([v.joints for v in views], [v.pose for v in views], [v.K for v in views], (160, 120))
    for i, v in enumerate(views):
        one = renderer.render(v.joints[None], v.pose[None], v.K[None], (160, 120))
        torch.testing.assert_close(batch.rgb[i], one.rgb[0])
        assert torch.equal(batch.mask[i], one.mask[0])
        torch.testing.assert_close(batch.depth[i], one.depth[0])


def test_depth_is_the_camera_distance_of_the_surface(models, renderers, sample_view):
    model = models["panda"]
    view = sample_view(model, np.random.default_rng(31))
    out = renderers["panda"].render(view.joints[None], view.pose[None], view.K[None], view.size)
    depth, mask = out.depth[0].numpy(), out.mask[0].numpy()
    assert (depth[~mask] == 0).all() and (depth[mask] > 0).all()
    z = (_mesh_vertices(model, view.joints) @ view.pose[:3, :3].T + view.pose[:3, 3])[:, 2]
    assert z.min() - 1e-3 <= depth[mask].min() and depth[mask].max() <= z.max() + 1e-3


@pytest.mark.parametrize("size", [(64, 48), (128, 96), (320, 240), (640, 480)])
def test_no_holes_or_speckle(models, renderers, sample_view, size):
    """Against the same view rendered 4x finer: no pixel is background where all 16 of its
    sub-pixels are robot (a hole), and none is robot where none of them is (speckle)."""
    model, renderer = models["panda"], renderers["panda"]
    rng = np.random.default_rng(32)
    views = [sample_view(model, rng, size=size, dist=(0.6, 1.5)) for _ in range(3)]
    fine_K = []
    for v in views:
        K = v.K.copy()
        K[:2, :2] *= 4
        K[:2, 2] = (K[:2, 2] + 0.5) * 4 - 0.5
        fine_K.append(K)
    w, h = size
    joints, poses = [v.joints for v in views], [v.pose for v in views]
    mask = renderer.render(joints, poses, [v.K for v in views], size).mask.numpy()
    fine = renderer.render(joints, poses, fine_K, (4 * w, 4 * h)).mask.numpy()
    cover = fine.reshape(len(views), h, 4, w, 4).sum((2, 4))
    assert mask.sum() > 0.01 * mask.size
    assert not (~mask & (cover == 16)).any(), "holes inside the robot"
    assert not (mask & (cover == 0)).any(), "speckle outside the robot"


def test_back_face_culling_keeps_every_pixel(models, renderers, sample_view):
    """Back faces are skipped only on closed meshes (the shipped meshes' holes capped:
    ``mesh_repair.py``), so the silhouette does not change. The depth changes only where a cap
    seen from behind was nearest: the surface behind it shows, as it does without the caps."""
    renderer = renderers["panda"]
    view = sample_view(models["panda"], np.random.default_rng(33), dist=(0.6, 1.2))
    pose = torch.as_tensor(view.pose)[None]
    verts, _ = renderer.camera_vertices(renderer.camera_links(view.joints[None], pose))
    faces = torch.as_tensor(models["panda"].mesh.drawn_faces)
    cullable = torch.as_tensor(models["panda"].mesh.closed_faces())
    K = torch.as_tensor(view.K)[None]
    assert cullable.float().mean() > 0.9
    both = rasterize(verts, faces, K, view.size)
    culled = rasterize(verts, faces, K, view.size, cullable)
    assert torch.equal(both.mask, culled.mask)
    deeper = (culled.depth - both.depth)[both.mask]
    assert deeper.min() > -2e-5
    assert (deeper > 2e-5).float().mean() < 1e-3


def test_lighting_and_colour_scale_change_colour_not_mask(models, renderers, sample_view):
    renderer = renderers["kuka"]
    view = sample_view(models["kuka"], np.random.default_rng(13), dist=(1.5, 2.0))
    args = (view.joints[None], view.pose[None], view.K[None], view.size)
    base = renderer.render(*args)
    dim = renderer.render(*args, lighting=Lighting(ambient=0.1, diffuse=0.2, specular=0.0))
    red = renderer.render(*args, color_scale=torch.tensor([1.0, 0.2, 0.2]).expand(1, len(models["kuka"].links), 3))
    assert torch.equal(base.mask, dim.mask) and torch.equal(base.mask, red.mask)
    m = base.mask[0]
    assert dim.rgb[0][:, m].mean() < base.rgb[0][:, m].mean() - 0.05
    assert red.rgb[0][1, m].mean() < 0.5 * base.rgb[0][1, m].mean()


def test_unshaded_renders_the_same_silhouette_and_depth(models, renderers, sample_view):
    """``shade=False`` (the fit's renders) leaves the colours out, and nothing else."""
    view = sample_view(models["panda"], np.random.default_rng(14))
    args = (view.joints[None], view.pose[None], view.K[None], view.size)
    renderer = renderers["panda"]
    shaded, bare = renderer.render(*args), renderer.render(*args, shade=False)
    assert bare.rgb is None and bare.mask.any()
    assert torch.equal(shaded.mask, bare.mask) and torch.equal(shaded.depth, bare.depth)
    tensors = renderer._tensors(torch.device("cpu"))
    verts, _ = renderer.camera_vertices(renderer.camera_links(view.joints[None], torch.from_numpy(view.pose[None])))
    K = torch.from_numpy(view.K[None])
    full = rasterize(verts, tensors["faces"], K, view.size, tensors["cullable"])
    lean = rasterize(verts, tensors["faces"], K, view.size, tensors["cullable"], barycentrics=False)
    assert lean.bary is None and full.bary is not None
    assert torch.equal(full.face, lean.face) and torch.equal(full.depth, lean.depth)


def test_unlit_colours_are_what_a_light_of_ambient_one_shows(models, renderers, sample_view):
    """Each pixel's face id picks the mesh's own colour (black where no face): the colours a
    render lit by ambient light alone shows, with no shading pass."""
    view = sample_view(models["panda"], np.random.default_rng(15))
    args = (view.joints[None], view.pose[None], view.K[None], view.size)
    renderer = renderers["panda"]
    bare = renderer.render(*args, shade=False)
    flat = renderer.render(*args, lighting=Lighting(ambient=1.0, diffuse=0.0, specular=0.0))
    assert torch.equal(bare.face >= 0, bare.mask) and torch.equal(bare.face, flat.face)
    colors = renderer.unlit_colors(bare.face[0].numpy())
    assert np.allclose(colors, flat.rgb[0].permute(1, 2, 0).numpy(), atol=1e-6)
    assert len(np.unique(colors[bare.mask[0].numpy()].round(2), axis=0)) > 3  # white links, black joints, greys


@pytest.mark.parametrize("robot", ["panda", "kuka"])
def test_silhouettes_are_the_renders_masks(models, renderers, sample_view, robot, monkeypatch):
    """The coverage-only path (the fit's silhouette comparisons) gives the mask :meth:`render`
    gives, pixel for pixel: near and partly outside the image, in a batch, and across chunks."""
    rng = np.random.default_rng(15)
    views = [sample_view(models[robot], rng, dist=(0.4, 2.0)) for _ in range(6)]
    poses = np.stack([v.pose for v in views])
    poses[:2, 0, 3] += 0.4  # robots the image's right border cuts
    args = ([v.joints for v in views], poses, [v.K for v in views], (160, 120))
    masks = renderers[robot].render(*args, shade=False).mask
    assert masks.any() and not masks.all()
    assert torch.equal(renderers[robot].silhouettes(*args), masks)
    monkeypatch.setattr(rasterize_module, "rasterize_cpu", None)  # the tensor code, in small chunks
    monkeypatch.setattr(rasterize_module, "CHUNK", 5000)
    assert torch.equal(renderers[robot].silhouettes(*args), masks)


def _memory_for(renderer: RobotRenderer, method: str, rows: int, monkeypatch) -> list[int]:
    """Make ``renderer.<method>`` (its per-batch work) raise a CUDA out-of-memory error on
    batches of more than ``rows`` rows; returns the batch sizes it is then called with, in order."""
    real, calls = getattr(renderer, method), []

    def tight(q, *rest):
        calls.append(len(q))
        if len(q) > rows:
            raise torch.OutOfMemoryError("simulated")
        return real(q, *rest)

    monkeypatch.setattr(renderer, method, tight)
    return calls


def _render_args(models, sample_view, seed: int, n: int) -> tuple:
    views = [sample_view(models["panda"], np.random.default_rng(seed + i)) for i in range(n)]
    return [v.joints for v in views], [v.pose for v in views], [v.K for v in views], (96, 72)


def test_out_of_memory_falls_back_to_smaller_chunks(models, sample_view, monkeypatch):
    renderer = RobotRenderer(models["panda"])
    args = _render_args(models, sample_view, 40, 4)
    expected = renderer.render(*args)
    calls = _memory_for(renderer, "_render", 1, monkeypatch)
    got = renderer.render(*args)
    assert calls[0] == 4 and calls.count(1) == 4
    assert torch.equal(got.mask, expected.mask)
    torch.testing.assert_close(got.rgb, expected.rgb)
    bare = renderer.render(*args, shade=False)
    assert bare.rgb is None and torch.equal(bare.mask, expected.mask)


def test_silhouettes_fall_back_to_halves_on_out_of_memory(models, sample_view, monkeypatch):
    renderer = RobotRenderer(models["panda"])
    args = _render_args(models, sample_view, 50, 5)
    expected = renderer.silhouettes(*args)
    calls = _memory_for(renderer, "_silhouettes", 2, monkeypatch)
    assert torch.equal(renderer.silhouettes(*args), expected)
    assert calls == [5, 2, 3, 1, 2]
    _memory_for(renderer, "_silhouettes", 0, monkeypatch)
    with pytest.raises(torch.OutOfMemoryError):  # not even one row fits: the error is the caller's
        renderer.silhouettes(*args)


@pytest.mark.parametrize(
    ("change", "words"),
    [
        ({"size": (0, 48)}, "positive integers"),
        ({"K": np.full((1, 3, 3), np.nan)}, "finite"),
        ({"joints": np.zeros((2, 9))}, "batch sizes differ"),
        ({"joints": np.zeros((1, 3))}, "values per row"),
        ({"pose": torch.eye(4, device="meta")[None], "K": torch.eye(3)[None]}, "different devices"),
    ],
)
def test_bad_input_gets_one_clear_error(models, renderers, change, words):
    model = models["panda"]
    args = {"joints": np.zeros((1, len(model.joint_names))), "pose": np.eye(4)[None], "K": np.eye(3)[None]}
    args["pose"][0, 2, 3] = 2.0
    args["K"][0, :2] = [[100, 0, 32], [0, 100, 24]]
    size = change.pop("size", (64, 48))
    args.update(change)
    with pytest.raises(Monose3Error, match=words):
        renderers["panda"].render(args["joints"], args["pose"], args["K"], size)


def _urdf(tmp_path, mesh: str | None) -> str:
    visual = f'<visual><geometry><mesh filename="{mesh}"/></geometry></visual>' if mesh else ""
    return (
        '<robot name="stick"><link name="base">'
        + visual
        + '</link><link name="tip"/>'
        + '<joint name="j1" type="revolute"><parent link="base"/><child link="tip"/>'
        + '<axis xyz="0 0 1"/><limit lower="-1" upper="1"/></joint></robot>'
    )


def _custom_robot(tmp_path, mesh: str | None):
    (tmp_path / "robot.urdf").write_text(_urdf(tmp_path, mesh))
    (tmp_path / "kp.json").write_text('{"keypoints": [{"name": "tip", "link": "tip"}]}')
    return spec_from_files(tmp_path / "robot.urdf", tmp_path / "kp.json")


def test_a_users_urdf_with_obj_meshes_renders(tmp_path):
    # a 0.2 m cube with a red material
    (tmp_path / "cube.mtl").write_text("newmtl red\nKd 1 0 0\n")
    corners = [(x, y, z) for x in (-0.1, 0.1) for y in (-0.1, 0.1) for z in (-0.1, 0.1)]
    quads = [(1, 3, 4, 2), (5, 6, 8, 7), (1, 2, 6, 5), (3, 7, 8, 4), (1, 5, 7, 3), (2, 4, 8, 6)]
    text = "mtllib cube.mtl\nusemtl red\n" + "".join(f"v {x} {y} {z}\n" for x, y, z in corners)
    text += "".join("f " + " ".join(map(str, q)) + "\n" for q in quads)
    (tmp_path / "cube.obj").write_text(text)
    renderer = RobotRenderer(RobotModel(_custom_robot(tmp_path, "cube.obj")))
    K = np.array([[[200.0, 0, 63.5], [0, 200.0, 47.5], [0, 0, 1]]])
    pose = np.eye(4)[None]
    pose[0, 2, 3] = 1.0
    out = renderer.render(np.zeros((1, 1)), pose, K, (128, 96))
    # the cube's front face spans 0.2 m * 200 px / 0.9 m = 44 px, centred, red
    cols = np.nonzero(out.mask[0].numpy().any(0))[0]
    assert abs((cols.max() - cols.min() + 1) - 0.2 * 200 / 0.9) <= 1.5
    rgb = out.rgb[0][:, out.mask[0]]
    assert rgb[0].mean() > 0.5 and rgb[1].max() < 0.35


@pytest.mark.parametrize(
    ("mesh", "words"), [("missing.obj", "not found"), ("arm.dae", "convert it to OBJ or STL"), (None, "no visual")]
)
def test_robot_files_the_renderer_cannot_use(tmp_path, mesh, words):
    (tmp_path / "arm.dae").write_text("<COLLADA/>")
    with pytest.raises(Monose3Error, match=words):
        RobotModel(_custom_robot(tmp_path, mesh))


def test_row_spans_miss_no_pixel_of_a_box(monkeypatch):
    """Testing only each row's span of a triangle's box (the tensor code) finds every pixel testing
    the whole box does, on slivers, near-horizontal and near-vertical edges and large triangles alike."""
    rng = np.random.default_rng(5)
    centre = rng.uniform([0, 0], [160, 120], size=(300, 1, 2))
    uv = centre + rng.normal(scale=rng.choice([0.5, 4.0, 40.0], size=(300, 1, 1)), size=(300, 3, 2))
    uv[:100, 2] = uv[:100, 1] + rng.normal(scale=0.05, size=(100, 2))  # slivers
    uv[100:150, :, 1] = uv[100:150, :1, 1] + rng.normal(scale=[0, 1e-3, 30], size=(50, 3))  # a flat edge
    z = rng.uniform(1, 3, size=(300, 3, 1))
    K = torch.tensor([[[100.0, 0, 0], [0, 100.0, 0], [0, 0, 1]]], dtype=torch.float64)
    verts = torch.as_tensor(np.concatenate([uv / 100 * z, z], -1).reshape(1, -1, 3))
    faces = torch.arange(900).view(300, 3)
    monkeypatch.setattr(rasterize_module, "rasterize_cpu", None)  # the tensor code's row spans
    renders = {}
    for small_box in (0, rasterize_module.SMALL_BOX, 10**9):  # rows everywhere, as shipped, boxes everywhere
        monkeypatch.setattr(rasterize_module, "SMALL_BOX", small_box)
        renders[small_box] = rasterize(verts, faces, K, (160, 120))
    reference = renders.pop(10**9)
    assert reference.mask.sum() > 1000
    for fragments in renders.values():
        assert torch.equal(fragments.face, reference.face) and torch.equal(fragments.depth, reference.depth)
