"""Model weights as shards that travel: half-precision files of at most 16 MiB each plus a
small ``weights.json`` (configuration, step, samples seen, loss parts, each shard's SHA-256).

A remote GPU machine may return only a few files of at most 16 MiB per call, so a training run writes its
weights this way every minute; ``monose3 train --init`` and ``--checkpoint`` read them back.
Each save writes new shard files named by the step, then the JSON atomically, then removes
the previous shards: a run killed at any moment leaves one consistent set.
"""

from __future__ import annotations

import hashlib
import io
import json
from pathlib import Path
from typing import Any

import torch

from monose3.atomic import write_bytes, write_text
from monose3.errors import Monose3Error
from monose3.training.formats import SHARD_INDEX as INDEX

FORMAT = "monose3-shards-v1"
SHARD_BYTES = 15 * 2**20  # under 16 MiB per file (what a remote machine returns), with room for pickling


def _serialise(tensors: dict[str, torch.Tensor]) -> bytes:
    buf = io.BytesIO()
    torch.save(tensors, buf)
    return buf.getvalue()


def split_state(state: dict[str, torch.Tensor], limit: int = SHARD_BYTES) -> list[dict[str, torch.Tensor]]:
    """Half-precision copies of ``state``'s floats, packed in order into groups under ``limit`` bytes."""
    groups: list[dict[str, torch.Tensor]] = [{}]
    size = 0
    for name, value in state.items():
        value = value.detach().cpu()
        value = value.half() if value.is_floating_point() else value
        nbytes = value.numel() * value.element_size()
        if nbytes > limit:
            raise Monose3Error(f"tensor {name} ({nbytes / 2**20:.1f} MiB) does not fit one shard")
        if size + nbytes > limit and groups[-1]:
            groups.append({})
            size = 0
        groups[-1][name] = value.contiguous()
        size += nbytes
    return groups


def write_shards(folder: str | Path, state: dict[str, torch.Tensor], meta: dict[str, Any]) -> Path:
    """Write ``state`` (a model state dict) and ``meta`` (config, step, samples, losses) to ``folder``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    step = int(meta.get("step", 0))
    entries = []
    for i, group in enumerate(split_state(state)):
        data = _serialise(group)
        name = f"weights-{step:08d}-{i:02d}.pt"
        write_bytes(folder / name, data)
        entries.append({"file": name, "sha256": hashlib.sha256(data).hexdigest(), "tensors": list(group)})
    index = folder / INDEX
    previous = _listed_files(index)
    write_text(index, json.dumps({"format": FORMAT, **meta, "shards": entries}, indent=1))
    for name in previous - {e["file"] for e in entries}:
        (folder / name).unlink(missing_ok=True)
    return index


def _listed_files(index: Path) -> set[str]:
    try:
        return {e["file"] for e in json.loads(index.read_text())["shards"]}
    except (OSError, ValueError, KeyError, TypeError):
        return set()


def is_shard_set(path: str | Path) -> bool:
    path = Path(path)
    return path.name == INDEX or (path.is_dir() and (path / INDEX).is_file())


def read_shards(path: str | Path) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """The float32 state dict and the metadata of a shard set (its folder or its ``weights.json``).
    A missing, altered or truncated shard is an error that names it."""
    path = Path(path)
    index = path if path.name == INDEX else path / INDEX
    if not index.is_file():
        raise Monose3Error(f"no {INDEX} in {path}; pass a folder written by `monose3 train` or a .pt checkpoint")
    try:
        meta = json.loads(index.read_text())
        entries = meta.pop("shards")
    except (ValueError, KeyError) as err:
        raise Monose3Error(f"{index} is not a monose3 shard index ({err}); rewrite it with `monose3 train`") from None
    if meta.get("format") != FORMAT:
        raise Monose3Error(f"{index} is not a monose3 shard index (expected format {FORMAT})")
    state: dict[str, torch.Tensor] = {}
    for entry in entries:
        file = index.parent / entry["file"]
        if not file.is_file():
            raise Monose3Error(f"shard {file.name} listed in {index} is missing; copy every weights-*.pt file")
        data = file.read_bytes()
        if hashlib.sha256(data).hexdigest() != entry["sha256"]:
            raise Monose3Error(f"shard {file.name} is corrupt (checksum mismatch); copy it again")
        part = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
        state.update({k: v.float() if v.is_floating_point() else v for k, v in part.items()})
    return state, meta
