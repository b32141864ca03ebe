"""The parser's views of an image: the whole image padded to the parser's aspect, then a
zoomed box around the robot the first view found, each resized to the parser's input."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torchvision.ops import roi_align

from monose3.geometry.camera import crop_intrinsics, scale_K
from monose3.perception.parser import RobotParser, decode_keypoints

MASK_THRESHOLD = 0.5
MIN_MASK_FRACTION = 2e-4  # of the view's pixels: fewer robot pixels than this is "no robot"
ZOOM_MARGIN = 1.3  # the zoomed view spans the mask's box grown by this factor
ZOOM_MAX_FRACTION = 0.7  # zoom only when the mask's box is smaller than this fraction of the view
# The zoomed view's mask is the mean of its own and those of boxes this much wider about the
# same centre, resampled onto it: the parser learnt on whole images and masks a robot better
# with the scene around it, while the geometry keeps the zoomed view's resolution (held-out
# hard frames: mean mask IoU 0.814 -> 0.844, benchmarks/parser_masks.py; AUC 69.45 -> 73.56,
# benchmarks/accuracy.py; reallike 0.948 -> 0.942 and 96.93 -> 96.97).
CONTEXT_SCALES = (1.5, 2.0)

Region = tuple[int, int, int, int]  # x0, y0, x1, y1: a view's pixels [y0:y1, x0:x1]


@dataclass
class ViewEvidence:
    """What the parser sees in one view (a box of the image resized to the parser's input)."""

    mask: torch.Tensor  # [h, w] robot probability at the view's resolution
    keypoints: np.ndarray  # [K, 2] view pixels
    confidence: np.ndarray  # [K]
    K: np.ndarray  # [3, 3] the view's intrinsics
    box: np.ndarray  # [4] x1, y1, x2, y2 in the image (edge coordinates)
    image: np.ndarray | None = None  # [h, w, 3] float32 in [0, 1]: the view's pixels (None: no edge terms)
    image_size: tuple[int, int] | None = None  # (W, H) of the image the view was cut from (None: it fills the view)

    @property
    def size(self) -> tuple[int, int]:
        return int(self.mask.shape[1]), int(self.mask.shape[0])

    @property
    def valid(self) -> Region:
        """:meth:`valid_region` at the view's own size."""
        return self.valid_region(self.size)

    def valid_region(self, size: tuple[int, int]) -> Region:
        """The pixels ``[y0:y1, x0:x1]`` (returned as x0, y0, x1, y1) of the view, brought to
        ``size`` (w, h), that lie wholly inside the image: beyond it the view is padding, where
        the parser cannot see the robot, so the silhouette and the edges are compared inside only."""
        w, h = size
        if self.image_size is None:
            return 0, 0, w, h
        scale = np.array([w, h]) / (self.box[2:] - self.box[:2])
        lo = np.clip(np.ceil(-self.box[:2] * scale - 1e-6), 0, [w, h]).astype(int)
        hi = np.clip(np.floor((np.array(self.image_size) - self.box[:2]) * scale + 1e-6), lo, [w, h]).astype(int)
        return int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])

    @property
    def robot_fraction(self) -> float:
        return float((self.mask > MASK_THRESHOLD).float().mean())


def image_tensor(image: np.ndarray) -> torch.Tensor:
    """``[H, W, 3]`` uint8 to ``[1, 3, H, W]`` float in [0, 1]."""
    return torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None].float().div_(255.0)


@torch.no_grad()
def parse_view(parser: RobotParser, image: torch.Tensor, K: np.ndarray, box: np.ndarray,
               mirror: bool = True, context: tuple[float, ...] = ()) -> ViewEvidence:  # fmt: skip
    """Run the parser on ``box`` (edge coordinates; beyond the image is black, as padding) of
    ``image`` ``[1, 3, H, W]``, resized to the parser's input with anti-aliasing. With
    ``mirror``, the mask is the mean of the view's and its mirror image's (flipped back; of the
    logits); with ``context``, the mean probability of that and the same of the boxes that many
    times wider (:data:`CONTEXT_SCALES`), resampled onto the view."""
    size = parser.config.input_size
    view, mask_logits, kp_logits = parse_box(parser, image, box, mirror)
    mask = F.interpolate(mask_logits.float(), size=(size[1], size[0]), mode="bilinear", align_corners=False)
    masks = [mask]
    for wide in (grown_box(box, scale) for scale in context):
        masks.append(logits_within(parse_box(parser, image, wide, mirror)[1], wide, box, size))
    mask = torch.stack(masks).sigmoid().mean(0)  # all float32: logits_within's are too
    uv, conf = decode_keypoints(kp_logits.float())
    K_view = crop_intrinsics(torch.from_numpy(K)[None], torch.from_numpy(box)[None].double(), size)[0].numpy()
    pixels = view[0].permute(1, 2, 0).numpy().astype(np.float32)
    image_size = (int(image.shape[-1]), int(image.shape[-2]))
    return ViewEvidence(mask[0, 0].cpu(), uv[0].cpu().double().numpy(), conf[0].cpu().numpy(),
                        K_view, np.asarray(box, np.float64), pixels, image_size)  # fmt: skip


def parse_box(parser: RobotParser, image: torch.Tensor, box: np.ndarray,
              mirror: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:  # fmt: skip
    """``box`` of ``image`` at the parser's input (``[1, 3, h, w]``), and the parser's mask and
    keypoint logits on it (with ``mirror``, the mask's mean with its mirror image's)."""
    size = parser.config.input_size
    device = next(parser.parameters()).device
    rois = torch.tensor([[0.0, *box]], dtype=torch.float32)
    view = roi_align(image, rois, (size[1], size[0]), 1.0, sampling_ratio=0, aligned=True)
    if not mirror:
        return view, *parser(view.to(device))
    # Test-time augmentation: the parser's errors on a view and on its mirror image are
    # partly independent, so their mean is a better mask (benchmarks/accuracy.py). Only the
    # mask: a robot's keypoints may come in left/right pairs that a mirror swaps.
    mask_logits, kp_logits = parser(torch.cat([view, view.flip(-1)]).to(device))
    return view, (mask_logits[:1] + mask_logits[1:].flip(-1)) / 2, kp_logits[:1]


def grown_box(box: np.ndarray, scale: float) -> np.ndarray:
    """``box`` (edge coordinates) ``scale`` times as wide and high about its centre."""
    centre, half = (box[:2] + box[2:]) / 2, (box[2:] - box[:2]) / 2 * scale
    return np.concatenate([centre - half, centre + half])


def logits_within(logits: torch.Tensor, logits_box: np.ndarray, box: np.ndarray, size: tuple[int, int]) -> torch.Tensor:
    """``logits`` ``[1, 1, h', w']`` over the image box ``logits_box``, resampled onto ``box``'s
    view grid of ``size`` (w, h) (``box`` inside ``logits_box``)."""
    h, w = logits.shape[-2:]
    per_px = (logits_box[2:] - logits_box[:2]) / np.array([w, h])
    roi = np.concatenate([(box[:2] - logits_box[:2]) / per_px, (box[2:] - logits_box[:2]) / per_px])
    rois = torch.tensor([[0.0, *roi]], dtype=torch.float32)
    return roi_align(logits.float(), rois.to(logits.device), (size[1], size[0]), 1.0, sampling_ratio=2, aligned=True)


def parse_image(parser: RobotParser, image: np.ndarray, K: np.ndarray) -> ViewEvidence:
    """The default pipeline's view of ``image`` (``[H, W, 3]`` uint8 RGB, intrinsics ``K``): the
    whole image parsed, then the box around the mask it found where the robot is small in it
    (:func:`zoom_box`), so a small robot is parsed at a useful resolution, its mask with the
    context of wider boxes (:data:`CONTEXT_SCALES`). The whole image's
    view where the parser finds no robot there (``robot_fraction`` below
    :data:`MIN_MASK_FRACTION`: the caller says so) or none in the zoomed box."""
    size = parser.config.input_size
    aspect = size[0] / size[1]
    tensor = image_tensor(image)
    view = parse_view(parser, tensor, K, full_box((image.shape[1], image.shape[0]), aspect))
    box = zoom_box(view, aspect) if view.robot_fraction >= MIN_MASK_FRACTION else None
    if box is None:
        return view
    zoomed = parse_view(parser, tensor, K, box, context=CONTEXT_SCALES)
    return zoomed if zoomed.robot_fraction >= MIN_MASK_FRACTION else view


def full_box(image_size: tuple[int, int], aspect: float) -> np.ndarray:
    """The whole image padded (right/bottom) to ``aspect`` (w/h), as the estimator standardises it."""
    w, h = image_size
    return np.array([0.0, 0.0, max(w, h * aspect), max(h, w / aspect)])


def zoom_box(view: ViewEvidence, aspect: float) -> np.ndarray | None:
    """The image box around the robot that ``view``'s mask shows, or None when the robot
    already fills the view."""
    ys, xs = np.nonzero((view.mask > MASK_THRESHOLD).numpy())
    w, h = view.size
    if (xs.max() + 1 - xs.min()) * ZOOM_MARGIN > ZOOM_MAX_FRACTION * w:
        return None
    scale = (view.box[2:] - view.box[:2]) / np.array([w, h])
    lo = view.box[:2] + np.array([xs.min(), ys.min()]) * scale
    hi = view.box[:2] + np.array([xs.max() + 1, ys.max() + 1]) * scale
    return box_around(lo, hi, aspect)


def box_around(lo: np.ndarray, hi: np.ndarray, aspect: float) -> np.ndarray:
    """The box (edge coordinates) centred on the box ``lo``-``hi``, grown by :data:`ZOOM_MARGIN` and to ``aspect``."""
    half = (hi - lo) / 2 * ZOOM_MARGIN
    half = np.maximum(half, [half[1] * aspect, half[0] / aspect])
    centre = (lo + hi) / 2
    return np.concatenate([centre - half, centre + half])


def resized_view(view: ViewEvidence, size: tuple[int, int]) -> ViewEvidence:
    """``view`` at another resolution (the refinement's coarse pass): mask, keypoints, K and pixels scaled."""
    mask = F.interpolate(view.mask[None, None], size=(size[1], size[0]), mode="bilinear", align_corners=False)
    scale = np.array(size, float) / np.array(view.size, float)
    keypoints = (view.keypoints + 0.5) * scale - 0.5
    image = None if view.image is None else cv2.resize(view.image, size, interpolation=cv2.INTER_AREA)
    K = scale_K(view.K, view.size, size)
    return ViewEvidence(mask[0, 0], keypoints, view.confidence, K, view.box, image, view.image_size)
