"""The README's install command works on a fresh Python 3.11 venv with the pip it ships
(23.2.1 resolves without backtracking into ResolutionImpossible) and with the newest pip.

Slow (a real install, 1.5-3 minutes each): run when ``LRM_CVX_SLOW_TESTS=1`` (``.ci/run`` sets
it), so CI proves the README's command on every submission.
"""

from __future__ import annotations

import ensurepip
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def readme_install_command() -> str:
    """The ``pip install ...`` of the README's set-up block (so the test follows the README)."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    m = re.search(r"^(pip install [^\n&]+?)\s*(?:&&.*)?$", text, re.MULTILINE)
    assert m, "README has no 'pip install' line"
    return m[1]


def test_readme_install_command_is_the_dev_extra():
    assert readme_install_command() == 'pip install -e ".[dev]"'


@pytest.mark.slow
@pytest.mark.parametrize("pip", ["stock", "newest"])
def test_readme_install_in_a_fresh_venv(tmp_path, pip):
    base = getattr(sys, "_base_executable", sys.executable)  # the Python this venv came from
    venv = tmp_path / "venv"
    subprocess.run([base, "-m", "venv", str(venv)], check=True, timeout=300)
    py = venv / "bin" / "python"

    def run(*args, timeout=1800):
        return subprocess.run([str(py), *args], cwd=ROOT, capture_output=True, text=True,
                              timeout=timeout)

    version = run("-m", "pip", "--version").stdout.split()[1]
    if pip == "stock":  # exactly the pip the interpreter ships, as a new user has it
        assert version == ensurepip.version(), version
    else:
        assert run("-m", "pip", "install", "--quiet", "--upgrade", "pip").returncode == 0
    args = readme_install_command().split()[1:]  # install -e ".[dev]"
    proc = run("-m", "pip", *[a.strip('"') for a in args])
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "ResolutionImpossible" not in proc.stderr
    check = run("-c", "import lrm_cvx, distributed, s3fs, moto, boto3, hypothesis, pytest; "
                "print(lrm_cvx.__file__)")
    assert check.returncode == 0 and str(ROOT / "src") in check.stdout, check.stderr
    cli = subprocess.run([str(venv / "bin" / "lrm-cvx"), "--help"], capture_output=True,
                         text=True, timeout=300)
    assert cli.returncode == 0 and "usage: lrm-cvx" in cli.stdout
    # the README's own blocks run in the new environment
    tests = run("-m", "pytest", "-q", "-p", "no:cacheprovider", "tests/test_readme.py")
    assert tests.returncode == 0, tests.stdout[-3000:]
