"""The robot parser's configuration and its named presets (torch-free, so the commands' option
checks can read them)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ParserConfig:
    """The parser's network and training. ``input_size`` (w, h): every image is brought to it
    (zero-padded to 4:3 and resized, as the estimator's standardised image)."""

    robot: str = "panda"
    input_size: tuple[int, int] = (320, 240)
    num_keypoints: int = 7
    decoder_width: int = 48
    batch_size: int = 16
    lr: float = 1e-3
    warmup_steps: int = 200
    keypoint_sigma: float = 1.0  # output cells: the Gaussian the keypoint target spreads over
    keypoint_weight: float = 1.0
    seed: int = 0


PARSER_KIND = "robot-parser"  # the ``kind`` of a parser's weight files


def parser_config(data: dict) -> ParserConfig:
    """A :class:`ParserConfig` from its saved dictionary (JSON turns tuples into lists)."""
    known = {f for f in ParserConfig.__dataclass_fields__}
    return ParserConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.items() if k in known})


PARSER_PRESETS = {"cpu": ParserConfig(), "gpu": ParserConfig(batch_size=96, lr=2e-3, warmup_steps=300)}
