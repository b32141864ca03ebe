"""Fast smoke runs of the benchmarks in benchmarks/ at tiny sizes: they run end to end, print
their tables, and their measurements obey what the geometry guarantees."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
import torch

from monose3.errors import Monose3Error

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def load(name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(f"bench_{name}", BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture
def keep_threads():
    """The benchmarks' --threads changes torch's global thread count: restore it afterwards."""
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


def test_visdiff_small(tmp_path: Path) -> None:
    vd = load("visdiff")
    out = vd.run(scenes=12, reps=5, seed=1, timesteps=[1, 50, 100])
    res = out["results"]
    for name in ("VisDiff g=3", "VisDiff g=1", "FixPer", "FixPer matched", "FixPer@camera"):
        assert set(res[name]) == {1, 50, 100}
    g3, g1 = res["VisDiff g=3"], res["VisDiff g=1"]
    # At t = 1 the noise is tiny: every pose stays in view, rotations move by about a degree.
    assert g3[1]["in_view"] == 1.0 and g3[1]["rot_mean"] < 3.0
    assert g3[100]["rot_mean"] > 5 * g3[1]["rot_mean"]
    # gamma only divides the translation noise: more poses stay in view, rotations spread alike.
    assert g3[100]["in_view"] >= g1[100]["in_view"]
    assert abs(g3[100]["rot_mean"] - g1[100]["rot_mean"]) < 20.0
    # The matched FixPer's std was chosen to reproduce VisDiff's mean rotation angle.
    for t in (50, 100):
        assert res["FixPer matched"][t]["rot_mean"] == pytest.approx(g3[t]["rot_mean"], abs=12.0)
    # FixPer ignores t.
    assert res["FixPer"][1]["rot_mean"] == pytest.approx(res["FixPer"][100]["rot_mean"], abs=12.0)
    text = vd.report(out)
    assert "Effect of gamma" in text and "FixPer matched" in text
    png = vd.plot(out, tmp_path / "visdiff.png")
    assert png.stat().st_size > 10_000


def test_fixper_std_inversion() -> None:
    vd = load("visdiff")
    stds, means = vd.fixper_mean_angle_curve(seed=0, samples=2000)
    std = vd.std_for_mean_angle(45.0, stds, means)
    assert float(means[int(round(std))]) == pytest.approx(45.0, abs=1.5)
    assert vd.std_for_mean_angle(1e3, stds, means) == stds[-1]


@pytest.mark.slow
def test_train_speed_small(capsys: pytest.CaptureFixture[str], keep_threads: None) -> None:
    ts = load("train_speed")
    argv = ["--presets", "cpu", "--steps", "1", "--threads", "1", "--batch-size", "2"]
    assert ts.main([*argv, "--design", "flow-solve", "--flow-weight", "0.5"]) == 0
    text = capsys.readouterr().out
    for source in ("synthetic", "frames"):
        row = next(line for line in text.splitlines() if line.startswith(f"cpu    cpu  {source}"))
        make, render, network, end = (float(v) for v in row.split()[4:8])
        assert min(make, render, network, end) > 0 and end <= min(make, network)


@pytest.mark.slow
def test_inference_speed_small(capsys: pytest.CaptureFixture[str], keep_threads: None) -> None:
    bench = load("inference_speed")
    argv = ["--presets", "cpu", "--batches", "1", "--repeats", "1", "--no-profile", "--threads", "1"]
    assert bench.main([*argv, "--design", "flow-solve"]) == 0
    text = capsys.readouterr().out
    assert "design flow-solve" in text
    rows = [line for line in text.splitlines() if line.startswith("cpu    1 ")]
    assert [r.split()[2] for r in rows] == ["10", "5", "tracking"]
    fps = {r.split()[2]: float(r.split()[3 if r.split()[2] == "tracking" else 4]) for r in rows}
    # Tracking takes one network step, the default ten: it must be clearly faster (loose: shared CI cores).
    assert fps["tracking"] > 2 * fps["10"]


def test_uncertainty_from_priors(tmp_path: Path, tiny_dream: Path, capsys, keep_threads: None) -> None:
    """Exact priors: every prior is within 5 cm; the report and the per-frame JSON say so."""
    import json

    from conftest import save_tiny_checkpoint

    ck = save_tiny_checkpoint(tmp_path / "tiny.pt")
    unc = load("uncertainty")
    argv = ["--checkpoint", str(ck), "--data", str(tiny_dream), "--chains", "2", "--prior", "0", "0"]
    argv += ["--plot", str(tmp_path / "u.png"), "--json", str(tmp_path / "u.json")]
    assert unc.main(argv) == 0
    out = capsys.readouterr().out
    assert "start: a prior = ground truth moved by 0 mm" in out
    assert "mean ADD 0.0 mm, 6 within 50 mm" in out.split("the priors themselves:")[1].splitlines()[0]
    data = json.loads((tmp_path / "u.json").read_text())["sets"][tiny_dream.name]
    assert len(data["add"]) == 6 and max(data["prior_add"]) < 1e-4
    assert (tmp_path / "u.png").stat().st_size > 10_000


def test_a_benchmark_reports_bad_input_in_one_line(tmp_path: Path) -> None:
    import subprocess

    from conftest import save_tiny_checkpoint

    ck = save_tiny_checkpoint(tmp_path / "tiny.pt")
    cmd = [sys.executable, str(BENCHMARKS / "uncertainty.py"), "--checkpoint", str(ck), "--data", str(tmp_path)]
    out = subprocess.run(cmd, capture_output=True, text=True)
    lines = [line for line in out.stderr.splitlines() if not line.startswith("pybullet build time")]
    assert out.returncode == 2 and len(lines) == 1, out.stderr
    assert lines[0].startswith("uncertainty.py: error:") and "neither DREAM frames" in lines[0]


def _fake_design_pool(n: int, seed: int) -> dict[str, torch.Tensor]:
    """A pool in the layout of denoiser_designs.build_pool, from random images and poses."""
    from monose3.geometry.poses import make_pose
    from monose3.geometry.rotations import euler_xyz_to_matrix

    gen = torch.Generator().manual_seed(seed)

    def poses(scale: float) -> torch.Tensor:
        rot = euler_xyz_to_matrix(torch.randn(n, 3, generator=gen) * scale)
        return make_pose(rot, torch.randn(n, 3, generator=gen) * 0.05 + torch.tensor([0.0, 0.0, 1.2]))

    K = torch.tensor([[150.0, 0, 64], [0, 150, 48], [0, 0, 1]]).repeat(n, 1, 1)
    depth = torch.zeros(n, 96, 128)
    depth[:, 24:72, 32:96] = 1.2  # the render's visible surface: a slab in the middle
    return {
        "depth": depth,
        "render": torch.randint(0, 255, (n, 3, 96, 128), dtype=torch.uint8, generator=gen),
        "crop": torch.randint(0, 255, (n, 3, 96, 128), dtype=torch.uint8, generator=gen),
        "t": torch.randint(1, 101, (n,), generator=gen),
        "pose_ref_t": poses(0.3),
        "pose_ref_0": poses(0.3),
        "K_crop": K,
        "points_ref": torch.randn(n, 64, 3, generator=gen) * 0.3,
    }


@pytest.mark.slow
def test_denoiser_designs_small(tmp_path: Path, capsys: pytest.CaptureFixture[str], keep_threads: None) -> None:
    import json

    import numpy as np

    bench = load("denoiser_designs")
    pools = tmp_path / "pools"
    (pools / "cpu").mkdir(parents=True)  # pools are kept per preset
    for name, n, seed in (("train", 16, 0), ("held", 8, 1)):
        np.savez(pools / "cpu" / f"{name}.npz", **{k: v.numpy() for k, v in _fake_design_pool(n, seed).items()})
    argv = ["--pool-dir", str(pools), "--pool-size", "16", "--held-size", "8", "--samples", "8", "--batch-size", "4"]
    argv += ["--evals", "2", "--out", str(tmp_path / "out"), "--designs", "concat", "concat-grid"]
    argv += ["--rotation-output", "so3", "--train-t-max", "60"]
    assert bench.main(argv) == 0
    text = capsys.readouterr().out
    assert "identity" in text and "concat " in text and "concat-grid" in text
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    for result in summary["results"]:
        assert [row["samples"] for row in result["curve"]] == [4, 8]
        assert set(result["ablation_pct"]) == {"zero", "swap"}
        assert set(result["ablation_pct_by_t"]["swap"]) <= {"1-10", "11-20", "21-50", "51-100"}
    assert "render zeroed / swapped, xy/rot % by t" in text
    assert (tmp_path / "out" / "designs.png").stat().st_size > 10_000
    argv[argv.index("concat") : argv.index("concat-grid") + 1] = ["cost-volume", "flow-solve"]
    argv[argv.index("so3")] = "6d"
    assert bench.main([*argv, "--flow-weight", "1", "--tag", "flow", "--field-ceiling"]) == 0
    text = capsys.readouterr().out
    assert "cost-volume [flow]" in text and "flow-solve [flow]" in text and "flow L1 with zero field" in text
    assert "true field, stride 8" in text
    np.savez(pools / "cpu" / "held.npz", **{k: v.numpy() for k, v in _fake_design_pool(8, 1).items() if k != "depth"})
    with pytest.raises(Monose3Error, match="no render depth"):
        bench.main(argv)


@pytest.mark.slow
def test_denoiser_designs_judges_trained_weights(tmp_path: Path, keep_threads: None, capsys) -> None:
    """A run trained elsewhere is judged on a held-out pool drawn on the fly (synthetic scenes)."""
    import json

    from monose3.method.config import get_preset
    from monose3.method.designs import build_denoiser
    from monose3.training.checkpoints import save_checkpoint

    config = get_preset("cpu")
    save_checkpoint(
        tmp_path / "m.pt", {"model": build_denoiser(config.network).state_dict(), "config": config.to_dict()}
    )
    bench = load("denoiser_designs")
    argv = ["--held-data", "synthetic", "--held-size", "16", "--weights", str(tmp_path / "m.pt")]
    assert bench.main([*argv, "--pool-dir", str(tmp_path / "pools"), "--out", str(tmp_path / "out")]) == 0
    result = json.loads((tmp_path / "out" / "result_weights00.json").read_text())
    assert set(result["ablation_pct"]) == {"zero", "swap"} and "1-10" in result["curve"][0]["buckets"]
    assert "concat [m.pt]" in capsys.readouterr().out


@pytest.mark.parametrize("sanity", ["clean", "rotation"])
def test_denoiser_designs_builds_sanity_pools(sanity: str, keep_threads: None) -> None:
    """The sanity pools draw clean scenes (the ``clean`` profile); ``rotation`` gives H_0 H_t's translation."""
    import numpy as np

    from monose3.method.config import get_preset, with_section

    bench = load("denoiser_designs")
    config = with_section(get_preset("cpu"), "train", batch_size=2)
    pool = bench.build_pool("synthetic", config, 2, 0, sanity)
    assert pool["render"].shape[0] == 2 and pool["render"].dtype == np.uint8
    same_translation = np.allclose(pool["pose_ref_0"][:, :3, 3], pool["pose_ref_t"][:, :3, 3])
    assert same_translation == (sanity == "rotation")


@pytest.mark.slow
def test_accuracy_small(tmp_path: Path, tiny_dream: Path, capsys, keep_threads: None) -> None:
    """Every stage row, the refinement, the flag and tracking lines, and the JSON."""
    import json

    acc = load("accuracy")
    assert acc.main(["--data", str(tiny_dream), "--limit", "2", "--json", str(tmp_path / "a.json")]) == 0
    out = capsys.readouterr().out
    for line in (*acc.STAGES, "end closer", "reliable flag", "images/s"):
        assert line in out
    data = json.loads((tmp_path / "a.json").read_text())[tiny_dream.name]
    assert set(data["stages"]) == set(acc.STAGES) and 0 <= data["refinement"]["closer_share"] <= 1
    assert data["frames"]["count"] == 2 and f"digest {data['frames']['digest']}" in out


def test_accuracy_tracking_only_measures_tracking_from_the_same_starts(tmp_path: Path, tiny_dream: Path, capsys,
                                                                       keep_threads: None) -> None:  # fmt: skip
    acc = load("accuracy")
    args = ["--data", str(tiny_dream), "--limit", "2", "--tracking-only", "--json", str(tmp_path / "t.json")]
    assert acc.main(args) == 0
    out = capsys.readouterr().out
    assert "images/s" in out and "end closer" not in out and not any(stage in out for stage in acc.STAGES)
    data = json.loads((tmp_path / "t.json").read_text())[tiny_dream.name]
    assert set(data) == {"tracking", "frames"} and data["frames"]["count"] == 2


def test_depth_bias_reads_the_line_of_sight_and_runs_small(tmp_path: Path, tiny_dream: Path, capsys,
                                                           keep_threads: None) -> None:  # fmt: skip
    bias = load("depth_bias")
    assert bias.main(["--data", str(tiny_dream), "--limit", "1", "--json", str(tmp_path / "b.json")]) == 0
    data = json.loads((tmp_path / "b.json").read_text())[tiny_dream.name]
    assert {"fit", *bias.REFINEMENTS, *bias.SYNTHETIC} <= set(data) and data["frames"] == 1
    assert "outline edges alone" in capsys.readouterr().out
    # the measure itself: the truth is 0, the truth pushed 1 % further along the line of sight +1 %
    from monose3.api import load_estimator
    from monose3.data.datasets import open_dataset

    estimator = load_estimator()
    frame = open_dataset(str(tiny_dream), estimator.robot)[0]
    assert bias.line_of_sight_mm(estimator, frame, frame.pose) == pytest.approx(0.0, abs=1e-9)
    further = frame.pose.copy()
    further[:3, 3] += 0.01 * (frame.pose[:3, :3] @ estimator.robot.centroid(
        estimator.robot.surface_points(frame.joints[None])[0]) + frame.pose[:3, 3])  # fmt: skip
    expected = 0.01 * bias.centroid_distance_mm(estimator, frame, frame.pose)
    assert bias.line_of_sight_mm(estimator, frame, further) == pytest.approx(expected)


def test_sequences_compare_the_track_with_single_frames_on_their_frames() -> None:
    seq = load("sequences")
    rows = [{"add_mm": a} for a in (1.0, 50.0, 50.0, 3.0, 50.0, 50.0, 5.0)]  # frames 0, 3, 6: 1, 3, 5
    assert seq.same_frames_ratio(rows, {"median_add_mm": 2.0}, 3) == pytest.approx(1.5)


@pytest.mark.slow
def test_reliable_flag_small(tiny_dream: Path, capsys, keep_threads: None) -> None:
    """The model is fitted on a folder's fits and the shipped flag's recall and false alarms reported there."""
    flag = load("reliable_flag")
    assert flag.main(["--data", str(tiny_dream), "--recall", "1"]) == 0
    out = capsys.readouterr().out
    assert "frames" in out and "FLAG_MODEL = " in out and "as shipped there" in out


@pytest.mark.slow
def test_reliable_flag_check_measures_without_searching(
    tiny_dream: Path, tmp_path: Path, capsys, keep_threads: None
) -> None:
    """``--check`` reports the shipped flag with intervals, and fits no model there."""
    out_json = tmp_path / "flag.json"
    assert load("reliable_flag").main(["--check", str(tiny_dream), "--json", str(out_json)]) == 0
    out = capsys.readouterr().out
    assert "the flag as shipped" in out and "false alarms" in out and "95 %" in out and "FLAG_MODEL" not in out
    result = json.loads(out_json.read_text())[str(tiny_dream)]
    assert len(result["features"]["add"]) == result["frames"] > 0 and len(result["false_alarms_95"]) == 2


def test_parser_masks_small(tiny_dream: Path, tmp_path: Path, capsys, keep_threads: None) -> None:
    """The mask IoU per frame and its summary, printed and in the JSON; no fit without --fit."""
    out_json = tmp_path / "masks.json"
    assert load("parser_masks").main(["--data", str(tiny_dream), "--limit", "2", "--json", str(out_json)]) == 0
    assert "mask IoU with the true silhouette" in capsys.readouterr().out
    result = json.loads(out_json.read_text())[tiny_dream.name]
    ious = [row["mask_iou"] for row in result["frames"]]
    assert len(ious) == result["summary"]["frames"] == 2 and all(0 <= iou <= 1 for iou in ious)
    assert "bands" not in result["summary"] and "add" not in result["frames"][0]


def test_parser_masks_split_the_frames_by_mask_iou_and_by_which_pose_fits_it_better() -> None:
    masks = load("parser_masks")
    figures = [(0.5, 0.2, 0.6), (0.0, float("inf"), 0.0), (0.85, 0.01, 0.85), (0.95, 0.04, 0.9), (1.0, 0.002, 0.995)]
    rows = [{"mask_iou": iou, "add": add, "fit_iou": fit_iou} for iou, add, fit_iou in figures]
    summary = masks.summary(rows, bad_mm=30.0)
    bands = summary["bands"]
    assert [b["frames"] for b in bands] == [2, 1, 2]  # an IoU of 1 is in the top band
    assert [b["bad"] for b in bands] == [2, 0, 1]  # a robot not found (ADD inf) is a bad estimate
    assert bands[0]["median_add_mm"] is None  # inf: strict JSON has none
    assert bands[2]["median_add_mm"] == pytest.approx(21.0)
    # of the fair masks (0.8 or more): the bad estimate's truth fits 0.05 better, the good ones' not 0.01
    assert summary["truth_fits_better"] == {"bad": [1, 1], "good": [0, 2]}


def test_wilson_interval_holds_the_share_and_narrows_with_frames() -> None:
    wilson = load("reliable_flag").wilson
    lo, hi = wilson(6, 41)
    assert lo == pytest.approx(0.069, abs=1e-3) and hi == pytest.approx(0.284, abs=1e-3)  # the textbook values
    assert wilson(60, 410)[1] - wilson(60, 410)[0] < hi - lo
    assert wilson(0, 10)[0] == pytest.approx(0.0, abs=1e-12) and 0 < wilson(0, 10)[1] < 0.3


def test_reliable_flag_fits_its_model_on_saved_features(tmp_path: Path, capsys) -> None:
    """``--features`` fits the model on what ``--json`` wrote (a robot not found among them),
    fitting no frame: it flags the bad estimates it is asked to and predicts each folder by the
    others; a bad file is one line."""
    flag = load("reliable_flag")
    rng = np.random.default_rng(0)

    def folder(n: int) -> dict[str, list]:
        edge = rng.uniform(0.3, 1.5, n)
        add = np.where(edge > 1.0, 0.1, 0.005)  # off where the outline is off the edges
        fixed = {
            "support": [0.6] * n,
            "spread": [2.0] * n,
            "inside": [1.0] * n,
            "depth_per_pixel": [10.0] * n,
            "inner_support": [0.6] * n,
        }
        return {"add": add.tolist(), "iou": rng.uniform(0.8, 0.95, n).tolist(), "edge_distance": edge.tolist(), **fixed}

    saved = [tmp_path / "a.json", tmp_path / "b.json"]
    for path in saved:
        frames = folder(60)
        # a robot not found, as --json writes it (infinite and unmeasured numbers null)
        lost = {"add": None, "iou": 0.0, "edge_distance": None, "support": 0.0, "spread": 0.0, "inside": 0.0,
                "depth_per_pixel": None, "inner_support": None}  # fmt: skip
        for key, value in lost.items():
            frames[key][0] = value
        path.write_text(json.dumps({"frames": {"features": frames}, "all": {"features": folder(2)}}))
    model = flag.fit_model({k: np.array(v) for k, v in folder(200).items()}, 0.9)
    assert model.weights["edge_distance"] > 0 and abs(model.weights["edge_distance"]) > abs(model.weights["iou"])
    assert flag.main(["--features", *map(str, saved), "--recall", "1"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("120 frames,") and "FLAG_MODEL = DoubtModel(" in out and "as shipped there" in out
    assert "recall 100.0 %" in out and "by a model fitted on the others" in out and f"{saved[1]}:frames" in out
    assert "FLAG_MODEL_WITHOUT_INNER = DoubtModel(" in out
    assert flag.main(["--features", str(tmp_path / "missing.json")]) == 2
    assert "--features" in capsys.readouterr().err
    # features written before the flag read the inner edges: one line that says so and what to do
    old = folder(10)
    del old["inner_support"]
    (tmp_path / "old.json").write_text(json.dumps({"frames": {"features": old}}))
    assert flag.main(["--features", str(tmp_path / "old.json")]) == 2
    err = capsys.readouterr().err
    assert "lack inner_support" in err and "--check" in err and len(err.strip().splitlines()) == 1


def test_reliable_flag_asks_for_frames() -> None:
    with pytest.raises(SystemExit):
        load("reliable_flag").main([])
    with pytest.raises(SystemExit):
        load("reliable_flag").main(["--data", "somewhere", "--json", "flag.json"])  # --json needs --check


def test_reliable_flag_refuses_a_missing_folder_before_fitting(tiny_dream: Path, tmp_path: Path, capsys) -> None:
    """A bad --data folder is named before the --check frames are fitted (minutes of work)."""
    missing = tmp_path / "nowhere"
    assert load("reliable_flag").main(["--check", str(tiny_dream), "--data", str(missing)]) == 2
    captured = capsys.readouterr()
    assert "nowhere" in captured.err and "the flag as shipped" not in captured.out


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["--designs", "concat", "--backbone", "efficientnet-lite0"], "--backbone efficientnet-lite0 needs --designs"),
        (["--designs", "concat", "--flow-weight", "1"], "--flow-weight needs --designs among"),
    ],
)
def test_denoiser_designs_refuses_a_design_its_options_do_not_fit(tmp_path: Path, args, words) -> None:
    from monose3.errors import Monose3Error

    with pytest.raises(Monose3Error, match=words):
        load("denoiser_designs").main([*args, "--out", str(tmp_path)])
