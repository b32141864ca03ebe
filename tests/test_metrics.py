import math

import numpy as np
import pytest

from monose3.errors import Monose3Error
from monose3.report.metrics import add_per_frame, auc, auc_interval, format_table, summarize


def reference_auc(adds, max_threshold=0.1, step=1e-5):
    """Independent, deliberately naive computation: explicit threshold loop and trapezoid sum."""
    adds = [a if math.isfinite(a) else math.inf for a in adds]
    n_thr = int(round(max_threshold / step))  # thresholds 0, step, ..., max_threshold - step
    fractions = []
    for i in range(n_thr):
        thr = np.arange(0.0, max_threshold, step)[i]
        fractions.append(sum(1 for a in adds if a <= thr) / len(adds))
    area = sum((fractions[i] + fractions[i + 1]) / 2 * step for i in range(n_thr - 1))
    return area / max_threshold * 100


def test_add_hand_computed():
    gt = np.zeros((2, 2, 3))
    pred = np.zeros((2, 2, 3))
    pred[0, 0] = [0.03, 0.04, 0.0]  # 5 cm
    pred[0, 1] = [0.0, 0.0, 0.01]  # 1 cm
    pred[1] += [0.0, 0.0, -0.02]  # both 2 cm
    np.testing.assert_allclose(add_per_frame(pred, gt), [0.03, 0.02])


def test_add_nonfinite_prediction_is_failure():
    gt = np.ones((3, 4, 3))
    pred = gt.copy()
    pred[1, 2, 0] = np.nan
    pred[2, 0, 1] = np.inf
    out = add_per_frame(pred, gt)
    assert out[0] == 0.0 and np.isinf(out[1]) and np.isinf(out[2])


def test_add_rejects_bad_shapes_and_gt():
    with pytest.raises(Monose3Error, match="same shape"):
        add_per_frame(np.zeros((2, 3, 3)), np.zeros((2, 4, 3)))
    gt = np.zeros((1, 2, 3))
    gt[0, 0, 0] = np.nan
    with pytest.raises(Monose3Error, match="ground-truth"):
        add_per_frame(np.zeros((1, 2, 3)), gt)


@pytest.mark.parametrize(
    "adds",
    [
        [0.0, 0.005, 0.0123, 0.05, 0.2],
        [0.001, np.inf, 0.03, np.nan, 0.0999],
        list(np.random.default_rng(0).exponential(0.03, size=40)),
    ],
)
def test_auc_matches_independent_computation(adds):
    assert auc(adds) == pytest.approx(reference_auc(adds), abs=1e-9)


def test_auc_extremes():
    # The reference thresholds exclude 0.1 itself, so a perfect estimator scores 99.99.
    assert auc(np.zeros(7)) == pytest.approx(99.99, abs=1e-9)
    assert auc([0.1, 0.2, 5.0]) == 0.0
    assert auc([np.inf, np.nan]) == 0.0


def test_auc_single_frame_closed_form_and_failures_dilute():
    a = 0.040005  # between thresholds 0.04 and 0.04001
    # fraction is 0 up to 0.04, 1 from 0.04001 to 0.09999; the trapezoid adds half a step for the ramp
    expected = ((0.09999 - 0.04001) + 0.5e-5) / 0.1 * 100
    assert auc([a]) == pytest.approx(expected, abs=1e-6)
    # a failed frame stays in the denominator and halves the score
    assert auc([a, np.inf]) == pytest.approx(expected / 2, abs=1e-6)


def test_auc_rejects_empty_and_negative():
    with pytest.raises(Monose3Error):
        auc([])
    with pytest.raises(Monose3Error):
        auc([-0.01, 0.02])


def test_summarize_keys_and_values():
    adds = np.array([0.005, 0.015, 0.03, 0.05, np.inf])
    s = summarize(adds, fps=2.5)
    assert s["n"] == 5 and s["failures"] == 1
    assert s["mean"] == pytest.approx(np.mean([0.005, 0.015, 0.03, 0.05]))
    assert s["median"] == pytest.approx(0.0225)
    assert s["under_10mm"] == pytest.approx(0.2)
    assert s["under_20mm"] == pytest.approx(0.4)
    assert s["under_40mm"] == pytest.approx(0.6)
    assert s["under_60mm"] == pytest.approx(0.8)
    assert s["auc"] == pytest.approx(reference_auc(list(adds)), abs=1e-9)
    assert s["fps"] == 2.5


def test_summarize_all_failed():
    s = summarize([np.inf, np.inf])
    assert s["failures"] == 2 and math.isnan(s["mean"]) and s["auc"] == 0.0


def test_format_table():
    rows = {
        "RealSense-Franka": summarize([0.01, 0.02, 0.03], fps=1.3),
        "Azure": summarize([0.05, np.inf]),
    }
    text = format_table(rows)
    lines = text.splitlines()
    assert "AUC" in lines[0] and "FPS" in lines[0] and "failures" in lines[0]
    assert len(lines) == 4
    assert lines[2].startswith("RealSense-Franka") and "1.30" in lines[2] and "0.0200" in lines[2]
    assert f"{rows['Azure']['auc']:.2f}" in lines[3]
    assert "FPS" not in format_table({"a": summarize([0.01])})


def test_auc_interval_holds_the_auc_and_narrows_with_more_frames():
    rng = np.random.default_rng(0)
    few, many = rng.uniform(0, 0.1, 30), rng.uniform(0, 0.1, 3000)
    for adds in (few, many):
        lo, hi = auc_interval(adds)
        assert lo <= auc(adds) <= hi
    assert np.diff(auc_interval(many)) < np.diff(auc_interval(few)) / 5
    assert auc_interval(np.full(10, 0.02)) == pytest.approx((auc(np.full(10, 0.02)),) * 2)
