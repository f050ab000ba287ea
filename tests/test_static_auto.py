"""``place_sensors(model, n, training=...)``: the criterion chosen on the training snapshots
(``criterion="auto"``, planning/static_auto.py), checked against a naive recomputation through
the public API (refit, place with each candidate, score the fold-in by hand, argmin)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import xarray as xr

from lrm_cvx.belief.posterior import fold_in_snapshots
from lrm_cvx.errors import PlanningError
from lrm_cvx.glrm import GLRM, SpatialOptions
from lrm_cvx.planning import place_sensors
from lrm_cvx.planning import static_auto as sa
from lrm_cvx.validation.search import BlockGuard

HOT = (1, 2)  # the cell of a planted independent, strong signal


def _field(seed: int, hot: float = 0.0, T: int = 14, ny: int = 6, nx: int = 7):
    """A rank-2 field plus white noise on a 6 x 7 grid; ``hot`` adds an independent signal of
    that std at the cell :data:`HOT` (which no low-rank or smooth model explains)."""
    rng = np.random.default_rng(seed)
    lat, lon = np.arange(ny) * 1.0, np.arange(nx) * 1.0
    base = rng.normal(size=(2, ny, nx))
    f = (rng.normal(size=(T, 2, 1, 1)) * base[None]).sum(1) + 0.3 * rng.normal(size=(T, ny, nx))
    if hot:
        f[:, HOT[0], HOT[1]] += hot * rng.normal(size=T)
    da = xr.DataArray(f, dims=("time", "lat", "lon"),
                      coords=dict(time=np.arange(T), lat=lat, lon=lon))
    return _fit(da), da


def _fit(da):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return GLRM(2, random_state=0, progress=False, offset=True,
                    spatial="exponential").fit(da)


def _naive(model, train, n):
    """The rule of the module docstring from scratch: blocks of round(T / 10) (>= 3), as many
    as fit up to four with >= 3 snapshots before the first; refit on the snapshots before each;
    place with each candidate; score by hand; the guard on the per-window changes;
    ``(windows, per-snapshot MSE per candidate, choice)``."""
    T = train.sizes["time"]
    h = max(3, round(T / 10))
    W = min(4, (T - 5) // h)  # rank 2 + offset: refits on >= 5 snapshots
    windows = [(T - j * h, T - (j - 1) * h) for j in range(W, 0, -1)]
    per = {"risk+exchange": [], "gp-variance+exchange": [], "gp-variance": []}
    window_mse = {lab: [] for lab in per}
    for a, b in windows:
        early = train.isel(time=slice(None, a))
        fit = _fit(early)
        values = fit.region_.stack(train.isel(time=slice(a, b))).astype(np.float64)
        cells = {"risk+exchange": place_sensors(fit, n, training=early, criterion="risk",
                                                exchange=n < a).cells,
                 "gp-variance+exchange": place_sensors(fit, n, criterion="gp-variance",
                                                       exchange=True).cells,
                 "gp-variance": place_sensors(fit, n, criterion="gp-variance").cells}
        for lab, S in cells.items():
            V = np.full(values.shape, np.nan)
            V[:, S] = values[:, S]
            pred, *_ = fold_in_snapshots(fit.latent_prior("empirical", spatial=True), V)
            e = np.mean((pred - values) ** 2, axis=1)
            per[lab].extend(e)
            window_mse[lab].append(e.mean())
    per = {lab: np.array(v) for lab, v in per.items()}
    window_mse = {lab: np.array(v) for lab, v in window_mse.items()}
    risk = window_mse["risk+exchange"]
    choice, best = "risk+exchange", risk.mean()
    for lab in ("gp-variance+exchange", "gp-variance"):
        d = window_mse[lab] - risk  # one placement draw per window: the window is the unit
        ucb = (d.mean() + sa.AUTO_CONFIDENCE * d.std(ddof=1) / np.sqrt(d.size)) / risk.mean()
        if ucb < 0 and window_mse[lab].mean() < best:
            choice, best = lab, window_mse[lab].mean()
    return windows, per, choice


@pytest.mark.parametrize("seed, hot, confidence", [
    (0, 0.0, 1.645), (0, 3.0, 1.645), (4, 3.0, 1.645),
    (0, 0.0, 0.0), (3, 0.0, 0.0),  # no guard: gp-variance + exchange wins these
])
def test_the_choice_is_the_naive_rule_and_the_plan_its_criterion(seed, hot, confidence,
                                                                  monkeypatch):
    monkeypatch.setattr(sa, "AUTO_CONFIDENCE", confidence)
    model, train = _field(seed, hot)
    n = 4
    plan = place_sensors(model, n, training=train)
    sel = plan.refinement["selection"]
    windows, per, choice = _naive(model, train, n)
    held = np.concatenate([np.arange(a, b) for a, b in windows])
    assert list(zip(sel["window_start"].values, sel["window_stop"].values,
                    strict=True)) == windows
    for lab, e in per.items():
        np.testing.assert_allclose(sel["mse_snapshot"].sel(candidate=lab).values, e,
                                   rtol=1e-8)
        assert float(sel["score"].sel(candidate=lab)) == pytest.approx(
            np.mean([e[(held >= a) & (held < b)].mean() for a, b in windows]), rel=1e-8)
    assert sel.attrs["choice"] == choice and sel.attrs["skipped"] == ""
    if confidence == 0.0:
        assert choice == "gp-variance+exchange"
    # the plan is the chosen criterion's on the full model and training
    crit, exchange = sa.AUTO_CANDIDATES[choice]
    if crit == "risk":
        ref = place_sensors(model, n, training=train, criterion="risk", exchange=True)
    else:
        ref = place_sensors(model, n, criterion="gp-variance", exchange=exchange)
    assert plan.criterion == crit and plan.cells.tolist() == ref.cells.tolist()
    # criterion="auto" is the default
    assert place_sensors(model, n, training=train, criterion="auto").cells.tolist() \
        == plan.cells.tolist()


def _rigged(model, train):
    """The real validation (refits and fold-in scores) with rigged placements: the gp-variance
    candidates get four well-spread cells, risk one of them only; ``(table, cells, V)``."""
    region = model.region_
    V = region.stack(train).astype(np.float64)
    gi = region.grid_index
    spread = np.array([int(np.flatnonzero((gi == c).all(axis=1))[0])
                       for c in ((1, 1), (1, 5), (4, 1), (4, 5))])
    table = sa.select_criterion(model, region, 4, V,
                                lambda p, Vtr, crit, ex: spread[:1] if crit == "risk" else spread,
                                region.n_cells)
    return table, spread, V


def test_the_guard_keeps_risk_unless_a_candidate_is_surely_better():
    """Rigged placements through the real validation (refits and fold-in scores): the
    gp-variance candidates get four well-spread cells, risk one of them only (surely worse)
    -> the four win; every candidate the same cells -> risk."""
    model, train = _field(0, T=30)
    rigged, spread, V = _rigged(model, train)
    assert rigged.attrs["choice"] == "gp-variance+exchange"  # first of the equal two
    assert (rigged["ucb"].values[1:] < 0).all()
    region = model.region_
    same = sa.select_criterion(model, region, 4, V, lambda *a: spread, region.n_cells)
    assert same.attrs["choice"] == "risk+exchange"
    # the planted hot cell: risk validates best, and surely
    model, train = _field(4, 3.0)
    sel = place_sensors(model, 4, training=train).refinement["selection"]
    assert sel.attrs["choice"] == "risk+exchange" and (sel["ucb"].values[1:] > 0).all()


def test_the_guard_counts_windows_not_snapshots():
    """The bound by hand on ``mse (candidates, windows)``: the paired change per window, its
    spread over the windows; a candidate that wins one window by far and loses the other is
    not surely better however many snapshots each window holds; one window never switches."""
    mse = np.array([[10.0, 10.0, 10.0], [6.0, 11.0, 7.0], [9.0, 9.5, 9.2]])
    d1, d2 = np.array([-4.0, 1.0, -3.0]), np.array([-1.0, -0.5, -0.8])
    ref = [(d.mean() + sa.AUTO_CONFIDENCE * d.std(ddof=1) / np.sqrt(3)) / 10.0 for d in (d1, d2)]
    # snapshots of a window: every value of mse[c, w] twice, so the window means are mse
    E = np.repeat(mse, 2, axis=1)[:, None, :]
    guard = BlockGuard([(0, 2), (2, 4), (4, 6)], sa.AUTO_CONFIDENCE)
    np.testing.assert_allclose(guard(E).ucb, [0.0, *ref], rtol=1e-12)
    assert ref[0] > 0 > ref[1]  # the erratic candidate keeps risk, the steady one does not
    assert guard(E).choice == 2
    assert BlockGuard([(0, 2)], sa.AUTO_CONFIDENCE)(E[..., :2]).ucb.tolist() == [0.0, np.inf,
                                                                                  np.inf]
    # through the real validation: 8 snapshots leave room for one window (rank 2 + offset refits
    # on >= 5), so rigged placements that beat risk by far still do not switch
    one, *_ = _rigged(*_field(0, T=8))
    assert one.sizes["window"] == 1 and one.attrs["choice"] == "risk+exchange"
    assert float(one["score"][1]) < float(one["score"][0])


def test_the_printed_table_has_each_candidate_per_block():
    model, train = _field(0)
    sel = place_sensors(model, 4, training=train).refinement["selection"]
    lines = sa.format_placement_selection(sel).splitlines()
    assert lines[0].startswith(f"criterion auto: {sel.attrs['choice']} ")
    assert len(lines) == 1 + sel.sizes["candidate"]
    for line, lab in zip(lines[1:], sel["candidate"].values, strict=True):
        per = line[line.index("[") + 1:line.index("]")].split()
        np.testing.assert_allclose([float(v) for v in per],
                                   sel["mse"].sel(candidate=lab).values, rtol=1e-3)
        assert line.split()[0] == lab and ("<- chosen" in line) == (lab == sel.attrs["choice"])


def test_a_block_is_never_scored_by_what_saw_it():
    """Poisoning the last block changes its own scores only: the first window's placements,
    refit and scores never read it (no look-ahead)."""
    model, train = _field(0)
    sel = place_sensors(model, 4, training=train).refinement["selection"]
    a = int(sel["window_start"].values[1])
    bad = train.copy()
    bad[a:] = 1e3 * np.random.default_rng(9).normal(size=bad[a:].shape)
    sel2 = place_sensors(model, 4, training=bad).refinement["selection"]
    np.testing.assert_array_equal(sel2["mse"].isel(window=0).values,
                                  sel["mse"].isel(window=0).values)
    assert not np.allclose(sel2["mse"].isel(window=1).values, sel["mse"].isel(window=1).values)


def test_deterministic_and_the_windows_rule():
    model, train = _field(3)
    p1, p2 = (place_sensors(model, 4, training=train) for _ in range(2))
    assert p1.cells.tolist() == p2.cells.tolist()
    np.testing.assert_array_equal(p1.refinement["selection"]["mse"].values,
                                  p2.refinement["selection"]["mse"].values)
    assert sa.validation_windows(6) == [(3, 6)]  # room for one block of 3 only
    assert sa.validation_windows(14, min_fit=5) == [(5, 8), (8, 11), (11, 14)]
    assert sa.validation_windows(14, min_fit=9) == [(11, 14)]
    with pytest.raises(PlanningError, match="training has 7, it needs at least 8"):
        sa.validation_windows(7, min_fit=5)
    assert sa.validation_windows(14) == [(5, 8), (8, 11), (11, 14)]
    assert sa.validation_windows(55) == [(31, 37), (37, 43), (43, 49), (49, 55)]
    assert sa.validation_windows(100) == [(60, 70), (70, 80), (80, 90), (90, 100)]
    assert sa.validation_windows(500) == [(452, 464), (464, 476), (476, 488), (488, 500)]


def test_skipped_above_the_cell_limit_and_without_a_spatial_residual(monkeypatch):
    model, train = _field(0)
    monkeypatch.setattr(sa, "AUTO_MAX_CELLS", 10)
    plan = place_sensors(model, 4, training=train)
    sel = plan.refinement["selection"]
    assert sel.attrs["choice"] == "risk+exchange" and "AUTO_MAX_CELLS" in sel.attrs["skipped"]
    ref = place_sensors(model.Y_, model.region_, 4, prior=model, training=train)  # risk
    assert plan.criterion == "risk" and plan.cells.tolist() == ref.cells.tolist()
    # above the limit no refit is needed: a LatentPosterior prior is enough
    prior = model.latent_prior("empirical", spatial=True)
    assert place_sensors(model.Y_, model.region_, 4, prior=prior, training=train,
                         criterion="auto").cells.tolist() == ref.cells.tolist()
    monkeypatch.undo()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        flat = GLRM(2, random_state=0, progress=False, offset=True).fit(train)
    sel = place_sensors(flat, 4, training=train).refinement["selection"]
    assert sel.attrs["choice"] == "risk+exchange" and "spatial" in sel.attrs["skipped"]


def test_bad_input_is_a_one_line_error_naming_training():
    model, train = _field(0)
    cases = [
        (dict(criterion="auto"), "training"),
        (dict(criterion="auto", training=train.isel(time=slice(0, 5))), "training has 5"),
        (dict(training=train.isel(time=slice(0, 5))), "training has 5"),
        (dict(criterion="auto", training=train, exchange=True), "exchange"),
        (dict(criterion="auto", training=train, paper=True), "paper=True"),
        (dict(criterion="auto", training=train, ridge=0.1), "ridge"),
    ]
    for kw, match in cases:
        with pytest.raises(PlanningError, match=match) as err:
            place_sensors(model, 4, **kw)
        assert "\n" not in str(err.value)
    prior = model.latent_prior("empirical", spatial=True)
    with pytest.raises(PlanningError, match="fitted GLRM"):
        place_sensors(model.Y_, model.region_, 4, prior=prior, training=train, criterion="auto")
    with pytest.raises(PlanningError, match="fitted GLRM"):
        place_sensors(model.Y_, model.region_, 4, training=train, criterion="auto")


def test_the_refits_keep_the_kernel_the_model_chose():
    """A model whose kernel was validated (``spatial="auto"``) is refitted with that kernel's
    family and anisotropy, its parameters fitted to the refit's own residuals: the same
    covariance a refit that validates the kernel again gets when it chooses that family."""
    _, da = _field(0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(2, random_state=0, progress=False, offset=True, spatial="auto").fit(da)
    region = model.region_
    V = region.stack(da).astype(np.float64)
    fit = sa._refit(model, V[:10], region)
    chosen = model.spatial_cov_
    assert fit.spatial == SpatialOptions(chosen.model, chosen.anisotropy)
    assert fit.spatial_cov_.model == chosen.model
    assert fit.spatial_cov_.range != chosen.range  # refitted, not copied
    params = {**model.get_params(), "temporal": None, "calibration": None}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        again = GLRM(**params).fit(xr.DataArray(V[:10], dims=("time", "cell")), region=region)
    assert again.spatial_cov_.model == chosen.model and again.spatial_cov_.anisotropy == 1.0
    assert fit.spatial_cov_ == again.spatial_cov_
    np.testing.assert_array_equal(fit.Y_, again.Y_)


def test_another_sensor_count_shares_the_refits(monkeypatch):
    """A second call on the same model and training refits nothing and gives the table a
    fresh validation gives; other training snapshots (or another model) refit."""
    model, train = _field(4, 3.0)
    calls = []
    refit = sa._refit
    monkeypatch.setattr(sa, "_refit", lambda m, V, r: calls.append(V.shape[0]) or refit(m, V, r))
    sa._REFITS.clear()
    first = place_sensors(model, 4, training=train).refinement["selection"]
    n_windows = first.sizes["window"]
    assert len(calls) == n_windows
    second = place_sensors(model, 5, training=train).refinement["selection"]
    assert len(calls) == n_windows
    sa._REFITS.clear()
    fresh = place_sensors(model, 5, training=train).refinement["selection"]
    assert len(calls) == 2 * n_windows
    np.testing.assert_array_equal(second["mse_snapshot"].values, fresh["mse_snapshot"].values)
    assert second.attrs["choice"] == fresh.attrs["choice"]
    other = train.copy()
    other[0, 0, 0] += 1.0
    place_sensors(model, 5, training=other)
    assert len(calls) == 3 * n_windows
    place_sensors(_fit(other), 5, training=other)
    assert len(calls) == 4 * n_windows
