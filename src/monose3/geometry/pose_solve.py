"""The pose that moves 3D points onto target pixels: damped Gauss-Newton on reprojections.

One solve for both pipelines: the ``flow-solve`` denoiser solves H_0 from its displacement
field (``method.flow_pose.pose_from_field``), and the geometric fit refines its hypotheses on
silhouette, edge and keypoint correspondences (``perception.fitting``). Batched, differentiable,
float32 or float64; poses are ``[B, 4, 4]``, pixels in OpenCV's convention (pixel u's centre at u).
"""

from __future__ import annotations

import torch

from monose3.geometry.camera import project, projection_jacobian
from monose3.geometry.poses import make_pose
from monose3.geometry.rotations import rotvec_to_matrix

SOLVE_ITERATIONS = 3  # damped Gauss-Newton steps from H_t (the update is small after the first)
SOLVE_DAMPING = 1e-2  # Marquardt damping: lambda * diag(J^T W J), so no direction is ever unbounded
MAX_STEP = 0.5  # largest Gauss-Newton step per coordinate: radians, and units of depth
MIN_SOLVE_DEPTH = 0.05  # metres; points are projected as if at least this far while solving


def reprojection_jacobian(cam_points: torch.Tensor, rotated: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """d(pixel)/d(omega, delta) ``[B, N, 2, 6]`` of points X = R P + t under the left update
    R <- exp(omega) R, t <- t + delta (rotation about the frame's origin, camera axes).

    ``cam_points``: X ``[B, N, 3]``; ``rotated``: R P ``[B, N, 3]``; K ``[B, 3, 3]``. Each row p of
    d(pixel)/dX gives the row -p [R P]_x = (R P) x p for omega: a cross product, not a 2x3 @ 3x6
    product per point (many small matrix products are slow on the CPU)."""
    d_point = projection_jacobian(cam_points, K)
    d_omega = torch.linalg.cross(rotated[..., None, :].expand_as(d_point), d_point, dim=-1)
    return torch.cat([d_omega, d_point], -1)


def solve_pose(
    pose: torch.Tensor,
    K: torch.Tensor,
    points: torch.Tensor,
    target_uv: torch.Tensor,
    weights: torch.Tensor,
    prior: torch.Tensor | None = None,
    iterations: int = SOLVE_ITERATIONS,
    damping: float = SOLVE_DAMPING,
) -> torch.Tensor:
    """The pose ``[B, 4, 4]`` that moves ``points`` ``[B, N, 3]`` (in ``pose``'s frame) to pixels
    ``target_uv`` ``[B, N, 2]`` under K ``[B, 3, 3]``: weighted least squares over pixel
    residuals (``weights`` ``[B, N]``, >= 0), damped Gauss-Newton from ``pose``. Points with
    zero weight, or a sample with none, leave it where it is. Differentiable.

    ``prior`` ``[B, 6]`` (>= 0, optional): precisions of a zero-mean Gaussian on the update from
    ``pose`` (rotation vector in radians, translation in units of ``pose``'s depth), so the
    solution is the MAP pose: a field the solve cannot trust as a whole moves the pose less."""
    scale = torch.cat([torch.ones_like(pose[:, :3, 3]), pose[:, 2:3, 3].abs().expand(-1, 3)], 1)
    total = torch.zeros_like(scale)  # the update so far, in the prior's units
    batch = len(pose)
    # The normal equations over all 2N pixel rows at once (one matrix product per sample).
    row_weights = weights[..., None].expand(*weights.shape, 2).reshape(batch, 1, -1)
    for _ in range(iterations):
        rotated = points @ pose[:, :3, :3].transpose(1, 2)
        cam = rotated + pose[:, None, :3, 3]
        cam = torch.cat([cam[..., :2], cam[..., 2:].clamp_min(MIN_SOLVE_DEPTH)], -1)
        residual = (target_uv - project(cam, K)).reshape(batch, -1, 1)
        jac = (reprojection_jacobian(cam, rotated, K) * scale[:, None, None]).reshape(batch, -1, 6)
        weighted = jac.transpose(1, 2) * row_weights
        normal = weighted @ jac
        rhs = (weighted @ residual)[..., 0]
        diag = torch.diagonal(normal, dim1=-2, dim2=-1)
        if prior is not None:
            normal = normal + torch.diag_embed(prior)
            rhs = rhs - prior * total
        normal = normal + torch.diag_embed(damping * diag + 1e-9)
        step = torch.linalg.solve(normal, rhs[..., None])[..., 0]
        # A trust region: far from the solution (large t) Gauss-Newton can overshoot, most of all in depth.
        step = step * (MAX_STEP / step.abs().amax(1, keepdim=True).clamp_min(MAX_STEP))
        total = total + step
        step = step * scale
        pose = make_pose(rotvec_to_matrix(step[:, :3]) @ pose[:, :3, :3], pose[:, :3, 3] + step[:, 3:])
    return pose
