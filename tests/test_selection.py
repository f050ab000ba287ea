"""temporal="auto": a temporal model chosen by rolling-origin validation (validation.selection)."""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import pytest
import xarray as xr
from scipy.stats import norm

from lrm_cvx import GLRM
from lrm_cvx.errors import DataError, ModelError
from lrm_cvx.glrm.calibrated import prediction_factor
from lrm_cvx.io.samples import synthetic_dynamic_field
from lrm_cvx.validation.paired import BOOTSTRAP_DRAWS, BOOTSTRAP_SEED
from lrm_cvx.validation.selection import _rule, format_selection, select_temporal


def _fit(data, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return GLRM(rank=kw.pop("rank", 3), random_state=0, progress=False, **kw).fit(data)


@pytest.fixture(scope="module")
def seasonal_field():
    """Monthly, a strong season and weak persistence: the seasonal climatology wins."""
    return synthetic_dynamic_field(72, (8, 9), 3, seed=1, seasonal_period=12,
                                   seasonal_amplitude=1.0, A=0.2 * np.eye(3),
                                   Q=0.02 * np.eye(3), freq="MS", missing=0.1, noise=0.1)


@pytest.fixture(scope="module")
def persistent_field():
    """Daily, no season, strong persistence (eigenvalues of A 0.95), noise large enough that
    15 samples do not pin the latent state alone: AR(1) wins. (With noise 0.1 this seed's
    validation was a tie, ratio 0.99, which a change of the validation's draws flipped.)"""
    return synthetic_dynamic_field(100, (8, 9), 3, seed=2, A=0.95 * np.eye(3),
                                   Q=0.1 * (1 - 0.95 ** 2) * np.eye(3), freq="D", missing=0.1,
                                   noise=0.3)


@pytest.fixture(scope="module")
def white_field():
    """Independent snapshots (A = 0): nothing to carry forward."""
    return synthetic_dynamic_field(60, (8, 9), 3, seed=3, A=np.zeros((3, 3)),
                                   Q=0.1 * np.eye(3), freq="D", missing=0.1)


def test_auto_picks_the_season_of_a_seasonal_record(seasonal_field):
    model = _fit(seasonal_field, temporal="auto")
    sel = model.selection_
    assert sel.attrs["choice_kind"] == "seasonal"
    assert model.dynamics_.kind == "seasonal"
    assert np.isclose(model.dynamics_.blend, sel.attrs["choice_alpha"])
    # the chosen candidate cuts the validation error below memoryless (noise 0.1: a floor of
    # 0.01 in every MSE) and beats every AR(1) candidate
    chosen = sel.sel(candidate=sel.attrs["choice"])
    assert float(chosen["ratio"].max()) < 0.95
    ar1 = sel["ratio"].where(sel["kind"] == "ar1", drop=True)
    assert float(chosen["ratio"].max()) < float(ar1.max("size").min())


def test_auto_picks_ar1_on_a_persistent_record_and_skips_a_season_it_cannot_carry(
        persistent_field):
    model = _fit(persistent_field, temporal="auto")
    sel = model.selection_
    assert sel.attrs["choice_kind"] == "ar1"
    assert sel.attrs["choice_alpha"] >= 0.5
    assert "seasonal" in sel.attrs["skipped"]  # 100 days: no day of year seen twice
    assert set(sel["kind"].values) == {"none", "ar1"}


def test_auto_on_independent_snapshots_never_chooses_a_harmful_model(white_field):
    sel = _fit(white_field, temporal="auto").selection_
    chosen = sel.sel(candidate=sel.attrs["choice"])
    assert bool(chosen["admissible"])
    assert float(chosen["ucb"].max()) <= sel.attrs["tolerance"] + 1e-12
    assert float(chosen["ratio"].max()) <= 1.0 + 1e-12


def test_the_rule_against_a_naive_reading():
    rng = np.random.default_rng(0)
    n_days = 30
    base = 1.0 + 0.1 * rng.random((2, n_days))
    E = np.stack([base,
                  base * 0.9,                                       # 10 % better, steady
                  base * (0.8 + 0.6 * (rng.random((2, n_days)) > 0.5)),  # noisy, often worse
                  base * 0.95])
    labels = ["none", "a:1", "b:1", "c:1"]
    meta = {lab: (lab.split(":")[0], 1.0, 1.0) for lab in labels}
    sel = _rule(E, labels, meta, [5, 15], ("route",), 1.645, 0.01, set())
    rng = np.random.default_rng(BOOTSTRAP_SEED)  # the paired bootstrap's draws, written out
    for s in range(2):
        counts = rng.multinomial(n_days, np.full(n_days, 1.0 / n_days), size=BOOTSTRAP_DRAWS)
        picks = [np.repeat(np.arange(n_days), row) for row in counts]
        for c in range(4):  # naive, candidate by candidate and size by size
            draws = [E[c, s, p].mean() / E[0, s, p].mean() - 1 for p in picks]
            assert np.isclose(sel["ucb"].values[c, s], np.quantile(draws, norm.cdf(1.645)))
            assert np.isclose(sel["ratio"].values[c, s], E[c, s].mean() / E[0, s].mean())
    assert sel.attrs["choice"] == "a:1"
    assert not bool(sel["admissible"].sel(candidate="b:1"))


def test_one_standard_error_towards_the_larger_inflation():
    """The choice is the largest inflation of the best's kind and blend whose paired mean day
    error is within one standard error of the best's at every size (checked naively); a
    tie of another blend, or a larger inflation beyond one standard error at one size, is not
    taken."""
    rng = np.random.default_rng(1)
    n_days = 40
    base = 1.0 + 0.2 * rng.random((2, n_days))
    noise = 0.01 * rng.standard_normal((6, 2, n_days))
    noise -= noise.mean(axis=-1, keepdims=True)  # the ties differ by their 0.1 % alone
    best = 0.8 * base
    tie = best * 1.001  # worse on average by much less than a standard error of the noise
    E = np.stack([base,                                  # none
                  best,                                  # ar1:1, the lowest worst ratio
                  tie + noise[2],                        # ar1:1 x2
                  tie + noise[3],                        # ar1:1 x4
                  tie + noise[4] + np.stack([0 * base[0], 0.05 + 0 * base[1]]),  # x8
                  tie + noise[5]])                       # ar1:0.5, another blend
    labels = ["none", "ar1:1", "ar1:1 x2", "ar1:1 x4", "ar1:1 x8", "ar1:0.5"]
    meta = {"none": ("none", 0.0, 1.0), "ar1:1": ("ar1", 1.0, 1.0),
            "ar1:1 x2": ("ar1", 1.0, 2.0), "ar1:1 x4": ("ar1", 1.0, 4.0),
            "ar1:1 x8": ("ar1", 1.0, 8.0), "ar1:0.5": ("ar1", 0.5, 1.0)}
    sel = _rule(E, labels, meta, [5, 15], ("route",), 1.645, 0.01, set())
    ties = []
    for c in (2, 3, 4):  # naive: the paired differences to the lowest worst ratio
        d = E[c] - E[1]
        se = d.std(axis=1, ddof=1) / np.sqrt(n_days)
        if np.all(d.mean(axis=1) <= se):
            ties.append(labels[c])
    assert sel.attrs["best"] == "ar1:1"
    assert ties == ["ar1:1 x2", "ar1:1 x4"]
    assert sel.attrs["choice"] == "ar1:1 x4" and sel.attrs["choice_inflation"] == 4.0
    assert "within one standard error" in format_selection(sel)
    # with the ties made worse by two standard errors, the best stays the choice
    E2 = E.copy()
    E2[2:4] += 2 * 0.01 * np.sqrt(2 / n_days) + 0.01
    assert _rule(E2, labels, meta, [5, 15], ("route",), 1.645, 0.01, set()).attrs[
        "choice"] == "ar1:1"


def test_one_standard_error_towards_the_lower_rank():
    """Under ``rank="auto"`` the rule takes the lowest rank of the best's kind and blend within
    one standard error of the best at every size (checked naively), then that rank's largest
    such inflation; a rank worse by more than one standard error at one size, or a tie of
    another blend, is not taken."""
    rng = np.random.default_rng(2)
    n_days = 40
    base = 1.0 + 0.2 * rng.random((2, n_days))
    noise = 0.01 * rng.standard_normal((7, 2, n_days))
    noise -= noise.mean(axis=-1, keepdims=True)
    best = 0.8 * base
    tie = best * 1.001
    worse_at_15 = np.stack([0 * base[0], 0.05 + 0 * base[1]])
    E = np.stack([base,                               # rank 5 none (the reference)
                  best,                               # rank 12 ar1:1, the lowest worst ratio
                  tie + noise[2],                     # rank 8 ar1:1
                  tie + noise[3],                     # rank 5 ar1:1
                  tie + noise[4],                     # rank 5 ar1:1 x2
                  tie + noise[5] + worse_at_15,       # rank 3 ar1:1
                  tie + noise[6]])                    # rank 3 ar1:0.5, another blend
    labels = ["rank 5 none", "rank 12 ar1:1", "rank 8 ar1:1", "rank 5 ar1:1",
              "rank 5 ar1:1 x2", "rank 3 ar1:1", "rank 3 ar1:0.5"]
    meta = {labels[0]: ("none", 0.0, 1.0, 5), labels[1]: ("ar1", 1.0, 1.0, 12),
            labels[2]: ("ar1", 1.0, 1.0, 8), labels[3]: ("ar1", 1.0, 1.0, 5),
            labels[4]: ("ar1", 1.0, 2.0, 5), labels[5]: ("ar1", 1.0, 1.0, 3),
            labels[6]: ("ar1", 0.5, 1.0, 3)}
    ties = []
    for c in range(2, 6):  # naive: the paired differences to the lowest worst ratio
        d = E[c] - E[1]
        if np.all(d.mean(axis=1) <= d.std(axis=1, ddof=1) / np.sqrt(n_days)):
            ties.append(labels[c])
    assert ties == labels[2:5]
    lowest = min(meta[lab][3] for lab in ties)
    expected = max((lab for lab in ties if meta[lab][3] == lowest), key=lambda t: meta[t][2])
    sel = _rule(E, labels, meta, [5, 15], ("route",), 1.645, 0.01, set(), ranked=True)
    assert sel.attrs["best"] == "rank 12 ar1:1"
    assert sel.attrs["choice"] == expected == "rank 5 ar1:1 x2"
    assert sel.attrs["choice_rank"] == 5 and sel.attrs["choice_inflation"] == 2.0


def test_selection_never_reads_the_test_block(seasonal_field):
    """evaluate fits on all but the last n_test snapshots: poisoning them changes nothing."""
    from lrm_cvx.evaluation import EvaluationProtocol

    n_test = 6
    poisoned = seasonal_field.copy()
    poisoned[-n_test:] = 1e6 * np.sign(np.random.default_rng(0).standard_normal(
        poisoned[-n_test:].shape))
    fits = []
    for data in (seasonal_field, poisoned):
        proto = EvaluationProtocol(data, rank=3, n_test=n_test, budgets=(5,), n_starts=1,
                                   methods=("greedy",), temporal="auto", progress=False)
        fits.append(proto._fit().model.selection_)
    xr.testing.assert_identical(fits[0], fits[1])


def test_selection_is_deterministic_and_saved(seasonal_field, tmp_path):
    a = _fit(seasonal_field, temporal="auto")
    b = _fit(seasonal_field, temporal="auto")
    xr.testing.assert_identical(a.selection_, b.selection_)
    a.save(tmp_path / "m.nc")
    loaded = GLRM.load(tmp_path / "m.nc")
    xr.testing.assert_identical(loaded.selection_, a.selection_)
    assert loaded.dynamics_.kind == a.dynamics_.kind
    np.testing.assert_array_equal(loaded.dynamics_.A, a.dynamics_.A)
    assert "chose" in format_selection(loaded.selection_)
    assert getattr(_fit(seasonal_field), "selection_", None) is None


def test_memoryless_choice_leaves_no_dynamics(white_field):
    model = _fit(white_field, temporal="auto")
    forced = select_temporal(model, white_field, kinds=("ar1",), tolerance=-1.0)
    assert forced.attrs["choice"] == "none"  # nothing is admissible but memoryless
    from lrm_cvx.validation.selection import apply_selection

    apply_selection(model, forced)
    assert model.dynamics_ is None
    from lrm_cvx.monitor import MonitorState

    assert MonitorState.from_model(model).memoryless


def test_auto_on_a_360_day_calendar():
    da = synthetic_dynamic_field(48, (6, 7), 2, seed=4, seasonal_period=12,
                                 seasonal_amplitude=1.0, A=0.2 * np.eye(2),
                                 Q=0.02 * np.eye(2), freq="MS", missing=0.1)
    times = xr.date_range("2090-01-16", periods=48, freq="MS", calendar="360_day",
                          use_cftime=True)
    model = _fit(da.assign_coords(time=times), rank=2, temporal="auto")
    sel = model.selection_
    assert not sel.attrs["skipped"]  # 360-day months are months: the season is learnt
    assert "seasonal:1" in sel["candidate"].values
    assert bool(sel["admissible"].sel(candidate=sel.attrs["choice"]))


def test_campaigns_use_the_models_choice(persistent_field):
    from lrm_cvx import simulate_campaign

    train, test = persistent_field.isel(time=slice(None, -3)), persistent_field.isel(
        time=slice(-3, None))
    model = _fit(train, temporal="auto")
    cell = int(np.flatnonzero(np.isfinite(model.region_.stack(test)[0]))[0])
    auto = simulate_campaign(model, test, cell, 4.0, method="greedy", temporal="auto")
    given = simulate_campaign(model, test, cell, 4.0, method="greedy",
                              temporal=model.dynamics_)
    np.testing.assert_array_equal(auto["mse"].values, given["mse"].values)
    default = simulate_campaign(model, test, cell, 4.0, method="greedy")  # RECOMMENDED's "auto"
    np.testing.assert_array_equal(default["mse"].values, auto["mse"].values)
    # a model without a validated choice or dynamics: "auto" is its own, memoryless
    plain = _fit(train)
    assert plain.dynamics_ is None
    mine = simulate_campaign(plain, test, cell, 4.0, method="greedy", temporal="auto")
    memoryless = simulate_campaign(plain, test, cell, 4.0, method="greedy", temporal=None)
    ar1 = simulate_campaign(plain, test, cell, 4.0, method="greedy", temporal="ar1")
    np.testing.assert_array_equal(mine["mse"].values, memoryless["mse"].values)
    assert not np.array_equal(mine["mse"].values, ar1["mse"].values)


def test_auto_bad_input(persistent_field):
    with pytest.raises(ModelError, match="at least 8 snapshots"):
        _fit(persistent_field.isel(time=slice(0, 2)), temporal="auto")
    with pytest.raises(DataError, match="DataArray"):
        _fit(np.asarray(persistent_field.values).reshape(100, -1), temporal="auto")
    irregular = persistent_field.assign_coords(time=pd.Timestamp("2000-01-01") + pd.to_timedelta(
        np.cumsum(np.r_[0, np.random.default_rng(0).integers(1, 9, 99)]), "D"))
    with pytest.raises(ModelError, match="regularly spaced"):
        _fit(irregular, temporal="auto")
    model = _fit(persistent_field, temporal="ar1")
    with pytest.raises(ModelError, match="'ar1' or 'seasonal'"):
        model.fit_dynamics("auto")
    with pytest.raises(ModelError, match="alphas"):
        select_temporal(model, persistent_field, alphas=(1.5,))


def test_shared_kriging_equals_each_posteriors_own_map():
    """The candidates' maps from one kriging call equal each posterior's own prediction."""
    from lrm_cvx.belief.filter import LatentFilter
    from lrm_cvx.validation.blending import blend_dynamics, memoryless_cov
    from lrm_cvx.validation.selection import _map_means

    da = synthetic_dynamic_field(30, (9, 10), 3, seed=5, freq="D", missing=0.1, noise=0.1)
    model = _fit(da, temporal="ar1", offset=True, spatial="exponential")
    S = memoryless_cov(model, model.dynamics_)
    dyns = [None] + [blend_dynamics(model.dynamics_, a, S) for a in (0.5, 1.0)]
    states = [LatentFilter.from_model(model, dynamics=d, memoryless=d is None) for d in dyns]
    V = model.region_.stack(da)
    cells = np.flatnonzero(np.isfinite(V[-1]))[::4]
    t = da.time.values[-1] + np.timedelta64(1, "D")
    for s in states:
        s.assimilate((cells, V[-1, cells] + 0.3), time=t)
    assert states[0].posterior.obs_model.is_spatial
    targets = np.flatnonzero(np.isfinite(V[-1]))[1::3]
    got = _map_means(np.stack([s.posterior.mean for s in states]),
                     states[0].posterior.obs_model, cells, V[-1, cells] + 0.3, targets)
    for row, s in zip(got, states, strict=True):
        np.testing.assert_allclose(row, s.posterior.predict(cells=targets)[0], rtol=1e-9,
                                   atol=1e-12)
    assert not np.allclose(got[0], got[2])  # the candidates' maps differ


def test_residual_inflation_is_a_candidate_applied_and_saved(persistent_field, tmp_path):
    """Every temporal candidate is also scored with the residual and noise variances inflated
    (AUTO_INFLATIONS); the choice's factor becomes ``residual_inflation_``, which every
    observation model of the model carries, and the model file keeps it."""
    from lrm_cvx.belief.observation import ObservationModel
    from lrm_cvx.validation.selection import AUTO_INFLATIONS, apply_selection

    model = _fit(persistent_field, temporal="auto")
    sel = model.selection_
    assert sorted(set(sel["inflation"].values)) == sorted(AUTO_INFLATIONS)
    assert model.residual_inflation_ == sel.attrs["choice_inflation"]
    n_models = int((sel["inflation"] == 1.0).sum())
    assert sel.sizes["candidate"] == n_models * len(AUTO_INFLATIONS)
    # force an inflated candidate: the observation model's noise is that factor times
    forced = select_temporal(model, persistent_field, inflations=(8.0,), tolerance=np.inf)
    forced = forced.copy()
    forced.attrs.update(choice="ar1:1 x8", choice_kind="ar1", choice_alpha=1.0,
                        choice_inflation=8.0)
    apply_selection(model, forced)
    assert model.residual_inflation_ == 8.0
    obs = ObservationModel.from_model(model)
    assert np.isclose(obs.noise_var, 8.0 * model.noise_std_ ** 2 * prediction_factor(model))
    assert "x8" in format_selection(forced) and "N times the fitted" in format_selection(forced)
    model.save(tmp_path / "m.nc")
    loaded = GLRM.load(tmp_path / "m.nc")
    assert loaded.residual_inflation_ == 8.0
    assert loaded.selection_.attrs["choice_inflation"] == 8.0
    assert GLRM(rank=3).fit(persistent_field.values.reshape(100, -1)[:, :20]
                            ).residual_inflation_ == 1.0


def test_inflation_is_rejected_where_the_basis_is_right():
    """A rank-2 field with a smooth residual fitted at rank 2: inflating the residual only
    blurs good latent updates, the validation sees it (every inflated candidate of the
    memoryless model is worse) and keeps the fitted variances."""
    from scipy.spatial.distance import cdist

    rng = np.random.default_rng(0)
    T, ny, nx = 62, 12, 14
    yy, xx = np.mgrid[0:ny, 0:nx].astype(float)
    pats = np.stack([np.sin(xx / 3.0) + 0.1 * yy, np.cos(yy / 2.5) * 0.5 + xx / nx])
    g = np.column_stack([yy.ravel(), xx.ravel()])
    K = np.exp(-(cdist(g, g) / 3.0) ** 2) + 1e-8 * np.eye(g.shape[0])
    res = (np.linalg.cholesky(K) @ rng.standard_normal((g.shape[0], T))).T
    X = rng.normal(size=(T, 2)) * [2.0, 1.0]
    vals = 10.0 + X @ pats.reshape(2, -1) + res + 0.05 * rng.standard_normal(res.shape)
    data = xr.DataArray(vals.reshape(T, ny, nx), dims=("time", "lat", "lon"),
                        coords={"time": pd.date_range("2000-01-01", periods=T, freq="D"),
                                "lat": 30.0 + np.arange(ny), "lon": 200.0 + np.arange(nx)})
    model = _fit(data, rank=2, offset=True, spatial="exponential", temporal="auto")
    sel = model.selection_
    assert sel.attrs["choice_inflation"] == 1.0 and model.residual_inflation_ == 1.0
    memoryless = sel["ratio"].where(sel["kind"] == "none", drop=True).max("size")
    assert float(memoryless.sel(candidate="none x8")) > 1.1


def test_a_short_record_validates_on_the_windows_its_refits_can_carry(persistent_field):
    """The earliest refit must leave residual degrees of freedom at the model's rank: a short
    record gets fewer (or shorter) validation windows instead of a refit's error, and a record
    too short for any gets :class:`AutoUnavailable` (a one-line ModelError) naming the cause.
    ``refit_carries`` is checked against the fit itself: it says True exactly where
    ``GLRM(rank=3, offset=True).fit`` of the first ``lo`` snapshots succeeds."""
    from lrm_cvx.validation.refits import refit_carries
    from lrm_cvx.validation.search import RollingOrigin
    from lrm_cvx.validation.selection import AutoUnavailable

    V = persistent_field.values.reshape(persistent_field.shape[0], -1)

    def fits(lo):
        try:
            _fit(persistent_field.isel(time=slice(0, lo)), rank=3, offset=True, max_iter=2)
        except ModelError:
            return False
        return True

    def carries(lo):
        return lo >= 1 and refit_carries(np.isfinite(V[:lo]), 3, True)

    assert [carries(lo) for lo in range(2, 9)] == [fits(lo) for lo in range(2, 9)]
    first = next(lo for lo in range(1, 12) if carries(lo))
    assert first > 3  # the check has something to decide here
    split = RollingOrigin(3, 2).split
    n = first + 6  # room for both windows
    assert split(n, carries) == [(n - 6, n - 3), (n - 3, n)]
    assert split(first + 5, carries) == [(first + 2, first + 5)]  # one window of 3 days
    assert split(first + 2, carries) == [(first, first + 2)]      # one window of 2 days
    assert split(first + 1, carries) is None  # none: select_temporal says AutoUnavailable
    # through the fit: 10 snapshots at rank 3 with an offset (two windows of 3 would leave 4)
    short = persistent_field.isel(time=slice(0, 10))
    model = _fit(short, rank=3, offset=True, temporal="auto")
    assert model.selection_.attrs["n_days"] in (2, 3)
    with pytest.raises(ModelError, match="cannot validate on 8 snapshots") as err:
        _fit(persistent_field.isel(time=slice(0, 8)), rank=5, offset=True, temporal="auto")
    assert isinstance(err.value, AutoUnavailable) and "\n" not in str(err.value)


def test_cli_fit_on_a_record_too_short_for_the_validation_falls_back(persistent_field,
                                                                      tmp_path, capsys):
    """``lrm-cvx fit`` (temporal='auto' by default) on 8 snapshots at rank 5: no refit before a
    window can carry the rank, so it fits without dynamics with a note (it failed with a
    refit's "T=5 times" error before); asked for by name, auto is a one-line error."""
    from lrm_cvx.cli import main

    path, out = tmp_path / "short.nc", tmp_path / "m.nc"
    persistent_field.isel(time=slice(0, 8)).rename("v").to_netcdf(path)
    assert main(["-q", "fit", str(path), "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "note: the recommended temporal='auto' cannot run on these data (temporal='auto' " \
           "cannot validate on 8 snapshots" in text
    assert GLRM.load(out).dynamics_ is None
    assert main(["-q", "fit", str(path), "--temporal", "auto", "-o", str(out),
                 "--overwrite"]) == 2
    errors = [ln for ln in capsys.readouterr().err.splitlines()
              if ln.startswith("lrm-cvx fit: error:")]
    assert len(errors) == 1 and "cannot validate on 8 snapshots" in errors[0]
