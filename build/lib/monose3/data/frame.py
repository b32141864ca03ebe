"""The one Frame type: an image with its joints and intrinsics, and ground truth when known.

Every reader returns it: plain folders and videos (:mod:`monose3.data.frames`), DREAM
(:mod:`monose3.data.dream`) and RoboKeyGen (:mod:`monose3.data.robokeygen`), so evaluate,
calibrate and track see the same thing. Torch-free.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from monose3.data.inputs import load_image
from monose3.data.validation import check_image
from monose3.errors import Monose3Error


@dataclass
class Frame:
    """One frame in the project's conventions (meters, OpenCV camera axes).

    The image is a file (``image_path``, read on demand: datasets never hold images) or an
    array already in memory (``image``, e.g. a video frame). ``joints`` follow
    ``RobotModel.joint_names``; ``K`` and ``image_size`` (width, height) are the intrinsics.

    Ground truth, when the source has it (DREAM, RoboKeyGen): ``pose`` is camera-from-base;
    ``keypoints_3d`` / ``keypoints_2d`` are camera-frame points and pixels of
    ``keypoint_names``; ``pose_residual`` is the RMS error (m) of the rigid fit that produced
    the pose for real frames, 0.0 when the pose was stored.
    """

    name: str
    K: np.ndarray
    image_size: tuple[int, int]
    joints: np.ndarray
    image_path: Path | None = None
    image: np.ndarray | None = None
    pose: np.ndarray | None = None
    keypoints_3d: np.ndarray | None = None
    keypoints_2d: np.ndarray | None = None
    keypoint_names: list[str] | None = None
    pose_residual: float = 0.0

    def load_image(self) -> np.ndarray:
        """The image as RGB uint8 ``[H, W, 3]``; refused when its size is not ``image_size``."""
        if self.image is None and self.image_path is None:
            raise Monose3Error(f"frame {self.name} has neither an image nor an image path")
        img = self.image if self.image is not None else load_image(self.image_path)
        where = self.image_path.name if self.image_path is not None else f"frame {self.name}"
        h, w = img.shape[:2]
        if (w, h) != tuple(self.image_size):
            raise Monose3Error(
                f"{where} is {w}x{h} but the camera intrinsics are for {self.image_size[0]}x{self.image_size[1]}; "
                "give intrinsics calibrated at the images' resolution"
            )
        return check_image(img, where, content=False)
