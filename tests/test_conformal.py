"""Conformal intervals (item 3b): the split-conformal threshold's exact finite-sample
guarantee, the conformal calibration of a model on cross-validated fold-ins (never reading the
test block), and adaptive conformal inference online in the filter."""

from __future__ import annotations

import sys
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
from scipy.stats import norm

from lrm_cvx.belief.posterior import LatentPosterior
from lrm_cvx.errors import ModelError
from lrm_cvx.glrm import GLRM
from lrm_cvx.glrm.calibrated import (
    SCORE_GRID,
    AdaptiveConformal,
    Calibration,
    conformal_quantile,
    gaussian_multiplier,
    interval_coverage,
)
from lrm_cvx.validation.calibration import calibrate

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))


def same(a: Calibration, b: Calibration) -> None:
    """Two calibrations are equal field by field (NaN equal to NaN)."""
    from dataclasses import asdict

    np.testing.assert_equal(asdict(a), asdict(b))


# ----------------------------------------------------------------------------- the threshold
@pytest.mark.parametrize("n", [19, 50, 200])
@pytest.mark.parametrize("dist", ["halfnormal", "laplace"])
def test_split_conformal_has_the_exact_finite_sample_coverage(n, dist):
    """Over 2000 draws of a calibration set and a test score from the same (known)
    distribution: coverage >= level and < level + 1 / (n + 1), and equal to k / (n + 1)."""
    rng = np.random.default_rng(n)
    draws = 2000
    if dist == "halfnormal":
        cal = np.abs(rng.standard_normal((draws, n)))
        test = np.abs(rng.standard_normal((draws, 50)))
        cdf = lambda q: 2 * norm.cdf(q) - 1  # noqa: E731
    else:
        cal = rng.exponential(size=(draws, n))  # |Laplace|
        test = rng.exponential(size=(draws, 50))
        cdf = lambda q: 1 - np.exp(-q)  # noqa: E731
    levels = np.array([0.68, 0.9, 0.95])
    q = conformal_quantile(cal, levels)  # (draws, 3), vectorised
    assert q.shape == (draws, 3)
    for i, lv in enumerate(levels):
        k = np.ceil((n + 1) * lv)
        exact = k / (n + 1)
        assert lv <= exact < lv + 1 / (n + 1)
        # the conditional coverage of each draw, from the known CDF: its mean is exact
        cov = cdf(q[:, i]) if k <= n else np.ones(draws)
        se = cov.std() / np.sqrt(draws) + 1e-12
        assert abs(cov.mean() - exact) < 4 * se
        assert cov.mean() >= lv - 4 * se and cov.mean() < lv + 1 / (n + 1) + 4 * se
        # and counted on fresh test scores
        hit = (test <= q[:, i:i + 1]).mean()
        assert abs(hit - exact) < 4 * np.sqrt(exact * (1 - exact) / test.size) + 4 * se
    # the naive quantile (level n-th) under-covers where ceil((n+1) lv) > ceil(n lv)
    naive = np.quantile(cal, 0.95, axis=1, method="inverted_cdf")
    if np.ceil(n * 0.95) < np.ceil((n + 1) * 0.95):
        assert cdf(naive).mean() < 0.95


def test_conformal_quantile_edges_and_bad_levels():
    s = np.arange(1.0, 11.0)  # 10 scores
    assert conformal_quantile(s, 0.5) == 6.0  # ceil(11 * 0.5) = 6th smallest
    assert np.isinf(conformal_quantile(s, 0.95))  # ceil(10.45) = 11 > 10
    np.testing.assert_array_equal(conformal_quantile(np.r_[s, np.nan], [0.5, 0.9]), [6.0, 10.0])
    for bad in (0.0, 1.0, 1.2, -0.1, np.nan, "x"):
        with pytest.raises(ModelError, match="level"):
            conformal_quantile(s, bad)
    with pytest.raises(ModelError, match="levels"):
        Calibration(method="conformal", levels=(1.5,), quantiles=(1.0,))
    with pytest.raises(ModelError, match="method"):
        Calibration(method="bayes")
    with pytest.raises(ModelError, match="multipliers"):
        interval_coverage([1.0], 0.0, 1.0, levels=(0.68, 0.95), multipliers=(1.0,))


def test_calibration_multipliers_and_attrs():
    grid_q = np.linspace(0.0, 4.0, len(SCORE_GRID))
    cal = Calibration(scale=1.2, n_residuals=1000, method="conformal", levels=(0.68, 0.95),
                      quantiles=(1.1, 2.3), score_table=tuple(grid_q))
    assert cal.is_conformal
    assert cal.multiplier(0.68) == 1.1 and cal.multiplier(0.95) == 2.3
    assert np.isinf(cal.multiplier(0.9995))  # beyond 1 - 1/(n+1)
    same(Calibration.from_attrs(cal.to_attrs()), cal)
    plain = Calibration(scale=2.0)
    assert not plain.is_conformal
    assert plain.multiplier(0.95) == pytest.approx(1.959963984540054)
    same(Calibration.from_attrs(plain.to_attrs()), plain)


def test_per_size_thresholds_interpolate_in_the_sample_count():
    """``size_quantiles`` give each design size its own thresholds; a belief with ``n``
    samples takes them interpolated in ``log n`` (clamped outside the sizes); without ``n`` or
    at another level the pooled ones; the filter's replace them in ``for_filter``."""
    per = np.array([[1.2, 2.4], [1.0, 2.0], [0.8, 1.6]])  # sizes 5, 15, 50 x levels
    cal = Calibration(method="conformal", levels=(0.68, 0.95), quantiles=(1.0, 2.1),
                      sizes="5,15,50", size_quantiles=tuple(per.ravel()),
                      temporal_quantiles=(0.9, 1.9),
                      temporal_size_quantiles=tuple((0.5 * per).ravel()),
                      score_table=tuple(np.linspace(0.0, 4.0, len(SCORE_GRID))))
    assert cal.design_sizes == (5, 15, 50)
    for n, j in ((5, 0), (15, 1), (50, 2)):
        assert cal.multiplier(0.68, n) == pytest.approx(per[j, 0])
        assert cal.multiplier(0.95, n) == pytest.approx(per[j, 1])
    mid = int(round(np.sqrt(15 * 50)))  # the log midpoint of 15 and 50
    w = (np.log(mid) - np.log(15)) / (np.log(50) - np.log(15))
    assert cal.multiplier(0.95, mid) == pytest.approx((1 - w) * 2.0 + w * 1.6)
    assert cal.multiplier(0.95, 1) == pytest.approx(2.4)  # clamped below
    assert cal.multiplier(0.95, 400) == pytest.approx(1.6)  # and above
    assert cal.multiplier(0.95) == 2.1  # no count: pooled
    assert cal.multiplier(0.9, 50) == cal.score_quantile(0.9)  # another level: the table
    filt = cal.for_filter()
    assert filt.multiplier(0.95, 50) == pytest.approx(0.8) and filt.multiplier(0.95) == 1.9
    same(Calibration.from_attrs(cal.to_attrs()), cal)
    # placed at the samples the fold-ins held (gaps: fewer than the design sizes)
    gappy = replace(cal, size_samples=(4.0, 12.0, 40.0))
    assert gappy.multiplier(0.95, 40) == pytest.approx(1.6)
    assert gappy.multiplier(0.95, 12) == pytest.approx(2.0)
    assert gappy.multiplier(0.95, 50) == pytest.approx(1.6)
    same(Calibration.from_attrs(gappy.to_attrs()), gappy)
    with pytest.raises(ModelError, match="size_samples"):
        replace(cal, size_samples=(4.0, 12.0))
    with pytest.raises(ModelError, match="size_quantiles"):
        Calibration(method="conformal", levels=(0.68,), quantiles=(1.0,), sizes="5,15",
                    size_quantiles=(1.0, 2.0, 3.0))
    # a size with too few scores for the level (inf): the nearest size's, not NaN from interp
    few = replace(cal, size_quantiles=(1.2, np.inf, 1.0, 2.0, 0.8, 1.6))
    assert few.multiplier(0.95, 5) == np.inf and few.multiplier(0.95, 40) == pytest.approx(1.6)
    assert few.multiplier(0.95, 8) == np.inf  # nearest in log n: 5, not 15
    assert few.multiplier(0.95, 12) == pytest.approx(2.0)
    assert few.multiplier(0.68, 8) == pytest.approx(cal.multiplier(0.68, 8))  # finite: interp
    # ACI scores a day against the thresholds of its belief's sample count
    aci = AdaptiveConformal(calibration=cal, gamma=0.1)
    scores = np.full(10, 1.7)  # inside the pooled 95 % (2.1), outside the 50-sample one (1.6)
    np.testing.assert_array_equal(aci.update(scores, 50), [1.0, 1.0])
    np.testing.assert_allclose(aci.alpha, [0.32 + 0.1 * (0.32 - 1.0), 0.05 + 0.1 * (0.05 - 1.0)])
    aci2 = AdaptiveConformal(calibration=cal, gamma=0.1)
    np.testing.assert_array_equal(aci2.update(scores), [1.0, 0.0])  # no count: pooled


def test_per_size_thresholds_hold_each_size():
    """Records of two design sizes whose scores differ in scale (the storms' shrink with the
    sample count): over 1000 draws of the calibration records, each size's own threshold covers
    a new score of that size at >= level (the split-conformal guarantee per size), while the
    pooled threshold under-covers the wide size and over-covers the narrow one."""
    from lrm_cvx.validation.calibration import _size_quantiles

    rng = np.random.default_rng(3)
    sigma = {5: 1.5, 50: 0.7}
    levels = (0.68, 0.95)
    draws, per_rec = 1000, 10
    cover = {s: np.zeros(2) for s in sigma}
    pooled_cover = {s: np.zeros(2) for s in sigma}
    for _ in range(draws):
        records = [(rng.standard_normal(per_rec) * sg, 0.0, 1, t, 0.0, s, s)
                   for s, sg in sigma.items() for t in range(8)]
        scores = np.abs(np.concatenate([r[0] for r in records]))
        pooled = conformal_quantile(scores, levels)
        per = np.reshape(_size_quantiles(records, scores, (5, 50), levels,
                                         pooled)["size_quantiles"], (2, 2))
        for i, (s, sg) in enumerate(sigma.items()):
            cover[s] += 2 * norm.cdf(per[i] / sg) - 1  # the conditional coverage, exactly
            pooled_cover[s] += 2 * norm.cdf(pooled / sg) - 1
    for s in sigma:
        n = 8 * per_rec
        got = cover[s] / draws
        assert np.all(got >= np.array(levels) - 0.005)
        assert np.all(got < np.array(levels) + 1 / (n + 1) + 0.005)
    assert np.all(pooled_cover[5] / draws < np.array(levels) - 0.04)
    assert np.all(pooled_cover[50] / draws > np.array(levels) + 0.02)


# ----------------------------------------------------------------------------- the model
N_TEST = 60  # many test snapshots: a snapshot's latent error is shared by all its cells


def _heavy(T=120, ny=12, nx=14, k=2, seed=0):
    """Data from the fold-in's model but with Student-t (3 dof) noise: one variance scale
    cannot hit both the 68 % and the 95 % quantile of it."""
    rng = np.random.default_rng(seed)
    L = ny * nx
    Y = rng.normal(size=(k, L))
    X = rng.normal(size=(k, T)) * np.array([[2.0], [1.0]])
    D = X.T @ Y + 0.3 * rng.standard_t(3, size=(T, L))
    times = np.arange(T).astype("datetime64[D]").astype("datetime64[ns]")
    return xr.DataArray(D.reshape(T, ny, nx), dims=("time", "lat", "lon"),
                        coords={"time": times, "lat": np.arange(ny) * 1.0,
                                "lon": np.arange(nx) * 1.0})


_KW = {"n_blocks": 8, "max_snapshots": 2, "residual": False, "sizes": (15,),
       "kinds": ("scattered",), "folds": "interleaved"}
# design-matched: the test campaigns are 15 scattered cells; iid snapshots (no drift), so
# interleaved folds (refits on 7/8 of the record) are the tighter estimate


@pytest.fixture(scope="module")
def heavy_model():
    data = _heavy()
    train = data.isel(time=slice(None, -N_TEST))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(rank=2, progress=False, random_state=0).fit(train)
        cal = calibrate(model, train, method="conformal", **_KW)
    return data, train, model, cal


def _test_coverage(model, data, n_test=N_TEST, size=15, seed=1):
    """Pooled coverage of the posterior's intervals at the unsampled cells of the test block."""
    V = model.region_.stack(data.isel(time=slice(-n_test, None))).astype(float)
    rng = np.random.default_rng(seed)
    prior = LatentPosterior.prior(model, "empirical")
    hits, count = np.zeros(2), 0
    for t in range(n_test):
        for _ in range(2):
            cells = np.sort(rng.choice(V.shape[1], size, replace=False))
            held = np.setdiff1d(np.arange(V.shape[1]), cells)
            post = prior.update(cells, V[t, cells])
            hits += post.interval_coverage(V[t, held], cells=held) * held.size
            count += held.size
    return hits / count


def test_conformal_calibration_holds_both_levels_out_of_sample(heavy_model):
    data, train, model, cal = heavy_model
    assert cal.is_conformal and cal.levels == (0.68, 0.95)
    assert 0 < cal.quantiles[0] < cal.quantiles[1] < np.inf
    # heavy tails: the 95 % threshold is wider, relative to the normal's, than the 68 % one
    assert cal.quantiles[1] / gaussian_multiplier(0.95) > cal.quantiles[0] / gaussian_multiplier(
        0.68)
    conformal = _test_coverage(model, data)
    np.testing.assert_allclose(conformal, [0.68, 0.95], atol=0.03)
    model.calibration_ = replace(cal, method="gaussian", levels=(), quantiles=(),
                                 score_table=(), size_quantiles=())
    gaussian = _test_coverage(model, data)
    model.calibration_ = cal
    # one variance scale misses at least one level by more than the conformal thresholds do
    assert np.abs(gaussian - [0.68, 0.95]).max() > np.abs(conformal - [0.68, 0.95]).max()


def test_posterior_interval_uses_the_thresholds(heavy_model):
    data, train, model, cal = heavy_model
    V = model.region_.stack(data.isel(time=-1)).astype(float)
    post = LatentPosterior.prior(model, "empirical").update(np.arange(0, 160, 9),
                                                            V[np.arange(0, 160, 9)])
    np.testing.assert_array_equal(post.interval_multipliers(), cal.quantiles)  # one size: 15
    assert post.n_samples == 18 and cal.design_sizes == (15,)
    mean, _, pstd = post.predict_all()
    lo, hi = post.interval(0.95)
    np.testing.assert_allclose(lo, mean - cal.quantiles[1] * pstd)
    np.testing.assert_allclose(hi, mean + cal.quantiles[1] * pstd)
    lo9, _ = post.interval(0.9)  # another level: the score table
    assert np.all(lo9 > lo)
    lo2, hi2 = post.interval(0.95, multiplier=1.0)
    np.testing.assert_allclose(hi2 - lo2, 2 * pstd)
    for bad in (0.0, 1.0, 1.5):
        with pytest.raises(ModelError, match="level"):
            post.interval(bad)
    with pytest.raises(ModelError, match="levels"):
        calibrate(model, train, method="conformal", levels=(0.68, 1.0), **_KW)
    with pytest.raises(ModelError, match="method"):
        calibrate(model, train, method="isotonic", **_KW)
    with pytest.raises(ModelError, match="folds"):
        calibrate(model, train, method="conformal", **{**_KW, "folds": "random"})


def test_forward_folds_calibrate_on_the_future(heavy_model, refits):
    """The conformal default, folds="forward": each block of the second half is folded in by
    a model refitted on the snapshots before it only; the thresholds come out finite and
    ordered."""
    data, train, model, cal = heavy_model
    try:
        fwd = calibrate(model, train, method="conformal", **{**_KW, "folds": None})
    finally:
        model.calibration_ = cal  # the fixture's
    T = train.sizes["time"]
    starts = [b[0] for b in np.array_split(np.arange(T), 8)[4:]]
    assert [n for _, n in refits] == starts  # refitted on the snapshots before each block
    assert 0 < fwd.quantiles[0] < fwd.quantiles[1] < np.inf


def test_conformal_calibration_is_saved_with_the_model(heavy_model, tmp_path):
    data, train, model, cal = heavy_model
    model.save(tmp_path / "m.nc")
    back = GLRM.load(tmp_path / "m.nc")
    same(back.calibration_, cal)


def test_the_calibration_never_reads_the_test_block(heavy_model):
    """Poison every snapshot from the origin on (NaN and huge values): the rolling-origin
    protocol's calibration (benchmarks/bench_generalization.py) is unchanged."""
    import bench_generalization as bg

    data, train, model, cal = heavy_model
    origin = data.sizes["time"] - N_TEST
    poisoned = data.copy(deep=True)
    vals = poisoned.values
    vals[origin:] = 1e30
    vals[origin:, ::2] = np.nan
    tr_bad, through_bad = bg.origin_split(poisoned, origin, N_TEST)
    assert through_bad.sizes["time"] == origin + N_TEST  # the test block is there to be read
    assert not np.isfinite(through_bad.values[origin:]).all()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m_bad = GLRM(rank=2, progress=False, random_state=0).fit(tr_bad)
        got = bg.calibrated_variants(m_bad, tr_bad, **_KW)
    same(got["conformal"], cal)
    assert got["gaussian"].scale == cal.scale and not got["gaussian"].is_conformal


# ----------------------------------------------------------------------------- online (ACI)
def test_aci_long_run_coverage_on_a_drifting_sequence():
    rng = np.random.default_rng(5)
    T, n = 3000, 10
    sigma = np.exp(np.linspace(0.0, np.log(4.0), T)) * (1 + 0.5 * np.sin(np.arange(T) / 40))
    scores = np.abs(rng.standard_normal((T, n)) * sigma[:, None])  # the model says sigma = 1
    gamma = 0.02
    aci = AdaptiveConformal(levels=(0.68, 0.95), gamma=gamma)
    for t in range(T):  # a loop over days (sequential by nature)
        aci.update(scores[t])
    target = np.array([0.68, 0.95])
    bound = (np.maximum(1 - target, target) + gamma) / (gamma * T)  # Gibbs & Candes Prop. 4.1
    assert np.all(np.abs(aci.coverage - target) <= bound)
    static = np.array([(scores <= gaussian_multiplier(lv)).mean() for lv in target])
    assert np.all(static < target - 0.2)  # without ACI the drift wrecks the coverage
    with pytest.raises(ModelError, match="gamma"):
        AdaptiveConformal(gamma=0.0)
    with pytest.raises(ModelError, match="levels"):
        AdaptiveConformal(levels=(0.95, 1.2))


def test_monitor_state_scores_the_forecast_before_assimilating(tmp_path):
    from lrm_cvx.io.samples import synthetic_dynamic_field
    from lrm_cvx.monitor import MonitorState

    data = synthetic_dynamic_field(30, (8, 10), rank=2, missing=0.1, noise=0.05, seed=4)
    train, test = data.isel(time=slice(None, -4)), data.isel(time=slice(-4, None))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(rank=2, temporal="ar1", progress=False, random_state=0).fit(train)
    model.calibration_ = Calibration(method="conformal", levels=(0.68, 0.95),
                                     quantiles=(0.8, 1.5), n_residuals=500,
                                     score_table=tuple(np.linspace(0.01, 3.0, len(SCORE_GRID))))
    state = MonitorState.from_model(model).adaptive_conformal(gamma=0.1)
    V = model.region_.stack(test).astype(float)
    alpha = np.array([0.32, 0.05])
    for i, t in enumerate(test["time"].values):
        cells = np.flatnonzero(np.isfinite(V[i]))[::4]
        prior = state._propagated(state._coerce(t))
        mean, _, pstd = prior.predict_all(cells=cells)  # the forecast, before assimilating
        z = np.abs(V[i, cells] - mean) / pstd
        m = state.interval_multipliers()
        if i == 0:
            np.testing.assert_array_equal(m, [0.8, 1.5])  # starts from the calibration
        alpha = alpha + 0.1 * (np.array([0.32, 0.05]) - (z[None, :] > m[:, None]).mean(1))
        state.assimilate((cells, V[i, cells]), time=t)
        np.testing.assert_allclose(state.aci.alpha, alpha, rtol=1e-12)
    assert state.aci.n_days == 4
    path, mpath = tmp_path / "s.nc", tmp_path / "m.nc"
    model.save(mpath)
    state.model_path = str(mpath)
    state.save(path)
    back = MonitorState.load(path)
    np.testing.assert_allclose(back.aci.alpha, state.aci.alpha)
    assert back.aci.n_days == 4 and back.aci.levels == (0.68, 0.95)
    np.testing.assert_allclose(back.interval_multipliers(), state.interval_multipliers())
    plain = MonitorState.from_model(model, online=False)
    assert plain.aci is None
    np.testing.assert_array_equal(plain.interval_multipliers(), [0.8, 1.5])
    default = MonitorState.from_model(model)  # online by default, from the offline thresholds
    assert default.aci is not None
    np.testing.assert_array_equal(default.interval_multipliers(), [0.8, 1.5])


def test_level_index_finds_a_level_to_rounding_only():
    from lrm_cvx.glrm.calibrated import level_index

    assert level_index((0.68, 0.95), 0.95) == 1
    assert level_index((0.68, 0.95), 0.68 + 1e-13) == 0  # a float's rounding
    assert level_index((0.68, 0.95), 0.9) is None
    assert level_index((), 0.5) is None
