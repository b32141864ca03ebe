"""How fast the ``monose3`` command answers before any model loads: ``--help``, a command's
``--help`` and an input error (a missing image), each in a fresh subprocess.

Usage: ``python benchmarks/cli_speed.py [--repeat N]``

Prints the median wall-clock seconds of each against the goal (under 1 s) as PASS/MISS, and
whether torch or pybullet was imported (they must not be: the option parsers and the input
checks live in torch-free modules). The numbers depend on the machine and on what else runs
on it; nothing is asserted.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

from monose3.errors import run_reporting_errors

GOAL_S = 1.0
SRC = Path(__file__).resolve().parents[1] / "src"
PROBE = (
    "import sys\nfrom monose3.apps.cli import main\n"
    "try:\n    rc = main(sys.argv[1:])\nexcept SystemExit as e:\n    rc = e.code or 0\n"
    "print('HEAVY=' + ','.join(m for m in ('torch', 'pybullet') if m in sys.modules), file=sys.stderr)\n"
    "sys.exit(rc)\n"
)
CASES = {
    "monose3 --help": ["--help"],
    "monose3 estimate --help": ["estimate", "--help"],
    "monose3 estimate (missing image)": ["estimate", "--image", "nope.png", "--joints", "j.json", "--camera", "c.json"],
}


def time_case(args: list[str], repeat: int) -> tuple[float, int, str]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(SRC), os.environ.get("PYTHONPATH", "")])}
    times, rc, heavy = [], 0, ""
    for _ in range(repeat):
        tick = time.perf_counter()
        res = subprocess.run([sys.executable, "-c", PROBE, *args], env=env, capture_output=True, text=True)
        times.append(time.perf_counter() - tick)
        rc = res.returncode
        heavy = next((ln[6:] for ln in res.stderr.splitlines() if ln.startswith("HEAVY=")), "?")
    return statistics.median(times), rc, heavy or "none"


def run(repeat: int = 3) -> dict[str, float]:
    out = {}
    for name, args in CASES.items():
        seconds, rc, heavy = time_case(args, repeat)
        verdict = "PASS" if seconds < GOAL_S else "MISS"
        print(f"{name:<36} {seconds:6.3f} s  (goal < {GOAL_S:g} s: {verdict}; exit {rc}; heavy imports: {heavy})")
        out[name] = seconds
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeat", type=int, default=3, help="runs per case; the median is printed (default 3)")
    args = parser.parse_args()
    return run_reporting_errors(lambda: run(max(1, args.repeat)) and 0, "cli_speed")


if __name__ == "__main__":
    sys.exit(main())
