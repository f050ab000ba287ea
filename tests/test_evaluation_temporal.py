"""evaluate(temporal=...) and the coverage outputs."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from lrm_cvx.errors import ModelError
from lrm_cvx.evaluation import PlanningOptions, ScoringOptions, evaluate, summary
from lrm_cvx.glrm import GLRM
from lrm_cvx.glrm.calibrated import prediction_factor
from lrm_cvx.io.samples import synthetic_dynamic_field
from lrm_cvx.planning import transect
from lrm_cvx.validation.calibration import Z68, Z95

N_TEST = 4


@pytest.fixture(scope="module")
def data():
    return synthetic_dynamic_field(24, (9, 11), rank=3, missing=0.1, noise=0.05, seed=3)


@pytest.fixture(scope="module")
def model(data):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return GLRM(rank=3, progress=False, random_state=0).fit(
            data.isel(time=slice(None, -N_TEST)))


KW = dict(n_test=N_TEST, budgets=(8, 16), n_starts=3,
          progress=False, methods=("greedy", "transect-up", "random"),
          paper=True,
          planning=PlanningOptions(random_trials=2, certify=False),
          scoring=ScoringOptions(min_observations=3))  # the paper's fold-in unless a test asks


def test_temporal_none_is_the_default_protocol(data, model):
    a = evaluate(data, model=model, **KW)
    b = evaluate(data, model=model, temporal=None, **KW)
    for name in a.data_vars:
        np.testing.assert_array_equal(a[name].values, b[name].values)
    assert "mse_memoryless" not in b and b.attrs["temporal"] == "none"


def test_memoryless_errors_and_coverage_against_a_direct_fold_in(data, model):
    res = evaluate(data, model=model, **KW)
    region = model.region_
    Y = model._Yv
    V = region.stack(data.isel(time=slice(-N_TEST, None))).astype(float)
    m = list(res.method.values).index("transect-up")
    for s, start in enumerate(res.start_cell.values):
        for b, budget in enumerate(res.budget.values):
            plan = transect(region, int(start), float(budget), "up", Y=Y)
            cells = np.asarray(plan.cells)
            for t in range(N_TEST):
                c = cells[np.isfinite(V[t, cells])]
                if c.size < KW["scoring"].min_observations:
                    assert np.isnan(res.mse.values[m, b, s, 0, t])
                    continue
                x = np.linalg.lstsq(Y[:, c].T, V[t, c], rcond=None)[0]  # the paper's fold-in
                pred = Y.T @ x
                obs = np.isfinite(V[t])
                mse = np.mean((pred[obs] - V[t, obs]) ** 2)
                assert res.mse.values[m, b, s, 0, t] == pytest.approx(mse, rel=1e-8)
                # coverage: sigma^2 (Y_S Y_S^T)^-1 plus the noise of a new measurement
                s2 = model.noise_std_ ** 2 * prediction_factor(model)  # a new snapshot's
                cov_x = s2 * np.linalg.inv(Y[:, c] @ Y[:, c].T)
                sd = np.sqrt(np.einsum("ai,ab,bi->i", Y, cov_x, Y) + s2)
                held = obs.copy()
                held[c] = False
                z = np.abs(V[t, held] - pred[held]) / sd[held]
                want = [np.mean(z <= Z68), np.mean(z <= Z95)]
                got = [res.coverage68.values[m, b, s, 0, t], res.coverage95.values[m, b, s, 0, t]]
                assert got == pytest.approx(want, abs=1e-12)


def test_temporal_campaigns_run_and_memoryless_loop_matches_the_protocol(data, model):
    kw = {**KW, "scoring": ScoringOptions(min_observations=3, fold_in={"prior": "empirical"})}
    base = evaluate(data, model=model, **kw)
    res = evaluate(data, model=model, temporal="ar1", **kw)
    assert res.attrs["temporal"] == "ar1"
    for name in ("coverage68", "coverage95", "coverage68_memoryless", "coverage95_memoryless"):
        v = res[name].values
        v = v[np.isfinite(v)]
        assert v.size and np.all((v >= 0) & (v <= 1))
    # a transect flies the same cells every day: the memoryless campaign is the protocol's
    # empirical-prior fold-in of each snapshot on its own
    sel = dict(method="transect-up", trial=0)
    np.testing.assert_allclose(res.mse_memoryless.sel(sel).values, base.mse.sel(sel).values,
                               rtol=1e-8)
    # the filter carries information: on planted persistent dynamics it helps on average
    assert float(res.mse.sel(sel).mean()) < float(res.mse_memoryless.sel(sel).mean())
    df = summary(res)
    assert {"mse_memoryless_mean", "temporal_cut", "coverage95_mean"} <= set(df.columns)
    row = df.set_index(["method", "budget"]).loc[("transect-up", 16.0)]
    sel16 = {**sel, "budget": 16.0}
    tm, ml = res.mse.sel(sel16), res.mse_memoryless.sel(sel16)
    both = np.isfinite(tm) & np.isfinite(ml)
    want = 1 - float(tm.where(both).mean()) / float(ml.where(both).mean())
    assert row["temporal_cut"] == pytest.approx(want)
    # the figures draw memoryless and temporal side by side
    import matplotlib

    matplotlib.use("Agg")
    from lrm_cvx.plots import plot_metrics, plot_temporal_metrics

    fig = plot_temporal_metrics(res)
    assert len(fig.axes) == 3 and len(fig.axes[0].lines) == 2 * len(res.method)
    fig2 = plot_metrics(res)
    labels = [ln.get_label() for ln in fig2.axes[1].lines]
    assert sum(lab.endswith("(memoryless)") for lab in labels) == len(res.method)


def test_unknown_temporal_is_refused(data, model):
    with pytest.raises(ModelError, match="temporal"):
        evaluate(data, model=model, temporal="daily", **KW)


def test_the_memoryless_twin_is_the_model_as_fitted(data, model):
    """A model whose residual inflation was validated with its temporal model (temporal=
    "auto"): the campaigns' memoryless twin is the model as temporal=None fits it
    (inflation 1), the reference the choice was validated against."""
    import copy

    kw = {**KW, "scoring": ScoringOptions(min_observations=3, fold_in={"prior": "empirical"})}
    inflated = copy.copy(model)
    inflated.residual_inflation_ = 4.0
    base = evaluate(data, model=model, **kw)
    base4 = evaluate(data, model=inflated, **kw)
    res = evaluate(data, model=inflated, temporal="ar1", **kw)
    sel = dict(method="transect-up", trial=0)
    np.testing.assert_allclose(res.mse_memoryless.sel(sel).values, base.mse.sel(sel).values,
                               rtol=1e-8)
    assert not np.allclose(base4.mse.sel(sel).values, base.mse.sel(sel).values, rtol=1e-3)
    assert np.isnan(res.coverage95_memoryless.values).all()  # calibrated for x4, not for x1
    assert np.isfinite(res.coverage95.sel(sel).values).any()


def test_a_memoryless_auto_model_runs_each_campaign_once(data, model, monkeypatch):
    """temporal="auto" on a model without dynamics: its campaigns are its memoryless twin's,
    so each runs once and both columns hold it; a model with dynamics runs both."""
    import lrm_cvx.campaign as campaign

    calls = []
    real = campaign.posterior_campaign

    def counted(*args, **kwargs):
        calls.append(kwargs.get("temporal"))
        return real(*args, **kwargs)

    monkeypatch.setattr(campaign, "posterior_campaign", counted)
    kw = {**KW, "scoring": ScoringOptions(min_observations=3, fold_in={"prior": "empirical"})}
    n_campaigns = 3 * 2 * (2 + 2)  # starts x budgets x (greedy, transect, 2 random trials)
    assert getattr(model, "dynamics_", None) is None
    res = evaluate(data, model=model, temporal="auto", **kw)
    assert len(calls) == n_campaigns and set(calls) == {"auto"}
    for name in ("mse", "coverage68", "coverage95"):
        np.testing.assert_array_equal(res[name].values, res[f"{name}_memoryless"].values)
    assert np.isfinite(res.mse.values).any()
    calls.clear()
    res = evaluate(data, model=model, temporal="ar1", **kw)
    assert len(calls) == 2 * n_campaigns and set(calls) == {"ar1", None}
    assert not np.array_equal(res.mse.values, res.mse_memoryless.values, equal_nan=True)
