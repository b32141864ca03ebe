"""Checkpoints: written atomically, and checked against the robot and preset on load."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from monose3.atomic import atomic_path
from monose3.errors import Monose3Error
from monose3.method.config import DESIGNS, ROTATION_OUTPUTS, Config
from monose3.method.denoiser import Denoiser
from monose3.method.designs import build_denoiser
from monose3.perception.config import PARSER_KIND, parser_config
from monose3.perception.parser import RobotParser
from monose3.training.formats import CHECKPOINT_FORMAT as FORMAT


def save_checkpoint(path: str | Path, state: dict[str, Any]) -> None:
    """Write ``state`` to ``path`` via a temporary file and an atomic rename, so a crash or
    ``kill -9`` leaves either the old or the new checkpoint, never a torn one."""
    with atomic_path(path) as tmp:
        torch.save({"format": FORMAT, **state}, tmp)


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    if path.is_dir():
        raise Monose3Error(f"checkpoint {path} is a folder; give the checkpoint file (.pt) inside it")
    if not path.is_file():
        raise Monose3Error(f"checkpoint not found: {path} (train one with `monose3 train` or omit --checkpoint)")
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as err:  # noqa: BLE001 - any unpickling failure means the same to the user
        raise Monose3Error(
            f"cannot read checkpoint {path}: {type(err).__name__}; is it a monose3 checkpoint?"
        ) from None
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise Monose3Error(f"{path} is not a monose3 checkpoint (expected format {FORMAT})")
    return state


def read_weights(path: str | Path) -> dict[str, Any]:
    """``{"model": state dict, "config": dict, "step": int, ...}`` from a .pt checkpoint or a shard set."""
    from monose3.training.shards import is_shard_set, read_shards

    if is_shard_set(path):
        weights, meta = read_shards(path)
        return {"model": weights, **meta}
    if Path(path).is_dir():
        raise Monose3Error(f"{path} is a folder without weights.json; pass a .pt checkpoint or a shard folder")
    return read_checkpoint(path)


def load_model(
    path: str | Path, robot: str | None = None, preset: str | None = None, device: str = "cpu"
) -> tuple[Denoiser, Config]:
    """The network and its configuration from a checkpoint or a shard set (a folder holding
    ``weights.json``, as ``monose3 train`` writes), in eval mode.

    ``robot``/``preset``, when given, must match what the checkpoint was trained for.
    """
    state = read_weights(path)
    config = Config.from_dict(state["config"])
    if robot is not None and config.robot != robot:
        raise Monose3Error(
            f"checkpoint {Path(path).name} was trained for robot {config.robot!r}, not {robot!r}; "
            f"use a {robot} checkpoint or --robot {config.robot}"
        )
    if preset is not None and config.preset != preset:
        raise Monose3Error(
            f"checkpoint {Path(path).name} uses preset {config.preset!r}, not {preset!r}; "
            f"pass --preset {config.preset} or train a {preset} model"
        )
    net = config.network
    if net.design not in DESIGNS or net.rotation_output not in ROTATION_OUTPUTS:
        raise Monose3Error(
            f"checkpoint {Path(path).name} holds a {net.design!r} denoiser with the {net.rotation_output!r} output, "
            "which monose3 no longer builds (removed after the design study, docs/DESIGNS.md); train a new model"
        )
    model = build_denoiser(net, pretrained=False)  # the checkpoint's weights replace them
    weights = {k: v.float() for k, v in state["model"].items()}
    model.load_state_dict(weights)
    return model.to(device).eval(), config


def export_model(checkpoint: str | Path, out: str | Path, half: bool = True) -> Path:
    """A shippable copy of a training checkpoint: weights (fp16 by default), configuration,
    robot and step; no optimiser state. ``load_model`` reads it like any checkpoint."""
    state = read_checkpoint(checkpoint)
    weights = {k: (v.half() if half and v.is_floating_point() else v) for k, v in state["model"].items()}
    slim = {"model": weights, "config": state["config"], "robot": state["config"]["robot"], "step": state["step"]}
    save_checkpoint(out, slim)
    return Path(out)


def load_parser(path: str | Path, device: str = "cpu") -> RobotParser:
    """A robot parser (:mod:`monose3.perception.parser`), in eval mode, from the file
    :func:`export_parser` writes or from a training run's shard folder."""
    return read_parser(path)[0].to(device).eval()


def read_parser(path: str | Path) -> tuple[RobotParser, dict]:
    """The parser in ``path`` (as :func:`load_parser` reads it, on the CPU) and its metadata
    (``step``, ``samples``, ``parser``: its configuration), from one read of the files."""
    from monose3.training.shards import is_shard_set, read_shards

    path = Path(path)
    if not path.exists():
        raise Monose3Error(f"robot parser weights not found: {path}; pass --parser FILE or reinstall monose3")
    if is_shard_set(path):
        state, meta = read_shards(path)
    else:
        meta = read_checkpoint(path)
        state = meta["model"]
    if meta.get("kind") != PARSER_KIND or not isinstance(meta.get("parser"), dict):
        raise Monose3Error(f"{path} holds no robot parser (a denoiser checkpoint?); pass the parser's weights")
    config = parser_config(meta["parser"])
    model = RobotParser(config, pretrained=False)
    try:
        model.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in state.items()})
    except RuntimeError as err:
        raise Monose3Error(f"{path}: weights do not fit the robot parser ({str(err)[:120]})") from None
    return model, meta


def export_parser(shards: str | Path, out: str | Path) -> Path:
    """A shippable fp16 file of a parser's training shards (what the package bundles)."""
    from monose3.training.shards import read_shards

    state, meta = read_shards(shards)
    return save_parser(state, out, {k: meta[k] for k in ("kind", "parser", "step", "samples")})


def save_parser(state: dict[str, torch.Tensor], out: str | Path, meta: dict[str, Any]) -> Path:
    """A parser's weights ``state`` as the fp16 file :func:`load_parser` reads, written atomically;
    ``meta`` holds ``kind`` and ``parser`` (its configuration) and whatever else describes it."""
    weights = {k: v.detach().cpu().half() if v.is_floating_point() else v.detach().cpu() for k, v in state.items()}
    save_checkpoint(out, {"model": weights, "robot": meta["parser"]["robot"], **meta})
    return Path(out)
