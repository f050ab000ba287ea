"""place_sensors' recommended default and the scalable form of the risk /
gp-variance greedy and exchange (item 6, planning/static_risk.py), checked against the dense
``L x L`` reference and the fold-in recomputed from scratch on tiny grids."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import xarray as xr
from test_static import _J, _setup

from lrm_cvx.errors import PlanningError
from lrm_cvx.glrm import GLRM
from lrm_cvx.planning import place_sensors
from lrm_cvx.planning import static_risk as sr


@pytest.mark.parametrize("spatial", [True, False])
@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("exchange", [False, True])
def test_factored_risk_equals_the_dense_reference(seed, spatial, exchange):
    region, Y, prior, train = _setup(seed + 40, spatial, ny=6, nx=7, T=5)
    kw = dict(criterion="risk", prior=prior, training=train, exchange=exchange, sweeps=10)
    dense = place_sensors(Y, region, 5, method="dense", **kw)
    fact = place_sensors(Y, region, 5, method="factored", **kw)
    assert fact.refinement["form"] == "factored" and dense.refinement["form"] == "dense"
    assert fact.cells.tolist() == dense.cells.tolist()
    J = _J(prior, region, train, fact.cells)
    assert fact.refinement["objective"] == pytest.approx(J, rel=1e-9)
    assert dense.refinement["objective"] == pytest.approx(J, rel=1e-9)
    if not exchange:  # every pick's gain is the drop of the from-scratch error
        np.testing.assert_allclose(fact.history["gain"], dense.history["gain"], rtol=1e-7)


@pytest.mark.parametrize("seed", range(3))
def test_factored_gp_variance_exchange_equals_the_dense_reference(seed):
    region, Y, prior, _ = _setup(seed + 50, True, ny=6, nx=7)
    kw = dict(criterion="gp-variance", prior=prior, exchange=True, sweeps=10)
    dense = place_sensors(Y, region, 4, method="dense", **kw)
    fact = place_sensors(Y, region, 4, method="factored", **kw)
    assert fact.cells.tolist() == dense.cells.tolist()
    assert fact.refinement["objective"] == pytest.approx(dense.refinement["objective"],
                                                         rel=1e-9)


def test_factored_exchange_reaches_a_brute_force_local_optimum():
    region, Y, prior, train = _setup(61, True, ny=4, nx=5, T=6)
    ex = place_sensors(Y, region, 3, criterion="risk", prior=prior, training=train,
                       exchange=True, sweeps=20, method="factored")
    J = lambda S: _J(prior, region, train, S)  # noqa: E731
    S = [int(c) for c in ex.cells]
    Je = J(S)
    assert ex.refinement["converged"]
    for i in range(len(S)):
        for x in set(range(region.n_cells)) - set(S):
            assert J(S[:i] + [x] + S[i + 1:]) >= Je * (1 - 1e-7)


def test_thinned_candidates_stand_on_the_lattice_and_count_every_cell():
    region, Y, prior, train = _setup(70, True, ny=8, nx=9, T=4)
    allowed = np.arange(region.n_cells)
    pool = sr.candidate_pool(region, allowed, 20)
    gi = region.grid_index[pool]
    s = int(np.ceil(np.sqrt(allowed.size / 20)))
    assert pool.size <= 20 and np.all(gi % s == 0) or np.all(gi % (s + 1) == 0)
    plan = place_sensors(Y, region, 3, criterion="risk", prior=prior, training=train,
                         exchange=True, max_candidates=20)
    assert set(plan.cells.tolist()) <= set(pool.tolist())
    assert plan.refinement["n_candidates"] == pool.size
    # the objective still sums the error over every cell
    assert plan.refinement["objective"] == pytest.approx(_J(prior, region, train, plan.cells),
                                                         rel=1e-9)


# ----------------------------------------------------------------------- the default
@pytest.fixture(scope="module")
def fitted():
    rng = np.random.default_rng(3)
    T, ny, nx = 14, 6, 7
    lat, lon = np.arange(ny) * 1.0, np.arange(nx) * 1.0
    base = rng.normal(size=(2, ny, nx))
    field = (rng.normal(size=(T, 2, 1, 1)) * base[None]).sum(1) \
        + 0.3 * rng.normal(size=(T, ny, nx))
    da = xr.DataArray(field, dims=("time", "lat", "lon"),
                      coords=dict(time=np.arange(T), lat=lat, lon=lon))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(2, random_state=0, progress=False, offset=True,
                     spatial="exponential").fit(da)
    return model, da


def test_default_with_a_model_and_training_is_the_validated_choice(fitted):
    model, train = fitted
    plan = place_sensors(model, 5, training=train)  # criterion="auto" (test_static_auto.py)
    assert plan.refinement["selection"].attrs["choice"] in ("risk+exchange",
                                                            "gp-variance+exchange",
                                                            "gp-variance")
    # the (model, region, n) form is the same call
    assert place_sensors(model, model.region_, 5, training=train).cells.tolist() \
        == plan.cells.tolist()
    # an explicit exchange keeps the risk: risk + exchange, the dense reference's sensors
    forced = place_sensors(model, 5, training=train, exchange=True)
    assert forced.criterion == "risk" and forced.method == "greedy+exchange"
    ref = place_sensors(model.Y_, model.region_, 5, criterion="risk", training=train,
                        prior=model.latent_prior("empirical", spatial=True), exchange=True,
                        method="dense")
    assert forced.cells.tolist() == ref.cells.tolist()
    # without training: gp-variance (the model has a spatial residual)
    assert place_sensors(model, 5).criterion == "gp-variance"


def test_paper_and_fisher_reproduce_the_old_placement(fitted):
    model, _ = fitted
    old = place_sensors(model.Y_, model.region_, 5)  # the raw-Y default: unchanged (Fisher)
    assert old.criterion == "fisher" and old.method == "greedy"
    for plan in (place_sensors(model, 5, paper=True),
                 place_sensors(model, 5, criterion="fisher"),
                 place_sensors(model.Y_, model.region_, 5, paper=True)):
        assert plan.criterion == "fisher"
        assert plan.cells.tolist() == old.cells.tolist()
    # the paper's greedy from scratch: QR start of k cells, then the largest log det gain
    Y = np.asarray(model.Y_, np.float64)
    k = Y.shape[0]
    S = [int(c) for c in old.cells[:k]]
    while len(S) < 5:
        M = Y[:, S] @ Y[:, S].T
        vals = [-np.inf if x in S else np.linalg.slogdet(M + np.outer(Y[:, x], Y[:, x]))[1]
                for x in range(Y.shape[1])]
        S.append(int(np.argmax(vals)))
    assert S == old.cells.tolist()


def test_bad_input_is_a_one_line_error(fitted):
    model, train = fitted
    arr = model.region_.stack(train)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        bare = GLRM(2, random_state=0, progress=False).fit(np.asarray(arr).T)
    with pytest.raises(PlanningError, match="no region"):
        place_sensors(bare, 3, training=train)
    other = train.isel(lat=slice(0, 4))
    with pytest.raises(PlanningError, match="training is not on the region's grid"):
        place_sensors(model, 3, training=other)
    with pytest.raises(PlanningError, match="only .* cells can hold a sensor"):
        place_sensors(model, model.region_.n_cells + 1, training=train)
    with pytest.raises(PlanningError, match="paper=True"):
        place_sensors(model, 3, training=train, paper=True)
    with pytest.raises(PlanningError, match="paper=True"):
        place_sensors(model, 3, criterion="risk", paper=True)
    with pytest.raises(PlanningError, match="method"):
        place_sensors(model, 3, training=train, method="fast")
    with pytest.raises(PlanningError, match="max_candidates"):
        place_sensors(model, 5, training=train, max_candidates=5)  # a 4-cell lattice
    with pytest.raises(PlanningError, match="max_candidates"):
        place_sensors(model, 5, training=train, max_candidates=3)
    with pytest.raises(PlanningError, match="n_sensors is missing"):
        place_sensors(model.Y_, model.region_)
    for exc in (PlanningError,):
        try:
            place_sensors(bare, 3)
        except exc as e:
            assert "\n" not in str(e)


# ----------------------------------------------------------------------- the CLI
def test_cli_place_default_is_the_recommended_and_paper_the_fisher(tmp_path, capsys):
    import pandas as pd

    from lrm_cvx.cli import main

    rng = np.random.default_rng(5)
    T, ny, nx, k = 12, 6, 7, 2
    X, Y = rng.normal(size=(k, T)), rng.normal(size=(k, ny * nx))
    v = (X.T @ Y + 0.3 * rng.normal(size=(T, ny * nx))).reshape(T, ny, nx)
    da = xr.DataArray(v, dims=("time", "lat", "lon"), name="temp",
                      coords={"time": np.arange(T), "lat": 40 + np.arange(ny) * 0.5,
                              "lon": -70 + np.arange(nx) * 0.5})
    data, model_path = tmp_path / "field.nc", tmp_path / "model.nc"
    da.to_netcdf(data)
    assert main(["-q", "fit", str(data), "--rank", "2", "--recommended", "-o",
                 str(model_path)]) == 0
    model = GLRM.load(model_path)
    out = tmp_path / "sensors.csv"
    assert main(["-q", "place", str(model_path), str(data), "--sensors", "4", "-o",
                 str(out)]) == 0
    text = capsys.readouterr().out
    ref = place_sensors(model, 4, training=xr.open_dataarray(data))
    assert f"criterion auto: {ref.refinement['selection'].attrs['choice']}" in text
    assert f"{ref.criterion} greedy" in text and "exchange:" in text
    assert ref.method == "greedy+exchange"
    assert pd.read_csv(out)["cell"].tolist() == ref.cells.tolist()
    out2 = tmp_path / "paper.csv"
    assert main(["-q", "place", str(model_path), "--paper", "--sensors", "4", "-o",
                 str(out2)]) == 0
    assert pd.read_csv(out2)["cell"].tolist() == \
        place_sensors(model.Y_, model.region_, 4).cells.tolist()
    assert main(["-q", "place", str(model_path), str(data), "--paper", "--sensors", "4"]) == 2
    assert "--paper" in capsys.readouterr().err
    def fit_then_place(hold_out: int):
        """Fit with --hold-out, place on the whole file: (model, cells placed, printed)."""
        fitted, placed = tmp_path / f"held{hold_out}.nc", tmp_path / f"held{hold_out}.csv"
        assert main(["-q", "fit", str(data), "--rank", "2", "--recommended", "--hold-out",
                     str(hold_out), "-o", str(fitted)]) == 0
        capsys.readouterr()
        assert main(["-q", "place", str(fitted), str(data), "--sensors", "4", "-o",
                     str(placed)]) == 0
        return (GLRM.load(fitted), pd.read_csv(placed)["cell"].tolist(),
                capsys.readouterr().out)

    # a model fitted with --hold-out: DATA's later snapshots stay out of the placement
    held, cells, text = fit_then_place(3)
    assert "DATA cut to the 9 snapshots" in text and "the 3 later ones" in text
    ref = place_sensors(held, 4, training=da.isel(time=slice(None, -3)))
    assert cells == ref.cells.tolist()
    # too few snapshots for the validation (rank 2 + offset: 5 to refit, 3 held out): the
    # default places by risk with the recommended exchange, with a note, not an error
    m, cells, text = fit_then_place(5)
    assert "cannot validate its criterion on these data (criterion='auto' validates on the " \
           "training snapshots: training has 7" in text and "placing by risk" in text
    ref = place_sensors(m.Y_, m.region_, 4, prior=m, training=da.isel(time=slice(None, -5)))
    assert ref.criterion == "risk" and ref.method == "greedy+exchange"
    assert cells == ref.cells.tolist()


def test_default_exchanges_with_as_many_sensors_as_training_snapshots(fitted):
    """The risk's exchange runs whatever ``n`` against the snapshot count (on the
    training snapshots the exchange lowered the error of every storm record at ``n >= T``)."""
    model, train = fitted
    T = train.sizes["time"]
    Y, region = model.Y_, model.region_  # the (Y, region, n) form's default: risk
    plan = place_sensors(Y, region, T, prior=model, training=train)
    assert plan.method == "greedy+exchange" and "exchange_skipped" not in plan.refinement
    ref = place_sensors(model, T, training=train, exchange=True)
    assert plan.cells.tolist() == ref.cells.tolist()
    greedy = place_sensors(model, T, training=train, exchange=False)
    assert plan.refinement["objective"] <= greedy.refinement["objective"] * (1 + 1e-12)


@pytest.mark.parametrize("model_name, anisotropy", [("exponential", 1.0), ("matern32", 1.0),
                                                    ("exponential", 2.0)])
def test_factored_windows_smaller_than_the_grid_equal_the_dense_reference(model_name,
                                                                         anisotropy):
    """A short range: the per-sensor FFT window and the kernel cut are smaller than the grid
    (and sensors sit near its edges), so the window indexing is exercised; with an anisotropy
    the windows differ per axis."""
    from lrm_cvx import Region
    from lrm_cvx.belief.posterior import LatentPosterior, ObservationModel
    from lrm_cvx.spatial import ResidualCovariance

    rng = np.random.default_rng(7)
    ny, nx, k, T = 26, 31, 2, 6
    lat, lon = np.arange(ny) * 1.0, np.arange(nx) * 1.0
    grid = xr.DataArray(np.zeros((ny, nx)), dims=("lat", "lon"), coords=dict(lat=lat, lon=lon))
    region = Region.from_dataarray(grid, mask=rng.random((ny, nx)) > 0.15)
    L = region.n_cells
    Y = rng.normal(size=(k, L)) * 0.3
    cov = ResidualCovariance(model_name, sill=1.0, range=0.6 / anisotropy, nugget=0.05,
                             anisotropy=anisotropy)
    obs = ObservationModel(Y=Y, offset=rng.normal(size=L), scale=rng.uniform(0.5, 2.0, L),
                           spatial_cov=cov, region=region)
    prior = LatentPosterior.from_moments(obs, rng.normal(size=k), np.eye(k))
    train = xr.DataArray(rng.normal(size=(T, ny, nx)), dims=("time", "lat", "lon"),
                         coords=dict(time=np.arange(T), lat=lat, lon=lon))
    rr, rc = sr._radius(cov, 1e-12, region.shape)
    assert rr < ny - 5 and rc < nx - 5 and (rr < rc) == (anisotropy > 1)
    kw = dict(criterion="risk", prior=prior, training=train, exchange=True, sweeps=3)
    dense = place_sensors(Y, region, 6, method="dense", **kw)
    fact = place_sensors(Y, region, 6, method="factored", **kw)
    assert fact.cells.tolist() == dense.cells.tolist()
    assert fact.refinement["objective"] == pytest.approx(dense.refinement["objective"],
                                                         rel=1e-9)
    np.testing.assert_allclose(fact.history["gain"], dense.history["gain"], rtol=1e-7)
