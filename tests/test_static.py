"""Static placement on the fold-in's training error (criterion="risk") and the exchange search
(planning/static.py): checked against the fold-in itself (``fold_in_snapshots``) recomputed from
scratch, and against brute force on tiny regions."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr

from lrm_cvx import Region
from lrm_cvx.belief.posterior import LatentPosterior, ObservationModel, fold_in_snapshots
from lrm_cvx.errors import PlanningError
from lrm_cvx.information import gp_variance_value
from lrm_cvx.planning import place_sensors, plan_greedy
from lrm_cvx.planning import static as st
from lrm_cvx.spatial import ResidualCovariance


def _setup(seed: int, spatial: bool = True, ny: int = 5, nx: int = 6, T: int = 7):
    """A tiny region, a fold-in prior (offset, scale, spatial residual or per-cell noise) and
    training snapshots drawn from a field that is *not* the prior's model."""
    rng = np.random.default_rng(seed)
    lat, lon = np.arange(ny) * 1.0, np.arange(nx) * 1.0
    grid = xr.DataArray(np.zeros((ny, nx)), dims=("lat", "lon"), coords=dict(lat=lat, lon=lon))
    region = Region.from_dataarray(grid, mask=rng.random((ny, nx)) > 0.2)
    L = region.n_cells
    k = 2
    Y = rng.normal(size=(k, L))
    B = rng.normal(size=(k, k))
    S0 = B @ B.T + 0.3 * np.eye(k)
    m0 = rng.normal(size=k)
    offset = rng.normal(size=L)
    scale = rng.uniform(0.5, 2.0, L)
    if spatial:
        cov = ResidualCovariance("exponential", sill=0.4, range=1.5, nugget=0.05)
        obs = ObservationModel(Y=Y, offset=offset, scale=scale, spatial_cov=cov, region=region)
    else:
        obs = ObservationModel(Y=Y, offset=offset, scale=scale,
                               noise_var=rng.uniform(0.05, 0.3, L))
    prior = LatentPosterior.from_moments(obs, m0, S0)
    field = rng.normal(size=(T, ny, nx)) + np.sin(lon)[None, None, :] * rng.normal(size=(T, 1, 1))
    train = xr.DataArray(field, dims=("time", "lat", "lon"),
                         coords=dict(time=np.arange(T), lat=lat, lon=lon))
    return region, Y, prior, train


def _J(prior, region, train, cells) -> float:
    """The fold-in's squared error over the training snapshots from ``cells``, from scratch."""
    V = region.stack(train).astype(np.float64)
    W = np.full(V.shape, np.nan)
    cells = np.asarray(cells, dtype=np.int64)
    W[:, cells] = V[:, cells]
    pred, *_ = fold_in_snapshots(prior, W)
    return float(np.sum((pred - V) ** 2))


def _place(region, Y, prior, train, n, **kw):
    return place_sensors(Y, region, n, criterion="risk", prior=prior, training=train, **kw)


@pytest.mark.parametrize("spatial", [True, False])
@pytest.mark.parametrize("seed", range(2))
def test_first_pick_is_the_brute_force_best_single_cell(seed, spatial):
    region, Y, prior, train = _setup(seed, spatial)
    errs = np.array([_J(prior, region, train, [x]) for x in range(region.n_cells)])
    plan = _place(region, Y, prior, train, 1)
    assert int(plan.cells[0]) == int(np.argmin(errs))
    assert plan.refinement["objective"] == pytest.approx(errs.min(), rel=1e-8)


@pytest.mark.parametrize("spatial", [True, False])
@pytest.mark.parametrize("seed", range(2))
def test_greedy_equals_a_naive_greedy_on_the_fold_in(seed, spatial):
    region, Y, prior, train = _setup(seed + 10, spatial)
    n = 4
    picked: list[int] = []
    values = []
    for _ in range(n):
        cand = [x for x in range(region.n_cells) if x not in picked]
        errs = [_J(prior, region, train, picked + [x]) for x in cand]
        picked.append(cand[int(np.argmin(errs))])
        values.append(min(errs))
    plan = _place(region, Y, prior, train, n)
    assert [int(c) for c in plan.cells] == picked
    np.testing.assert_allclose(plan.history["objective"], values, rtol=1e-8)
    # gain of each pick = the drop of the from-scratch error
    drops = -np.diff([_J(prior, region, train, [])] + values)
    np.testing.assert_allclose(plan.history["gain"], drops, rtol=1e-6, atol=1e-9)
    assert plan.path["kind"] == "static" and plan.criterion == "risk"
    assert plan.cost == n and plan.start == -1


def test_risk_objective_is_the_fold_in_error():
    region, Y, prior, train = _setup(3)
    cells = [0, 5, 9]
    assert st.risk_objective(prior, train, cells, region) == pytest.approx(
        _J(prior, region, train, cells), rel=1e-9)


@pytest.mark.parametrize("seed", range(3))
def test_exchange_never_worsens_and_stops_at_a_local_optimum(seed):
    region, Y, prior, train = _setup(seed + 20, ny=4, nx=5, T=6)
    L, n = region.n_cells, 3
    greedy = _place(region, Y, prior, train, n)
    ex = _place(region, Y, prior, train, n, exchange=True, sweeps=20)
    J = lambda S: _J(prior, region, train, S)  # noqa: E731
    Jg, Je = J(greedy.cells), J(ex.cells)
    assert Je <= Jg * (1 + 1e-9)
    assert ex.refinement["converged"]
    assert ex.refinement["objective_after"] <= ex.refinement["objective_before"]
    assert ex.method == "greedy+exchange" and len(set(ex.cells.tolist())) == n
    S = [int(c) for c in ex.cells]
    for i in range(n):
        for x in range(L):
            if x in S:
                continue
            trial = S[:i] + [x] + S[i + 1:]
            assert J(trial) >= Je * (1 - 1e-7), (i, x)


def test_gp_variance_exchange_never_worsens_and_is_a_local_optimum():
    region, Y, prior, _ = _setup(4, ny=4, nx=5)
    info = prior.information()
    S0, cov, tw = info["prior_cov"], info["spatial_cov"], info["target_weights"]
    value = lambda S: gp_variance_value(Y, region, cov, S0, S, target_weights=tw)  # noqa: E731
    n, L = 3, region.n_cells
    g = place_sensors(Y, region, n, criterion="gp-variance", prior=prior)
    e = place_sensors(Y, region, n, criterion="gp-variance", prior=prior, exchange=True,
                      sweeps=20)
    assert value(e.cells) <= value(g.cells) * (1 + 1e-9)
    assert e.refinement["objective"] == pytest.approx(value(e.cells), rel=1e-8)
    S = [int(c) for c in e.cells]
    for i in range(n):
        for x in set(range(L)) - set(S):
            assert value(S[:i] + [x] + S[i + 1:]) >= value(S) * (1 - 1e-7)


def test_deterministic_static_plan_and_certificate():
    region, Y, prior, train = _setup(5)
    a = _place(region, Y, prior, train, 5, exchange=True)
    cert = a.certify()
    assert cert.plan_criterion == "risk" and np.isnan(cert.gap)
    df = a.to_dataframe()
    assert list(df["cell"]) == [int(c) for c in a.cells]


def test_traversable_restricts_the_sensor_sites():
    region, Y, prior, train = _setup(6)
    mask = xr.DataArray(np.zeros(region.shape, bool), dims=("lat", "lon"),
                        coords=dict(lat=region.lat.values, lon=region.lon.values))
    mask[:, :3] = True
    plan = _place(region, Y, prior, train, 3, traversable=mask, exchange=True)
    gi = region.grid_index[plan.cells]
    assert np.all(gi[:, 1] < 3)
    assert plan.path["traversable"] == "mask"


def test_bad_inputs_name_the_argument(monkeypatch):
    region, Y, prior, train = _setup(7)
    L = region.n_cells
    with pytest.raises(PlanningError, match="n_sensors"):
        _place(region, Y, prior, train, 0)
    with pytest.raises(PlanningError, match="n_sensors"):
        _place(region, Y, prior, train, L + 1)
    other = train.assign_coords(lat=train.lat + 0.5)
    with pytest.raises(PlanningError, match="training"):
        _place(region, Y, prior, other, 3)
    with pytest.raises(PlanningError, match="training"):
        _place(region, Y, prior, np.zeros((4, L + 2)), 3)
    with pytest.raises(PlanningError, match="training="):
        place_sensors(Y, region, 3, criterion="risk", prior=prior)
    with pytest.raises(PlanningError, match="prior="):
        place_sensors(Y, region, 3, criterion="risk", training=train)
    with pytest.raises(PlanningError, match="exchange"):
        place_sensors(Y, region, 3, criterion="fisher", ridge=1e-3, exchange=True)
    with pytest.raises(PlanningError, match="sweeps"):
        _place(region, Y, prior, train, 3, exchange=True, sweeps=0)
    with pytest.raises(PlanningError, match="Y"):
        _place(region, Y + 1.0, prior, train, 3)
    with pytest.raises(PlanningError, match=r"\['ridge'\]"):
        _place(region, Y, prior, train, 3, ridge=1.0)
    with pytest.raises(TypeError, match="training"):
        plan_greedy(Y, region, 0, 5.0, training=train, progress=False)
    monkeypatch.setattr(st, "RISK_MAX_CELLS", L - 1)  # the cap of the dense reference only
    with pytest.raises(PlanningError, match="RISK_MAX_CELLS"):
        _place(region, Y, prior, train, 3, method="dense")
    with pytest.raises(PlanningError, match="RISK_MAX_CELLS"):
        place_sensors(Y, region, 3, criterion="gp-variance", prior=prior, exchange=True,
                      method="dense")
    assert len(_place(region, Y, prior, train, 3).cells) == 3  # the scalable form: no cap


# --------------------------------------------------------------------------- the CLI
@pytest.fixture(scope="module")
def cli_files(tmp_path_factory):
    from lrm_cvx.cli import main

    rng = np.random.default_rng(1)
    T, ny, nx, k = 12, 6, 7, 2
    X, Y = rng.normal(size=(k, T)), rng.normal(size=(k, ny * nx))
    v = (X.T @ Y + 0.3 * rng.normal(size=(T, ny * nx))).reshape(T, ny, nx)
    da = xr.DataArray(v.astype(np.float32), dims=("time", "lat", "lon"), name="temp",
                      coords={"time": np.arange(T), "lat": 40 + np.arange(ny) * 0.5,
                              "lon": -70 + np.arange(nx) * 0.5})
    d = tmp_path_factory.mktemp("place")
    data, model = d / "field.nc", d / "model.nc"
    da.to_netcdf(data)
    assert main(["-q", "fit", str(data), "--rank", "2", "--recommended", "-o", str(model)]) == 0
    return d, data, model


def test_cli_place_writes_the_python_placement(cli_files, capsys):
    import pandas as pd

    from lrm_cvx.cli import main
    from lrm_cvx.glrm import GLRM

    d, data, model_path = cli_files
    out = d / "sensors.csv"
    assert main(["-q", "place", str(model_path), str(data), "--sensors", "4", "--exchange",
                 "-o", str(out)]) == 0
    assert "risk greedy" in capsys.readouterr().out
    model = GLRM.load(model_path)
    ref = place_sensors(model.Y_, model.region_, 4, criterion="risk",
                        prior=model.latent_prior("empirical", spatial=True),
                        training=xr.open_dataarray(data), exchange=True)
    assert pd.read_csv(out)["cell"].tolist() == [int(c) for c in ref.cells]
    geo = d / "sensors.geojson"
    assert main(["-q", "place", str(model_path), "--sensors", "3", "-o", str(geo)]) == 0
    import json

    feats = json.loads(geo.read_text())["features"]
    assert [f["geometry"]["type"] for f in feats] == ["Point"] * 3


@pytest.mark.parametrize("argv, message", [
    (["--sensors", "3", "--criterion", "risk"], "needs DATA"),
    (["DATA", "--sensors", "3", "--criterion", "fisher"], "is for --criterion risk"),
    (["--sensors", "3", "--criterion", "bogus"], "--criterion must be"),
    (["--sensors", "0"], "sensors"),
    (["--sensors", "999"], "n_sensors"),
])
def test_cli_place_bad_input_exits_2(cli_files, capsys, argv, message):
    from lrm_cvx.cli import main

    _, data, model_path = cli_files
    argv = [str(data) if a == "DATA" else a for a in argv]
    assert main(["-q", "place", str(model_path), *argv]) == 2
    assert message in capsys.readouterr().err
