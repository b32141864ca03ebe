"""The evidence denoiser's training data (training/evidence_cache.py): the parser's outputs on
synthesised scenes cached in resumable shards, augmented like the parser's mistakes, turned into
training batches; and ``monose3 train --preset evidence`` on them, with its refusals."""

from __future__ import annotations

import pytest
import torch

from monose3.apps import cli
from monose3.method.config import get_preset
from monose3.method.evidence import EVIDENCE_CHANNELS, Evidence
from monose3.method.scheduler import make_noiser
from monose3.robot.renderer import RobotRenderer
from monose3.training.checkpoints import load_parser
from monose3.training.evidence_cache import EvidenceCache, evidence_batch, make_cache, parser_mistakes, shard_path
from monose3.training.formats import BUNDLED_PARSER


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    out = tmp_path_factory.mktemp("evidence")
    make_cache(out, 4, 0, load_parser(BUNDLED_PARSER), image_size=(320, 240), progress=False, shard_samples=2)
    return out


def test_the_cache_holds_the_parsers_evidence_and_resumes_by_shard(cache, panda):
    assert shard_path(cache, 0).is_file() and shard_path(cache, 1).is_file()
    data = EvidenceCache([cache])
    assert len(data) == 4
    assert data.arrays["mask"].dtype == torch.uint8 and data.arrays["mask"].shape == (4, 240, 320)
    assert data.arrays["keypoints"].shape == (4, len(panda.keypoint_names), 2)
    assert (data.arrays["mask"].flatten(1).amax(1) > 200).all()  # the parser found each robot
    before = shard_path(cache, 0).stat().st_mtime_ns
    make_cache(cache, 4, 0, load_parser(BUNDLED_PARSER), image_size=(320, 240), progress=False, shard_samples=2)
    assert shard_path(cache, 0).stat().st_mtime_ns == before  # complete shards are kept


def test_the_parsers_mistakes_are_drawn_from_the_generator(cache):
    samples = EvidenceCache([cache]).take(torch.arange(4))
    ev = Evidence(samples["mask"][:, None].float() / 255, samples["box"], samples["keypoints"], samples["confidence"])
    a, b = (parser_mistakes(ev, torch.Generator().manual_seed(3)) for _ in range(2))
    assert torch.equal(a.mask, b.mask) and torch.equal(a.keypoints, b.keypoints)
    drawn = [parser_mistakes(ev, torch.Generator().manual_seed(seed)) for seed in range(5)]
    changed = [not (torch.equal(x.mask, ev.mask) and torch.equal(x.confidence, ev.confidence)
                    and torch.equal(x.keypoints, ev.keypoints)) for x in drawn]  # fmt: skip
    assert any(changed)


def test_a_training_batch_from_the_cache(cache, panda):
    config = get_preset("evidence")
    samples = EvidenceCache([cache]).take(torch.arange(4))
    batch = evidence_batch(samples, panda, RobotRenderer(panda), make_noiser(config.diffusion), config,
                           torch.Generator().manual_seed(0), torch.device("cpu"))  # fmt: skip
    assert batch["render"].shape == batch["crop"].shape == (4, EVIDENCE_CHANNELS, 48, 64)
    assert batch["render"][:, 0].flatten(1).amax(1).min() == 1 and (batch["t"] >= 1).all()


def test_train_command_on_the_cache_and_its_refusals(cache, tmp_path, capsys):
    out = tmp_path / "run"
    argv = ["train", "--preset", "evidence", "--evidence", str(cache), "--steps", "2", "--batch-size", "4"]
    assert cli.main([*argv, "--out", str(out)]) == 0
    assert (out / "weights.json").is_file() and "trained to step 2" in capsys.readouterr().out
    cases = [
        (["train", "--evidence", str(cache)], "--preset evidence"),
        (["train", "--preset", "evidence", "--synthetic"], "--preset evidence"),
        (["train", "--preset", "evidence", "--evidence", str(cache), "--synthetic"], "alone"),
        (["train", "--preset", "evidence", "--evidence", str(tmp_path / "none")], "--evidence"),
    ]
    for extra, message in cases:
        assert cli.main([*extra, "--out", str(tmp_path / "no")]) == 2
        err = capsys.readouterr().err.strip()
        assert message in err and "\n" not in err, err
