import math

import pytest
import torch
from conftest import crop_K, random_poses, slab_surface

from monose3.geometry.rotations import euler_xyz_to_matrix, rotation_6d_to_matrix
from monose3.method.config import DESIGNS, Config, NetworkConfig, get_preset, with_section
from monose3.method.denoiser import Denoiser, timestep_embedding
from monose3.method.designs import DESIGN_CLASSES, FIELD_DESIGNS, build_denoiser
from monose3.method.designs.blocks import local_correlation
from monose3.method.loss import disentangled_loss
from monose3.method.update import apply_update, raw_to_update, true_update, update_to_raw


def test_gram_schmidt_gives_proper_rotations():
    r6 = torch.randn(1000, 6, dtype=torch.float64) * 5
    rot = rotation_6d_to_matrix(r6)
    eye = torch.eye(3, dtype=torch.float64).expand(1000, 3, 3)
    assert torch.allclose(rot.transpose(1, 2) @ rot, eye, atol=1e-10)
    assert torch.allclose(torch.det(rot), torch.ones(1000, dtype=torch.float64), atol=1e-10)
    # The first column keeps r1's direction.
    assert torch.allclose(rot[:, :, 0], torch.nn.functional.normalize(r6[:, :3], dim=1), atol=1e-10)


def test_update_maps_noisy_pose_onto_target_with_true_parameters():
    h_t, h_0, K = random_poses(16, 0), random_poses(16, 1), crop_K(16)
    v_xy, d_rot, v_z = true_update(h_t, h_0, K)
    assert torch.allclose(apply_update(h_t, v_xy, d_rot, v_z, K), h_0, atol=1e-5)


def test_loss_is_zero_for_the_true_update_and_positive_otherwise():
    h_t, h_0, K = random_poses(8, 2), random_poses(8, 3), crop_K(8)
    points = torch.randn(8, 200, 3) * 0.3
    raw = update_to_raw(*true_update(h_t, h_0, K), render_width=320)
    loss, parts = disentangled_loss(raw, h_t, h_0, K, points, 320)
    assert loss.item() < 1e-5
    for key in ("xy", "rot", "z"):
        wrong = raw.clone()
        wrong[:, {"xy": 0, "rot": 3, "z": 8}[key]] += 0.2
        _, bad_parts = disentangled_loss(wrong, h_t, h_0, K, points, 320)
        # Each part only sees its own prediction (Eq. 10 is disentangled).
        assert bad_parts[key].item() > 1e-3
        assert all(bad_parts[k].item() < 1e-5 for k in bad_parts if k != key)


def test_zero_output_is_identity_update():
    v_xy, d_rot, v_z = raw_to_update(torch.zeros(3, 9), 320)
    h_t, K = random_poses(3, 4), crop_K(3)
    assert torch.allclose(apply_update(h_t, v_xy, d_rot, v_z, K), h_t, atol=1e-6)


def test_denoiser_takes_ten_channels_and_depends_on_t():
    cfg = NetworkConfig(backbone="resnet18", render_size=(64, 48))
    net = build_denoiser(cfg)
    assert net.net.conv1.in_channels == 10
    torch.nn.init.normal_(net.net.fc.weight, std=0.1)
    net.eval()
    x = torch.rand(2, 3, 48, 64)
    surface = slab_surface((64, 48))
    out_a = net(x, x, torch.tensor([1, 1]), surface).raw
    out_b = net(x, x, torch.tensor([90, 90]), surface).raw
    assert out_a.shape == (2, 9)
    assert not torch.allclose(out_a, out_b)


def test_timestep_embedding_is_sinusoidal():
    emb = timestep_embedding(torch.tensor([0, 10]), 4)
    assert emb.shape == (2, 4)
    assert torch.allclose(emb[0], torch.tensor([0.0, 0.0, 1.0, 1.0]))


@pytest.mark.parametrize("design", DESIGNS)
def test_each_design_starts_as_identity_and_learns_from_the_render(design):
    torch.manual_seed(0)
    net = build_denoiser(NetworkConfig(backbone="resnet18", render_size=(64, 48), design=design))
    c = net.channels
    render = torch.rand(4, c, 48, 64, requires_grad=True)
    crop, t = torch.rand(4, c, 48, 64), torch.tensor([1, 5, 50, 90])
    h_t, h_0, K = random_poses(4, 5), random_poses(4, 6), crop_K(4)
    surface = slab_surface((64, 48), h_t, K)
    surface.keypoints_ref = torch.randn(4, 7, 3) * 0.3
    if design != "evidence-solve":  # that one starts as a PnP step toward the parser's keypoints (test_evidence.py)
        # A zero head: the identity update at init (Eq. 9 with v_xy = 0, dR = I, v_z = 1).
        assert torch.allclose(net(render, crop, t, surface).raw, torch.zeros(4, 9), atol=1e-6)
    optimizer = torch.optim.Adam(net.parameters(), lr=1e-3)
    raw = net(render, crop, t, surface).raw
    loss, _ = disentangled_loss(raw, h_t, h_0, K, torch.randn(4, 50, 3) * 0.3, 64)
    loss.backward()
    optimizer.step()
    net.eval()
    (grad,) = torch.autograd.grad(net(render, crop, t, surface).raw.square().sum(), render)
    assert grad.abs().sum() > 0  # the output depends on the render after one step


def test_configs_saved_before_the_design_field_load_as_concat():
    old = get_preset("cpu").to_dict()
    del old["network"]["design"]
    assert Config.from_dict(old).network.design == "concat"
    assert Config.from_dict(old) == get_preset("cpu")


def test_unknown_design_is_refused():
    with pytest.raises(ValueError, match="design"):
        build_denoiser(NetworkConfig(backbone="resnet18", design="nope"))


@pytest.mark.parametrize("design", ["concat-grid", "cost-volume", "flow-solve"])
def test_grid_designs_give_nine_outputs_at_any_render_size(design):
    for size in ((64, 48), (128, 96), (320, 240)):
        net = build_denoiser(NetworkConfig(backbone="resnet18", render_size=size, design=design)).eval()
        w, h = size
        render, crop = torch.rand(2, 3, h, w), torch.rand(2, 3, h, w)
        assert net(render, crop, torch.tensor([3, 70]), slab_surface(size)).raw.shape == (2, 9)


@pytest.mark.parametrize("design", DESIGNS)
def test_every_design_round_trips_through_a_checkpoint(design, tmp_path):
    from monose3.training.checkpoints import load_model, save_checkpoint

    config = with_section(get_preset("cpu"), "network", render_size=(64, 48), design=design)
    torch.manual_seed(1)
    net = build_denoiser(config.network)
    with torch.no_grad():  # non-zero weights everywhere, so the comparison below means something
        for p in net.parameters():
            p.add_(torch.randn_like(p) * 0.01)
    net.eval()
    c = net.channels
    render, crop, t = torch.rand(2, c, 48, 64), torch.rand(2, c, 48, 64), torch.tensor([4, 60])
    surface = slab_surface((64, 48))
    surface.keypoints_ref = torch.randn(2, 7, 3) * 0.3
    save_checkpoint(tmp_path / "m.pt", {"model": net.state_dict(), "config": config.to_dict(), "step": 1})
    loaded, loaded_config = load_model(tmp_path / "m.pt")
    assert loaded_config.network.design == design
    with torch.no_grad():
        out, expected = loaded(render, crop, t, surface).raw, net(render, crop, t, surface).raw
        assert torch.allclose(out, expected, atol=1e-5) and not torch.allclose(out, torch.zeros_like(out))


def test_the_so3_output_starts_as_identity_round_trips_and_means_its_rotation(tmp_path):
    from monose3.method.denoiser import so3_raw
    from monose3.training.checkpoints import load_model, save_checkpoint

    config = with_section(
        get_preset("cpu"), "network", render_size=(64, 48), design="concat-grid", rotation_output="so3"
    )
    net = build_denoiser(config.network).eval()
    render, crop, t = torch.rand(2, 3, 48, 64), torch.rand(2, 3, 48, 64), torch.tensor([4, 60])
    surface = slab_surface((64, 48))
    with torch.no_grad():
        assert torch.allclose(net(render, crop, t, surface).raw, torch.zeros(2, 9), atol=1e-6)
        for p in net.parameters():
            p.add_(torch.randn_like(p) * 0.01)
    save_checkpoint(tmp_path / "m.pt", {"model": net.state_dict(), "config": config.to_dict(), "step": 1})
    loaded, saved = load_model(tmp_path / "m.pt")
    assert saved.network.rotation_output == "so3"
    with torch.no_grad():
        assert torch.allclose(loaded(render, crop, t, surface).raw, net(render, crop, t, surface).raw, atol=1e-6)
    raw = torch.zeros(2, 9)
    raw[:, 2:5] = torch.tensor([[0.0, 0.0, 0.3], [0.2, -0.1, 0.05]])
    _, d_rot, _ = raw_to_update(so3_raw(raw), 64)
    assert torch.allclose(d_rot[0], euler_xyz_to_matrix(torch.tensor([[0.0, 0.0, 0.3]]))[0], atol=1e-6)
    assert torch.allclose(d_rot @ d_rot.transpose(1, 2), torch.eye(3).expand(2, 3, 3), atol=1e-6)


def test_cost_volume_peaks_at_the_displacement_between_its_inputs():
    torch.manual_seed(2)
    a = torch.randn(2, 16, 10, 12)
    b = torch.roll(a, shifts=(1, -2), dims=(2, 3))  # b(x + d) = a(x) for d = (dy, dx) = (1, -2)
    cost = local_correlation(a, b, radius=3)
    assert cost.shape == (2, 49, 10, 12)
    inner = cost[:, :, 3:-3, 3:-3].mean(dim=(0, 2, 3))  # away from the zero padding
    dy, dx = divmod(int(inner.argmax()), 7)
    assert (dy - 3, dx - 3) == (1, -2)
    assert torch.allclose(inner.max(), torch.tensor(1.0), atol=1e-5)  # normalised features: cosine 1


def test_only_the_field_designs_return_a_field():
    render, crop, t = torch.rand(2, 3, 48, 64), torch.rand(2, 3, 48, 64), torch.tensor([3, 40])
    surface = slab_surface((64, 48))
    assert set(FIELD_DESIGNS) == {"cost-volume", "flow-solve", "evidence-solve"}
    out = build_denoiser(NetworkConfig(backbone="resnet18", render_size=(64, 48), design="cost-volume"))(
        render, crop, t, surface
    )
    assert out.raw.shape == (2, 9) and out.field.shape == (2, 2, 3, 4)
    net = build_denoiser(NetworkConfig(backbone="resnet18", render_size=(64, 48), design="flow-solve"))
    out = net(render, crop, t, surface)
    assert torch.allclose(out.raw, torch.zeros(2, 9), atol=1e-6) and out.field.shape == (2, 3, 6, 8)  # identity
    net = build_denoiser(NetworkConfig(backbone="resnet18", render_size=(64, 48), design="flow-solve", field_stride=4))
    out = net(render, crop, t, surface)
    assert torch.allclose(out.raw, torch.zeros(2, 9), atol=1e-6) and out.field.shape == (2, 3, 12, 16)
    assert (
        build_denoiser(NetworkConfig(backbone="resnet18", render_size=(64, 48)))(render, crop, t, surface).field is None
    )
    with pytest.raises(ValueError, match="field_stride must be one of"):
        build_denoiser(NetworkConfig(backbone="resnet18", design="flow-solve", field_stride=2))
    with pytest.raises(ValueError, match="rotation_output='6d'"):
        build_denoiser(NetworkConfig(backbone="resnet18", design="flow-solve", rotation_output="so3"))


def test_the_registry_builds_every_configured_design_and_only_those():
    assert tuple(DESIGN_CLASSES) == DESIGNS
    for design in DESIGNS:
        net = build_denoiser(NetworkConfig(backbone="resnet18", render_size=(64, 48), design=design))
        assert isinstance(net, Denoiser) and type(net) is DESIGN_CLASSES[design]


def test_flow_solve_runs_on_the_pretrained_trunk_and_starts_from_imagenet_weights():
    from monose3.networks.backbone import pretrained_lite0

    config = NetworkConfig(backbone="efficientnet-lite0", render_size=(64, 48), design="flow-solve")
    net = build_denoiser(config).eval()
    imagenet = pretrained_lite0().state_dict()
    assert torch.equal(net.net.fine[0][0].conv.weight, imagenet["_conv_stem.weight"])
    render, crop, t = torch.rand(2, 3, 48, 64), torch.rand(2, 3, 48, 64), torch.tensor([3, 40])
    out = net(render, crop, t, slab_surface((64, 48)))
    assert torch.allclose(out.raw, torch.zeros(2, 9), atol=1e-6) and out.field.shape == (2, 3, 6, 8)
    with pytest.raises(ValueError, match="unknown backbone"):
        build_denoiser(NetworkConfig(backbone="efficientnet-lite0", render_size=(64, 48)))


def test_a_field_with_a_scale_channel_is_judged_by_the_laplace_likelihood():
    from monose3.method.loss import flow_errors, flow_loss

    target, mask = torch.full((1, 2, 3, 4), 0.05), torch.ones(1, 1, 3, 4, dtype=torch.bool)
    mask[..., 0] = False  # cells without robot do not count
    field = torch.zeros(1, 3, 3, 4)
    assert flow_loss(field[:, :2], target, mask) == pytest.approx(0.05)  # two channels: L1
    losses = []
    for scale in (0.01, 0.05, 0.2):
        field[:, 2] = math.log(scale)
        losses.append(flow_loss(field, target, mask).item())
        assert losses[-1] == pytest.approx(0.05 / scale + math.log(scale), rel=1e-5)
    assert losses[1] < min(losses[0], losses[2])  # the likelihood is best where the scale is the error
    assert torch.allclose(flow_errors(field, target, mask), torch.tensor([0.05]))  # judged on the field alone


def test_timestep_of_inverts_the_embedding():
    from monose3.method.denoiser import timestep_of

    t = torch.tensor([1, 5, 10, 50, 99, 100])
    for dim in (4, 8):
        assert torch.allclose(timestep_of(timestep_embedding(t, dim)), t.float(), atol=1e-3)
