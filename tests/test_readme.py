"""The README's Python example runs as written (bundled model, bundled sample)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def readme_python_snippet() -> str:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    start = text.index("The same from Python")
    match = re.search(r"```python\n(.*?)```", text[start:], re.S)
    assert match, "no ```python block after 'The same from Python' in README.md"
    return match.group(1)


def test_readme_snippet_is_complete_and_runs(tmp_path):
    code = readme_python_snippet()
    for name in ("load_image", "load_joints", "load_camera", "monose3.Tracker"):
        assert name in code
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src"), "OMP_NUM_THREADS": "1"}
    res = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600
    )
    assert res.returncode == 0, res.stderr[-2000:]
    assert (tmp_path / "overlay.png").stat().st_size > 1000
    assert "True" in res.stdout or "False" in res.stdout  # each tracked frame's reliable flag printed
