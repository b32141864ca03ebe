"""The parser's adaptation to a user's frames: labelled views, the split, the guard, the command."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from monose3.adaptation import (
    AdaptConfig,
    HeldOutFits,
    adapt_parser,
    guard_keeps,
    save_adapted_parser,
    split_frames,
)
from monose3.apps.arguments import ADAPTED_PARSER_FILE
from monose3.apps.cli import main
from monose3.data.datasets import open_dataset
from monose3.data.scenes.sequences import SequenceConfig, write_sequence
from monose3.errors import Monose3Error
from monose3.perception.views import parse_image
from monose3.training.checkpoints import load_parser
from monose3.training.scene_views import LabelledFrame, SceneViews

SIZE = (320, 240)


@pytest.fixture(scope="module")
def scene_folder(tmp_path_factory):
    """Six frames of a static camera on a clear scene, the robot moving."""
    out = tmp_path_factory.mktemp("adapt") / "scene"
    return write_sequence(out, SequenceConfig(frames=6, camera="static"), seed=5, profile="reallike", size=SIZE)


@pytest.fixture(scope="module")
def estimator():
    from monose3.api import load_estimator

    est = load_estimator()
    yield est
    est.close()


def fits(reliable: list[bool], quality: list[float]) -> HeldOutFits:
    return HeldOutFits(np.tile(np.eye(4), (len(reliable), 1, 1)), np.array(reliable), np.array(quality))


# ---- labelled views ---------------------------------------------------------------------------


def test_view_labels_lie_on_the_robot_in_every_kind_of_view(models, renderers, sample_view):
    """An image whose pixels are the robot's own silhouette: every view's label (the render at
    the view's intrinsics) must match the view's pixels, whole, zoomed, jittered or widened."""
    model, renderer = models["panda"], renderers["panda"]
    rng = np.random.default_rng(4)
    frames = []
    for _ in range(3):
        v = sample_view(model, rng, size=(640, 480), dist=(1.5, 2.5))
        mask = renderer.silhouettes(v.joints[None], v.pose[None], v.K[None], v.size)[0].numpy()
        frames.append(LabelledFrame(np.repeat(mask[..., None], 3, 2).astype(np.uint8) * 255, v.K, v.joints, v.pose))
    views = SceneViews(frames, model, renderer, SIZE, seed=1)
    batch = views.batch(12, torch.device("cpu"))
    assert batch.image.shape == (12, 3, SIZE[1], SIZE[0]) and batch.mask.shape == (12, 1, SIZE[1] // 2, SIZE[0] // 2)
    pixels = torch.nn.functional.avg_pool2d(batch.image[:, :1], 2)
    for seen, label in zip(pixels, batch.mask, strict=True):
        inter = (torch.minimum(seen, label)).sum()
        assert label.sum() > 20 and inter / torch.maximum(seen, label).sum() > 0.9
    # The keypoints project through the same crops: they lie on (or right next to) the robot.
    cells = (batch.keypoints / 2).round().long().clamp(min=0)
    on_robot = [
        float(pixels[i, 0, c[:, 1].clamp(max=SIZE[1] // 2 - 1), c[:, 0].clamp(max=SIZE[0] // 2 - 1)].mean())
        for i, c in enumerate(cells)
    ]
    assert np.median(on_robot) > 0.5


def test_split_holds_out_every_fourth_frame_and_spreads_long_sequences():
    frames = list(range(10))
    adapt_on, held = split_frames(frames, 4, 40)
    assert held == [2, 6] and adapt_on == [0, 1, 3, 4, 5, 7, 8, 9]
    assert split_frames([0, 1], 4, 40) == ([0], [1])
    adapt_on, held = split_frames(list(range(400)), 4, 40)
    assert len(adapt_on) + len(held) == 40 and adapt_on[0] == 0 and adapt_on[-1] == 399
    with pytest.raises(Monose3Error, match="at least 2 frames"):
        split_frames([0], 4, 40)


def test_guard_keeps_only_more_reliable_and_better_fitting_parsers():
    before = fits([True, False, True], [1.2, 0.6, 1.3])
    assert guard_keeps(before, fits([True, True, True], [1.3, 1.2, 1.4]))
    assert not guard_keeps(before, fits([True, False, False], [1.5, 1.5, 1.5]))  # fewer reliable
    assert not guard_keeps(before, fits([True, False, True], [1.2, 0.6, 1.3]))  # no better
    assert fits([True], [1.0]).summary(np.eye(4))["median_distance_to_fused_mm"] == 0.0


# ---- the whole adaptation, with the bundled parser ----------------------------------------------


@pytest.mark.slow
def test_a_harmful_fine_tuning_is_refused_and_the_parser_kept(estimator, scene_folder):
    frames = list(open_dataset(scene_folder, estimator.robot))
    original = estimator.parser
    reference = parse_image(original, frames[1].load_image(), frames[1].K).mask.clone()
    wrecking = AdaptConfig(steps=3, lr=0.5, warmup_steps=1, synthetic_per_step=1, views_per_step=2)
    result = adapt_parser(estimator, frames, wrecking, static_camera=True)
    assert result.steps == 3 and result.labels == "fused" and result.held_out_frames == ["000002"]
    assert not result.adapted and estimator.parser is original and result.parser is original
    assert "kept the original parser" in result.verdict
    assert result.after["median_iou_plus_support"] < result.before["median_iou_plus_support"]
    assert result.picture is not None and result.picture.shape[2] == 3  # the held-out frame, before | after
    assert result.picture.shape[1] > 2 * result.picture.shape[0]
    # The parser that stays was not touched by the fine-tuning of its copy.
    assert torch.equal(parse_image(original, frames[1].load_image(), frames[1].K).mask, reference)


@pytest.mark.slow
def test_adapt_command_writes_a_parser_only_when_kept(scene_folder, tmp_path, capsys):
    out = tmp_path / "adapted.pt"
    rc = main(["adapt", "--frames", str(scene_folder), "--out", str(out), "--static-camera", "--adapt-steps", "2",
               "--limit", "4"])  # fmt: skip
    printed = capsys.readouterr().out
    assert rc == 0 and "held-out frames: reliable" in printed
    if "kept the adapted parser" in printed:
        assert load_parser(out).config.input_size == SIZE and out.with_suffix(".png").exists()
    else:
        assert not out.exists() and not out.with_suffix(".png").exists() and "nothing written" in printed


@pytest.mark.slow
@pytest.mark.parametrize("command", ["calibrate", "track"])
def test_calibrate_and_track_adapt_first(command, scene_folder, tmp_path, capsys):
    out = tmp_path / command
    extra = ["--gif-every", "0", "--static-camera"] if command == "track" else ["--overlay-frames", "0"]
    args = ["--frames", str(scene_folder), "--out", str(out), "--limit", "4", "--adapt", "--adapt-steps", "1"]
    rc = main([command, *args, *extra])
    printed = capsys.readouterr().out
    assert rc == 0 and "adapting the parser to 4 frames" in printed and "held-out frames: reliable" in printed
    kept = "kept the adapted parser" in printed
    assert (out / ADAPTED_PARSER_FILE).exists() == kept == (out / ADAPTED_PARSER_FILE).with_suffix(".png").exists()
    assert (out / ("calibration.json" if command == "calibrate" else "poses.jsonl")).exists()


@pytest.mark.slow
def test_saved_adapted_parser_loads_and_says_how_it_was_made(estimator, scene_folder, tmp_path):
    frames = list(open_dataset(scene_folder, estimator.robot))[:4]
    result = adapt_parser(estimator, frames, AdaptConfig(steps=1, synthetic_per_step=1, views_per_step=2))
    result.parser = result.candidate
    path = save_adapted_parser(result, tmp_path / "p.pt")
    loaded = load_parser(path)
    state = result.candidate.state_dict()
    assert all(torch.allclose(v.float(), state[k].float(), atol=1e-2) for k, v in loaded.state_dict().items())
    assert torch.load(path, weights_only=False)["adapted"]["steps"] == 1
    estimator.parser = result.candidate if result.adapted else estimator.parser


# ---- bad input ----------------------------------------------------------------------------------


def test_adapt_refuses_bad_input_in_one_line_and_writes_nothing(scene_folder, tmp_path, capsys):
    out = tmp_path / "p.pt"
    single = tmp_path / "single"
    single.mkdir()
    for name in ("000000.json", "000000.rgb.jpg", "_camera_settings.json"):
        (single / name).write_bytes((scene_folder / name).read_bytes())
    cases = [
        (["--frames", str(single)], "at least 2 frames"),
        (["--frames", str(tmp_path / "missing")], "not found"),
        (["--frames", str(scene_folder), "--adapt-steps", "0"], "--adapt-steps"),
        (["--frames", str(scene_folder), "--adapt-minutes", "-1"], "--adapt-minutes must be positive"),
    ]
    for args, message in cases:
        assert main(["adapt", *args, "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1
    assert main(["adapt", "--frames", str(scene_folder), "--out", str(tmp_path)]) == 2
    assert "is a folder" in capsys.readouterr().err
    assert main(["adapt", "--frames", str(scene_folder), "--out", str(tmp_path / "p.txt")]) == 2
    assert "unsupported extension" in capsys.readouterr().err
    assert main(["calibrate", "--frames", str(single), "--adapt"]) == 2
    assert "at least 2 frames" in capsys.readouterr().err
    assert main(["track", "--video", str(tmp_path / "v.mp4"), "--adapt"]) == 2
    assert not out.exists()


@pytest.mark.slow
def test_adapt_refuses_frames_without_a_reliable_fit(scene_folder, tmp_path, capsys):
    """Frames where no robot can be seen (the joints and camera of real frames, blank images)."""
    import cv2

    blank = tmp_path / "blank"
    blank.mkdir()
    for path in scene_folder.iterdir():
        if path.name.endswith(".rgb.jpg"):
            cv2.imwrite(str(blank / path.name), np.full((SIZE[1], SIZE[0], 3), 128, np.uint8))
        else:
            (blank / path.name).write_bytes(path.read_bytes())
    out = tmp_path / "p.pt"
    assert main(["adapt", "--frames", str(blank), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()  # the frames' progress bar, then the one line
    assert err.splitlines()[-1].startswith("monose3 adapt: error: no reliable fit") and "Traceback" not in err
    assert not out.exists()
