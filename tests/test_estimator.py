"""Inference: RoboPose's initialisation, the reverse process, batching and tracking."""

import numpy as np
import pytest
import torch
from conftest import TINY_NET, project_np

from monose3.errors import Monose3Error
from monose3.estimator import PoseEstimator
from monose3.geometry.rotations import rotation_angle
from monose3.method.config import get_preset
from monose3.method.designs import build_denoiser
from monose3.method.reverse import INIT_BOX_FRACTION


def make_estimator(fc_weight=None, seed: int = 0) -> PoseEstimator:
    """A tiny random model of its own; ``fc_weight(weight)`` re-initialises the last layer's weight
    in place (zeros: every update is the identity)."""
    torch.manual_seed(seed)
    config = get_preset("cpu", network=TINY_NET)
    model = build_denoiser(config.network)
    if fc_weight is not None:
        with torch.no_grad():
            fc_weight(model.net.fc.weight)
    return PoseEstimator(model, config)


def _unchanged(est: PoseEstimator):
    """Yield ``est``, then check that no test changed its weights (module fixtures are shared)."""
    before = {k: v.clone() for k, v in est.model.state_dict().items()}
    yield est
    est.close()
    after = est.model.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before), "a test changed a shared estimator's weights"


@pytest.fixture(scope="module")
def estimator():
    """The tiny model as initialised (seed 0); never modified."""
    yield from _unchanged(make_estimator())


@pytest.fixture(scope="module")
def zero_estimator():
    """The tiny model with a zero last layer: the network predicts H_0 = H_t; never modified."""
    yield from _unchanged(make_estimator(torch.nn.init.zeros_))


def _inputs(frames, n):
    return (
        [f.load_image() for f in frames[:n]],
        np.stack([f.K for f in frames[:n]]),
        np.stack([f.joints for f in frames[:n]]),
    )


def test_initialisation_fits_the_central_box(estimator, frames):
    images, Ks, joints = _inputs(frames, 2)
    batch = estimator.reverse.prepare(images, Ks, joints, 1)
    pose = estimator.reverse.initial_poses(batch)
    pts = batch.points_ref @ pose[:, :3, :3].transpose(1, 2) + pose[:, None, :3, 3]
    uv = (
        pts[..., :2] / pts[..., 2:] * torch.stack([batch.K[:, 0, 0], batch.K[:, 1, 1]], 1)[:, None]
        + batch.K[:, None, :2, 2]
    )
    extent = (uv.amax(1) - uv.amin(1)) / batch.size
    # The larger side of the robot's image spans about 3/5 of the image (perspective enlarges
    # the near side a little) and the robot sits in the middle of the image.
    assert ((extent.amax(1) > INIT_BOX_FRACTION - 0.05) & (extent.amax(1) < INIT_BOX_FRACTION + 0.12)).all()
    middle = (uv.amax(1) + uv.amin(1)) / 2 / batch.size
    assert torch.allclose(middle, torch.full_like(middle, 0.5), atol=0.12)


def test_zero_network_keeps_the_pose_and_directreg_equals_history(zero_estimator, frames):
    images, Ks, joints = _inputs(frames, 2)
    est = zero_estimator.estimate(images, Ks, joints, sampler="directreg", ddim_steps=1, direct_steps=1)
    # The identity update leaves the initial pose in place at every step.
    assert np.allclose(est.history[0], est.history[-1], atol=1e-9)
    assert len(est.history) == 3 and est.poses.shape == (2, 4, 4)


def test_revdiff_ddim_pulls_towards_the_prediction(zero_estimator, frames):
    """With a network predicting H_0 = H_t (identity), the last DDIM step (to t = 0) returns the
    prediction; earlier steps move the pose through the schedule; with eta's noise term and
    perturbed starts the chains differ."""
    images, Ks, joints = _inputs(frames, 1)
    det = zero_estimator.estimate(images, Ks, joints, ddim_steps=3, direct_steps=0)
    assert np.allclose(det.history[-2], det.history[-1], atol=1e-6)
    assert not np.allclose(det.history[0], det.history[1], atol=1e-4)
    sto = zero_estimator.estimate(images, Ks, joints, ddim_steps=3, direct_steps=0, hypotheses=3, stochastic=True)
    assert sto.hypotheses.shape == (1, 3, 4, 4) and sto.spread_mm[0] > 1.0


def _small_normal(weight: torch.Tensor) -> None:
    torch.manual_seed(1)
    torch.nn.init.normal_(weight, std=1e-3)


def test_batched_estimate_equals_one_by_one(frames):
    estimator = make_estimator(_small_normal)  # its own: a network that moves the pose a little
    images, Ks, joints = _inputs(frames, 3)
    try:
        both = estimator.estimate(images, Ks, joints, ddim_steps=2, direct_steps=1)
        single = [
            estimator.estimate(images[i : i + 1], Ks[i : i + 1], joints[i : i + 1], ddim_steps=2, direct_steps=1)
            for i in range(3)
        ]
    finally:
        estimator.close()
    assert not np.allclose(both.poses, both.history[0][:, 0], atol=1e-4)  # the network did move it
    assert np.allclose(both.poses, np.concatenate([s.poses for s in single]), atol=1e-4)
    assert set(both.timings) >= {"render", "crop", "network", "update", "total"}


def test_tracking_is_one_network_step_from_the_previous_pose(zero_estimator, frames):
    images, Ks, joints = _inputs(frames, 1)
    prev = np.stack([frames[0].pose])
    est = zero_estimator.track(images, Ks, joints, prev)
    assert len(est.history) == 2
    assert np.allclose(est.poses, prev, atol=1e-6) and est.in_view.all()


def test_estimate_out_of_the_image_is_flagged(zero_estimator, frames):
    images, Ks, joints = _inputs(frames, 1)
    far = frames[0].pose.copy()
    far[0, 3] += 50.0  # 50 m to the side
    # the premise, checked independently: every keypoint projects far right of the image
    uv = project_np(zero_estimator.robot.keypoints(joints)[0], far, Ks[0])
    assert (uv[:, 0] > 10 * images[0].shape[1]).all(), uv
    est = zero_estimator.track(images, Ks, joints, far[None])
    assert not est.in_view[0]
    assert np.allclose(est.poses, far[None], atol=1e-6)  # flagged, not moved (the identity network)
    # and the flag is the pose's doing: the same call from the true pose is in view
    assert zero_estimator.track(images, Ks, joints, frames[0].pose[None]).in_view[0]


@pytest.mark.parametrize("sampler", ["revdiff", "fit"])
def test_tracking_refuses_previous_poses_it_cannot_start_from(zero_estimator, frames, sampler):
    """Checked before any work, on either sampler (a NaN pose reached the renderer before)."""
    images, Ks, joints = _inputs(frames, 1)
    bent = frames[0].pose.copy()
    bent[:3, :3] *= 2.0
    cases = [(np.full((1, 4, 4), np.nan), "previous pose 0: the pose contains NaN"),
             (bent[None], "previous pose 0: the pose is not a rigid transform"),
             (frames[0].pose, r"previous pose must be \[1, 4, 4\]")]  # fmt: skip
    for previous, needle in cases:
        with pytest.raises(Monose3Error, match=needle):
            zero_estimator.track(images, Ks, joints, previous, sampler=sampler)


def test_chains_from_a_low_start_spread_less(zero_estimator, frames):
    """Chains refining a prior from a small t start as close together as that t's noise allows."""
    images, Ks, joints = _inputs(frames, 1)
    prior = np.stack([frames[0].pose])

    def start_spread(start_t):
        kw = {"hypotheses": 8, "stochastic": True, "init_poses": prior, "start_t": start_t}
        est = zero_estimator.estimate(images, Ks, joints, ddim_steps=1, direct_steps=0, **kw)
        return np.degrees(rotation_angle(est.history[0][0, :, :3, :3], prior[0, :3, :3])).mean()

    low, high = start_spread(10), start_spread(None)
    assert 0 < low < 0.2 * high


@pytest.mark.parametrize(
    ("sampler", "steps", "needle"),
    [
        ("revdiff", (0, 5), "ddim_steps >= 1"),
        ("directreg", (0, 0), "at least one step"),
        ("revdiff", (2, -1), "negative"),
        ("fancy", (1, 1), "unknown sampler"),
    ],
)
def test_step_counts_the_reverse_process_cannot_run_are_refused(zero_estimator, frames, sampler, steps, needle):
    images, Ks, joints = _inputs(frames, 1)
    with pytest.raises(Monose3Error, match=needle):
        zero_estimator.estimate(images, Ks, joints, sampler=sampler, ddim_steps=steps[0], direct_steps=steps[1])
