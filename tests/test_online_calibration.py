"""The monitor loop's online calibration: adaptive conformal inference's long-run coverage bound
over many synthetic draws (and its failure for a broken update), on by default in
``MonitorState`` and ``lrm-cvx monitor``, its state saved and loaded back, and the opt-out that
keeps the offline thresholds."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import xarray as xr
from scipy.stats import norm

from lrm_cvx.belief.filter import LatentFilter
from lrm_cvx.cli import main
from lrm_cvx.glrm import GLRM
from lrm_cvx.glrm.calibrated import (
    ONLINE_GAMMA,
    SCORE_GRID,
    AdaptiveConformal,
    Calibration,
)
from lrm_cvx.io.samples import synthetic_dynamic_field
from lrm_cvx.monitor import MonitorState

LEVELS = (0.68, 0.95)
_NORMAL = Calibration(method="conformal", score_table=tuple(norm.ppf(0.5 + 0.5 * np.asarray(
    SCORE_GRID))))
"""Offline thresholds of standard normal scores (a table: fast multipliers in long loops)."""


# ----------------------------------------------------------------------------- the guarantee
def _stream(rng: np.random.Generator, T: int, per_day: int) -> np.ndarray:
    """``(T, per_day)`` absolute scores whose scale drifts and jumps (not exchangeable): a
    calm start, a storm three times wider, then a slow return."""
    sd = np.r_[np.linspace(0.5, 1.0, T // 3), np.full(T // 3, 3.0),
               np.linspace(3.0, 0.3, T - 2 * (T // 3))]
    sd = sd * np.exp(0.3 * rng.standard_normal(T))
    return np.abs(rng.standard_normal((T, per_day)) * sd[:, None])


class _SignFlipped(AdaptiveConformal):
    """A deliberately broken update: the step goes the wrong way."""

    def update(self, scores, n_samples=None):
        z = np.asarray(scores, dtype=np.float64).ravel()
        err = np.mean(z[None, :] > self.multipliers(n_samples)[:, None], axis=1)
        self.alpha = self.alpha - self.gamma * (self.target - err)
        self.n_days += 1
        self.miss_sum = self.miss_sum + err
        return err


def _miscoverage_gaps(cls, gamma: float, draws: int, T: int, per_day: int) -> np.ndarray:
    """``(draws, levels)``: ``|mean(err) - a|`` of ``cls`` over ``draws`` drifting streams."""
    rng = np.random.default_rng(7)
    gaps = np.empty((draws, len(LEVELS)))
    for d in range(draws):
        aci = cls(LEVELS, gamma, _NORMAL)
        for day in _stream(rng, T, per_day):  # a loop over days
            aci.update(day)
        gaps[d] = np.abs(aci.miss_sum / T - aci.target)
    return gaps


@pytest.mark.parametrize("gamma", [0.02, ONLINE_GAMMA, 0.2])
def test_aci_long_run_miscoverage_bound_holds_on_many_draws(gamma):
    """|mean(err) - a| <= (max(alpha_1, 1 - alpha_1) + gamma) / (gamma T) on every draw and
    level (Gibbs & Candes 2021, Prop. 4.1, here in its batch form: a day's miss fraction)."""
    T, draws = 200, 20
    gaps = _miscoverage_gaps(AdaptiveConformal, gamma, draws, T, per_day=15)
    a1 = 1.0 - np.array(LEVELS)
    bound = (np.maximum(a1, 1.0 - a1) + gamma) / (gamma * T)
    assert np.all(gaps <= bound[None, :] + 1e-12), (gaps.max(axis=0), bound)


def test_aci_bound_fails_for_a_broken_update():
    """The same check catches an update that steps the wrong way."""
    T, gamma = 200, ONLINE_GAMMA
    gaps = _miscoverage_gaps(_SignFlipped, gamma, 5, T, per_day=15)
    a1 = 1.0 - np.array(LEVELS)
    bound = (np.maximum(a1, 1.0 - a1) + gamma) / (gamma * T)
    assert np.any(gaps > bound[None, :])


def test_offline_thresholds_alone_miss_the_bound_on_the_drifting_stream():
    """Without the update (the offline thresholds: the normal quantiles here) the drifting
    streams' miscoverage is far from its target: the bound is the online update's doing."""
    T, gamma = 200, ONLINE_GAMMA
    rng = np.random.default_rng(7)
    z = _stream(rng, T, 15)
    m = AdaptiveConformal(LEVELS, gamma, _NORMAL).multipliers()
    gaps = np.abs((z[..., None] > m).mean(axis=(0, 1)) - (1 - np.array(LEVELS)))
    bound = (np.maximum(1 - np.array(LEVELS), np.array(LEVELS)) + gamma) / (gamma * T)
    assert np.any(gaps > bound)


# ----------------------------------------------------------------------------- the monitor
@pytest.fixture(scope="module")
def model_and_test():
    data = synthetic_dynamic_field(36, (8, 10), rank=2, missing=0.1, noise=0.05, seed=4)
    train, test = data.isel(time=slice(None, -6)), data.isel(time=slice(-6, None))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(rank=2, temporal="ar1", progress=False, random_state=0).fit(train)
    model.calibration_ = Calibration(method="conformal", levels=LEVELS, quantiles=(0.8, 1.5),
                                     n_residuals=500,
                                     score_table=tuple(np.linspace(0.01, 3.0,
                                                                   len(SCORE_GRID))))
    V = model.region_.stack(test).astype(float)
    return model, test, V


def _days(state, test, V, n=None):
    """Assimilate the test days (every third observed cell); the multipliers after each."""
    out = []
    for i, t in enumerate(test["time"].values[:n]):
        cells = np.flatnonzero(np.isfinite(V[i]))[::3]
        state.assimilate((cells, V[i, cells]), time=t)
        out.append(state.interval_multipliers())
    return np.array(out)


def test_online_is_the_default_and_the_opt_out_is_the_offline_loop(model_and_test):
    model, test, V = model_and_test
    default = MonitorState.from_model(model)
    assert default.aci is not None and default.aci.gamma == ONLINE_GAMMA
    off = MonitorState.from_model(model, online=False)
    core = LatentFilter.from_model(model)  # the loop without any online calibration
    assert off.aci is None and core.aci is None
    m_on, m_off, m_core = (_days(s, test, V) for s in (default, off, core))
    np.testing.assert_array_equal(m_off, m_core)
    np.testing.assert_array_equal(m_off, np.tile([0.8, 1.5], (len(m_off), 1)))
    assert default.aci.n_days == len(m_on) and not np.allclose(m_on[-1], [0.8, 1.5])
    # the online calibration moves the intervals only: the maps are the same bit for bit
    for name in ("mean", "std", "predictive_std"):
        np.testing.assert_array_equal(default.predict()[name].values, off.predict()[name].values)
    np.testing.assert_array_equal(default.posterior.precision, core.posterior.precision)


def test_online_thresholds_round_trip_and_old_files_start_offline(model_and_test, tmp_path):
    model, test, V = model_and_test
    mpath = tmp_path / "m.nc"
    model.save(mpath)
    state = MonitorState.from_model(model)
    _days(state, test, V, n=3)
    state.model_path = str(mpath)
    state.save(tmp_path / "s.nc")
    back = MonitorState.load(tmp_path / "s.nc")
    np.testing.assert_array_equal(back.aci.alpha, state.aci.alpha)
    np.testing.assert_array_equal(back.aci.miss_sum, state.aci.miss_sum)
    assert (back.aci.n_days, back.aci.gamma, back.aci.levels) == (3, ONLINE_GAMMA, LEVELS)
    np.testing.assert_array_equal(back.interval_multipliers(), state.interval_multipliers())
    # the next day goes on identically from the loaded state
    np.testing.assert_array_equal(_days(back, test.isel(time=slice(3, 4)), V[3:4]),
                                  _days(state, test.isel(time=slice(3, 4)), V[3:4]))
    # an opt-out state stays offline when loaded
    off = MonitorState.from_model(model, online=False)
    off.model_path = str(mpath)
    off.save(tmp_path / "off.nc")
    assert MonitorState.load(tmp_path / "off.nc").aci is None
    # a state file written before the online calibration: its offline thresholds, then online
    with xr.open_dataset(tmp_path / "s.nc") as ds:
        old = ds.load()
    for key in [k for k in old.attrs if k.startswith("aci_")] + ["online_calibration"]:
        del old.attrs[key]
    old.to_netcdf(tmp_path / "old.nc")
    loaded = MonitorState.load(tmp_path / "old.nc")
    assert loaded.aci is not None and loaded.aci.n_days == 0
    np.testing.assert_array_equal(loaded.interval_multipliers(), [0.8, 1.5])


def test_a_corrupt_online_state_is_one_line(model_and_test, tmp_path, capsys):
    model, test, V = model_and_test
    model.save(tmp_path / "m.nc")
    state = MonitorState.from_model(model)
    state.model_path = str(tmp_path / "m.nc")
    state.save(tmp_path / "s.nc")
    with xr.open_dataset(tmp_path / "s.nc") as ds:
        bad = ds.load()
    bad.attrs["aci_alpha"] = np.array([0.3])  # one level short
    bad.to_netcdf(tmp_path / "bad.nc")
    assert main(["-q", "monitor", "map", str(tmp_path / "bad.nc"), "-o",
                 str(tmp_path / "map.nc")]) == 2
    err = capsys.readouterr().err
    assert "alpha" in err and err.count("\n") == 1
    assert not (tmp_path / "map.nc").exists()


def test_cli_recalibrates_by_default_and_offline_intervals_opts_out(tmp_path, capsys):
    da = synthetic_dynamic_field(34, (6, 7), 3, seed=4, noise=0.03)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(3, progress=False, max_iter=20, temporal="ar1", offset=True).fit(
            da.isel(time=slice(0, 30)))
    model.save(tmp_path / "model.nc")
    da.isel(time=30).to_dataset(name="ndvi").to_netcdf(tmp_path / "obs30.nc")
    for flag, online in (((), True), (("--offline-intervals",), False)):
        state = tmp_path / f"state{online}.nc"
        assert main(["-q", "monitor", "init", str(tmp_path / "model.nc"), "--state",
                     str(state), *flag]) == 0
        capsys.readouterr()
        assert main(["-q", "monitor", "assimilate", str(state), str(tmp_path / "obs30.nc"),
                     "--time", "2013-01-31"]) == 0
        out = capsys.readouterr().out
        loaded = MonitorState.load(state)
        assert ("recalibrated online (1 day(s) scored)" in out) is online
        assert (loaded.aci is not None) is online
        if online:
            assert loaded.aci.n_days == 1
