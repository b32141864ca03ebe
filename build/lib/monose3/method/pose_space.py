"""The pose space of the diffusion (Sec. III-B): the robot's centroid frame and the monocular
normalisation of Eq. 4 and its inverse (Eq. 6-7), batched over the leading dimension.

The diffusion works on the pose of the robot's *centroid frame* (origin at the centre of the
posed robot's bounding box, base-frame orientation), so rotating a pose does not move the
robot in the image.
"""

from __future__ import annotations

import torch

from monose3.geometry.poses import make_pose
from monose3.geometry.rotations import matrix_to_rotation_6d, rotation_6d_to_matrix

# The nearest a diffused or denoised pose may come to the camera, metres (the camera-frame depth
# tz of the centroid frame). One floor for the forward process (VisDiff and FixPer) and for the
# reverse step: 0.1 m, the forward process's floor since training began, so the denoiser is
# never asked at inference about a depth it was never trained on (the estimator's reverse step
# used 0.05 m before; no real camera sits 5-10 cm from a robot's centroid, and the demo's poses
# never come near either floor). A sample behind or onto the camera cannot be rendered.
MIN_DEPTH = 0.1


def centroid_frame(pose: torch.Tensor, centroid: torch.Tensor) -> torch.Tensor:
    """Camera-from-centroid pose from camera-from-base ``[B, 4, 4]`` and base-frame centroids ``[B, 3]``."""
    out = pose.clone()
    out[:, :3, 3] = pose[:, :3, 3] + (pose[:, :3, :3] @ centroid[:, :, None])[..., 0]
    return out


def base_frame(pose_ref: torch.Tensor, centroid: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`centroid_frame`: camera-from-base from camera-from-centroid."""
    out = pose_ref.clone()
    out[:, :3, 3] = pose_ref[:, :3, 3] - (pose_ref[:, :3, :3] @ centroid[:, :, None])[..., 0]
    return out


def normalize_pose(pose: torch.Tensor, K: torch.Tensor, image_size: torch.Tensor, c_z: float) -> torch.Tensor:
    """Monocular normalisation, Eq. 4: ``[B, 4, 4]`` to ``[B, 9]`` = (r1, r2, f tx/(w tz), f ty/(h tz), tz - c_z).

    r1, r2 are the first two columns of R; fx is used for x and fy for y; ``image_size`` is
    ``[B, 2]`` (w, h) of the image that K belongs to.
    """
    t = pose[:, :3, 3]
    tz = t[:, 2]
    x = K[:, 0, 0] * t[:, 0] / (image_size[:, 0] * tz)
    y = K[:, 1, 1] * t[:, 1] / (image_size[:, 1] * tz)
    return torch.cat([matrix_to_rotation_6d(pose[:, :3, :3]), torch.stack([x, y, tz - c_z], dim=1)], dim=1)


def denormalize_pose(x: torch.Tensor, K: torch.Tensor, image_size: torch.Tensor, c_z: float) -> torch.Tensor:
    """Inverse normalisation, Eq. 6-7: ``[B, 9]`` to ``[B, 4, 4]``.

    Rotation by Gram-Schmidt on (r1, r2) (Eq. 6); tz = z + c_z, tx = w tz x / f, ty = h tz y / f (Eq. 7).
    """
    rot = rotation_6d_to_matrix(x[:, :6])
    tz = x[:, 8] + c_z
    tx = image_size[:, 0] * tz * x[:, 6] / K[:, 0, 0]
    ty = image_size[:, 1] * tz * x[:, 7] / K[:, 1, 1]
    return make_pose(rot, torch.stack([tx, ty, tz], dim=1))


def floor_depth(x: torch.Tensor, c_z: float) -> torch.Tensor:
    """Clamp the depth of normalised poses ``[B, 9]`` (Eq. 4's z = tz - c_z) to :data:`MIN_DEPTH`.

    In place; returns ``x``."""
    x[:, 8] = x[:, 8].clamp_min(MIN_DEPTH - c_z)
    return x
