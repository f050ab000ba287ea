"""The towed (leg-average) sensor's certificate bounds every route (docs/certificate.md §12).

Reference: on tiny grids, every visiting order of distinct stops (start first) whose route is
within the budget, found by exhaustive depth-first search with distances built in
``test_certificate_paths`` (independently of ``planning/paths.py``). Each order's observations
are written out here: the start's own cell, then one per leg, the equal-weight mean of the
leg's distinct cells (its two stops and the cells between: those a straight leg crosses, or a
shortest path of the 8-neighbour travel graph), a closed tour's return leg included. The
whitened rows are ``Y a / sqrt(v)``, ``v = sum a^2`` (independent cell errors) or 1 (shared).
The bound must be at least the best ``log det(ridge I + sum u u^T)`` over all of them.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_certificate_paths import field_Y, graph, make_region, route_orders, straight

from lrm_cvx.errors import PlanningError
from lrm_cvx.planning import PathOptions
from lrm_cvx.planning.certificate import plan_bound
from lrm_cvx.planning.plan import line_cells


def info_of_rows(Y: np.ndarray, rows: list[list[int]], ridge: float, errors: str) -> float:
    """``log det(ridge I + sum u u^T)`` of equal-weight averages over the cell lists ``rows``."""
    M = ridge * np.eye(Y.shape[0])
    for cells in rows:
        m = len(cells)
        u = Y[:, cells].mean(axis=1) * (math.sqrt(m) if errors == "independent" else 1.0)
        M += np.outer(u, u)
    s, v = np.linalg.slogdet(M)
    return v if s > 0 else -math.inf


def straight_leg(region, a: int, b: int) -> list[int]:
    return sorted({a, b, *line_cells(region, a, b)[0].tolist()})


def graph_paths(G: np.ndarray, step: np.ndarray):
    """A shortest-path reconstruction over the 8-neighbour graph ``step`` (one step's length,
    inf: no edge) given its all-pairs distances ``G``: the next hop from ``a`` to ``b`` is a
    neighbour ``x`` with ``step[a, x] + G[x, b] == G[a, b]`` (the lowest index)."""

    def leg(a: int, b: int) -> list[int]:
        cells, cur = [a], a
        while cur != b:
            ok = np.flatnonzero(np.isclose(step[cur] + G[:, b], G[cur, b]) & np.isfinite(step[cur])
                                & (np.arange(G.shape[0]) != cur))
            cur = int(ok[0])
            cells.append(cur)
        return sorted(set(cells))

    return leg


def rows_of(order: list[int], leg, closed: bool) -> list[list[int]]:
    rows = [[order[0]]]
    stops = order + ([order[0]] if closed and len(order) > 1 else [])
    rows += [leg(a, b) for a, b in zip(stops[:-1], stops[1:], strict=True)]
    return rows


@pytest.mark.parametrize("errors", ["independent", "shared"])
@pytest.mark.parametrize("closed, budget", [(False, 3.2), (True, 4.3)])
@pytest.mark.parametrize("k, ridge, seed", [(2, 0.0, 3), (3, 0.05, 4)])
def test_straight_legs_bound_covers_every_route(errors, closed, budget, k, ridge, seed):
    region = make_region(5, 6, masked=[(0, 5), (3, 3)])
    Y = field_Y(region, k, seed)
    start = int(region.cell_grid[2, 2])
    D = straight(region, "grid", None)
    leg = lambda a, b: straight_leg(region, a, b)  # noqa: E731
    best, n_rows, n_cells = -math.inf, 0, 0
    for order in route_orders(D, start, budget, closed):
        rows = rows_of(order, leg, closed)
        best = max(best, info_of_rows(Y, rows, ridge, errors))
        n_rows = max(n_rows, len(rows))
        n_cells = max(n_cells, sum(len(r) for r in rows))
    assert math.isfinite(best)
    cert = plan_bound(Y, region, start, budget, ridge=ridge, tol=1e-6,
                      path=PathOptions(closed=closed, sensor=f"leg-average,errors={errors}"))
    assert cert.bound >= best - 1e-7
    assert cert.towed[0] >= n_rows and cert.towed[1] >= n_cells  # the counts hold
    assert cert.information is None and cert.gap is None  # no plan given


@pytest.mark.parametrize("errors", ["independent", "shared"])
@pytest.mark.parametrize("closed, budget", [(False, 3.5), (True, 5.0)])
def test_travel_graph_legs_bound_covers_every_route(errors, closed, budget):
    region = make_region(5, 5, masked=[(1, 2), (2, 2), (3, 2)])  # a wall to go around
    Y = field_Y(region, 3, 8)
    start = int(region.cell_grid[2, 1])
    S = straight(region, "grid", None)
    adj = (np.abs(region.grid_index[:, None, 0] - region.grid_index[None, :, 0]) <= 1) & (
        np.abs(region.grid_index[:, None, 1] - region.grid_index[None, :, 1]) <= 1)
    step = np.where(adj, S, np.inf)
    G = graph(region, S)
    leg = graph_paths(G, step)
    best = max(info_of_rows(Y, rows_of(order, leg, closed), 0.01, errors)
               for order in route_orders(G, start, budget, closed))
    cert = plan_bound(Y, region, start, budget, ridge=0.01, tol=1e-6,
                      path=PathOptions(closed=closed, traversable="valid",
                                       sensor=f"towed,errors={errors}"))
    assert cert.bound >= best - 1e-7


def test_fleet_of_two_towed_routes():
    region = make_region(4, 5)
    Y = field_Y(region, 2, 6)
    starts = [int(region.cell_grid[0, 0]), int(region.cell_grid[3, 4])]
    budgets = [2.2, 2.5]
    D = straight(region, "grid", None)
    leg = lambda a, b: straight_leg(region, a, b)  # noqa: E731
    per_robot = [[rows_of(o, leg, False) for o in route_orders(D, s, b)]
                 for s, b in zip(starts, budgets, strict=True)]
    best = max(info_of_rows(Y, A + B, 0.0, "independent")
               for A in per_robot[0] for B in per_robot[1])
    cert = plan_bound(Y, region, starts, budgets, tol=1e-6, path=PathOptions(sensor="towed"))
    assert cert.bound >= best - 1e-7
    assert cert.path["n_robots"] == 2


def test_greedy_towed_plan_is_certified():
    from lrm_cvx.oracles import row_information
    from lrm_cvx.planning import plan_greedy
    from lrm_cvx.planning.sensors import observation_rows

    region = make_region(8, 8)
    Y = field_Y(region, 3, 0)
    for closed in (False, True):
        plan = plan_greedy(Y, region, 10, 9.0, ridge=1e-3, progress=False,
                           path=PathOptions(sensor="leg-average", closed=closed))
        cert = plan.certify(tol=1e-6)
        info = row_information(Y, observation_rows(plan), 1e-3, errors="independent")
        assert cert.information == pytest.approx(plan.information) == pytest.approx(info)
        assert cert.bound >= cert.information and cert.gap >= 0
        assert cert.towed is not None and "towed sensor" in repr(cert)
        assert "leg cells" in cert._repr_html_() and "initial set" not in cert._repr_html_()
    # the same route certified against half its budget is refused, naming the route's cost
    plan = plan_greedy(Y, region, 10, 9.0, ridge=1e-3, progress=False,
                       path=PathOptions(sensor="leg-average"))
    with pytest.raises(PlanningError, match="not a route within budget=4"):
        plan_bound(Y, region, 10, 4.0, ridge=1e-3, plan=plan)


def test_towed_bound_errors():
    region = make_region(4, 4)
    Y = field_Y(region, 2, 0)
    with pytest.raises(PlanningError, match="static"):
        plan_bound(Y, region, None, 3, path=PathOptions(sensor="towed"))
    import xarray as xr

    from lrm_cvx.region import Region

    lon = xr.DataArray(np.arange(0.0, 360.0, 30.0), dims=("lon",))
    lat = xr.DataArray(np.array([-10.0, 0.0, 10.0]), dims=("lat",))
    wrapped = Region(lat=lat, lon=lon, mask=np.ones((3, 12), bool))
    Yw = field_Y(wrapped, 2, 1)
    with pytest.raises(PlanningError, match="wrap"):
        plan_bound(Yw, wrapped, 0, 3.0, path=PathOptions(sensor="towed"))


@pytest.mark.parametrize("errors", ["independent", "shared"])
def test_towed_relaxation_equals_the_weighted_design_problem(errors):
    """The bound is the optimum of ``max log det(ridge I + sum w_c y_c y_c^T)`` over ``0 <= w_c
    <= rows``, ``sum w <= cells`` (shared: ``rows``) and Lemma 9's limits (``sum w`` over the
    cells at chart distance ``>= r`` from the start at most each cap), solved here by cvxpy on
    the family's candidates: the scaled relaxation computes that problem, not a looser one,
    and the limits cut it."""
    import cvxpy as cp

    from lrm_cvx.planning.families import leg_family, path_spec
    from lrm_cvx.planning.request import PathOptions

    region = make_region(5, 6, masked=[(0, 5), (3, 3)])
    Y = field_Y(region, 3, 4)
    start, budget, ridge = int(region.cell_grid[2, 2]), 3.2, 0.05
    cert = plan_bound(Y, region, start, budget, ridge=ridge, tol=1e-7,
                      path=PathOptions(sensor=f"towed,errors={errors}"))
    fam = leg_family(path_spec(region, None, start, budget, PathOptions(), "path", None),
                     region, 3)
    total = fam.cells if errors == "independent" else fam.rows
    Yc = Y[:, fam.cand]
    gi, gs = region.grid_index[fam.cand], region.grid_index[start]
    chart = np.hypot(*(gi - gs).T)  # the chart distance, written out
    thr, caps_i, caps_s = fam.limits
    caps = caps_i if errors == "independent" else caps_s
    w = cp.Variable(fam.cand.size)
    objective = cp.Maximize(cp.log_det(ridge * np.eye(3) + Yc @ cp.diag(w) @ Yc.T))
    box = [w >= 0, w <= fam.rows, cp.sum(w) <= total]
    limits = [cp.sum(w[chart >= r]) <= c for r, c in zip(thr, caps, strict=True)
              if (chart >= r).any()]
    loose = cp.Problem(objective, box)
    loose.solve(solver="CLARABEL")
    prob = cp.Problem(objective, box + limits)
    prob.solve(solver="CLARABEL")
    assert (fam.rows, fam.cells) == cert.towed
    assert cert.bound >= prob.value - 1e-6
    assert cert.bound <= prob.value + 1e-4
    assert prob.value < loose.value - 1e-3  # the limits bind on this grid


@pytest.mark.parametrize("kind, closed, budget", [("straight", False, 4.6), ("straight", True, 5.2),
                                                  ("graph", False, 4.5), ("graph", True, 5.0)])
def test_leg_limits_hold_on_every_route(kind, closed, budget):
    """Lemma 9 checked route by route: on every route within the budget, the leg cells at
    distance ``>= r`` from the start (a cell once per leg through it) and the legs reaching
    them are at most the caps, for every threshold; some cap is met to within 4 cells (the
    straight-leg cap allows for diagonal legs and a cut leg's extra cells, which a tiny grid
    cannot all show at once), so the test would see a vacuous formula."""
    from lrm_cvx.planning.families import leg_family, path_spec
    from lrm_cvx.planning.request import PathOptions

    region = make_region(6, 6, masked=[(1, 3), (2, 3)] if kind == "graph" else [(0, 5)])
    start = int(region.cell_grid[2, 1])
    S = straight(region, "grid", None)
    if kind == "graph":
        adj = (np.abs(region.grid_index[:, None, 0] - region.grid_index[None, :, 0]) <= 1) & (
            np.abs(region.grid_index[:, None, 1] - region.grid_index[None, :, 1]) <= 1)
        G = graph(region, S)
        D, leg = G, graph_paths(G, np.where(adj, S, np.inf))
        options = PathOptions(traversable="valid", closed=closed)
    else:
        D, leg = S, (lambda a, b: straight_leg(region, a, b))
        options = PathOptions(closed=closed)
    fam = leg_family(path_spec(region, None, start, budget, options, "path", None), region, 2)
    thr, caps_i, caps_s = fam.limits
    tightest = np.inf
    for order in route_orders(D, start, budget, closed):
        legs = rows_of(order, leg, closed)[1:]  # the start's own cell is at distance 0
        for r, ci, cs in zip(thr, caps_i, caps_s, strict=True):
            beyond = [sum(fam.dist[c] >= r for c in cells) for cells in legs]
            assert sum(beyond) <= ci
            assert sum(b > 0 for b in beyond) <= cs
            tightest = min(tightest, ci - sum(beyond))
    assert tightest <= 4


@pytest.mark.parametrize("straight_legs", [True, False])
def test_leg_limits_are_a_ladder_of_the_lemma(straight_legs):
    """A long route's limits are a subset of Lemma 9's, one per ``floor(x) = m`` written out
    here (``x`` just below ``m + 1`` legs of arc beyond ``rho``), the farthest threshold
    (``m = 0``) kept; a short route keeps every one."""
    from lrm_cvx.planning.families import NUDGE, leg_limits

    shift = np.sqrt(2.0) / 2 if straight_legs else 0.0
    for span, unit in ((4.6, 1.0), (200.0, 1.0), (130.0, 1.5)):
        thr, ci, cs = leg_limits(span, shift, unit, straight=straight_legs)
        full = {}
        for m in range(int(span // unit) + 1):
            x = m + 1 - NUDGE
            r = span + shift - x * unit
            if r > 0:
                cap = np.floor(np.sqrt(2.0) * x + m + 3) if straight_legs else 2 * m + 1
                full[m] = (r, cap, m + 1)
        got = {int(s) - 1: (t, i, s) for t, i, s in zip(thr, ci, cs, strict=True)}
        assert np.all(np.diff(thr) > 0)
        assert set(got) <= set(full) and 0 in got
        for m, (t, i, s) in got.items():
            assert t == pytest.approx(full[m][0], rel=1e-9) and t >= full[m][0]
            assert (i, s) == full[m][1:]
        if span < 10:
            assert set(got) == set(full)
        else:
            assert len(got) < len(full)


def polyline_midpoint(points: np.ndarray) -> np.ndarray:
    """The point at half the arc length of the polyline through ``points`` (m, 2)."""
    seg = np.hypot(*np.diff(points, axis=0).T)
    if seg.sum() == 0:
        return points[0]
    half, cum = seg.sum() / 2, np.concatenate([[0.0], np.cumsum(seg)])
    i = min(int(np.searchsorted(cum, half, side="right")) - 1, seg.size - 1)
    t = (half - cum[i]) / seg[i] if seg[i] > 0 else 0.0
    return points[i] + t * (points[i + 1] - points[i])


@pytest.mark.parametrize("closed, budget", [(False, 4.6), (True, 5.2)])
def test_midpoint_limits_hold_on_every_route(closed, budget):
    """Lemma 10 checked route by route at the route's own midpoint ``c`` (the tightest square
    holding it, of side 0): every leg cell, the start's own observation included, lies within
    ``G / 2 + sqrt 2 / 2`` of ``c``, and the leg cells at distance ``>= s`` from ``c`` (once
    per leg) and the legs reaching them are at most the caps, for every threshold; some cap
    is met to within 7 cells (each side's cap allows Lemma 9's slack, and one route cannot
    meet both sides' at once), and the farthest cap is below the leg cells in all (the limit
    binds): a vacuous formula would show."""
    from lrm_cvx.planning.families import leg_family, leg_midpoint_limits, path_spec
    from lrm_cvx.planning.request import PathOptions

    region = make_region(6, 6, masked=[(0, 5)])
    start = int(region.cell_grid[2, 1])
    D = straight(region, "grid", None)
    fam = leg_family(path_spec(region, None, start, budget, PathOptions(closed=closed), "path",
                               None), region, 2)
    G = fam.cover_span
    assert G is not None and G >= budget
    thr, caps_i, caps_s = leg_midpoint_limits(G)
    pos = region.grid_index.astype(np.float64)
    tightest, n_routes = np.inf, 0
    for order in route_orders(D, start, budget, closed):
        stops = order + ([order[0]] if closed and len(order) > 1 else [])
        c = polyline_midpoint(pos[stops])
        rows = rows_of(order, lambda a, b: straight_leg(region, a, b), closed)
        dist = [np.hypot(*(pos[cells] - c).T) for cells in rows]
        assert max(d.max() for d in dist) <= G / 2 + math.sqrt(2) / 2 + 1e-9
        for s, ci, cs in zip(thr, caps_i, caps_s, strict=True):
            beyond = [int((d >= s).sum()) for d in dist]
            assert sum(beyond) <= ci
            assert sum(b > 0 for b in beyond) <= cs
            tightest = min(tightest, ci - sum(beyond))
        n_routes += 1
    assert n_routes > 100 and tightest <= 7 and caps_i.min() < fam.cells


def test_midpoint_cover_tightens_the_towed_bound():
    """On a 12 x 12 grid the cover's bound is below the one without it (``tighten=False``:
    Lemma 9's limits only) and still above the greedy towed plan's information, which lies in
    one of its pieces; the certificate lists the pieces."""
    from lrm_cvx.planning import plan_greedy

    region = make_region(12, 12)
    Y = field_Y(region, 3, 0)
    plan = plan_greedy(Y, region, 30, 6.0, ridge=1e-3, progress=False,
                       path=PathOptions(sensor="towed"))
    cert = plan.certify(tol=1e-6)
    loose = plan.certify(tol=1e-6, tighten=False)
    assert cert.information <= cert.bound < loose.bound - 1e-3
    assert cert.tightened and len(cert.leaves) > 4 and not loose.leaves


@pytest.mark.parametrize("errors", ["independent", "shared"])
def test_towed_cover_check_refuses_legs_outside_every_piece(errors):
    """The plan check of the cover: the greedy's own legs lie in a piece; the same legs with
    one more observation averaging a far corner of the grid (beyond ``G / 2 + sqrt 2 / 2`` of
    every piece) do not, which is a PlanningError."""
    import scipy.sparse as sps

    from lrm_cvx.planning import plan_greedy
    from lrm_cvx.planning.families import leg_family, leg_midpoint_limits, path_spec
    from lrm_cvx.planning.request import PathOptions
    from lrm_cvx.planning.sensors import observation_rows
    from lrm_cvx.planning.towed_certificate import _check_towed_cover

    region = make_region(12, 12)
    Y = field_Y(region, 3, 0)
    plan = plan_greedy(Y, region, 30, 6.0, ridge=1e-3, progress=False,
                       path=PathOptions(sensor=f"towed,errors={errors}"))
    cert = plan.certify(tol=1e-6)
    span = leg_family(path_spec(region, None, 30, 6.0, PathOptions(), "path", None), region,
                      3).cover_span
    rows = observation_rows(plan)
    limits = leg_midpoint_limits(span)
    independent = errors == "independent"
    _check_towed_cover(rows, region, list(cert.leaves), span, limits, independent)
    far = sps.csr_matrix(([1.0], ([0], [int(region.cell_grid[11, 11])])), shape=(1, rows.shape[1]))
    with pytest.raises(PlanningError, match="no piece of the midpoint cover"):
        _check_towed_cover(sps.vstack([rows, far]), region, list(cert.leaves), span, limits,
                           independent)
