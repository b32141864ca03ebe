"""A derivative-free local search on the whole-silhouette score, between the refinement's passes.

Not in the paper. The refinement (``fitting.refine_poses``) is ICP on silhouettes: each step
follows correspondences between the rendered outline and the mask's nearest outline. Where the
parser's mask is wrong in part (an occluder taken in, a white link on a white wall missed), the
nearest outline can lie on the wrong part, and ICP climbs into a pose that fits that part while
the score of the whole silhouette (IoU less the keypoint term, as the hypotheses are scored)
is higher elsewhere near by. On the held-out hard frames refined from the truth moved by
5 deg / 3 cm, the score preferred the truth over ICP's end in 6 of 7 frames that ended further
away. The search compares whole silhouettes instead: a (1 + lambda) evolution strategy, each
generation ``population`` trial poses around each current best (turned about the robot's centre
so a turn does not swing it across the image), one batch of renders, the best kept when it
scores higher, the steps shrinking by ``shrink`` per generation.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from monose3.geometry.poses import perturb_poses


@dataclass(frozen=True)
class SearchConfig:
    generations: int = 5
    population: int = 10  # trial poses per start and generation
    rot_deg: float = 5.0  # first generation's std per axis: what the refinement's starts are off by
    trans_m: float = 0.03
    shrink: float = 0.75  # steps per generation: 5 deg, 3.75, ... 1.6 deg at the fifth
    # Silhouettes are compared at this size: a render costs by the pixel it covers (a large
    # robot 29 ms at 160x120, 5 ms here), and the fine pass gives the precision.
    size: tuple[int, int] = (80, 60)
    seed: int = 0  # the trial poses are drawn from this seed: the same image gives the same pose


DEFAULT_SEARCH = SearchConfig()


def search_locally(poses: np.ndarray, score: Callable[[np.ndarray], np.ndarray], pivot: np.ndarray | None,
                   config: SearchConfig = DEFAULT_SEARCH) -> np.ndarray:  # fmt: skip
    """The best pose found near each of ``poses`` ``[H, 4, 4]`` by ``score`` (``[N, 4, 4]`` ->
    ``[N]``, higher is better; one call per generation with all starts' trials), turning the
    trials about ``pivot`` ``[3]`` (base frame; None: the base origin). Never returns a pose
    scoring lower than its start."""
    rng = np.random.default_rng(config.seed)
    best = np.array(poses, np.float64)
    best_scores = score(best)
    n, p = len(best), config.population
    for g in range(config.generations):
        step = config.shrink**g
        trials = perturb_poses(np.repeat(best, p, 0), rng, config.trans_m * step, config.rot_deg * step, pivot)
        scores = score(trials).reshape(n, p)
        top = scores.argmax(1)
        better = scores[np.arange(n), top] > best_scores
        best[better] = trials.reshape(n, p, 4, 4)[better, top[better]]
        best_scores[better] = scores[better, top[better]]
    return best
