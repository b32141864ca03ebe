"""Evaluation end to end: per-frame ADD, failures as infinite ADD, JSON, plot and overlays."""

import json

import numpy as np
import pytest
from conftest import TINY_NET, save_tiny_checkpoint

from monose3.api import load_estimator
from monose3.apps.cli import main
from monose3.data.datasets import open_dataset
from monose3.estimator import PoseEstimator
from monose3.method.config import get_preset
from monose3.method.designs import build_denoiser
from monose3.report.evaluation import evaluate_dataset
from monose3.report.metrics import add_per_frame
from monose3.report.sequences import track_sequence
from monose3.tracking import MODE_FULL


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory):
    return save_tiny_checkpoint(tmp_path_factory.mktemp("ck") / "tiny.pt")


def test_add_of_each_frame_matches_the_returned_poses(tiny_dream):
    config = get_preset("cpu", network=TINY_NET)
    est = PoseEstimator(build_denoiser(config.network), config)
    frames = open_dataset(tiny_dream, "panda")
    result = evaluate_dataset(est, frames, "tiny", ddim_steps=1, direct_steps=1, batch_size=4, progress=False)
    est.close()
    assert len(result.adds) == len(frames)
    for frame, rec in zip(frames, result.frames, strict=True):
        pose = np.asarray(rec["camera_from_base"])
        kp = est.robot.keypoints(frame.joints[None])[0] @ pose[:3, :3].T + pose[:3, 3]
        expected = add_per_frame(kp[None], frame.keypoints_3d[None])[0]
        assert (rec["add_m"] is None and not rec["in_view"]) or rec["add_m"] == pytest.approx(expected)
    assert result.summary()["n"] == len(frames)


def test_cli_writes_table_json_plot_and_overlays(tiny_dream, tiny_checkpoint, tmp_path, capsys):
    out_json, plot, overlays = tmp_path / "r.json", tmp_path / "add.png", tmp_path / "ov"
    code = main(
        [
            "evaluate",
            "--data",
            str(tiny_dream),
            "--checkpoint",
            str(tiny_checkpoint),
            "--steps",
            "1",
            "1",
            "--json",
            str(out_json),
            "--plot",
            str(plot),
            "--overlays",
            str(overlays),
            "--overlay-frames",
            "0",
        ]
    )
    assert code == 0
    table = capsys.readouterr().out
    assert "AUC" in table.upper() and tiny_dream.name in table
    data = json.loads(out_json.read_text())
    frames = data["datasets"][tiny_dream.name]["frames"]
    assert len(frames) == 6 and np.asarray(frames[0]["camera_from_base"]).shape == (4, 4)
    assert plot.stat().st_size > 1000 and len(list(overlays.glob("*.png"))) == 1


def test_cli_tracking_mode_reports_the_shared_tracking_policy(tiny_dream, tiny_checkpoint, tmp_path):
    """``evaluate --sampler tracking`` and ``monose3 track`` run one policy: the per-frame poses,
    modes and re-initialisation reasons evaluate reports equal track_sequence's on the same frames."""
    out_json = tmp_path / "track.json"
    argv = ["evaluate", "--data", str(tiny_dream), "--checkpoint", str(tiny_checkpoint), "--sampler", "tracking"]
    assert main([*argv, "--limit", "4", "--json", str(out_json)]) == 0
    records = json.loads(out_json.read_text())["datasets"][tiny_dream.name]["frames"]
    estimator = load_estimator(tiny_checkpoint)
    try:
        expected = track_sequence(estimator, open_dataset(tiny_dream, estimator.robot)[:4], sampler="revdiff")
    finally:
        estimator.close()
    assert len(records) == len(expected) == 4
    assert records[0]["mode"] == MODE_FULL and records[0]["reason"] == "first"
    for rec, ref in zip(records, expected, strict=True):
        assert (rec["frame"], rec["mode"], rec["reason"], rec["in_view"]) == (
            ref.name,
            ref.mode,
            ref.reason,
            ref.in_view,
        )
        assert np.allclose(rec["camera_from_base"], ref.camera_from_base, atol=1e-9)
        if ref.in_view:
            assert rec["add_m"] == pytest.approx(ref.add_mm / 1000.0)
    # --steps sets the full process of the first frame (and of every re-initialisation).
    assert main([*argv, "--steps", "1", "0", "--limit", "2", "--json", str(out_json)]) == 0
    records = json.loads(out_json.read_text())["datasets"][tiny_dream.name]["frames"]
    assert [r["mode"] for r in records][:1] == [MODE_FULL] and len(records) == 2


def test_fit_records_say_whether_each_estimate_is_reliable_and_why(tiny_dream):
    """The default sampler's per-frame records carry the flag and what it read."""
    est = load_estimator()
    frames = open_dataset(tiny_dream, "panda")
    try:
        result = evaluate_dataset(est, frames, "tiny", limit=2, progress=False)
    finally:
        est.close()
    for rec in result.frames:
        assert {"silhouette_iou", "edge_support", "edge_distance_px", "reliable", "doubts"} <= set(rec)
        assert rec["reliable"] == (rec["in_view"] and not rec["doubts"]) and 0 <= rec["edge_support"] <= 1
        assert rec["edge_distance_px"] is None or rec["edge_distance_px"] >= 0
