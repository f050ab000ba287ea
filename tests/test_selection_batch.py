"""The batched filter of ``temporal="auto"``'s scoring (``filter.batch_*``, ``selection.
_window_errors``) against the naive path: one :class:`LatentFilter` per candidate."""

from __future__ import annotations

import copy
import warnings

import numpy as np
import pytest
import xarray as xr
from hypothesis import given, settings
from hypothesis import strategies as st

from lrm_cvx import GLRM
from lrm_cvx.belief.filter import LatentFilter, batch_start, batch_step, batch_transitions
from lrm_cvx.errors import ModelError
from lrm_cvx.glrm.dynamics import kind_dynamics
from lrm_cvx.io.samples import synthetic_dynamic_field
from lrm_cvx.validation.blending import blend_dynamics, memoryless_cov
from lrm_cvx.validation.designs import sample_sets
from lrm_cvx.validation.selection import MAX_SCORED, _window_errors


def _inflated(model, factor):
    """A shallow copy of ``model`` whose residual and noise variances are ``factor`` times."""
    out = copy.copy(model)
    out.residual_inflation_ = float(factor)
    return out


def _naive_window_errors(sub, dynamics, V, times, region, sizes, designs, rng, spatial,
                         inflation=None):
    """The scoring as it was written first: a LatentFilter per candidate (of a model with
    that candidate's ``residual_inflation_``), its posterior's own ``predict`` map (kriged
    residual included) at the scored cells. The designs are drawn among all of the region's
    cells, as a campaign flies them: a cell in a gap gives a NaN, which the filter ignores."""
    n = V.shape[0]
    err = np.full((len(dynamics), len(sizes), n), np.nan)
    inflation = [1.0] * len(dynamics) if inflation is None else inflation
    for s_i, size in enumerate(sizes):
        states = [LatentFilter.from_model(_inflated(sub, r), dynamics=d, memoryless=d is None,
                                          spatial=spatial)
                  for d, r in zip(dynamics, inflation, strict=True)]
        for i, t in enumerate(times):
            cells = sample_sets(region, np.ones(region.n_cells, bool), size,
                                designs[i % len(designs)], rng)
            h = np.isfinite(V[i])
            h[cells] = False
            h = np.flatnonzero(h)
            if h.size > MAX_SCORED:
                h = np.sort(rng.choice(h, MAX_SCORED, replace=False))
            for state in states:
                state.assimilate((cells, V[i, cells]), time=t)
            if h.size:
                for c, state in enumerate(states):
                    pred = state.posterior.predict_all(cells=h)[0]
                    err[c, s_i, i] = np.mean((pred - V[i, h]) ** 2)
    return err


def _setup(seed: int, spatial: str | None, freq: str = "MS", T: int = 40):
    data = synthetic_dynamic_field(T, (7, 8), 3, seed=seed, seasonal_period=12,
                                   seasonal_amplitude=0.8, A=0.6 * np.eye(3),
                                   Q=0.05 * np.eye(3), freq=freq, missing=0.15, noise=0.1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sub = GLRM(3, offset=spatial is not None, spatial=spatial, random_state=seed,
                   progress=False, temporal="ar1").fit(data[:-8])
    times = data["time"].values
    dyns = [None]
    for kind in ("ar1", "seasonal"):
        base = kind_dynamics(kind, sub, times[:-8])
        if base is None:
            continue
        S = memoryless_cov(sub, base)
        dyns += [blend_dynamics(base, a, S) for a in (0.0, 0.5, 1.0)]
    V = sub.region_.stack(data[-8:]).astype(np.float32)
    return sub, dyns, V, times[-8:]


@pytest.mark.parametrize("spatial", [None, "exponential"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_window_errors_equal_one_filter_per_candidate(seed, spatial):
    sub, dyns, V, times = _setup(seed, spatial)
    args = (sub, dyns, V, times, sub.region_, (2, 5, 12), ("route", "line", "scattered"))
    fast = _window_errors(*args, np.random.default_rng(seed), None)
    naive = _naive_window_errors(*args, np.random.default_rng(seed), None)
    assert np.isfinite(naive).all() and np.isnan(V).any()  # days with gaps
    np.testing.assert_allclose(fast, naive, rtol=1e-9, atol=0)


@pytest.mark.parametrize("spatial", [None, "exponential"])
def test_inflated_candidates_equal_filters_of_inflated_models(spatial):
    """A candidate scored with a residual inflation is the filter of the model whose
    ``residual_inflation_`` is that factor (its latent update trusts the samples less; the
    kriged residual keeps its weights): the same day errors as the naive path."""
    sub, dyns, V, times = _setup(3, spatial)
    dyns = dyns[:3] * 3
    infl = [1.0] * 3 + [2.0] * 3 + [8.0] * 3
    args = (sub, dyns, V, times, sub.region_, (2, 5, 12), ("route", "line", "scattered"))
    fast = _window_errors(*args, np.random.default_rng(3), None, infl)
    naive = _naive_window_errors(*args, np.random.default_rng(3), None, infl)
    np.testing.assert_allclose(fast, naive, rtol=1e-9, atol=0)
    assert not np.allclose(fast[:3], fast[6:])  # the inflation changes the maps


def test_batch_inflation_is_checked():
    sub, dyns, _, _ = _SETUP
    with pytest.raises(ModelError, match="inflation must hold"):
        batch_start(sub, dyns, inflation=[1.0])
    with pytest.raises(ModelError, match="inflation must hold"):
        batch_start(sub, dyns, inflation=[0.0] * len(dyns))


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(0, 9), nan=st.booleans())
def test_batch_step_equals_latent_filter(seed, n, nan):
    """One day of every candidate, any cells (repeats, none, NaN values): the same beliefs."""
    sub, dyns, V, times = _SETUP
    rng = np.random.default_rng(seed)
    batch = batch_start(sub, dyns)
    states = [LatentFilter.from_model(sub, dynamics=d, memoryless=d is None) for d in dyns]
    for day in range(2):
        cells = rng.integers(0, sub.n_cells_, n)
        vals = rng.normal(size=n) + 10.0
        if nan and n:
            vals[0] = np.nan
        trans = batch_transitions(batch.dynamics, batch.time, times[day])
        batch = batch_step(batch, trans, cells, vals, times[day])
        for c, state in enumerate(states):
            state.assimilate((cells, vals), time=times[day])
            np.testing.assert_allclose(batch.mean[c], state.posterior.mean, rtol=1e-9,
                                       atol=1e-12)
            np.testing.assert_allclose(batch.cov[c], state.posterior.cov, rtol=1e-8,
                                       atol=1e-14)


_SETUP = _setup(5, "exponential")


@pytest.mark.parametrize("scale", [False, True])
def test_residual_covariance_is_the_fits_own(scale):
    """The refits' covariance (predictive.residual_covariance) with a fit's pairs is the one
    GLRM(spatial=...).fit sets: the same residual rows, the same variogram fit."""
    from lrm_cvx.glrm.predictive import residual_covariance

    data = synthetic_dynamic_field(30, (9, 10), 3, seed=7, freq="D", missing=0.2, noise=0.1)
    model = GLRM(3, offset=True, scale=scale, spatial="exponential", random_state=0,
                 progress=False).fit(data)
    V = model.region_.stack(data).astype(np.float32)
    got = residual_covariance(model, V, "exponential")
    want = model.spatial_cov_
    for name in ("sill", "range", "nugget"):
        assert np.isclose(getattr(got, name), getattr(want, name), rtol=1e-6)
    fewer = residual_covariance(model, V, "exponential", max_pairs=2_000)
    assert not np.isclose(fewer.range, want.range, rtol=1e-6)  # max_pairs is used


def test_first_window_never_sees_later_snapshots(monkeypatch):
    """The shared residual covariance comes from the earliest refit: poisoning the last
    window's snapshots leaves every score of the first window as it was."""
    import lrm_cvx.validation.selection as sel

    data = synthetic_dynamic_field(40, (8, 9), 3, seed=3, seasonal_period=12,
                                   seasonal_amplitude=0.8, A=0.6 * np.eye(3),
                                   Q=0.05 * np.eye(3), freq="MS", missing=0.1, noise=0.1)
    n_val = 8
    poisoned = data.copy()
    poisoned[-n_val:] = poisoned[-n_val:] + 50.0 * np.sign(
        np.random.default_rng(1).standard_normal(poisoned[-n_val:].shape))
    seen, covs = [], []
    orig = sel._window_errors
    monkeypatch.setattr(sel, "_window_errors",
                        lambda sub, *a: seen.append((sub.spatial_cov_, orig(sub, *a)))
                        or seen[-1][1])
    for d in (data, poisoned):  # the model itself sees the poison (its covariance moves)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = GLRM(3, offset=True, spatial="exponential", random_state=0,
                         progress=False).fit(d)
            sel.select_temporal(model, d, n_val=n_val)
        covs.append(model.spatial_cov_)
    (cov_a, first_a), (cov_a2, _), (cov_b, first_b), (cov_b2, second_b) = seen
    assert cov_a2 is cov_a and cov_b2 is cov_b  # one covariance for both refits
    assert (cov_a.sill, cov_a.range, cov_a.nugget) == (cov_b.sill, cov_b.range, cov_b.nugget)
    np.testing.assert_array_equal(first_a, first_b)
    assert not np.allclose(seen[1][1], second_b)  # the poison does reach the last window
    assert covs[0].sill != covs[1].sill


def test_fit_hands_its_stacked_snapshots_to_the_selection():
    """GLRM(temporal="auto").fit passes its own stacking (no second one): the same table as
    select_temporal stacking the data itself; a wrong shape is refused."""
    from lrm_cvx.errors import DataError
    from lrm_cvx.validation.selection import select_temporal

    data = synthetic_dynamic_field(40, (7, 8), 3, seed=2, seasonal_period=12,
                                   seasonal_amplitude=0.8, A=0.6 * np.eye(3),
                                   Q=0.05 * np.eye(3), freq="MS", missing=0.1, noise=0.1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(3, offset=True, spatial="exponential", temporal="auto", random_state=0,
                     progress=False).fit(data)
        again = select_temporal(model, data, seed=0)
    xr.testing.assert_identical(model.selection_, again)
    with pytest.raises(DataError, match="values must be"):
        select_temporal(model, data, values=np.zeros((3, model.n_cells_)))
