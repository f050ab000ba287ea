"""The static-placement benchmark (benchmarks/bench_static.py) scores what it claims.

Its score is the recommended fold-in's test MSE (checked against ``GLRM.complete`` snapshot by
snapshot), and its placements are the package's ``place_sensors`` (the methods themselves are
tested in tests/test_static.py).
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_static as bs  # noqa: E402

from lrm_cvx.datasets import load_sample  # noqa: E402
from lrm_cvx.planning import place_sensors  # noqa: E402


@pytest.fixture(scope="module")
def setup():
    da = load_sample("sst")
    train, test = da.isel(time=slice(None, -8)), da.isel(time=slice(-8, None))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = bs.fit(train)
    return model, train, test


def test_score_is_the_mse_of_the_recommended_completion(setup):
    """The batch fold-in the benchmark scores with equals ``GLRM.complete(prior="empirical",
    spatial=True)`` run snapshot by snapshot (the user-facing path)."""
    model, _, test = setup
    vals = model.region_.stack(test).astype(np.float64)
    S = np.array([3, 50, 120, 200, 300, 17])
    mses = []
    for v in vals:
        s = S[np.isfinite(v[S])]
        pred = model.complete((s, v[s]), prior="empirical", spatial=True)["prediction"]
        pred = model.region_.stack(pred).astype(np.float64)
        mses.append(np.nanmean((pred - v) ** 2))
    assert bs.score(model, vals, S) == pytest.approx(float(np.mean(mses)), rel=1e-6)


@pytest.mark.parametrize("criterion", ["gp-variance", "risk"])
def test_place_is_the_package_placement(setup, criterion):
    model, train, _ = setup
    prior = model.latent_prior("empirical", spatial=True)
    extra = {"training": train} if criterion == "risk" else {}
    ref = place_sensors(model.Y_, model.region_, 5, criterion=criterion, prior=prior,
                        exchange=False, **extra)
    np.testing.assert_array_equal(bs.place(model, train, 5, criterion, False), ref.cells)
