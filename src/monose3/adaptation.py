"""Adapting the robot parser to the user's own scene, from their frames and joints alone.

A user's frames hold what no synthetic set does: their robot under their light, before their
background, behind their occluders. Where the parser already fits some frames reliably, the
fits label the scene: the robot rendered at a fitted pose gives its mask and keypoints
(:mod:`monose3.training.scene_views`). With a static camera every frame is labelled at the
pose fused from the reliable fits, as ``calibrate`` fuses them, so the frames the parser got
wrong are labelled too. The parser is fine-tuned on these labels, mixed with synthetic scenes
so that it keeps what it knew, for a few minutes (self-training on the target images, as
CtRNet does, with the geometric fit as the teacher).

Nothing checks the labels but the fits themselves, so a guard decides: every
:attr:`AdaptConfig.held_out_every`-th frame is left out of the labels, fitted before and after,
and the adapted parser is kept only when those fits improve: no fewer reliable, and a higher
median of silhouette IoU plus edge support (the share of the outline on the image's own
edges, which the parser does not draw). Otherwise the parser it started from stays.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from monose3.atomic import json_number
from monose3.calibration import estimate_frames
from monose3.data.frames import load_images
from monose3.errors import Monose3Error
from monose3.geometry.averaging import pose_residuals, robust_consensus
from monose3.perception.config import PARSER_KIND
from monose3.perception.parser import RobotParser
from monose3.report.overlays import image_grid, pose_overlays
from monose3.training.checkpoints import save_parser
from monose3.training.parser_loop import ParserBatch, ParserBatchMaker, parser_losses, parser_optimizer
from monose3.training.scene_views import LabelledFrame, SceneViews

LABELS_FUSED = "fused"  # every frame at the static camera's fused pose
LABELS_PER_FRAME = "per-frame"  # each reliable frame at its own fit
PICTURE_FRAMES = 4  # held-out frames in the picture of the guard's check
PICTURE_TILE_WIDTH = 400


@dataclass(frozen=True)
class AdaptConfig:
    """The fine-tuning: ``steps`` steps (stopped early after ``minutes`` of wall clock), each step
    ``views_per_step`` labelled views of the user's frames and ``synthetic_per_step`` synthetic
    scenes, the learning rate warmed up over ``warmup_steps`` then decayed by a cosine to zero."""

    steps: int = 90  # three minutes on a 2-core CPU
    minutes: float = 4.0
    lr: float = 5e-4
    views_per_step: int = 8
    synthetic_per_step: int = 4
    warmup_steps: int = 10
    held_out_every: int = 4
    max_frames: int = 40  # frames adapted on and checked on, spread evenly over a longer sequence
    batch_size: int = 4  # frames estimated together
    seed: int = 0


@dataclass
class HeldOutFits:
    """How the parser's fits of the held-out frames look, without ground truth."""

    poses: np.ndarray  # [N, 4, 4]
    reliable: np.ndarray  # [N] bool
    quality: np.ndarray  # [N] silhouette IoU + edge support (0 where no robot was found)

    @property
    def median_quality(self) -> float:
        return float(np.median(self.quality))

    def summary(self, fused: np.ndarray | None = None) -> dict:
        out = {"reliable": int(self.reliable.sum()), "frames": len(self.reliable),
               "median_iou_plus_support": round(self.median_quality, 4)}  # fmt: skip
        if fused is not None:  # a static camera: how far the held-out fits lie from the fused pose
            finite = np.isfinite(self.poses).all((1, 2))
            mm = pose_residuals(self.poses[finite], fused)[0] if finite.any() else np.array([math.inf])
            out["median_distance_to_fused_mm"] = json_number(round(float(np.median(mm)), 2))
        return out


@dataclass
class AdaptResult:
    """What the adaptation did; ``parser`` is the one kept (``candidate``, the fine-tuned one,
    only when ``adapted``)."""

    parser: RobotParser
    candidate: RobotParser | None
    adapted: bool
    labels: str
    labelled_frames: list[str]
    held_out_frames: list[str]
    before: dict
    after: dict | None
    steps: int
    seconds: dict[str, float] = field(default_factory=dict)
    skipped: list[dict] = field(default_factory=list)
    picture: np.ndarray | None = None  # held-out frames fitted before (left) and after (right)

    @property
    def verdict(self) -> str:
        if self.after is None:
            return "kept the original parser: no training step ran"
        b, a = self.before, self.after
        held = (
            f"held-out frames: reliable {b['reliable']} -> {a['reliable']} of {b['frames']}, median IoU + edge "
            f"support {b['median_iou_plus_support']:.3f} -> {a['median_iou_plus_support']:.3f}"
        )
        if self.adapted:
            return f"kept the adapted parser; {held}"
        return f"kept the original parser (the adapted one did not fit the held-out frames better); {held}"

    def to_dict(self) -> dict:
        return {"adapted": self.adapted, "verdict": self.verdict, "labels": self.labels,
                "labelled_frames": self.labelled_frames, "held_out_frames": self.held_out_frames,
                "before": self.before, "after": self.after, "steps": self.steps,
                "seconds": {k: round(v, 1) for k, v in self.seconds.items()}, "skipped": self.skipped}  # fmt: skip


def check_frame_count(count: int) -> None:
    if count < 2:
        raise Monose3Error(f"adaptation needs at least 2 frames (some to learn from, some to check on), got {count}")


def split_frames(frames: Sequence, every: int, most: int) -> tuple[list, list]:
    """At most ``most`` frames spread evenly over ``frames``: those to adapt on and the held-out
    ones (every ``every``-th, from the middle of the first stride, so a short sequence holds some out too)."""
    check_frame_count(len(frames))
    frames = [frames[int(i)] for i in np.unique(np.linspace(0, len(frames) - 1, min(most, len(frames))).round())]
    held = set(range(min(every // 2, len(frames) - 1), len(frames), every))
    return [f for i, f in enumerate(frames) if i not in held], [f for i, f in enumerate(frames) if i in held]


def label_frames(estimator, frames: Sequence, static_camera: bool, config: AdaptConfig, skipped: list[dict],
                 progress: bool) -> tuple[list[LabelledFrame], list[str], np.ndarray | None]:  # fmt: skip
    """The frames with the poses that label them (each reliable fit, or with ``static_camera``
    every frame at the reliable fits' fused pose), their names and the fused pose (else None)."""
    usable, results = estimate_frames(estimator, frames, 1, config.batch_size, config.seed, skipped, progress,
                                      desc="fit frames")  # fmt: skip
    if not results:
        raise Monose3Error(f"no usable frame to adapt on: all {len(frames)} were skipped ({skipped[0]['reason']})")
    reliable = [i for i, r in enumerate(results) if r.in_view and r.fit_reliable]
    if not reliable:
        raise Monose3Error(
            f"no reliable fit in the {len(results)} frames to adapt on: adaptation learns the scene from frames the "
            "parser already fits; add frames where the robot is clearly visible"
        )
    fused = None
    if static_camera:
        fused = robust_consensus(np.stack([results[i].camera_from_base for i in reliable])).pose
        chosen = [(f, fused) for f in usable]
    else:
        chosen = [(usable[i], results[i].camera_from_base) for i in reliable]
    labelled = [LabelledFrame(f.load_image(), np.asarray(f.K, np.float64), np.asarray(f.joints, np.float64), pose)
                for f, pose in chosen]  # fmt: skip
    return labelled, [str(f.name) for f, _ in chosen], fused


def held_out_fits(estimator, images: list[np.ndarray], frames: Sequence, batch_size: int) -> HeldOutFits:
    """The current parser's fits of ``frames`` (their ``images``)."""
    poses, reliable, quality = [], [], []
    for first in range(0, len(frames), batch_size):
        chunk = frames[first : first + batch_size]
        est = estimator.estimate(images[first : first + batch_size], np.stack([f.K for f in chunk]),
                                 np.stack([f.joints for f in chunk]), sampler="fit")  # fmt: skip
        poses.append(est.poses)
        reliable.append(est.reliable)
        quality.append(np.where(est.found, np.nan_to_num(est.fit_iou) + np.nan_to_num(est.edge_support), 0.0))
    return HeldOutFits(np.concatenate(poses), np.concatenate(reliable), np.concatenate(quality))


def check_picture(renderer, frames: Sequence, images: list[np.ndarray], before: HeldOutFits,
                  after: HeldOutFits) -> np.ndarray | None:  # fmt: skip
    """Up to :data:`PICTURE_FRAMES` held-out frames as the guard saw them: the robot at each
    frame's fit with the original parser (left) and the adapted one (right); None when no frame
    was fitted both times."""
    both = [i for i in range(len(frames)) if np.isfinite(before.poses[i]).all() and np.isfinite(after.poses[i]).all()]
    picks = both[:: max(1, len(both) // PICTURE_FRAMES)][:PICTURE_FRAMES]
    if not picks:
        return None
    label = lambda fits, i, when: (  # noqa: E731
        f"{frames[i].name} {when}: IoU + support {fits.quality[i]:.2f}, {'' if fits.reliable[i] else 'UN'}RELIABLE"
    )
    tiles = pose_overlays(
        renderer,
        [images[i] for i in picks for _ in range(2)],
        [frames[i].K for i in picks for _ in range(2)],
        [frames[i].joints for i in picks for _ in range(2)],
        [pose for i in picks for pose in (before.poses[i], after.poses[i])],
        [text for i in picks for text in (label(before, i, "before"), label(after, i, "adapted"))],
        max_width=PICTURE_TILE_WIDTH,
    )
    return image_grid(tiles, cols=2, pad=4, background=255)


def guard_keeps(before: HeldOutFits, after: HeldOutFits) -> bool:
    """The adapted parser is kept when its held-out fits are no fewer reliable and their median
    IoU + edge support is higher."""
    return bool(after.reliable.sum() >= before.reliable.sum()) and after.median_quality > before.median_quality


def freeze_batchnorm(model: torch.nn.Module) -> None:
    """Batch norms keep their statistics: a fine-tuning batch of one scene would overwrite them."""
    for m in model.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.eval()


def fine_tune(parser: RobotParser, views: SceneViews, config: AdaptConfig, progress: bool = False,
              backgrounds: str | Path | None = None) -> tuple[RobotParser, int]:  # fmt: skip
    """A copy of ``parser`` fine-tuned on ``views`` mixed with synthetic scenes; and its steps."""
    device = next(parser.parameters()).device
    torch.manual_seed(config.seed)
    model = copy.deepcopy(parser).train()
    freeze_batchnorm(model)
    optimizer = parser_optimizer(model, config.lr)
    synthetic = None
    if config.synthetic_per_step > 0:
        scenes = replace(parser.config, batch_size=config.synthetic_per_step, seed=config.seed + 1)
        synthetic = ParserBatchMaker(scenes, device, 0, 0, backgrounds)
    started, step = time.perf_counter(), 0
    bar = tqdm(desc="adapt parser", unit="step", total=config.steps, disable=not progress)
    while step < config.steps:
        spent = max((time.perf_counter() - started) / (config.minutes * 60), step / config.steps)
        if spent >= 1.0:
            break
        lr = config.lr * min(1.0, (step + 1) / config.warmup_steps) * 0.5 * (1 + math.cos(math.pi * spent))
        for group in optimizer.param_groups:
            group["lr"] = lr * group["scale"]
        batch = views.batch(config.views_per_step, device)
        if synthetic is not None:
            batch = joined(batch, synthetic.batch(step))
        parts = parser_losses(model, batch, parser.config)
        loss = parts["mask"] + parser.config.keypoint_weight * parts["keypoints"]
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
        optimizer.step()
        step += 1
        bar.update(1)
        bar.set_postfix({k: f"{v.item():.3f}" for k, v in parts.items()})
    bar.close()
    return model.eval(), step


def joined(a: ParserBatch, b: ParserBatch) -> ParserBatch:
    return ParserBatch(*(torch.cat([getattr(a, k), getattr(b, k)]) for k in ("image", "mask", "keypoints")))


def adapt_parser(estimator, frames: Sequence, config: AdaptConfig | None = None, static_camera: bool = False,
                 progress: bool = False, backgrounds: str | Path | None = None) -> AdaptResult:  # fmt: skip
    """Fine-tune ``estimator``'s parser on ``frames`` (objects with ``name``, ``K``, ``joints``
    and ``load_image()``) and keep the adapted parser in the estimator only when the guard
    says it fits the held-out frames better. Raises Monose3Error with fewer than 2 frames or no
    reliable fit to learn from."""
    config = config or AdaptConfig()
    if estimator.parser is None:
        raise Monose3Error(f"no robot parser for {estimator.robot.name} to adapt; pass one with --parser FILE")
    clock, seconds, skipped = time.perf_counter(), {}, []
    adapt_on, held_out = split_frames(frames, config.held_out_every, config.max_frames)
    held_out, held_images = load_images(held_out, skipped)
    if not held_out:
        raise Monose3Error("no readable frame to check the adaptation on; see the skipped frames")
    labelled, names, fused = label_frames(estimator, adapt_on, static_camera, config, skipped, progress)
    before = held_out_fits(estimator, held_images, held_out, config.batch_size)
    seconds["labels"], clock = time.perf_counter() - clock, time.perf_counter()
    original = estimator.parser
    views = SceneViews(labelled, estimator.robot, estimator.renderer, original.config.input_size, config.seed)
    adapted, steps = fine_tune(original, views, config, progress, backgrounds)
    seconds["training"], clock = time.perf_counter() - clock, time.perf_counter()
    after = None
    if steps > 0:
        estimator.parser = adapted
        try:
            after = held_out_fits(estimator, held_images, held_out, config.batch_size)
        finally:  # an interrupted check leaves the estimator as it was
            estimator.parser = original
    keep = after is not None and guard_keeps(before, after)
    estimator.parser = adapted if keep else original
    picture = None if after is None else check_picture(estimator.renderer, held_out, held_images, before, after)
    seconds["check"] = time.perf_counter() - clock
    return AdaptResult(
        parser=estimator.parser,
        candidate=adapted if steps > 0 else None,
        adapted=keep,
        labels=LABELS_FUSED if static_camera else LABELS_PER_FRAME,
        labelled_frames=names,
        held_out_frames=[str(f.name) for f in held_out],
        before=before.summary(fused),
        after=None if after is None else after.summary(fused),
        steps=steps,
        seconds=seconds,
        skipped=skipped,
        picture=picture,
    )


def save_adapted_parser(result: AdaptResult, out: str | Path) -> Path:
    """The adapted parser as a file ``--parser`` reads (fp16, written atomically), with how it was made."""
    meta = {"kind": PARSER_KIND, "parser": asdict(result.parser.config), "step": 0, "samples": 0,
            "adapted": result.to_dict()}  # fmt: skip
    return save_parser(result.parser.state_dict(), out, meta)
