"""The file formats of models, without torch: checkpoint and weight-shard names, and the robot a
checkpoint was trained for, read from its pickle with every tensor skipped, so a command can
check the user's joints against the right robot before the model loads."""

from __future__ import annotations

import json
import pickle
import zipfile
from pathlib import Path

from monose3.errors import Monose3Error
from monose3.robot import get_spec, robot_reference

CHECKPOINT_FORMAT = "monose3-checkpoint-v1"
SHARD_INDEX = "weights.json"  # the index file of a shard set (monose3.training.shards)
BUNDLED_CHECKPOINT = Path(__file__).resolve().parent.parent / "assets" / "panda_cpu.pt"
BUNDLED_PARSER = BUNDLED_CHECKPOINT.with_name("panda_parser.pt")  # the robot parser (perception.parser)
BUNDLED_PARSER_ROBOT = "panda"


class _PeekUnpickler(pickle.Unpickler):
    """Reads a torch checkpoint's dictionary with every tensor replaced by None."""

    def find_class(self, module: str, name: str):  # noqa: ANN201
        if module.startswith("torch") or module == "numpy" or module.startswith("numpy."):
            return lambda *a, **k: None
        if module == "collections" and name == "OrderedDict":
            import collections

            return collections.OrderedDict
        raise pickle.UnpicklingError(f"unexpected {module}.{name}")

    def persistent_load(self, pid):  # noqa: ANN001, ANN201
        return None


def checkpoint_robot(path: str | Path | None) -> str | None:
    """The robot a checkpoint was trained for, read without torch; None when the file is not a
    zip checkpoint this reader understands (then the torch loader decides)."""
    p = BUNDLED_CHECKPOINT if path is None else Path(path)
    if not p.exists():
        if path is None:
            raise Monose3Error(f"the bundled model {p.name} is missing; reinstall monose3 or pass --checkpoint")
        raise Monose3Error(f"checkpoint not found: {p} (train one with `monose3 train` or omit --checkpoint)")
    index = p if p.name == SHARD_INDEX else p / SHARD_INDEX
    if index.is_file():  # a shard set written by `monose3 train`
        try:
            robot = json.loads(index.read_text())["config"]["robot"]
        except (ValueError, KeyError, TypeError):
            raise Monose3Error(f"{index} is not a monose3 shard index; rewrite it with `monose3 train`") from None
        return robot if isinstance(robot, str) else None
    if p.is_dir():
        inside = sorted(p.glob("*.pt"))
        hint = f" such as {inside[0]}" if inside else ""
        raise Monose3Error(
            f"checkpoint {p} is a folder without weights.json; give a run folder or a checkpoint file (.pt){hint}"
        )
    try:
        with zipfile.ZipFile(p) as z:
            name = next(n for n in z.namelist() if n.endswith("/data.pkl") or n == "data.pkl")
            with z.open(name) as fh:
                state = _PeekUnpickler(fh).load()
    except (zipfile.BadZipFile, StopIteration, pickle.UnpicklingError, EOFError, OSError, AttributeError, TypeError):
        return None
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        raise Monose3Error(f"{p} is not a monose3 checkpoint (expected format {CHECKPOINT_FORMAT})")
    config = state.get("config")
    robot = config.get("robot") if isinstance(config, dict) else None
    return robot if isinstance(robot, str) else None


def check_checkpoint(path: str | Path | None, robot: str | None = None) -> str | None:
    """The robot name to check inputs against before the model loads: ``robot`` (which must
    exist and match the checkpoint's) or the checkpoint's own. None: not known until loading."""
    if robot is not None:
        get_spec(robot)
        robot = robot_reference(robot)
    found = checkpoint_robot(path)
    if robot is not None and found is not None and found != robot:
        name = Path(path).name if path is not None else BUNDLED_CHECKPOINT.name
        raise Monose3Error(
            f"checkpoint {name} was trained for robot {found!r}, not {robot!r}; use a {robot} checkpoint or "
            f"--robot {found}"
        )
    return robot or found
