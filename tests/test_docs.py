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
