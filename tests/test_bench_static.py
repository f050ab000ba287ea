"""The static-placement benchmark's methods (benchmarks/bench_static.py) are what they claim.

* its linear Gaussian-process predictor is the recommended fold-in (same predictions);
* the training-risk greedy's rank-one updates give the exact training error of its set;
* the exchange search never worsens its objective.
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
from lrm_cvx.glrm.posterior import fold_in_snapshots  # noqa: E402


@pytest.fixture(scope="module")
def setup():
    da = load_sample("sst")
    train, test = da.isel(time=slice(None, -8)), da.isel(time=slice(-8, None))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = bs.fit(train)
    C0, noise = bs.gp_prior(model)
    return model, train, test, C0, noise


def test_linear_predictor_is_the_recommended_fold_in(setup):
    model, train, test, C0, noise = setup
    vals = model.region_.stack(test).astype(np.float64)
    mean, _ = model.latent_prior("empirical", spatial=True).predict(True)
    S = [3, 50, 120, 200, 300, 17]
    V = np.full(vals.shape, np.nan)
    V[:, S] = vals[:, S]
    pred, *_ = fold_in_snapshots(model.latent_prior("empirical", spatial=True), V)
    R = np.where(np.isfinite(vals), vals - mean, 0.0)
    lin = mean + (R - bs._residual(C0, noise, R, S))
    np.testing.assert_allclose(lin, pred, atol=1e-7 * np.abs(pred).max())
    assert bs.score(model, vals, np.asarray(S)) == pytest.approx(
        float(np.mean(np.mean((pred - vals) ** 2, axis=1))))


def test_risk_greedy_steps_are_exact_and_exchange_never_worsens(setup):
    model, train, _, C0, noise = setup
    R = bs.training_residuals(model, train)
    cells = bs.place_risk(C0, noise, R, 6)
    assert np.unique(cells).size == 6
    errs = [float((bs._residual(C0, noise, R, cells[:j].tolist()) ** 2).sum())
            for j in range(7)]
    # each pick is the best single addition, recomputed from scratch for a few rivals
    for j in range(6):
        rest = cells[:j].tolist()
        rivals = np.random.default_rng(j).choice(R.shape[1], 15, replace=False)
        for x in rivals:
            if x in rest:
                continue
            e = float((bs._residual(C0, noise, R, rest + [int(x)]) ** 2).sum())
            assert errs[j + 1] <= e + 1e-9 * errs[0]
    better = bs.exchange(C0, noise, cells, R, sweeps=1)
    after = float((bs._residual(C0, noise, R, better.tolist()) ** 2).sum())
    assert after <= errs[-1] * (1 + 1e-12) and np.unique(better).size == 6
    gp = bs.exchange(C0, noise, cells, None, sweeps=1)
    tr = float(np.trace(bs._conditioned(C0, noise, gp.tolist())))
    assert tr <= float(np.trace(bs._conditioned(C0, noise, cells.tolist()))) * (1 + 1e-12)
