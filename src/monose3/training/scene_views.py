"""The parser's training views of the user's own frames, labelled by poses instead of by hand.

A frame with a pose it is known to be seen at (a reliable fit, or a static camera's fused
pose) labels itself: the robot rendered at that pose and the frame's joints gives its mask,
and the keypoints project to their pixels. The views are the ones the parser is shown at test
time (:func:`monose3.perception.views.parse_image`): the whole image padded to the parser's
aspect, the zoomed box around the robot and the wider boxes whose masks give it context, each
zoomed box jittered in scale and position so that the parser does not learn one framing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torchvision.ops import roi_align

from monose3.geometry.camera import crop_intrinsics, project
from monose3.perception.parser import OUTPUT_STRIDE
from monose3.perception.views import CONTEXT_SCALES, box_around, full_box, grown_box, image_tensor
from monose3.robot import RobotModel
from monose3.robot.renderer import RobotRenderer
from monose3.training.parser_loop import ParserBatch

ZOOM_JITTER_SCALE = (0.85, 1.2)  # a zoomed view's size, relative to the box around the robot
ZOOM_JITTER_SHIFT = 0.1  # and its centre's shift, as a share of its size


@dataclass
class LabelledFrame:
    """One frame and the pose that labels it (camera-from-base, meters)."""

    image: np.ndarray  # [H, W, 3] uint8 RGB
    K: np.ndarray  # [3, 3]
    joints: np.ndarray  # [J]
    pose: np.ndarray  # [4, 4]


class SceneViews:
    """Batches of pseudo-labelled parser views (:class:`~monose3.training.parser_loop.ParserBatch`)
    of ``frames``: a third whole images, the rest zoomed boxes (some widened by the parser's
    context scales), each at the parser's ``input_size``."""

    def __init__(self, frames: list[LabelledFrame], robot: RobotModel, renderer: RobotRenderer,
                 input_size: tuple[int, int], seed: int = 0):  # fmt: skip
        if not frames:
            raise ValueError("no labelled frames")
        self.frames, self.robot, self.renderer, self.size = frames, robot, renderer, input_size
        self.rng = np.random.default_rng(seed)
        self.images = [image_tensor(f.image) for f in frames]
        self.robot_boxes = [self._robot_box(f) for f in frames]

    def _robot_box(self, frame: LabelledFrame) -> np.ndarray:
        """The image box around the robot's rendered silhouette, grown as the zoomed view grows it."""
        h, w = frame.image.shape[:2]
        mask = self.renderer.silhouettes(frame.joints[None], frame.pose[None], frame.K[None], (w, h))[0].cpu().numpy()
        ys, xs = np.nonzero(mask)
        if len(xs) == 0:  # the pose puts the robot out of view: the whole image only
            return full_box((w, h), self.size[0] / self.size[1])
        return box_around(np.array([xs.min(), ys.min()], float), np.array([xs.max() + 1, ys.max() + 1], float),
                          self.size[0] / self.size[1])  # fmt: skip

    def view_box(self, i: int) -> np.ndarray:
        """A random view of frame ``i``: whole, zoomed, or zoomed with context, the zoom jittered."""
        kind = self.rng.integers(3 + len(CONTEXT_SCALES))
        h, w = self.frames[i].image.shape[:2]
        if kind < 2:
            return full_box((w, h), self.size[0] / self.size[1])
        box = grown_box(self.robot_boxes[i], float(self.rng.uniform(*ZOOM_JITTER_SCALE)))
        box = box + np.tile(self.rng.uniform(-ZOOM_JITTER_SHIFT, ZOOM_JITTER_SHIFT, 2) * (box[2:] - box[:2]), 2)
        return box if kind == 2 else grown_box(box, CONTEXT_SCALES[kind - 3])

    def batch(self, n: int, device: torch.device) -> ParserBatch:
        """``n`` views of randomly drawn frames, with their rendered masks and projected keypoints."""
        picks = self.rng.integers(len(self.frames), size=n)
        boxes = np.stack([self.view_box(i) for i in picks])
        w, h = self.size
        views = [
            roi_align(self.images[i], torch.tensor([[0.0, *box]], dtype=torch.float32), (h, w), 1.0, 0, True)
            for i, box in zip(picks, boxes, strict=True)
        ]
        Ks = np.stack([self.frames[i].K for i in picks])
        K_views = crop_intrinsics(torch.from_numpy(Ks), torch.from_numpy(boxes), self.size).numpy()
        joints = np.stack([self.frames[i].joints for i in picks])
        poses = np.stack([self.frames[i].pose for i in picks])
        mask = self.renderer.silhouettes(joints, poses, K_views, self.size).float()[:, None]
        uv = project(self.robot.keypoints(joints, poses), K_views)
        return ParserBatch(
            torch.cat(views).to(device),
            F.avg_pool2d(mask, OUTPUT_STRIDE).to(device),
            torch.as_tensor(uv, dtype=torch.float32, device=device),
        )
