"""Temporal dynamics of the latent columns: estimation, bad input, model io."""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import pytest
import xarray as xr

from lrm_cvx.errors import DataError, ModelError
from lrm_cvx.glrm import GLRM
from lrm_cvx.glrm.dynamics import (
    Dynamics,
    check_times,
    estimate_ar1,
    estimate_seasonal,
    time_numbers,
)
from lrm_cvx.io.samples import synthetic_dynamic_field


def _ar_series(A, Q, T, rng, mu=None):
    k = A.shape[0]
    L = np.linalg.cholesky(Q)
    X = np.empty((k, T))
    z = np.zeros(k)
    for t in range(T):
        z = A @ z + L @ rng.standard_normal(k)
        X[:, t] = z
    return X + (0 if mu is None else mu[:, None])


def _rel(a, b):
    return np.linalg.norm(a - b) / np.linalg.norm(b)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ar1_recovers_planted_dynamics(seed):
    da, truth = synthetic_dynamic_field(3000, (3, 4), 3, seed=seed, missing=0.0,
                                        return_truth=True)
    dyn = estimate_ar1(truth["X"], da.time)
    assert _rel(dyn.A, truth["A"]) < 0.10
    assert _rel(dyn.Q, truth["Q"]) < 0.15
    np.testing.assert_allclose(dyn.initial_mean, truth["X"][:, -1])
    assert dyn.step == 1.0 and dyn.time_kind == "datetime" and dyn.n_pairs == 2999


def test_ar1_nonsymmetric_matrix_and_mean():
    rng = np.random.default_rng(5)
    A = np.array([[0.7, 0.2], [-0.1, 0.5]])
    Q = np.array([[0.05, 0.01], [0.01, 0.02]])
    mu = np.array([2.0, -1.0])
    X = _ar_series(A, Q, 4000, rng, mu)
    dyn = estimate_ar1(X, np.arange(4000))
    assert _rel(dyn.A, A) < 0.10
    np.testing.assert_allclose(dyn.mean, mu, atol=0.05)
    # c of one step: x' = A x + (mu - A mu)
    An, Qn, c = dyn.transition(1)
    np.testing.assert_allclose(An, dyn.A)
    np.testing.assert_allclose(c, dyn.mean - dyn.A @ dyn.mean)


def test_ar1_is_stable_and_Q_psd():
    # a random walk (unit root) and a collinear series: A is scaled below 1, Q stays PSD
    rng = np.random.default_rng(0)
    walk = np.cumsum(rng.standard_normal((2, 50)), axis=1) * np.array([[1.0], [1.0]])
    walk[1] = 2 * walk[0]  # rank-deficient: Q has a zero eigenvalue before the floor
    dyn = estimate_ar1(walk, np.arange(50))
    assert np.max(np.abs(np.linalg.eigvals(dyn.A))) <= 0.99 + 1e-12
    assert np.linalg.eigvalsh(dyn.Q).min() > 0
    np.testing.assert_allclose(dyn.Q, dyn.Q.T)


def test_shrinkage_pulls_towards_zero():
    rng = np.random.default_rng(1)
    X = _ar_series(np.diag([0.8, 0.6]), 0.1 * np.eye(2), 200, rng)
    a0 = estimate_ar1(X, np.arange(200), shrinkage=0.0).A
    a1 = estimate_ar1(X, np.arange(200), shrinkage=1.0).A
    assert np.linalg.norm(a1) < np.linalg.norm(a0)
    # the closed form of the ridge least squares
    Z = X - X.mean(axis=1, keepdims=True)
    Z0, Z1 = Z[:, :-1], Z[:, 1:]
    lam = np.trace(Z0 @ Z0.T) / 2
    np.testing.assert_allclose(a1, Z1 @ Z0.T @ np.linalg.inv(Z0 @ Z0.T + lam * np.eye(2)))


def test_irregular_steps_use_pairs_one_step_apart_and_powers_of_A():
    rng = np.random.default_rng(2)
    A = np.diag([0.9, 0.5])
    X = _ar_series(A, 0.1 * np.eye(2), 400, rng)
    keep = np.ones(400, bool)
    keep[rng.choice(400, 60, replace=False)] = False  # gaps of 2+ steps
    t = np.arange(400)[keep]
    dyn = estimate_ar1(X[:, keep], t)
    assert dyn.step == 1.0
    assert dyn.n_pairs == int(np.sum(np.diff(t) == 1))
    assert dyn.n_steps(10, 13) == 3 and dyn.n_steps(10, 10) == 0
    A3, Q3, _ = dyn.transition(3)
    np.testing.assert_allclose(A3, np.linalg.matrix_power(dyn.A, 3))
    np.testing.assert_allclose(Q3, dyn.Q + dyn.A @ dyn.Q @ dyn.A.T
                               + dyn.A @ dyn.A @ dyn.Q @ dyn.A.T @ dyn.A.T)


def test_monthly_steps_count_one_per_month():
    times = pd.date_range("2000-01-01", periods=30, freq="MS")
    t, kind, _ = time_numbers(times.values)
    assert kind == "datetime" and t[1] == 31
    X = _ar_series(np.diag([0.5]), np.eye(1), 30, np.random.default_rng(0))
    dyn = estimate_ar1(X, times.values)
    assert dyn.n_pairs == 29  # 28..31 day months are all one step
    assert dyn.n_steps(times.values[0], times.values[3]) == 3


def test_seasonal_recovers_season_means_and_anomaly_dynamics():
    da, truth = synthetic_dynamic_field(12 * 150, (3, 3), 2, seed=3, missing=0.0,
                                        seasonal_period=12, freq="MS", return_truth=True)
    dyn = estimate_seasonal(truth["X"], da.time)
    assert dyn.season == "month" and dyn.season_means.shape == (12, 2)
    months = da.time.dt.month.values - 1
    planted = (truth["mu"][:, None] + truth["seasonal"])[:, :12]
    np.testing.assert_allclose(dyn.season_means[months[:12]], planted.T, atol=0.1)
    assert _rel(dyn.A, truth["A"]) < 0.15
    # the transition re-centres on the target month's mean
    t0, t1 = da.time.values[-1], da.time.values[-1] + np.timedelta64(31, "D")
    An, _, c = dyn.transition(1, t0, t1)
    m0, m1 = dyn.season_mean(t0), dyn.season_mean(t1)
    np.testing.assert_allclose(An @ m0 + c, m1)


def test_seasonal_with_a_cftime_calendar():
    times = xr.date_range("2001-01-01", periods=48, freq="MS", calendar="noleap",
                          use_cftime=True)
    rng = np.random.default_rng(4)
    season = np.sin(2 * np.pi * np.arange(48) / 12)
    X = np.vstack([season, -season]) + 0.1 * rng.standard_normal((2, 48))
    dyn = estimate_seasonal(X, times.values)
    assert dyn.time_kind == "cftime" and dyn.season == "month"
    np.testing.assert_allclose(dyn.season_means[:, 0], np.sin(2 * np.pi * np.arange(12) / 12),
                               atol=0.15)
    t, kind, cal = time_numbers(times.values)
    assert kind == "cftime" and cal == "noleap" and t[12] == 365


def test_seasonal_refuses_numbers_short_records_and_odd_steps():
    X = np.random.default_rng(0).standard_normal((2, 30))
    with pytest.raises(ModelError, match="datetime"):
        estimate_seasonal(X, np.arange(30))
    with pytest.raises(ModelError, match="two years"):
        estimate_seasonal(X[:, :14], pd.date_range("2000-01-01", periods=14, freq="MS").values)
    # 6-hourly for a week sees each day of year 4 times, but in one year: no season
    with pytest.raises(ModelError, match="two years"):
        estimate_seasonal(X[:, :28], pd.date_range("2000-01-01", periods=28, freq="6h").values)
    with pytest.raises(ModelError, match="monthly or daily"):
        estimate_seasonal(X, pd.date_range("2000-01-01", periods=30, freq="7D").values)


@pytest.mark.parametrize("times, match", [
    (np.array([0, 2, 1, 3]), "not sorted"),
    (np.array([0, 1, 1, 3]), "duplicated"),
    (np.array(["2000-01-01", "NaT", "2000-01-03", "2000-01-04"], dtype="datetime64[ns]"),
     "NaT"),
    (np.array([0.0, np.nan, 2, 3]), "non-finite"),
    (None, "time coordinate"),
])
def test_bad_times(times, match):
    X = np.zeros((2, 4))
    with pytest.raises(DataError, match=match):
        estimate_ar1(X, times)


def test_too_few_snapshots_and_length_mismatch():
    with pytest.raises(ModelError, match="at least 3"):
        estimate_ar1(np.zeros((2, 2)), np.arange(2))
    with pytest.raises(DataError, match="entries"):
        estimate_ar1(np.zeros((2, 5)), np.arange(4))
    with pytest.raises(ModelError, match="shrinkage"):
        estimate_ar1(np.zeros((2, 5)), np.arange(5), shrinkage=-1)
    with pytest.raises(DataError, match="sorted"):
        check_times(np.array([3, 2, 1]))


def test_dynamics_validates_shapes():
    with pytest.raises(ModelError, match="Q must have shape"):
        Dynamics(kind="ar1", A=np.eye(2), Q=np.eye(3), mean=np.zeros(2),
                 initial_mean=np.zeros(2), initial_cov=np.eye(2))
    with pytest.raises(ModelError, match="kind"):
        Dynamics(kind="ar2", A=np.eye(2), Q=np.eye(2), mean=np.zeros(2),
                 initial_mean=np.zeros(2), initial_cov=np.eye(2))


# ----------------------------------------------------------------------------- the model
@pytest.fixture(scope="module")
def field():
    return synthetic_dynamic_field(40, (8, 9), 3, seed=1, noise=0.03)


def _fit(data, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return GLRM(3, progress=False, max_iter=30, random_state=0, **kw).fit(data)


def test_model_temporal_none_keeps_todays_model(field, tmp_path):
    plain = _fit(field)
    assert plain.dynamics_ is None
    with_dyn = _fit(field, temporal="ar1")
    np.testing.assert_array_equal(plain._Xv, with_dyn._Xv)  # the fit itself is unchanged
    np.testing.assert_array_equal(plain._Yv, with_dyn._Yv)
    plain.save(tmp_path / "plain.nc")
    with xr.open_dataset(tmp_path / "plain.nc") as ds:
        assert "dynamics_kind" not in ds.attrs and "dynamics_A" not in ds
    assert GLRM.load(tmp_path / "plain.nc").dynamics_ is None


def test_model_dynamics_round_trip(field, tmp_path):
    model = _fit(field, temporal="ar1", offset=True)
    dyn = model.dynamics_
    assert dyn.kind == "ar1" and dyn.A.shape == (3, 3)
    np.testing.assert_allclose(dyn.initial_mean, model._Xv[:, -1])
    assert np.linalg.eigvalsh(dyn.initial_cov).min() > 0  # the last snapshot's fold-in cov
    model.save(tmp_path / "m.nc")
    back = GLRM.load(tmp_path / "m.nc")
    assert back.temporal == "ar1"
    for name in ("A", "Q", "mean", "initial_mean", "initial_cov", "error_cov"):
        np.testing.assert_array_equal(getattr(back.dynamics_, name), getattr(dyn, name))
    assert back.dynamics_.time == field.time.values[-1]
    # the fit corrects for the columns' estimation error: the mean fold-in covariance
    assert dyn.error_cov.shape == (3, 3) and np.linalg.eigvalsh(dyn.error_cov).min() > 0


def test_model_seasonal_round_trip(tmp_path):
    da = synthetic_dynamic_field(36, (5, 6), 2, seed=0, seasonal_period=12, freq="MS")
    model = _fit(da, temporal="seasonal")
    model.save(tmp_path / "s.nc")
    back = GLRM.load(tmp_path / "s.nc")
    assert back.dynamics_.season == "month"
    np.testing.assert_array_equal(back.dynamics_.season_means, model.dynamics_.season_means)


def test_model_temporal_bad_input(field):
    with pytest.raises(ModelError, match="temporal must be one of"):
        _fit(field, temporal="ar2")
    with pytest.raises(ModelError, match="at least 3"):
        _fit(field.isel(time=slice(0, 2)), temporal="ar1")
    with pytest.raises(DataError, match="not sorted"):
        _fit(field.isel(time=[0, 2, 1, 3, 4]), temporal="ar1")
    with pytest.raises(DataError, match="duplicated"):
        _fit(field.isel(time=[0, 1, 1, 3, 4]), temporal="ar1")
    with pytest.raises(DataError, match="needs a time coordinate"):
        _fit(field.drop_vars("time"), temporal="ar1")
    model = _fit(field)
    with pytest.raises(ModelError, match="'ar1' or 'seasonal'"):
        model.fit_dynamics("ar3")
    assert model.fit_dynamics("ar1").dynamics_.kind == "ar1"


def test_numpy_input_counts_rows_as_steps(field):
    from lrm_cvx.region import Region

    D = Region.from_dataarray(field).stack(field).astype(np.float64)
    model = _fit(D, temporal="ar1")
    assert model.dynamics_.time_kind == "numeric" and model.dynamics_.step == 1.0


def test_transformed_dynamics_are_the_same_process():
    rng = np.random.default_rng(3)
    A = np.array([[0.8, 0.1], [0.0, 0.5]])
    Q = np.array([[0.1, 0.02], [0.02, 0.05]])
    dyn = Dynamics(kind="ar1", A=A, Q=Q, mean=np.array([1.0, 0.0]),
                   initial_mean=np.array([0.5, 0.2]), initial_cov=0.01 * np.eye(2))
    T = rng.normal(size=(2, 2)) + 2 * np.eye(2)
    b = np.array([0.3, -0.1])
    new = dyn.transformed(T, b)
    A1, Q1, c1 = dyn.transition(2)
    A2, Q2, c2 = new.transition(2)
    x = rng.normal(size=2)
    # the mean of the next-next state, mapped: T (A1 x + c1) + b == A2 (T x + b) + c2
    np.testing.assert_allclose(T @ (A1 @ x + c1) + b, A2 @ (T @ x + b) + c2)
    np.testing.assert_allclose(T @ Q1 @ T.T, Q2)


# ----------------------------------------------------------------------------- the generator
def test_synthetic_dynamic_field_plants_its_truth():
    da, truth = synthetic_dynamic_field(50, (6, 7), 3, seed=0, noise=0.0, missing=0.0,
                                        return_truth=True)
    X, Y = truth["X"], truth["Y"]
    np.testing.assert_allclose(X, truth["mu"][:, None] + truth["seasonal"] + truth["trend"]
                               + truth["Z"])
    assert not truth["trend"].any()  # no trend unless asked for
    land = truth["land_mask"]
    expected = np.einsum("kt,kyx->tyx", X, Y)  # not clipped: exactly the planted model
    assert np.abs(expected[:, land]).max() > 1  # (this seed reaches beyond [-1, 1])
    np.testing.assert_allclose(da.values[:, land], expected[:, land], atol=1e-5)
    assert np.all(np.isnan(da.values[:, ~land]))
    # the AR part follows its recursion up to the innovations, whose covariance is Q
    W = truth["Z"][:, 1:] - truth["A"] @ truth["Z"][:, :-1]
    assert W.shape == (3, 49)
    assert np.max(np.abs(np.linalg.eigvals(truth["A"]))) < 1
    np.testing.assert_allclose(truth["Q"], 0.1 * (np.eye(3) - truth["A"] @ truth["A"].T))
    again = synthetic_dynamic_field(50, (6, 7), 3, seed=0, noise=0.0, missing=0.0)
    xr.testing.assert_identical(da, again)


def test_synthetic_dynamic_field_monthly_and_given_matrices():
    A = np.diag([0.5, 0.9])
    Q = np.diag([0.01, 0.02])
    da, truth = synthetic_dynamic_field(24, (4, 5), 2, A=A, Q=Q, seasonal_period=12,
                                        freq="MS", seed=1, return_truth=True)
    assert pd.Timestamp(da.time.values[1]) == pd.Timestamp("2013-02-01")
    np.testing.assert_array_equal(truth["A"], A)
    np.testing.assert_allclose(truth["seasonal"][:, :12], truth["seasonal"][:, 12:])
    assert np.all(truth["seasonal"][0] == 0)  # the level mode has no season


def test_synthetic_dynamic_field_forced_trend_yearly():
    """A forced trend is a quadratic ramp on mode 1 from the onset (closed form), added to the
    same AR and seasonal parts as without it (it draws no random numbers); yearly times."""
    kw = dict(n_times=21, shape=(4, 5), rank=3, seed=2, noise=0.0, missing=0.0,
              return_truth=True, freq="YS", start_date="1900-01-01")
    da, truth = synthetic_dynamic_field(trend=(2.0, 0.5), **kw)
    np.testing.assert_array_equal(synthetic_dynamic_field(trend=2.0, **kw)[1]["X"], truth["X"])
    flat, flat_truth = synthetic_dynamic_field(**kw)
    t = np.arange(21)
    expected = np.where(t >= 10, 2.0 * ((t - 10) / 10.0) ** 2, 0.0)
    np.testing.assert_allclose(truth["trend"][1], expected)
    assert not truth["trend"][[0, 2]].any()
    np.testing.assert_array_equal(truth["Z"], flat_truth["Z"])
    np.testing.assert_allclose(truth["X"] - flat_truth["X"], truth["trend"])
    land = truth["land_mask"]
    np.testing.assert_allclose(da.values[:, land] - flat.values[:, land],
                               np.einsum("t,yx->tyx", expected, truth["Y"][1])[:, land],
                               atol=1e-5)
    assert [pd.Timestamp(v).year for v in da.time.values[[0, -1]]] == [1900, 1920]
    assert "forced trend 2" in da.attrs["comment"]


@pytest.mark.parametrize("kw, match", [
    ({"trend": 1.0, "rank": 1}, "rank >= 2"),
    ({"trend": float("nan")}, "trend must be"),
    ({"trend": (1.0, 1.0)}, "onset"),
    ({"trend": (1.0,)}, "amount, onset"),
    ({"trend": (1.0, 0.5, 2.0)}, "amount, onset"),
    ({"A": np.eye(2) * 1.2}, "stable"),
    ({"A": np.eye(3)}, "A must be"),
    ({"Q": -np.eye(2)}, "semi-definite"),
    ({"freq": "W"}, "freq"),
    ({"seasonal_period": 1}, "seasonal_period"),
])
def test_synthetic_dynamic_field_bad_input(kw, match):
    kw = {"rank": 2, **kw}
    with pytest.raises(DataError, match=match):
        synthetic_dynamic_field(10, (3, 3), **kw)


def test_synthetic_field_default_is_unchanged_by_time_factors():
    from lrm_cvx.io.samples import synthetic_field

    da, truth = synthetic_field(12, (5, 6), 2, seed=3, return_truth=True)
    same = synthetic_field(12, (5, 6), 2, seed=3, time_factors=None)
    xr.testing.assert_identical(da, same)
    with pytest.raises(DataError, match="time_factors"):
        synthetic_field(12, (5, 6), 2, seed=3, time_factors=np.zeros((2, 11)))


# ----------------------------------------------------------------------------- validated blend
def test_validation_blend_shrinks_without_persistence_and_keeps_it_with():
    from lrm_cvx.belief.posterior import empirical_moments
    from lrm_cvx.glrm.dynamics import estimate

    rng = np.random.default_rng(0)
    white = rng.standard_normal((3, 120)) * np.array([[1.0], [0.5], [0.2]])
    d0 = estimate("ar1", white, np.arange(120), validation=0.3)
    assert d0.blend <= 0.3
    persistent = _ar_series(np.diag([0.9, 0.8, 0.7]), 0.1 * np.eye(3), 120, rng)
    d1 = estimate("ar1", persistent, np.arange(120), validation=0.3)
    assert d1.blend >= 0.8
    # the blend's closed form from the plain fit
    plain = estimate_ar1(persistent, np.arange(120))
    lam = d1.blend
    _, S0 = empirical_moments(persistent)
    np.testing.assert_allclose(d1.A, lam * plain.A)
    np.testing.assert_allclose(d1.Q, (1 - lam ** 2) * S0 + lam ** 2 * plain.Q)
    assert estimate("ar1", persistent, np.arange(120), validation=None).blend == 1.0
    with pytest.raises(ModelError, match="validation"):
        estimate("ar1", persistent, np.arange(120), validation=1.5)


def test_blend_zero_is_the_memoryless_prior():
    from lrm_cvx.belief.posterior import empirical_moments
    from lrm_cvx.glrm.dynamics import _stationary_cov, blend_moments

    X = np.random.default_rng(1).standard_normal((2, 30))
    dyn = estimate_ar1(X, np.arange(30))
    Z = X - X.mean(axis=1, keepdims=True)
    A0, Q0 = blend_moments(dyn.A, dyn.Q, _stationary_cov(Z), 0.0)
    assert not np.any(A0)
    np.testing.assert_allclose(Q0, empirical_moments(X)[1], rtol=1e-12)


def test_blend_round_trips_through_the_model_file(tmp_path):
    da = synthetic_dynamic_field(40, (5, 6), 2, seed=0)
    model = _fit(da, temporal="ar1")
    model.save(tmp_path / "m.nc")
    assert GLRM.load(tmp_path / "m.nc").dynamics_.blend == model.dynamics_.blend


# ----------------------------------------------------------------------------- errors in variables
def test_error_corrected_estimate_equals_its_closed_form():
    rng = np.random.default_rng(5)
    X = rng.normal(size=(2, 9))
    Se = np.array([[0.02, 0.005], [0.005, 0.01]])
    dyn = estimate_ar1(X, np.arange(9.0), shrinkage=0.0, error_cov=Se)
    Z = X - X.mean(axis=1, keepdims=True)
    n = 8
    C0 = sum(np.outer(Z[:, i], Z[:, i]) for i in range(n)) / n       # naive sums
    C1 = sum(np.outer(Z[:, i + 1], Z[:, i]) for i in range(n)) / n
    A = C1 @ np.linalg.inv(C0 - Se)                                   # bias-corrected Yule-Walker
    assert max(abs(np.linalg.eigvals(A))) < 0.99  # (no stability rescaling on this input)
    np.testing.assert_allclose(dyn.A, A, rtol=1e-10)
    R = sum(np.outer(Z[:, i + 1] - A @ Z[:, i], Z[:, i + 1] - A @ Z[:, i]) for i in range(n))
    np.testing.assert_allclose(dyn.Q, R / (n - 1) - Se - A @ Se @ A.T, rtol=1e-8)
    np.testing.assert_array_equal(dyn.error_cov, Se)
    # no error: plain least squares
    plain = estimate_ar1(X, np.arange(9.0), shrinkage=0.0)
    np.testing.assert_allclose(plain.A, C1 @ np.linalg.inv(C0), rtol=1e-10)
    with pytest.raises(ModelError, match="error_cov"):
        estimate_ar1(X, np.arange(9.0), error_cov=np.eye(3))


def test_error_correction_removes_the_attenuation_of_noisy_columns():
    rng = np.random.default_rng(0)
    A = np.array([[0.9, 0.05], [0.0, 0.7]])
    Q = 0.1 * np.eye(2)
    X = _ar_series(A, Q, 20000, rng)
    Se = np.diag([0.15, 0.05])  # the columns are estimates: x + e, e ~ N(0, Se)
    Xn = X + np.linalg.cholesky(Se) @ rng.standard_normal(X.shape)
    plain = estimate_ar1(Xn, np.arange(20000.0), shrinkage=0.0)
    fixed = estimate_ar1(Xn, np.arange(20000.0), shrinkage=0.0, error_cov=Se)
    assert _rel(plain.A, A) > 0.15      # least squares is biased towards 0
    assert _rel(fixed.A, A) < 0.03
    assert _rel(fixed.Q, Q) < 0.1


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fitted_model_recovers_planted_dynamics_in_the_planted_basis(seed):
    """A from a fitted model's X_ (not the true latent series), mapped to the planted latent
    coordinates (the fitted basis is a linear transform of the planted one)."""
    from lrm_cvx.validation.blending import unblended_dynamics

    da, truth = synthetic_dynamic_field(800, (12, 16), 3, missing=0.3, noise=0.02, seed=seed,
                                        return_truth=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(rank=3, offset=True, temporal="ar1", progress=False,
                     random_state=0).fit(da)
    X = truth["mu"][:, None] + truth["Z"]
    Xc = X - X.mean(axis=1, keepdims=True)
    Xf = model._Xv - model._Xv.mean(axis=1, keepdims=True)
    M = Xf @ Xc.T @ np.linalg.inv(Xc @ Xc.T)          # X_ ~ M X_true (least squares)
    dyn = unblended_dynamics(model).transformed(np.linalg.inv(M))
    assert _rel(dyn.A, truth["A"]) < 0.10


def test_rts_smoother_equals_the_dense_joint_posterior():
    from lrm_cvx.glrm.dynamics import rts_smooth

    rng = np.random.default_rng(0)
    T, k = 7, 3
    B = rng.normal(size=(k, k))
    A = 0.6 * B / np.abs(np.linalg.eigvals(B)).max()
    Q = np.eye(k) * 0.2 + 0.05 * np.ones((k, k))
    mu = rng.normal(size=k)
    P0 = np.eye(k) * 0.7
    G = np.empty((T, k, k))
    for t in range(T):
        C = rng.normal(size=(k, 2 + t % 3))
        G[t] = C @ C.T  # some steps leave directions unobserved
    b = rng.normal(size=(T, k))
    # dense: joint precision of x_0..x_{T-1} (prior AR chain + observations)
    n = T * k
    Qi, P0i = np.linalg.inv(Q), np.linalg.inv(P0)
    J = np.zeros((n, n))
    h = np.zeros(n)
    J[:k, :k] += P0i
    h[:k] += P0i @ mu
    c = mu - A @ mu  # x_t = A x_{t-1} + c + w
    for t in range(1, T):
        i, j = slice(t * k, (t + 1) * k), slice((t - 1) * k, t * k)
        J[i, i] += Qi
        J[j, j] += A.T @ Qi @ A
        J[i, j] -= Qi @ A
        J[j, i] -= A.T @ Qi
        h[i] += Qi @ c
        h[j] -= A.T @ Qi @ c
    for t in range(T):
        s = slice(t * k, (t + 1) * k)
        J[s, s] += G[t]
        h[s] += b[t]
    cov = np.linalg.inv(J)
    mean = cov @ h
    ms, Ps = rts_smooth(G, b, A, Q, mu, P0)
    np.testing.assert_allclose(ms.ravel(), mean, rtol=1e-9, atol=1e-10)
    for t in range(T):
        s = slice(t * k, (t + 1) * k)
        np.testing.assert_allclose(Ps[t], cov[s, s], rtol=1e-8, atol=1e-10)


def test_foldin_covs_match_the_per_snapshot_inverse():
    """``foldin_covs`` (one blocked product for every snapshot) against the per-snapshot
    ``inv(Y_O W Y_O^T)``; None for a snapshot with fewer than k cells or a singular Gram."""
    from lrm_cvx.glrm.dynamics import foldin_covs

    rng = np.random.default_rng(3)
    k, L = 3, 70_000  # more than one block of cells
    Y = rng.normal(size=(k, L))
    w = rng.uniform(0.5, 2.0, size=L)
    masks = [rng.random(L) < p for p in (0.9, 0.3, 0.001)]
    masks.append(np.zeros(L, bool))
    masks[-1][:2] = True  # 2 cells for k = 3: undetermined
    Yc = Y.copy()
    Yc[:, 100:] = 0.0
    Yc[2, :] = 0.0  # a zero row: singular Gram whatever the cells
    got = foldin_covs(Y, w, masks)
    for m, c in zip(masks, got, strict=True):
        obs = np.flatnonzero(m)
        if obs.size < k:
            assert c is None
            continue
        ref = np.linalg.inv((Y[:, obs] * w[obs]) @ Y[:, obs].T)
        np.testing.assert_allclose(c, ref, rtol=1e-9)
    assert foldin_covs(Yc, 1.0, [np.ones(L, bool)]) == [None]
