"""The generalization benchmark's paired per-start bounds (benchmarks/bench_generalization.py)."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_generalization as bg  # noqa: E402


def test_paired_upper_is_exact_without_spread_and_ignores_shared_start_effects():
    b = np.full(6, 2.0)
    assert bg.paired_upper(1.1 * b, b) == pytest.approx(0.1, abs=1e-12)  # no spread: the change
    rng = np.random.default_rng(0)
    start = rng.lognormal(0.0, 1.0, 40)  # start-to-start spread shared by both methods
    a = start * 0.9 + rng.normal(0, 0.01, 40)
    ub = bg.paired_upper(a, start)
    # the change is -10 %; the shared spread must not widen the bound beyond a few per cent
    assert -0.11 < ub < -0.05
    unpaired = (a.mean() + 1.645 * np.hypot(a.std(ddof=1), start.std(ddof=1))
                / np.sqrt(40)) / start.mean() - 1
    assert unpaired > ub + 0.2


def test_paired_upper_skips_missing_starts_and_needs_two():
    a = np.array([1.0, np.nan, 3.0, 5.0])
    b = np.array([1.0, 2.0, np.nan, 4.0])
    d = np.array([0.0, 1.0])
    want = (d.mean() + 1.645 * d.std(ddof=1) / np.sqrt(2)) / 2.5
    assert bg.paired_upper(a, b) == pytest.approx(want)
    assert np.isnan(bg.paired_upper(np.array([1.0]), np.array([2.0])))
