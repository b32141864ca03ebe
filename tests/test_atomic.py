"""atomic: an output file is the old one or the new one, never a partial one."""

import json
import math
import os

import numpy as np
import pytest

from monose3.atomic import atomic_path, json_number, write_bytes, write_text


def test_write_replaces_and_creates_folders(tmp_path):
    target = tmp_path / "a" / "b" / "out.json"
    write_text(target, "one")
    write_text(target, "two")
    assert target.read_text() == "two"
    write_bytes(target, b"\x00\x01")
    assert target.read_bytes() == b"\x00\x01"
    assert os.listdir(target.parent) == ["out.json"]  # no temporary file left behind


def test_a_failed_write_keeps_the_old_file_and_leaves_nothing(tmp_path):
    target = tmp_path / "out.txt"
    write_text(target, "old")
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("interrupted")
    assert target.read_text() == "old"
    assert os.listdir(tmp_path) == ["out.txt"]


def test_the_temporary_file_keeps_the_extension_and_the_umask_mode(tmp_path):
    target = tmp_path / "plot.png"
    with atomic_path(target) as tmp:
        assert tmp.suffix == ".png" and tmp.parent == tmp_path  # writers that pick the format by name
        tmp.write_bytes(b"png")
    mask = os.umask(0)
    os.umask(mask)
    assert target.stat().st_mode & 0o777 == 0o666 & ~mask


def test_json_number_turns_missing_and_non_finite_values_into_none():
    assert [json_number(v) for v in (None, math.nan, math.inf, -math.inf)] == [None] * 4
    value = json_number(np.float32(1.5))
    assert value == 1.5 and type(value) is float
    json.dumps([json_number(v) for v in (np.float64(2.0), math.nan)], allow_nan=False)
