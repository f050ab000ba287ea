"""The documentation runs as written: every Python block of the getting-started page and the
how-to guides executes in a fresh folder (blocks that need files the reader supplies, a NOAA
archive or a cluster, are named in ``NEEDS_READER_FILES`` and skipped)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

DOCS = Path(__file__).parents[1] / "docs"
PAGES = [DOCS / "getting-started.md", *sorted((DOCS / "howto").glob("*.md"))]
NEEDS_READER_FILES = ("open_ndvi_cdr(\"ndvi/", "Client(")


def _blocks() -> list[tuple[str, int, str]]:
    out = []
    for page in PAGES:
        for i, code in enumerate(re.findall(r"```python\n(.*?)```", page.read_text(), re.S)):
            if not any(s in code for s in NEEDS_READER_FILES):
                out.append((f"{page.relative_to(DOCS)}:{i}", i, code))
    return out


BLOCKS = _blocks()


def test_the_pages_have_python_blocks():
    assert len(BLOCKS) >= 6, [b[0] for b in BLOCKS]


@pytest.mark.parametrize("name,index,code", BLOCKS, ids=[b[0] for b in BLOCKS])
def test_a_documented_block_runs(name, index, code, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    exec(compile(code, name, "exec"), {"__name__": "__docs__"})


# ------------------------------------------------------------- docs are for users, not history
ROOT = Path(__file__).parents[1]
HISTORY = re.compile(
    r"\b[Ss]essions? \d+"                      # numbered rounds of the work
    r"|\b[Ii]ssues? #?\d+"                       # issue numbers
    r"|(?:^|[\s(])#\d{1,3}\b(?![\"';\w])"        # "#24" (not a colour such as "#000")
    r"|/work/|/root/|/home/\w+/"                 # paths of a development machine
    r"|\b(?:this|last|previous) session\b"
    r"|\bH\d\b")                               # the work's helpers ("H4")
SCANNED = ("src", "docs", "notebooks", "benchmarks")
SUFFIXES = {".py", ".md", ".ipynb", ".rst", ".txt", ".toml", ".cfg"}


def history_lines(root: Path = ROOT) -> list[str]:
    """``path:line: text`` of every line under :data:`SCANNED` citing the work's history."""
    found = []
    for top in SCANNED:
        for path in sorted((root / top).rglob("*")):
            if (path.suffix not in SUFFIXES or not path.is_file() or "_build" in path.parts
                    or "generated" in path.parts):
                continue
            for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
                if HISTORY.search(line):
                    found.append(f"{path.relative_to(root)}:{i}: {line.strip()[:120]}")
    return found


def test_the_pattern_catches_history_and_spares_colours_and_code():
    for text in ("measured in session 39", "(issue #24, item 3)", "see #25 item 6",
                 "Issue 13 targets", "/work/exp39/pieces.patch", "the last session's field",
                 "2026-11-23 (H4)"):
        assert HISTORY.search(text), text
    for text in ("text-shadow:0 0 2px #000\">", "# 2 cores", "H2O's GLRM", "x = y  # 30 s",
                 "color='#1f77b4'", "sessions of the robot"):
        assert not HISTORY.search(text), text


def test_no_history_in_src_docs_notebooks_or_benchmarks():
    found = history_lines()
    assert not found, ("the history of the work belongs in commit messages:\n"
                       + "\n".join(found[:50]))
