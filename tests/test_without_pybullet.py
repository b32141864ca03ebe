"""monose3 needs no pybullet: with its import blocked, the demo, the Python API, synthetic data
generation and training all run (pybullet stays an optional reference renderer)."""

from __future__ import annotations

import subprocess
import sys
import textwrap

BLOCK = textwrap.dedent(
    """
    import importlib.abc, sys

    class NoPybullet(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in ("pybullet", "pybullet_data"):
                raise ImportError(f"{name} is blocked for this test")
            return None

    sys.meta_path.insert(0, NoPybullet())
    """
)

SCRIPT = textwrap.dedent(
    """
    import sys
    from pathlib import Path
    from monose3.apps.cli import main

    out = Path(sys.argv[1])
    assert main(["demo", "--out", str(out / "demo")]) == 0
    assert main(["generate", "--out", str(out / "gen"), "--num", "1", "--workers", "0", "--size", "160x120"]) == 0
    assert main(["train", "--synthetic", "--data", str(out / "gen"), "--out", str(out / "run"), "--steps", "2",
                 "--batch-size", "2", "--workers", "0"]) == 0
    assert main(["generate", "--out", str(out / "ref"), "--num", "1", "--renderer", "tiny"]) == 2
    assert not any(name.startswith("pybullet") for name in sys.modules)
    print("ok")
    """
)


def test_the_package_runs_without_pybullet(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-c", BLOCK + SCRIPT, str(tmp_path)], capture_output=True, text=True, timeout=600
    )
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    assert proc.stdout.strip().endswith("ok")
    assert "needs pybullet" in proc.stderr  # the optional reference renderer says what it needs
