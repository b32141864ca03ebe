"""Training the robot parser: whole synthetic images with their masks and keypoints, the loop, its files."""

import numpy as np
import pytest
import torch

from monose3.perception.config import ParserConfig
from monose3.training.checkpoints import export_parser, load_parser
from monose3.training.parser_loop import ParserBatchMaker, train_parser
from monose3.training.shards import read_shards

TINY = ParserConfig(input_size=(160, 120), batch_size=2, warmup_steps=1)


def test_batches_hold_images_visible_masks_and_keypoint_pixels():
    maker = ParserBatchMaker(TINY, torch.device("cpu"), start_step=0, workers=0)
    for step in range(3):  # one batch of each scene profile
        batch = maker.batch(step)
        assert batch.image.shape == (2, 3, 120, 160) and batch.image.min() >= 0 and batch.image.max() <= 1
        assert batch.mask.shape == (2, 1, 60, 80) and (batch.mask.flatten(1).sum(1) > 0).all()
        assert batch.keypoints.shape == (2, 7, 2)
        # where the mask says robot, a keypoint is near: the keypoints are in the image's pixels
        for mask, uv in zip(batch.mask[:, 0], batch.keypoints, strict=True):
            ys, xs = np.nonzero(mask.numpy() > 0.5)
            inside = (uv[:, 0] > 0) & (uv[:, 0] < 160) & (uv[:, 1] > 0) & (uv[:, 1] < 120)
            if inside.any() and len(xs):
                cells = np.stack([xs, ys], -1) * 2 + 0.5
                gap = np.linalg.norm(cells[None] - uv[inside].numpy()[:, None], axis=-1).min(1)
                assert np.median(gap) < 15


@pytest.mark.slow
def test_training_writes_shards_continues_and_exports(tmp_path):
    meta = train_parser(TINY, tmp_path / "a", steps=2, progress=False)
    assert meta["step"] == 2 and meta["samples"] == 4
    state, saved = read_shards(tmp_path / "a")
    assert saved["kind"] == "robot-parser" and any(k.startswith("trunk.") for k in state)
    meta = train_parser(TINY, tmp_path / "b", steps=3, init=tmp_path / "a", progress=False)
    assert meta["step"] == 3 and meta["samples"] == 6
    export_parser(tmp_path / "b", tmp_path / "parser.pt")
    a, b = load_parser(tmp_path / "b"), load_parser(tmp_path / "parser.pt")
    x = torch.rand(1, 3, 120, 160)
    with torch.no_grad():
        assert torch.allclose(a(x)[0], b(x)[0], atol=0.05)  # fp16 export
    assert (tmp_path / "b" / "log.csv").is_file()


@pytest.mark.parametrize(
    ("extra", "needle"),
    [
        ([], "budget"),
        (["--steps", "1", "--preset", "huge"], "unknown parser preset"),
        (["--minutes", "-1"], "positive"),
        (["--steps", "1", "--lr", "0"], "--lr must be positive"),
    ],
)
def test_train_parser_refuses_bad_options_in_one_line(tmp_path, capsys, extra, needle):
    from monose3.apps.cli import main

    assert main(["train-parser", "--out", str(tmp_path / "run"), *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0]
