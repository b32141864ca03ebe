"""The front door: the README stays short, links resolve, figures are linked, and the project's
files speak of the project only (not of how it was worked on)."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MAX_README_LINES = 250
# Words about how the project was worked on, not about what it does. Spelt with escapes (\x20 a
# space, \x65 an e) so that this file itself holds none of them and the same search, run with
# git grep over the repository, finds nothing either.
PROCESS_WORDS = re.compile(r"[a-z]+th\x20session|this\x20session|\bl\x65nt\b|\bl\x65ases?\b|issue\x20[0-9]", re.I)
TEXT_SUFFIXES = {".md", ".py", ".toml", ".txt", ".json", ".yaml", ".yml", ".cfg", ".sh", ""}
LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")


def tracked_files() -> list[Path]:
    """The files git tracks (a clean clone's), or every file outside .git and the venv."""
    try:
        out = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout
        return [ROOT / line for line in out.splitlines() if line]
    except (OSError, subprocess.CalledProcessError):
        skip = {".git", ".venv", "__pycache__", "data", "runs"}
        return [p for p in ROOT.rglob("*") if p.is_file() and not skip & set(p.relative_to(ROOT).parts)]


def markdown_files() -> list[Path]:
    return [ROOT / "README.md", ROOT / "CHANGELOG.md", *sorted((ROOT / "docs").glob("*.md"))]


def test_readme_is_short():
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) <= MAX_README_LINES, f"README.md has {len(lines)} lines (at most {MAX_README_LINES})"


def test_process_words_are_found():
    """Guards the next test against a pattern that matches nothing."""
    samples = ("the nineteenth\x20session's run", "on a l\x65nt GPU", "l\x65ase 2", "see issue\x2011")
    assert all(PROCESS_WORDS.search(s) for s in samples)
    assert not PROCESS_WORDS.search("the robot's eighth link; a silent failure; released")


def test_the_project_speaks_of_itself_only():
    hits = []
    for path in tracked_files():
        if path.suffix not in TEXT_SUFFIXES or not path.is_file():
            continue
        for number, line in enumerate(path.read_text(encoding="utf-8", errors="ignore").splitlines(), 1):
            if PROCESS_WORDS.search(line):
                hits.append(f"{path.relative_to(ROOT)}:{number}: {line.strip()[:100]}")
    assert not hits, f"{len(hits)} line(s) about how the work was done:\n  " + "\n  ".join(hits)


def test_local_links_resolve():
    broken = []
    for doc in markdown_files():
        for target in LINK.findall(doc.read_text(encoding="utf-8")):
            if "://" in target or target.startswith("mailto:"):
                continue
            if not (doc.parent / target).exists():
                broken.append(f"{doc.relative_to(ROOT)} -> {target}")
    assert not broken, "broken links:\n  " + "\n  ".join(broken)


def test_every_figure_in_docs_results_is_referenced():
    """A figure or result file nothing names (no document, benchmark or test) is not kept."""
    texts = "\n".join(
        p.read_text(encoding="utf-8", errors="ignore")
        for p in [*markdown_files(), *ROOT.glob("benchmarks/*.py"), *ROOT.glob("tests/*.py"), *ROOT.glob("src/**/*.py")]
    )
    unreferenced = [p.name for p in sorted((ROOT / "docs" / "results").iterdir()) if p.name not in texts]
    assert not unreferenced, f"files in docs/results that nothing names: {unreferenced}"
