"""Sensors that see more than a point, against brute force.

Footprint rows against a cell-by-cell loop over the region, averaged rows against the dense
mean of the covered cells' factors, the greedy's gains against log det / trace / GP variance
recomputed from scratch on the averaged rows, the fold-in against the Gaussian conditional
written out in full, and the point sensor against today's results bit for bit.
"""

import math

import numpy as np
import pytest
import scipy.sparse as sps
import xarray as xr
from hypothesis import given, settings
from hypothesis import strategies as st
from references import naive_tour

from lrm_cvx.belief.foldin import fold_in, fold_in_rows
from lrm_cvx.belief.posterior import LatentPosterior, ObservationModel
from lrm_cvx.errors import DataError, PlanningError
from lrm_cvx.information import make_row_oracle, row_factors, row_information
from lrm_cvx.planning import PriorTerms, plan_greedy
from lrm_cvx.planning.request import PathOptions
from lrm_cvx.planning.sensors import (
    Sensor,
    footprint_matrix,
    leg_matrix,
    observe,
    observed_cells,
)
from lrm_cvx.region import EARTH_RADIUS_KM, Region
from lrm_cvx.spatial import ResidualCovariance

R = EARTH_RADIUS_KM


@pytest.fixture(scope="module")
def region():
    # ~9 km x 8.5 km cells with land (invalid cells) inside the grid
    lat, lon = np.linspace(40.0, 40.8, 10), np.linspace(10.0, 11.1, 12)
    values = np.ones((1, 10, 12))
    values[0, 3:6, 4:7] = np.nan  # an island
    values[0, 0, :3] = np.nan
    da = xr.DataArray(values, dims=("time", "lat", "lon"),
                      coords={"time": [0], "lat": lat, "lon": lon})
    return Region.from_dataarray(da)


@pytest.fixture(scope="module")
def Y(region):
    return np.random.default_rng(7).normal(size=(3, region.n_cells))


# --------------------------------------------------------------------------- references
def naive_footprint(region, sensor, c):
    """Weights of the footprint centred on cell ``c``, one cell at a time."""
    lat, lon = np.asarray(region.cell_lat), np.asarray(region.cell_lon)
    half = sensor.width_km / 2
    w = np.zeros(region.n_cells)
    for j in range(region.n_cells):
        if sensor.kind == "disc":
            p1, p2 = math.radians(lat[c]), math.radians(lat[j])
            h = (math.sin((p2 - p1) / 2) ** 2 + math.cos(p1) * math.cos(p2)
                 * math.sin(math.radians(lon[j] - lon[c]) / 2) ** 2)
            inside = 2 * R * math.asin(math.sqrt(h)) <= half + 1e-9
        else:
            dy = R * math.radians(lat[j] - lat[c])
            dx = R * math.cos(math.radians(lat[c])) * math.radians(lon[j] - lon[c])
            inside = abs(dx) <= half + 1e-9 and abs(dy) <= half + 1e-9
        w[j] = 1.0 if inside or j == c else 0.0
    return w / w.sum()


def naive_legs(route, waypoint, robot, L):
    """One row per stop: the distinct cells from the previous stop of the robot to it."""
    rows, prev, current = [], None, []
    for i, (c, w, r) in enumerate(zip(route, waypoint, robot, strict=True)):
        if i == 0 or robot[i - 1] != r:
            prev, current = None, []
        current.append(int(c))
        if w:
            cells = set(current) | ({prev} if prev is not None else set())
            row = np.zeros(L)
            row[sorted(cells)] = 1.0 / len(cells)
            rows.append(row)
            prev, current = int(c), []
    return np.array(rows)


def var_of(a, nv, shared):
    """Noise variance of the average a^T e: independent or equal (shared) cell errors."""
    nv = np.broadcast_to(nv, a.shape)
    return float(np.abs(a) @ np.sqrt(nv)) ** 2 if shared else float((a * a) @ nv)


def fisher_rows(Y, rows, ridge, noise=None, shared=False):
    """log det(ridge I + sum_r (Y a_r)(Y a_r)^T / var(a_r^T e)), from scratch."""
    nv = np.ones(Y.shape[1]) if noise is None else noise
    M = ridge * np.eye(Y.shape[0])
    for a in rows:
        y = Y @ a
        M += np.outer(y, y) / var_of(a, nv, shared)
    return np.linalg.slogdet(M)[1]


def aopt_rows(Y, rows, ridge, shared=False):
    M = ridge * np.eye(Y.shape[0])
    for a in rows:
        y = Y @ a
        M += np.outer(y, y) / var_of(a, np.ones(Y.shape[1]), shared)
    return float(np.trace(np.linalg.solve(M, Y @ Y.T)))


def residual_matrix(region, cov):
    lat, lon = np.radians(region.cell_lat), np.radians(region.cell_lon)
    h = (np.sin((lat[:, None] - lat[None]) / 2) ** 2 + np.cos(lat[:, None]) * np.cos(lat[None])
         * np.sin((lon[:, None] - lon[None]) / 2) ** 2)
    d = 2 * R * np.arcsin(np.sqrt(np.clip(h, 0, 1)))
    return cov.covariance(d, nugget=False)


def gp_rows_value(Y, S0, Kr, nugget, rows, shared=False):
    """Total posterior variance of f = Y^T x + r given z = A f + e (Var e = nugget sum a^2,
    or nugget (sum |a|)^2 with shared errors)."""
    Kf = Y.T @ S0 @ Y + Kr
    if len(rows) == 0:
        return float(np.trace(Kf))
    A = np.array(rows)
    Kz = A @ Kf @ A.T + np.diag(nugget * (np.abs(A).sum(1) ** 2 if shared else (A * A).sum(1)))
    Kfz = Kf @ A.T
    return float(np.trace(Kf) - np.trace(Kfz @ np.linalg.solve(Kz, Kfz.T)))


# --------------------------------------------------------------------------- the sensor
def test_sensor_parse_and_width():
    assert Sensor.of(None).is_point and Sensor.of("point") == Sensor()
    s = Sensor.of("disc:5km")
    assert (s.kind, s.width_km) == ("disc", 5.0)
    assert Sensor.of("Circle:2").kind == "disc"  # aliases, any case
    grow = Sensor.parse("square:1km,altitude=0.5km,fov=60")
    assert grow.width_km == pytest.approx(1.0 + 2 * 0.5 * math.tan(math.radians(30)))
    assert Sensor.of("towed").is_leg
    assert Sensor.of("disc:5km,errors=shared").errors == "shared"
    assert Sensor.of("disc:5km,errors=shared").describe() == "disc 5 km, shared errors"
    assert PathOptions(sensor="disc:5km").sensor == Sensor("disc", 5.0)
    assert PathOptions(sensor="point") == PathOptions()


@pytest.mark.parametrize("bad, match", [
    ("disc:-1km", "size_km"), ("blob:3", "sensor must be one of"), ("disc", "width > 0"),
    ("point:3", "has no footprint"), ("square:2,alt=1", "needs fov_deg"),
    ("square:2,alt=1,fov=190", "fov_deg must be in"), ("disc:abc", "not a number"),
    ("disc:2,colour=red", "unknown option"), ("disc:2,errors=some", "errors must be one of"),
    ("point,errors=shared", "not a point"),
])
def test_sensor_bad_input(bad, match):
    with pytest.raises(PlanningError, match=match):
        Sensor.of(bad)


def test_sensor_with_sense_along_or_refine_refused(region, Y):
    with pytest.raises(PlanningError, match="sense_along"):
        PathOptions(sensor="leg-average", sense_along=True)
    with pytest.raises(PlanningError, match="refine supports the point sensor"):
        plan_greedy(Y, region, 0, 20.0, refine=True, progress=False,
                    path=PathOptions(sensor="disc:10km"))


# --------------------------------------------------------------------------- footprint rows
@pytest.mark.parametrize("spec", ["disc:9km", "disc:30km", "square:9km", "square:25km",
                                  "square:0.01km", "disc:5,altitude=1,fov=90"])
def test_footprint_matrix_equals_cell_by_cell_loop(region, spec):
    sensor = Sensor.of(spec)
    cells = np.arange(region.n_cells)
    A = footprint_matrix(region, sensor, cells)
    want = np.array([naive_footprint(region, sensor, c) for c in cells])
    np.testing.assert_allclose(A.toarray(), want, rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.asarray(A.sum(axis=1)).ravel(), 1.0)


def test_averaged_row_is_the_mean_of_the_covered_factors(region, Y):
    sensor = Sensor.of("disc:25km")
    cells = np.array([0, 5, region.n_cells - 1])
    Yr, vr = row_factors(Y, footprint_matrix(region, sensor, cells))
    for i, c in enumerate(cells):
        covered = np.flatnonzero(naive_footprint(region, sensor, c))
        np.testing.assert_allclose(Yr[:, i], Y[:, covered].mean(axis=1), rtol=1e-13)
        assert vr[i] == pytest.approx(1.0 / covered.size)  # sum a^2 of equal weights


def test_point_footprint_rows_are_one_hot(region):
    A = footprint_matrix(region, "point", [3, 1, 3])
    assert A.toarray().tolist() == np.eye(region.n_cells)[[3, 1, 3]].tolist()
    B = footprint_matrix(region, "point", lat=[float(region.cell_lat[4])],
                         lon=[float(region.cell_lon[4])])
    assert B.indices.tolist() == [4]


def test_footprint_at_a_point_covering_no_cell_is_an_error(region):
    far = dict(lat=[-60.0], lon=[100.0])
    with pytest.raises(PlanningError, match="covers no valid cell"):
        footprint_matrix(region, "disc:5km", **far)
    island = dict(lat=[40.4], lon=[10.5])  # over the masked cells
    with pytest.raises(PlanningError, match="covers no valid cell"):
        footprint_matrix(region, "square:5km", **island)
    A = footprint_matrix(region, "disc:60km", **island)
    lat, lon = np.radians(region.cell_lat), np.radians(region.cell_lon)
    h = (np.sin((lat - math.radians(40.4)) / 2) ** 2 + np.cos(lat) * math.cos(math.radians(40.4))
         * np.sin((lon - math.radians(10.5)) / 2) ** 2)
    inside = 2 * R * np.arcsin(np.sqrt(h)) <= 30.0
    assert A.indices.tolist() == np.flatnonzero(inside).tolist() and inside.sum() > 1


def test_leg_matrix_equals_a_walk_along_the_route():
    route = np.array([4, 7, 8, 2, 2, 9, 1, 5, 6, 5])
    way = np.array([1, 0, 0, 1, 1, 1, 1, 0, 1, 1], bool)
    robot = np.array([0, 0, 0, 0, 0, 0, 1, 1, 1, 1])
    A = leg_matrix(route, way, robot, 12)
    np.testing.assert_allclose(A.toarray(), naive_legs(route, way, robot, 12))
    assert A.shape[0] == way.sum()


def test_observe_reweights_over_the_cells_with_a_value():
    rows = sps.csr_matrix(np.array([[0.5, 0.5, 0, 0], [0, 0.25, 0.75, 0], [0, 0, 0, 1.0]]))
    truth = np.array([1.0, np.nan, 3.0, np.nan])
    used, values = observe(truth, rows)
    assert values[0] == 1.0 and values[1] == 3.0 and np.isnan(values[2])
    np.testing.assert_allclose(used.toarray()[:2], [[1, 0, 0, 0], [0, 0, 1, 0]])
    full, v = observe(np.arange(4.0), rows)
    np.testing.assert_allclose(v, rows @ np.arange(4.0))
    assert observed_cells(rows).tolist() == [0, 1, 2, 3]


# --------------------------------------------------------------------------- oracles
@pytest.mark.parametrize("criterion", ["fisher", "a-optimal"])
def test_row_oracle_gains_equal_brute_force(region, Y, criterion):
    sensor = Sensor.of("square:25km")
    pool = np.arange(region.n_cells)
    A = footprint_matrix(region, sensor, pool)
    dense = A.toarray()
    ridge = 0.1
    init = [0, 7, 20]
    legs = dense[[3, 4]] * 0.5 + dense[[5, 6]] * 0.5  # two extra observations, any weights
    o = make_row_oracle(criterion, Y, ridge, init, pool=pool, rows=A,
                        extra_rows=sps.csr_matrix(legs))
    base = [dense[c] for c in init] + list(legs)
    f = fisher_rows if criterion == "fisher" else aopt_rows
    want = np.array([f(Y, base + [dense[x]], ridge) - f(Y, base, ridge) for x in pool])
    want = want if criterion == "fisher" else -want
    np.testing.assert_allclose(o.gains(pool), want, rtol=1e-9, atol=1e-12)
    o.add(11)
    want2 = f(Y, base + [dense[11], dense[12]], ridge) - f(Y, base + [dense[11]], ridge)
    assert o.gains([12])[0] == pytest.approx(abs(want2), rel=1e-9)
    assert o.value == pytest.approx(f(Y, base + [dense[11]], ridge), rel=1e-10)


@pytest.mark.parametrize("errors", ["independent", "shared"])
def test_row_gp_oracle_equals_brute_force_gp(region, Y, errors):
    cov = ResidualCovariance("exponential", sill=0.6, range=15.0, nugget=0.1, metric="km")
    S0 = np.diag([1.0, 0.5, 0.3])
    A = footprint_matrix(region, "disc:20km", np.arange(region.n_cells))
    dense = A.toarray()
    Kr = residual_matrix(region, cov)
    pool = np.arange(region.n_cells)
    o = make_row_oracle("gp-variance", Y, 0.0, [2], pool=pool, rows=A, region=region,
                        spatial_cov=cov, prior_cov=S0, errors=errors)
    base, sh = [dense[2]], errors == "shared"
    v0 = gp_rows_value(Y, S0, Kr, 0.1, base, sh)
    assert o.value == pytest.approx(v0, rel=1e-9)
    want = np.array([v0 - gp_rows_value(Y, S0, Kr, 0.1, base + [dense[x]], sh) for x in pool])
    np.testing.assert_allclose(o.gains(pool), want, rtol=1e-7, atol=1e-10)
    o.add(30)
    assert o.value == pytest.approx(gp_rows_value(Y, S0, Kr, 0.1, base + [dense[30]], sh),
                                    rel=1e-9)


# --------------------------------------------------------------------------- the greedy
@pytest.mark.parametrize("criterion, ridge", [("fisher", 0.0), ("a-optimal", 1e-2)])
@pytest.mark.parametrize("spec", ["disc:25km", "square:20km", "disc:25km,errors=shared"])
@pytest.mark.parametrize("start, budget", [(10, 14.0), ([10, 80], [8.0, 6.0])])
def test_greedy_gains_with_a_footprint_equal_brute_force(region, Y, criterion, ridge, spec,
                                                         start, budget):
    plan = plan_greedy(Y, region, start, budget, criterion=criterion, ridge=ridge, progress=False,
                       path=PathOptions(sensor=spec))
    sensor = Sensor.of(spec)
    rows = [naive_footprint(region, sensor, c) for c in plan.stops]
    n0 = plan.stops.size - plan.history["cell"].size
    assert plan.history["cell"].size >= 2
    shared = sensor.errors == "shared"

    def f(Y, rows, ridge):
        return (fisher_rows(Y, rows, ridge, shared=shared) if criterion == "fisher"
                else aopt_rows(Y, rows, ridge, shared))

    for t, gain in enumerate(plan.history["gain"]):
        before, after = f(Y, rows[:n0 + t], ridge), f(Y, rows[:n0 + t + 1], ridge)
        assert gain == pytest.approx(abs(after - before), rel=1e-8)
    np.testing.assert_allclose(plan.observation_rows().toarray(), np.array(rows), atol=1e-15)
    assert plan.information == pytest.approx(fisher_rows(Y, rows, ridge, shared=shared),
                                             rel=1e-10)
    assert plan.sensor == sensor
    assert plan.to_geojson()["properties"]["sensor"] == sensor.describe()


def test_greedy_gp_variance_with_a_footprint_equals_brute_force(region, Y):
    cov = ResidualCovariance("exponential", sill=0.6, range=15.0, nugget=0.1, metric="km")
    S0 = np.diag([1.0, 0.5, 0.3])
    plan = plan_greedy(Y, region, 10, 10.0, criterion="gp-variance", initial="start",
                       progress=False, path=PathOptions(sensor="disc:20km"),
                       prior=PriorTerms(spatial_cov=cov, prior_cov=S0))
    Kr = residual_matrix(region, cov)
    rows = [naive_footprint(region, Sensor.of("disc:20km"), c) for c in plan.stops]
    n0 = plan.stops.size - plan.history["cell"].size
    for t, gain in enumerate(plan.history["gain"]):
        want = (gp_rows_value(Y, S0, Kr, 0.1, rows[:n0 + t])
                - gp_rows_value(Y, S0, Kr, 0.1, rows[:n0 + t + 1]))
        assert gain == pytest.approx(want, rel=1e-7)


def test_greedy_leg_average_records_the_legs(region, Y):
    plan = plan_greedy(Y, region, 10, 12.0, ridge=1e-3, progress=False,
                       path=PathOptions(sensor="leg-average"))
    rows = naive_legs(plan.route, plan.waypoint, plan.route_robot, region.n_cells)
    assert rows.shape[0] == plan.stops.size  # one observation per stop
    np.testing.assert_allclose(plan.observation_rows().toarray(), rows)
    assert plan.information == pytest.approx(fisher_rows(Y, rows, 1e-3), rel=1e-10)
    assert (~plan.waypoint).any()  # the cells the legs pass are on the route
    closed = plan_greedy(Y, region, [10, 60], [10.0, 8.0], ridge=1e-3, progress=False,
                         path=PathOptions(sensor="leg", closed=True))
    rows = naive_legs(closed.route, closed.waypoint, closed.route_robot, region.n_cells)
    np.testing.assert_allclose(closed.observation_rows().toarray(), rows)


@pytest.mark.parametrize("kw", [{}, {"criterion": "a-optimal", "ridge": 1e-2},
                                {"sense_along": True}, {"metric": "km", "closed": True}])
def test_point_sensor_is_todays_plan_bit_for_bit(region, Y, kw):
    budget = 60.0 if kw.get("metric") == "km" else 12.0
    path = {key: kw.pop(key) for key in ("sense_along", "metric", "closed") if key in kw}
    a = plan_greedy(Y, region, 10, budget, progress=False, path=PathOptions(**path), **kw)
    for sensor in ("point", Sensor(), None):
        b = plan_greedy(Y, region, 10, budget, progress=False,
                        path=PathOptions(sensor=sensor, **path), **kw)
        assert np.array_equal(a.cells, b.cells) and np.array_equal(a.route, b.route)
        assert a.information == b.information
        for key in a.history:
            assert np.array_equal(a.history[key], b.history[key])
    rows = a.observation_rows()
    assert np.array_equal(rows.indices, a.cells) and np.all(rows.data == 1.0)
    assert "sensor" not in a.to_geojson()["properties"]  # exports unchanged


def test_a_tiny_footprint_plans_as_the_point_sensor(region, Y):
    a = plan_greedy(Y, region, 10, 12.0, progress=False)
    b = plan_greedy(Y, region, 10, 12.0, progress=False, path=PathOptions(sensor="square:0.01km"))
    assert np.array_equal(a.stops, b.stops)
    assert b.information == pytest.approx(a.information, rel=1e-12)


@pytest.mark.parametrize("spec", ["disc:25km", "square:20km,errors=shared"])
def test_footprint_certificate_is_the_relaxation_of_the_footprint_rows(region, Y, spec):
    """A footprint plan's certificate: its information is the plan's (the rows of its stops),
    the bound is at least it, and the count-only (static) bound is the D-optimal relaxation
    of every cell's footprint row written out by hand, at least the best of every placement
    (brute force over all triples)."""
    from itertools import combinations

    from lrm_cvx.planning import dopt_upper_bound, plan_bound

    sensor = Sensor.of(spec)
    shared = sensor.errors == "shared"
    plan = plan_greedy(Y, region, 10, 8.0, progress=False, path=PathOptions(sensor=spec))
    cert = plan.certify()
    assert cert.information == pytest.approx(plan.information, rel=1e-10)
    assert cert.bound >= cert.information - 1e-9 and 0 <= cert.gap < np.inf
    rows = np.array([naive_footprint(region, sensor, c) for c in range(region.n_cells)])
    U = np.column_stack([Y @ a / np.sqrt(var_of(a, np.ones(region.n_cells), shared))
                         for a in rows])  # (k, L): each cell's whitened footprint row
    ref = dopt_upper_bound(U, 3, ridge=1e-3, tol=1e-5).value
    static = plan_bound(Y, region, None, 3, path=PathOptions(sensor=spec), ridge=1e-3,
                        tol=1e-5)
    assert static.bound == pytest.approx(ref, abs=1e-4)
    G = np.einsum("ai,bi->iab", U, U)
    best = max(np.linalg.slogdet(1e-3 * np.eye(3) + G[list(t)].sum(0))[1]
               for t in combinations(range(0, region.n_cells, 3), 3))
    assert static.bound >= best - 1e-9
    point = plan_bound(Y, region, None, 3, ridge=1e-3, tol=1e-5)
    assert abs(point.bound - static.bound) > 1e-3  # the footprints were used


def test_leg_average_plans_are_certified(region, Y):
    """(The brute-force checks are in test_certificate_towed.py.)"""
    plan = plan_greedy(Y, region, 10, 12.0, ridge=1e-3, progress=False,
                       path=PathOptions(sensor="leg-average"))
    cert = plan.certify()
    assert cert.towed is not None and cert.bound >= cert.information


# --------------------------------------------------------------------------- fold-in
def _obs(region, Y, spatial):
    rng = np.random.default_rng(5)
    L = region.n_cells
    cov = (ResidualCovariance("exponential", sill=0.5, range=12.0, nugget=0.05, metric="km")
           if spatial else None)
    return ObservationModel(Y, offset=rng.normal(size=L), scale=rng.uniform(0.5, 2, L),
                            noise_var=rng.uniform(0.1, 1.0, L), spatial_cov=cov,
                            region=region if spatial else None)


def _rows(region, n=5, seed=2):
    A = footprint_matrix(region, "disc:20km", np.random.default_rng(seed).choice(
        region.n_cells, n, replace=False)).toarray()
    A[0, A[0] > 0] *= np.linspace(0.5, 1.5, int((A[0] > 0).sum()))  # one weighted row
    return A / A.sum(axis=1, keepdims=True)


@pytest.mark.parametrize("errors", ["independent", "shared"])
def test_update_rows_equals_the_bayesian_update_of_the_averaged_rows(region, Y, errors):
    obs = _obs(region, Y, spatial=False)
    A, v = _rows(region), np.array([0.3, -1.0, 2.0, 0.5, 1.1])
    m0, S0 = np.array([0.2, -0.1, 0.4]), np.diag([2.0, 1.0, 0.5])
    post = LatentPosterior.from_moments(obs, m0, S0).update_rows(sps.csr_matrix(A), v, errors)
    B = A * obs.scale
    z = v - A @ obs.offset
    Yr = Y @ B.T
    Rn = np.diag([var_of(b, obs.noise_var, errors == "shared") for b in B])
    P = np.linalg.inv(S0) + Yr @ np.linalg.solve(Rn, Yr.T)
    h = np.linalg.solve(S0, m0) + Yr @ np.linalg.solve(Rn, z)
    np.testing.assert_allclose(post.cov, np.linalg.inv(P), rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(post.mean, np.linalg.solve(P, h), rtol=1e-10, atol=1e-14)
    # in two steps, and with a NaN value dropped
    two = (LatentPosterior.from_moments(obs, m0, S0).update_rows(A[:2], v[:2], errors)
           .update_rows(np.vstack([A[2:], A[:1]]), np.r_[v[2:], np.nan], errors))
    np.testing.assert_allclose(two.mean, post.mean, rtol=1e-10)
    assert two.n_dropped == 1 and two.rows.shape[0] == 5


def test_one_hot_rows_are_point_observations(region, Y):
    cells, v = np.array([1, 8, 20, 33]), np.array([0.5, -0.2, 1.0, 0.7])
    x1, c1 = fold_in(Y, cells, v, ridge=0.1)
    x2, c2 = fold_in_rows(Y, np.eye(region.n_cells)[cells], v, ridge=0.1)
    np.testing.assert_allclose(x1, x2, rtol=1e-12)
    np.testing.assert_allclose(c1, c2, rtol=1e-12)


@pytest.mark.parametrize("errors", ["independent", "shared"])
def test_spatial_update_rows_equals_the_gaussian_conditional(region, Y, errors):
    obs = _obs(region, Y, spatial=True)
    cov = obs.spatial_cov
    A, v = _rows(region, 4), np.array([0.3, -1.0, 2.0, 0.5])
    cells, cv = np.array([3, 40]), np.array([1.5, -0.5])  # point observations too
    m0, S0 = np.array([0.2, -0.1, 0.4]), np.diag([2.0, 1.0, 0.5])
    post = (LatentPosterior.from_moments(obs, m0, S0).update(cells, cv)
            .update_rows(sps.csr_matrix(A), v, errors))
    # the joint Gaussian of (x, f, z), written out (fit units)
    L = region.n_cells
    Bfull = np.vstack([np.eye(L)[cells], A * obs.scale])
    z = np.r_[(cv - obs.offset[cells]) / obs.scale[cells], v - A @ obs.offset]
    Kr = residual_matrix(region, cov)
    Kf = Y.T @ S0 @ Y + Kr
    Kz = Bfull @ Kf @ Bfull.T + np.diag([var_of(b, cov.nugget, errors == "shared")
                                         for b in Bfull])
    Kxz = S0 @ Y @ Bfull.T
    gain = np.linalg.solve(Kz, z - Bfull @ Y.T @ m0)
    np.testing.assert_allclose(post.mean, m0 + Kxz @ gain, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(post.cov, S0 - Kxz @ np.linalg.solve(Kz, Kxz.T), rtol=1e-8,
                               atol=1e-10)
    Kfz = Kf @ Bfull.T
    mean_f = Y.T @ m0 + Kfz @ gain
    var_f = np.diag(Kf) - np.einsum("ij,ji->i", Kfz, np.linalg.solve(Kz, Kfz.T))
    mean, std = post.predict(spatial=True)
    np.testing.assert_allclose(mean, obs.offset + obs.scale * mean_f, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(std, obs.scale * np.sqrt(np.maximum(var_f, 0)), rtol=1e-6,
                               atol=1e-8)
    # the same observations the other way round: points after the rows
    other = (LatentPosterior.from_moments(obs, m0, S0).update_rows(A, v, errors)
             .update(cells, cv))
    np.testing.assert_allclose(other.mean, post.mean, rtol=1e-9, atol=1e-12)


def test_update_rows_bad_input(region, Y):
    post = LatentPosterior.from_moments(_obs(region, Y, False), np.zeros(3), np.eye(3))
    L = region.n_cells
    with pytest.raises(DataError, match="columns"):
        post.update_rows(np.ones((1, L + 1)), [1.0])
    with pytest.raises(DataError, match="without any weight"):
        post.update_rows(np.zeros((1, L)), [1.0])
    with pytest.raises(DataError, match="values has shape"):
        post.update_rows(np.ones((2, L)) / L, [1.0])
    with pytest.raises(DataError, match="finite"):
        post.update_rows(np.ones((1, L)) / L, [np.inf])


def test_row_information_of_one_hot_rows_is_fisher_information(region, Y):
    from lrm_cvx.information import fisher_information

    cells = [0, 4, 9, 30]
    rows = np.eye(region.n_cells)[cells]
    assert row_information(Y, rows, 0.1) == pytest.approx(fisher_information(Y, cells, 0.1),
                                                          rel=1e-13)
    A = footprint_matrix(region, "disc:25km", cells)
    assert row_information(Y, A, 0.1) == pytest.approx(fisher_rows(Y, A.toarray(), 0.1),
                                                       rel=1e-12)


def test_a_campaign_day_with_a_footprint():
    """The campaign's observation step: one averaged truth value per stop, assimilated by the
    filter as the posterior's update_rows of the day's belief."""
    from lrm_cvx.glrm import GLRM
    from lrm_cvx.io.samples import synthetic_field
    from lrm_cvx.monitor import MonitorState
    from lrm_cvx.planning.sensors import plan_observations

    da = synthetic_field(12, (10, 12), 2, seed=1, lat_range=(40.0, 40.8),
                         lon_range=(10.0, 11.1))
    model = GLRM(rank=2, random_state=0).fit(da.isel(time=slice(0, 10)))
    state = MonitorState.from_model(model)
    sensor = Sensor.of("disc:25km")
    plan = plan_greedy(model.Y_, model.region_, 5, 10.0, ridge=1e-6, progress=False,
                       path=PathOptions(sensor=sensor))
    truth = model.region_.stack(da.isel(time=10)).astype(np.float64)
    truth[plan.stops[0]] = np.nan  # a cloud over the first stop
    rows, values = plan_observations(plan, truth)
    snapshot = da.isel(time=10).where(~np.isnan(model.region_.unstack(truth)))
    rows2, values2 = plan.observe(snapshot)  # the (lat, lon) snapshot, xarray in
    np.testing.assert_allclose(values2, values, rtol=1e-6)  # float32 on the grid
    assert (rows2 != rows).nnz == 0
    for i, c in enumerate(plan.cells):
        covered = np.flatnonzero(naive_footprint(model.region_, sensor, c))
        seen = covered[np.isfinite(truth[covered])]
        assert values[i] == pytest.approx(truth[seen].mean(), rel=1e-12)
    t = state._coerce(da.time.values[10])
    day = state._propagated(t) if state._dt(t) != 0 else state.posterior
    want = day.update_rows(rows, values)
    state.assimilate_rows(rows, values, t)
    assert state.n_assimilated == len(values) and state.time == t
    np.testing.assert_allclose(state.posterior.mean, want.mean, rtol=1e-12)
    np.testing.assert_allclose(state.posterior.cov, want.cov, rtol=1e-12)
    # the update is the Bayesian update of the averaged rows from the day's belief
    obs = day.obs_model
    A = rows.toarray() * (1.0 if obs.scale is None else obs.scale)
    z = values - (0.0 if obs.offset is None else rows @ obs.offset)
    Yr = obs.Y @ A.T
    nv = np.broadcast_to(np.asarray(obs.noise_var, float), (obs.n_cells,))
    W = np.diag(1.0 / ((A * A) @ nv))
    P = day.precision + Yr @ W @ Yr.T
    np.testing.assert_allclose(state.posterior.cov, np.linalg.inv(P), rtol=1e-9)
    np.testing.assert_allclose(state.posterior.mean,
                               np.linalg.solve(P, day.shift + Yr @ W @ z), rtol=1e-9)


def test_refine_refuses_a_footprint(region, Y):
    from lrm_cvx.planning import refine

    plan = plan_greedy(Y, region, 10, 8.0, progress=False, path=PathOptions(sensor="disc:20km"))
    assert not plan.path.is_paper
    with pytest.raises(PlanningError):
        refine(plan)


def test_footprints_along_the_route(region, Y):
    plan = plan_greedy(Y, region, 10, 14.0, ridge=1e-3, initial="start", progress=False,
                       path=PathOptions(sensor="square:20km", sense_along=True,
                                        end=region.n_cells - 1))
    rows = np.array([naive_footprint(region, Sensor.of("square:20km"), c) for c in plan.cells])
    assert plan.cells.size > plan.stops.size  # the cells passed are footprints too
    np.testing.assert_allclose(plan.observation_rows().toarray(), rows, atol=1e-15)
    assert plan.information == pytest.approx(fisher_rows(Y, rows, 1e-3), rel=1e-10)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 9), st.booleans()), min_size=1, max_size=25),
       st.integers(0, 3))
def test_leg_matrix_random_routes(entries, n_robots):
    """Random routes of 1-4 robots (each starting at a stop, cells may repeat)."""
    route, way, robot = [], [], []
    chunks = np.array_split(np.arange(len(entries)), n_robots + 1)
    for r, idx in enumerate(chunks):
        for j, i in enumerate(idx):
            cell, stop = entries[i]
            route.append(cell)
            way.append(stop or j == 0)
            robot.append(r)
    keep = [i for i in range(len(route)) if len(chunks[robot[i]]) > 0]
    route, way, robot = (np.array([v[i] for i in keep]) for v in (route, way, robot))
    A = leg_matrix(route, way, robot, 10)
    np.testing.assert_allclose(A.toarray(), naive_legs(route, way, robot, 10).reshape(-1, 10))


@settings(max_examples=25, deadline=None)
@given(st.sampled_from(["square", "disc"]), st.floats(0.5, 60.0), st.floats(40.0, 40.8),
       st.floats(10.0, 11.1))
def test_footprint_at_any_point_equals_the_loop(kind, width, lat, lon):
    lat_g, lon_g = np.linspace(40.0, 40.8, 10), np.linspace(10.0, 11.1, 12)
    values = np.ones((1, 10, 12))
    values[0, 3:6, 4:7] = np.nan
    region = Region.from_dataarray(xr.DataArray(values, dims=("time", "lat", "lon"), coords={
        "time": [0], "lat": lat_g, "lon": lon_g}))
    sensor = Sensor(kind, width)
    cl, co = np.asarray(region.cell_lat), np.asarray(region.cell_lon)
    half = width / 2
    if kind == "disc":
        h = (np.sin(np.radians(cl - lat) / 2) ** 2 + np.cos(np.radians(cl)) * math.cos(
            math.radians(lat)) * np.sin(np.radians(co - lon) / 2) ** 2)
        inside = 2 * R * np.arcsin(np.sqrt(h)) <= half + 1e-9
    else:
        inside = ((np.abs(R * np.radians(cl - lat)) <= half + 1e-9)
                  & (np.abs(R * math.cos(math.radians(lat)) * np.radians(co - lon))
                     <= half + 1e-9))
    if not inside.any():
        with pytest.raises(PlanningError, match="covers no valid cell"):
            footprint_matrix(region, sensor, lat=[lat], lon=[lon])
        return
    A = footprint_matrix(region, sensor, lat=[lat], lon=[lon])
    np.testing.assert_allclose(A.toarray()[0], inside / inside.sum(), atol=1e-15)


@pytest.mark.parametrize("spatial", [False, True])
def test_one_hot_rows_equal_point_updates_with_adaptive_scale(region, Y, spatial):
    """The fold-in of one-hot rows is the point fold-in: belief, adaptive variance scale
    (the innovation statistic) and the kriged map."""
    from dataclasses import replace

    obs = replace(_obs(region, Y, spatial), adaptive_dof=4.0)
    m0, S0 = np.array([0.2, -0.1, 0.4]), np.diag([2.0, 1.0, 0.5])
    prior = LatentPosterior.from_moments(obs, m0, S0)
    cells, v = np.array([2, 17, 40, 61, 80]), np.array([0.5, -1.2, 0.3, 2.0, -0.4])
    a = prior.update(cells, v)
    b = prior.update_rows(np.eye(region.n_cells)[cells], v)
    np.testing.assert_allclose(b.mean, a.mean, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(b.cov, a.cov, rtol=1e-9, atol=1e-12)
    assert b.variance_scale == pytest.approx(a.variance_scale, rel=1e-9)
    assert b.day_n == a.day_n
    ma, sa = a.predict()
    mb, sb = b.predict()
    np.testing.assert_allclose(mb, ma, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(sb, sa, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("criterion", ["fisher", "a-optimal"])
def test_row_oracle_set_extra_equals_a_new_oracle(region, Y, criterion):
    A = footprint_matrix(region, "disc:20km", np.arange(region.n_cells))
    legs1 = sps.csr_matrix(A.toarray()[[1, 2, 3]])
    legs2 = sps.csr_matrix(A.toarray()[[4, 9, 30, 31]] * 0.5 + A.toarray()[[5, 6, 7, 8]] * 0.5)
    kw = dict(pool=np.arange(region.n_cells), rows=A, noise_var=np.linspace(0.5, 2, 108))
    o = make_row_oracle(criterion, Y, 0.1, [12], extra_rows=legs1, **kw)
    o.set_extra(legs2)
    new = make_row_oracle(criterion, Y, 0.1, [12], extra_rows=legs2, **kw)
    np.testing.assert_allclose(o.gains(), new.gains(), rtol=1e-10)
    assert o.value == pytest.approx(new.value, rel=1e-12)


@pytest.mark.parametrize("spec, criterion, ridge", [("disc:25km", "fisher", 0.0),
                                                     ("square:20km", "a-optimal", 1e-2),
                                                     ("disc:25km,errors=shared", "fisher",
                                                      1e-3)])
def test_greedy_with_a_footprint_equals_a_naive_greedy(region, Y, spec, criterion, ridge):
    """The paper's greedy literally, on the averaged rows: every nearest-neighbour tour and
    every criterion value recomputed from scratch for every candidate."""
    sensor = Sensor.of(spec)
    g, L, k = region.grid_index, region.n_cells, Y.shape[0]
    row = {c: naive_footprint(region, sensor, c) for c in range(L)}
    shared = sensor.errors == "shared"

    def value(P):
        rows = [row[c] for c in P]
        return (fisher_rows(Y, rows, ridge, shared=shared) if criterion == "fisher"
                else -aopt_rows(Y, rows, ridge, shared))

    start, budget = 10, 12.0
    d2 = ((g - g[start]) ** 2).sum(1)
    P = [int(c) for c in np.lexsort((np.arange(L), d2))[:k]]
    while True:
        v0, c0 = value(P), naive_tour(g, P)[0]
        best = None
        for x in range(L):
            if x in P:
                continue
            c1 = naive_tour(g, P + [x])[0]
            if c1 > budget + 1e-9:
                continue
            ratio = (value(P + [x]) - v0) / max(c1 - c0, 1e-12)
            if best is None or ratio > best[0] + 1e-12:
                best = (ratio, x)
        if best is None or not best[0] > 0:
            break
        P.append(best[1])
    plan = plan_greedy(Y, region, start, budget, criterion=criterion, ridge=ridge, progress=False,
                       path=PathOptions(sensor=sensor))
    assert plan.stops.tolist() == P


def test_a_route_certificate_builds_the_footprint_rows_of_its_candidates_only(region, Y,
                                                                              monkeypatch):
    """A route's certificate builds the footprint rows of the cells a route within the budget
    may visit, not of the whole region, and bounds as the point certificate of every cell's
    footprint row written out by hand."""
    import lrm_cvx.planning.sensors as sensors_module
    from lrm_cvx.planning import plan_bound

    spec = "disc:25km"
    sensor = Sensor.of(spec)
    rows = np.array([naive_footprint(region, sensor, c) for c in range(region.n_cells)])
    U = np.column_stack([Y @ a / np.sqrt(var_of(a, np.ones(region.n_cells), False))
                         for a in rows])
    asked = []
    real = sensors_module.footprint_matrix

    def spy(region_, sensor_, cells=None, **kw):
        asked.append(region_.n_cells if cells is None else np.size(cells))
        return real(region_, sensor_, cells, **kw)

    monkeypatch.setattr(sensors_module, "footprint_matrix", spy)
    plan = plan_greedy(Y, region, 10, 4.0, ridge=1e-3, progress=False,
                       path=PathOptions(sensor=spec))
    asked.clear()
    cert = plan.certify(tol=1e-5)
    ref = plan_bound(U, region, 10, 4.0, ridge=1e-3, tol=1e-5)  # a point sensor on U
    assert cert.bound == pytest.approx(ref.bound, abs=1e-4)
    assert cert.n_candidates == ref.n_candidates < region.n_cells
    assert asked and max(asked) < region.n_cells  # only the cells a plan may read
    assert max(asked) >= cert.n_candidates
    assert cert.information == pytest.approx(plan.information, rel=1e-10)
