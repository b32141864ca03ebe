"""perception.local_search: the (1 + lambda) search climbs a score and never returns a worse pose."""

import numpy as np

from monose3.geometry.poses import make_pose, perturb_poses, transform_points
from monose3.perception.local_search import SearchConfig, search_locally

POINTS = np.random.default_rng(0).uniform(-0.3, 0.3, (20, 3)) + [0, 0, 0.4]  # a robot-sized cloud, base frame
TRUE = make_pose(np.eye(3), np.array([0.05, -0.1, 1.4]))


def _score(poses: np.ndarray) -> np.ndarray:
    """Higher the nearer the poses put the points to where TRUE puts them."""
    return -np.linalg.norm(transform_points(poses, POINTS) - transform_points(TRUE, POINTS), axis=-1).mean(-1)


def test_the_search_climbs_towards_the_best_score():
    starts = perturb_poses(np.repeat(TRUE[None], 4, 0), np.random.default_rng(1), 0.03, 5.0)
    before = -_score(starts)
    assert before.mean() > 0.03
    assert (-_score(search_locally(starts, _score, POINTS.mean(0))) < before).all()
    longer = search_locally(starts, _score, POINTS.mean(0), SearchConfig(generations=8, population=15))
    assert (-_score(longer) < 0.5 * before).all()


def test_a_start_no_trial_beats_is_returned_unchanged():
    starts = perturb_poses(np.repeat(TRUE[None], 2, 0), np.random.default_rng(2), 0.03, 5.0)
    found = search_locally(starts, lambda poses: np.zeros(len(poses)), POINTS.mean(0), SearchConfig(generations=3))
    np.testing.assert_array_equal(found, starts)


def test_the_search_is_reproducible():
    starts = perturb_poses(TRUE[None], np.random.default_rng(3), 0.03, 5.0)
    np.testing.assert_array_equal(
        search_locally(starts, _score, POINTS.mean(0)), search_locally(starts, _score, POINTS.mean(0))
    )
