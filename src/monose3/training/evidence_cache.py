"""The evidence denoiser's training data: the robot parser's actual outputs on synthesised scenes,
computed once and cached on disk, and the training batches made from them.

``make_cache`` draws scenes as ``monose3 generate`` draws them (cycling through the profiles,
``train``, ``reallike`` and ``hard`` by default), renders and composes each frame, runs the
parser on it as the estimator does (``views.parse_image``: the whole image, then zoomed on the
robot) and keeps, per sample, the parser's mask, keypoints and confidences in the standardised
image, with the frame's intrinsics, true pose and joints. Shards of :data:`SHARD_SAMPLES` are
written atomically, so an interrupted job continues where it stopped (and a cache grows by
running it again with more samples).

At training time each sample's evidence goes through the forward process's H_t and the crop
around it (:func:`evidence_batch`), with augmentations that mimic the parser's mistakes beyond
those the cache already holds: holes in the mask, spurs beside it, dropped and misplaced keypoints.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from monose3 import atomic
from monose3.data.scenes.appearance import compose_frame
from monose3.data.scenes.profiles import get_profile
from monose3.data.scenes.sampling import frame_rng, sample_scene
from monose3.data.scenes.writer import make_renderer
from monose3.errors import Monose3Error
from monose3.estimator import evidence_of
from monose3.geometry.camera import standardized_K
from monose3.method.config import Config
from monose3.method.evidence import Evidence, evidence_crops, keypoints_ref, render_maps
from monose3.method.pose_space import base_frame
from monose3.method.scheduler import PoseNoiser
from monose3.perception.parser import RobotParser
from monose3.perception.views import parse_image
from monose3.robot import RobotModel
from monose3.robot.jobs import RenderJob
from monose3.robot.renderer import RobotRenderer
from monose3.training.samples import noisy_views

SHARD_SAMPLES = 250
PROFILES = ("train", "reallike", "hard")
FIELDS = ("mask", "box", "keypoints", "confidence", "K", "pose", "joints")
# The parser's mistakes, added at training time on top of its own (probability per sample).
HOLE_PROB, SPUR_PROB = 0.3, 0.3  # a rectangle of the mask cleared / a blob of robot added beside it
DROP_PROB, MISPLACE_PROB = 0.3, 0.2  # one keypoint's confidence zeroed / one keypoint moved
MISPLACE_PX = 12.0  # how far a misplaced keypoint moves (std, standardised-image pixels)


def shard_path(out: Path, index: int) -> Path:
    return out / f"evidence-{index:05d}.npz"


@torch.no_grad()
def make_cache(out: str | Path, samples: int, seed: int, parser: RobotParser, robot: str = "panda",
               profiles: tuple[str, ...] = PROFILES, image_size: tuple[int, int] = (640, 480),
               input_size: tuple[int, int] = (320, 240), progress: bool = True,
               shard_samples: int = SHARD_SAMPLES) -> Path:  # fmt: skip
    """Write (or complete) the cache of ``samples`` samples (whole shards of ``shard_samples``) in
    ``out``; returns ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    model = RobotModel(robot)
    renderer = make_renderer(model, "torch")
    parser = parser.eval()
    todo = [s for s in range(math.ceil(samples / shard_samples)) if not shard_path(out, s).is_file()]
    bar = tqdm(total=len(todo) * shard_samples, desc="evidence cache", unit="sample", disable=not progress)
    try:
        for shard in todo:
            rows = []
            for i in range(shard * shard_samples, (shard + 1) * shard_samples):
                rows.append(cache_sample(i, seed, model, renderer, parser, profiles, image_size, input_size))
                bar.update()
            arrays = {k: np.stack([r[k] for r in rows]) for k in FIELDS}
            with atomic.atomic_path(shard_path(out, shard)) as tmp, tmp.open("wb") as fh:
                np.savez_compressed(fh, **arrays)
    finally:
        bar.close()
        renderer.close()
    return out


def cache_sample(index: int, seed: int, model: RobotModel, renderer, parser: RobotParser, profiles: tuple[str, ...],
                 image_size: tuple[int, int], input_size: tuple[int, int]) -> dict[str, np.ndarray]:  # fmt: skip
    """One scene (profile ``profiles[index % len]``) and the parser's evidence on it."""
    rng = frame_rng(seed, index)
    profile = get_profile(profiles[index % len(profiles)])
    scene = sample_scene(rng, model, profile, image_size)
    rgb, mask = renderer.render(RenderJob(scene.joints, scene.pose, scene.K, image_size, scene.lighting))
    image, _ = compose_frame(rng, rgb, mask, profile, None)
    view = parse_image(parser, image, scene.K)
    evidence = evidence_of([view], [image_size], input_size)
    return {
        "mask": (evidence.mask[0, 0].numpy() * 255).round().astype(np.uint8),
        "box": evidence.box[0].numpy(),
        "keypoints": evidence.keypoints[0].numpy(),
        "confidence": evidence.confidence[0].numpy(),
        "K": standardized_K(scene.K, image_size, input_size),
        "pose": scene.pose,
        "joints": scene.joints,
    }


class EvidenceCache:
    """Every sample of one or more cache folders, in memory (masks as uint8)."""

    def __init__(self, folders: list[str | Path]):
        parts: dict[str, list[np.ndarray]] = {k: [] for k in FIELDS}
        for folder in folders:
            shards = sorted(Path(folder).glob("evidence-*.npz"))
            if not shards:
                raise Monose3Error(f"no evidence cache in {folder}; make one with make_cache (benchmarks/evidence.py)")
            for path in shards:
                with np.load(path) as data:
                    for k in FIELDS:
                        parts[k].append(data[k])
        self.arrays = {k: torch.from_numpy(np.concatenate(v)) for k, v in parts.items()}

    def __len__(self) -> int:
        return len(self.arrays["pose"])

    def take(self, indices: torch.Tensor) -> dict[str, torch.Tensor]:
        return {k: v[indices] for k, v in self.arrays.items()}


def parser_mistakes(evidence: Evidence, gen: torch.Generator) -> Evidence:
    """The parser's mistakes, drawn from ``gen``: holes in the mask, spurs beside it, dropped and
    misplaced keypoints (:data:`HOLE_PROB`... per sample)."""
    mask, kp, conf = evidence.mask.clone(), evidence.keypoints.clone(), evidence.confidence.clone()
    b, _, h, w = mask.shape
    for i in range(b):
        ys, xs = torch.nonzero(mask[i, 0] > 0.5, as_tuple=True)
        if len(ys) and torch.rand((), generator=gen) < HOLE_PROB:
            j = int(torch.randint(len(ys), (), generator=gen))
            r = int(torch.randint(2, max(3, w // 12), (), generator=gen))
            mask[i, 0, max(0, ys[j] - r) : ys[j] + r, max(0, xs[j] - r) : xs[j] + r] = 0
        if len(ys) and torch.rand((), generator=gen) < SPUR_PROB:
            j = int(torch.randint(len(ys), (), generator=gen))
            r = int(torch.randint(2, max(3, w // 10), (), generator=gen))
            dy, dx = (int(v) for v in torch.randint(-2 * r, 2 * r + 1, (2,), generator=gen))
            y, x = int(ys[j]) + dy, int(xs[j]) + dx
            mask[i, 0, max(0, y - r) : max(0, y + r), max(0, x - r) : max(0, x + r)] = 1
        k = int(torch.randint(kp.shape[1], (), generator=gen))
        if torch.rand((), generator=gen) < DROP_PROB:
            conf[i, k] = 0
        elif torch.rand((), generator=gen) < MISPLACE_PROB:
            kp[i, k] += torch.randn(2, generator=gen, dtype=kp.dtype) * MISPLACE_PX
    return Evidence(mask, evidence.box, kp, conf)


def evidence_batch(samples: dict[str, torch.Tensor], robot: RobotModel, renderer: RobotRenderer,
                   noiser: PoseNoiser, config: Config, gen: torch.Generator, device: torch.device,
                   t_max: int | None = None) -> dict[str, torch.Tensor]:  # fmt: skip
    """A training batch (as :func:`~monose3.training.objective.train_step` eats it) from cached
    samples: H_t from the forward process, the evidence in the crop around it (augmented) and the
    silhouette and keypoints at H_t (:mod:`monose3.method.evidence`)."""
    size = config.network.render_size
    joints = samples["joints"].numpy()
    views = noisy_views(robot, noiser, config, samples["pose"], joints, samples["K"], gen, t_max)
    evidence = Evidence(samples["mask"][:, None].float() / 255, samples["box"].double(),
                        samples["keypoints"].double(), samples["confidence"].float())  # fmt: skip
    crops = evidence_crops(parser_mistakes(evidence, gen), views.boxes, size)
    pose_t = base_frame(views.pose_ref_t, views.centroid)
    rendered = renderer.render(joints, pose_t.to(device), views.K_crop.to(device), size, shade=False)
    kp_cam = torch.from_numpy(robot.keypoints(joints, pose_t.numpy())).to(device)
    return {
        "render": render_maps(rendered.mask, kp_cam, views.K_crop.to(device)),
        "depth": rendered.depth,
        "crop": crops.to(device),
        "t": views.t.to(device),
        "pose_ref_t": views.pose_ref_t.float().to(device),
        "pose_ref_0": views.pose_ref_0.float().to(device),
        "K_crop": views.K_crop.float().to(device),
        "points_ref": views.points_ref.float().to(device),
        "keypoints_ref": keypoints_ref(robot, joints, views.centroid).float().to(device),
    }
