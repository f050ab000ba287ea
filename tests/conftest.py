"""Shared test fixtures.

``inputs_unchanged`` ("never write onto an input"): register every input file or folder
of a command with ``inputs_unchanged.watch(path, ...)`` before running it; at teardown (or on
``inputs_unchanged.check()``) the test fails if any watched file changed (SHA-256 of its bytes),
disappeared, or if a file appeared in or vanished from a watched folder. Use it in every
bad-input test: ``tests/test_bad_inputs*.py``.

``refits`` (the validated choices never read ahead): every model the validation refits through
``calibration.clone_model`` records ``(its overrides, the snapshots it was fitted on)``.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import pytest


def _digest(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def tree_state(*paths: str | os.PathLike) -> dict[str, str]:
    """``{file: sha256}`` of every file under ``paths`` (files, or folders walked recursively);
    a watched folder also records its own listing, so new or removed files show up."""
    state: dict[str, str] = {}
    for p in map(Path, paths):
        if p.is_dir():
            names = []
            for root, _, files in os.walk(p):
                for name in files:
                    f = Path(root) / name
                    state[str(f)] = _digest(f)
                    names.append(str(f.relative_to(p)))
            state[f"{p}/<listing>"] = "\n".join(sorted(names))
        elif p.exists():
            state[str(p)] = _digest(p)
        else:
            state[str(p)] = "<missing>"
    return state


class InputGuard:
    """Checksums of watched inputs, compared on :meth:`check`."""

    def __init__(self) -> None:
        self._before: dict[str, str] = {}
        self._paths: list[Path] = []

    def watch(self, *paths: str | os.PathLike) -> InputGuard:
        """Record the current content of ``paths`` (files or folders)."""
        self._paths += [Path(p) for p in paths]
        self._before.update(tree_state(*paths))
        return self

    def check(self) -> None:
        """Assert every watched file still has its recorded content."""
        after = tree_state(*self._paths)
        changed = sorted(k for k in self._before if after.get(k) != self._before[k])
        assert not changed, f"input files changed: {changed}"


@pytest.fixture
def inputs_unchanged():
    """An :class:`InputGuard`; every watched input is checked again after the test."""
    guard = InputGuard()
    yield guard
    guard.check()


@pytest.fixture
def refits(monkeypatch):
    """A list of ``(overrides, n_times)``, one per fit of a model made by
    ``lrm_cvx.validation.refits.clone_model`` during the test (the calibration's, the dynamics
    blend's and the temporal / rank validation's refits; patched where each module reads it)."""
    from lrm_cvx.validation import blending, calibration, refits

    seen: list[tuple[dict, int]] = []
    real = refits.clone_model

    def spy(model, **override):
        sub = real(model, **override)
        fit = sub.fit

        def recording_fit(data, **kw):
            seen.append((override, int(data.sizes[data.dims[0]])))
            return fit(data, **kw)

        sub.fit = recording_fit
        return sub

    for module in (refits, calibration, blending):
        monkeypatch.setattr(module, "clone_model", spy)
    return seen


# ------------------------------------------------------------------------------ workers
MAX_WORKERS = 4
"""Most pytest-xdist workers of ``-n auto`` (pyproject's addopts): each holds ~0.8 GB at its
peak, and the files are few enough that more workers mostly wait."""


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_auto_num_workers(config):
    """``-n auto``: one worker per core, at most :data:`MAX_WORKERS` (``-n 0`` runs serially)."""
    return max(1, min(os.cpu_count() or 1, MAX_WORKERS))


# ------------------------------------------------------------------------------ slow tests
SLOW_ENV = "LRM_CVX_SLOW_TESTS"


def pytest_configure(config):
    config.addinivalue_line(
        "markers", f"slow: minutes-long checks (a fresh install); run when ${SLOW_ENV}=1, as "
        ".ci/run does")


def pytest_collection_modifyitems(config, items):
    if os.environ.get(SLOW_ENV) == "1":
        return
    skip = pytest.mark.skip(reason=f"slow: set {SLOW_ENV}=1 to run (.ci/run does)")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)
