"""The command shell: every command module is cheap to import (its heavy imports live in run_<name>)."""

from __future__ import annotations

import subprocess
import sys

from monose3.apps.cli import COMMANDS, build_parser


def test_every_command_module_imports_without_torch_or_pybullet():
    code = (
        "import importlib, sys\n"
        "from monose3.apps.cli import COMMANDS\n"
        "for module, _ in COMMANDS.values(): importlib.import_module(module)\n"
        "print(sorted(m for m in ('torch', 'pybullet', 'monose3.estimator') if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_every_command_has_its_options_checks_and_run_in_its_own_module():
    from importlib import import_module

    parser = build_parser()
    for name, (module, _) in COMMANDS.items():
        mod, fn = import_module(module), name.replace("-", "_")
        for part in (f"add_{fn}_arguments", f"check_{fn}", f"run_{fn}"):
            assert callable(getattr(mod, part, None)), f"{module} lacks {part}"
    assert parser.parse_args(["demo"]).command == "demo"
