"""Bad and unusual inputs to the planners, the baselines and the certificate.

Each case asserts the project's named error class (with the argument named in the message) or
the correct result. Counted by outcome in the module docstring of the report: see
``test_case_count``.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import xarray as xr

from lrm_cvx import Region
from lrm_cvx.errors import DataError, LrmError, PlanningError, RegionError
from lrm_cvx.planning import PathOptions, PriorTerms, plan_bound, plan_greedy, random_walk, transect
from lrm_cvx.planning.request import PATH_FIELDS
from lrm_cvx.planning.terms import PRIOR_TERMS
from lrm_cvx.spatial import ResidualCovariance


def grid(ny=6, nx=6, masked=((0, 0),)):
    lat, lon = np.linspace(ny - 1, 0, ny), np.linspace(0, nx - 1, nx)
    mask = np.ones((ny, nx), bool)
    for r, c in masked:
        mask[r, c] = False
    return Region(lat=xr.DataArray(lat, dims="lat", coords={"lat": lat}),
                  lon=xr.DataArray(lon, dims="lon", coords={"lon": lon}), mask=mask)


REGION = grid()
Y = np.random.default_rng(0).standard_normal((2, REGION.n_cells))
START = int(REGION.cell_grid[3, 3])


def greedy(**kw):
    """plan_greedy with the table's keywords: path options into one PathOptions, prior terms
    into one PriorTerms (built in the call, so their checks are the call's)."""
    args = dict(Y=Y, region=REGION, start=START, budget=3.0, ridge=1e-3, progress=False)
    args.update(kw)
    path = {key: args.pop(key) for key in PATH_FIELDS if key in args}
    prior = {key: args.pop(key) for key in PRIOR_TERMS if key in args}
    return plan_greedy(args.pop("Y"), args.pop("region"), args.pop("start"), args.pop("budget"),
                       path=PathOptions(**path) if path else None,
                       prior=PriorTerms(**prior) if prior else None, **args)


# ------------------------------------------------------------------ errors: (call, class, text)
ERRORS = {
    "budget negative": (lambda: greedy(budget=-1), PlanningError, "budget"),
    "budget nan": (lambda: greedy(budget=math.nan), PlanningError, "budget"),
    "budget inf": (lambda: greedy(budget=math.inf), PlanningError, "budget"),
    "budget -inf": (lambda: greedy(budget=-math.inf), PlanningError, "budget"),
    "budget string": (lambda: greedy(budget="3"), PlanningError, "budget"),
    "budget bool": (lambda: greedy(budget=True), PlanningError, "budget"),
    "budget None": (lambda: greedy(budget=None), PlanningError, "budget"),
    "budget list": (lambda: greedy(budget=[3]), PlanningError, "budget"),
    "start outside the cells": (lambda: greedy(start=10**6), RegionError, "start"),
    "start negative index": (lambda: greedy(start=-1), RegionError, "start"),
    "start float index": (lambda: greedy(start=3.7), RegionError, "start"),
    "start integral float": (lambda: greedy(start=3.0), RegionError, "start"),
    "start string": (lambda: greedy(start="a"), RegionError, "start"),
    "start (lat, lon) on a masked cell": (lambda: greedy(start=(5.0, 0.0)), RegionError,
                                          "masked"),
    "start (lat, lon) outside the grid": (lambda: greedy(start=(50.0, 0.0)), RegionError,
                                          "outside"),
    "start (nan, lon)": (lambda: greedy(start=(math.nan, 1.0)), RegionError, "lat"),
    "criterion unknown": (lambda: greedy(criterion="d-opt"), PlanningError, "criterion"),
    "criterion not a name": (lambda: greedy(criterion=42), PlanningError, "criterion"),
    "cost unknown": (lambda: greedy(cost="tsp"), PlanningError, "cost"),
    "initial unknown": (lambda: greedy(initial="random"), PlanningError, "initial"),
    "ridge negative": (lambda: greedy(ridge=-1.0), PlanningError, "ridge"),
    "ridge nan": (lambda: greedy(ridge=math.nan), PlanningError, "ridge"),
    "a-optimal without ridge or prior": (lambda: greedy(criterion="a-optimal", ridge=0.0),
                                         PlanningError, "ridge"),
    "gp-variance without spatial_cov": (lambda: greedy(criterion="gp-variance"),
                                        PlanningError, "spatial_cov"),
    "gp-variance without prior_cov": (
        lambda: greedy(criterion="gp-variance",
                       spatial_cov=ResidualCovariance("exponential", 1.0, 2.0)),
        PlanningError, "prior_cov"),
    "singular initial set, ridge 0": (lambda: greedy(Y=np.ones((2, REGION.n_cells)), ridge=0.0),
                                      PlanningError, "singular"),
    "prior_precision wrong shape": (lambda: greedy(prior_precision=np.eye(3)), PlanningError,
                                    "prior_precision"),
    "noise_var negative": (lambda: greedy(noise_var=-1.0), PlanningError, "noise_var"),
    "rank above the number of cells": (lambda: greedy(Y=np.ones((40, REGION.n_cells))),
                                       PlanningError, "rank"),
    "Y with the wrong number of columns": (lambda: greedy(Y=Y[:, :5]), DataError, "columns"),
    "Y with a NaN": (lambda: greedy(Y=np.where(np.eye(2, REGION.n_cells) > 0, np.nan, Y)),
                     DataError, "non-finite"),
    "Y one-dimensional": (lambda: greedy(Y=Y[0]), DataError, "(k, L)"),
    "plan without a region (None)": (lambda: greedy(region=None), PlanningError, "region"),
    "plan with a DataArray, not a Region": (
        lambda: greedy(region=xr.DataArray(np.zeros((6, 6)), dims=("lat", "lon"))),
        PlanningError, "region"),
    "transect without a region": (lambda: transect(None, 0, 3, "up"), PlanningError, "region"),
    "random walk without a region": (lambda: random_walk(None, 0, 3), PlanningError, "region"),
    "bound without a region": (lambda: plan_bound(Y, None, 0, 3), PlanningError, "region"),
    "transect direction unknown": (lambda: transect(REGION, START, 3, "north"), PlanningError,
                                   "direction"),
    "transect budget nan": (lambda: transect(REGION, START, math.nan, "up"), PlanningError,
                            "budget"),
    "random walk budget negative": (lambda: random_walk(REGION, START, -2, 0), PlanningError,
                                    "budget"),
    "random walk rng unusable": (lambda: random_walk(REGION, START, 3, "seed"), PlanningError,
                                 "rng"),
    "bound budget negative": (lambda: plan_bound(Y, REGION, START, -2), PlanningError,
                              "budget"),
    "bound budget string": (lambda: plan_bound(Y, REGION, START, "2"), PlanningError, "budget"),
    "bound metric unknown": (lambda: plan_bound(Y, REGION, START, 2,
                                                path=PathOptions(metric="miles")),
                             PlanningError, "metric"),
    "certify a baseline built without Y": (lambda: transect(REGION, START, 3, "up").certify(),
                                           PlanningError, "no model"),
}


@pytest.mark.parametrize("case", list(ERRORS))
def test_bad_input_raises_the_named_error(case):
    call, error, text = ERRORS[case]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(error, match=None) as info:
            call()
    assert isinstance(info.value, LrmError) and isinstance(info.value, ValueError)
    assert text in str(info.value), str(info.value)
    assert "\n" not in str(info.value)  # one line


# ------------------------------------------------------------------ unusual but valid
def test_budget_zero_gives_the_forced_initial_set_with_a_warning():
    with pytest.warns(UserWarning, match="initial cells"):
        plan = greedy(budget=0)
    assert len(plan) == 2 and plan.cells[0] == START and plan.budget == 0
    assert transect(REGION, START, 0, "up").cells.tolist() == [START]
    walk = random_walk(REGION, START, 0, 1)
    assert walk.cells.tolist() == [START] and walk.cost == 0


def test_huge_budget_reaches_every_useful_cell_and_stays_in_budget():
    plan = greedy(budget=1e12)
    assert plan.cost <= 1e12 and len(plan) == REGION.n_cells  # every cell has a positive gain
    assert plan.to_dataframe()["cumulative_cost"].iloc[-1] == plan.cost
    t = transect(REGION, START, 1e3, "up")  # a lawnmower that covers the grid many times
    assert set(t.cells.tolist()) == set(range(REGION.n_cells))
    assert t.to_dataframe()["cumulative_cost"].iloc[-1] == t.cost <= 1e3


def test_numpy_scalar_budget_and_start_are_accepted():
    a = greedy(budget=np.float32(3.0), start=np.int64(START))
    b = greedy()
    assert a == b


def test_start_as_lat_lon_resolves_to_the_cell():
    lat, lon = REGION.cell_lat[START], REGION.cell_lon[START]
    assert greedy(start=(float(lat), float(lon))) == greedy()


def test_one_cell_region():
    region = grid(1, 1, masked=())
    Y1 = np.array([[2.0]])
    plan = plan_greedy(Y1, region, 0, 5, progress=False)
    assert plan.cells.tolist() == [0] and plan.cost == 0
    assert plan.information == pytest.approx(math.log(4.0))
    cert = plan.certify(tighten=False)
    assert cert.bound == pytest.approx(math.log(4.0)) and cert.gap == pytest.approx(0, abs=1e-9)
    for d in ("up", "down", "left", "right"):
        t = transect(region, 0, 5, d)
        assert t.cells.tolist() == [0] and t.cost == 0
    assert random_walk(region, 0, 5, 0).cost == 0
    with pytest.raises(PlanningError, match="rank"):
        plan_greedy(np.ones((2, 1)), region, 0, 5, progress=False)


def test_aliases_are_accepted_and_stored_canonically():
    plan = greedy(criterion="AOPT", cost="nn")
    assert plan.criterion == "a-optimal" and plan.cost_function == "nearest-neighbor"


@pytest.mark.parametrize("criterion", ["fisher", "a-optimal", "gp-variance"])
def test_certify_each_criterion(criterion):
    kw = {}
    if criterion == "gp-variance":
        kw = dict(spatial_cov=ResidualCovariance("exponential", 0.5, 2.0, 0.1),
                  prior_cov=np.eye(2))
    plan = greedy(criterion=criterion, **kw)
    cert = plan.certify(tighten=False, criterion="fisher")
    assert cert.criterion == "fisher" and cert.plan_criterion == criterion
    assert cert.information <= cert.bound + 1e-9
    if criterion == "fisher":
        assert cert.gap >= 0 and np.isfinite(cert.volume_ratio)
    else:
        assert math.isnan(cert.gap) and "no gap" in repr(cert)


def test_certify_a_plan_against_a_budget_it_exceeds_is_refused():
    plan = greedy(budget=6)
    with pytest.raises(PlanningError, match="not feasible|not a path"):
        plan_bound(Y, REGION, START, 2, ridge=1e-3, plan=plan, tighten=False)


def test_case_count():
    """At least 20 bad-input cases (the brief's target); this file holds many more."""
    assert len(ERRORS) >= 20


# ------------------------------------------------------- a budget that cannot leave the start
def test_a_budget_that_cannot_leave_the_start_is_an_error_naming_the_nearest_cell():
    # the grid's cells are 1 apart: a budget of 0.5 grid units reaches no cell from the start
    with pytest.raises(PlanningError, match=r"^the budget 0\.5 grid units cannot reach any "
                       r"cell beyond its start: the nearest cell is 1 grid units away"):
        greedy(budget=0.5, initial="start")
    with pytest.raises(PlanningError, match=r"a route to it costs 2 grid units \(there and "
                       r"back\).*at least 2 grid units"):
        greedy(budget=1.5, initial="start", closed=True)
    # km: the nearest cell of the 1-degree grid is ~111 km away
    with pytest.raises(PlanningError, match=r"nearest cell is 111\.\d km away"):
        greedy(budget=10, initial="start", metric="km")
    assert len(greedy(budget=1.0, initial="start").cells) > 1  # one step is enough


def test_a_fleet_names_every_robot_that_cannot_leave():
    corner, edge = int(REGION.cell_grid[5, 5]), int(REGION.cell_grid[0, 3])
    with pytest.raises(PlanningError, match=r"^robot 1's budget 0\.5 grid units cannot reach"):
        greedy(start=[START, corner], budget=[3.0, 0.5], initial="start")
    with pytest.raises(PlanningError, match=r"^robot 0's budget 0\.2 .*; robot 2's budget 0\.7"):
        greedy(start=[START, corner, edge], budget=[0.2, 3.0, 0.7], initial="start")


def test_forced_initial_cells_and_stay_keep_a_tiny_budget_legitimate():
    with pytest.warns(UserWarning, match="initial cells"):  # the rank's nearest cells: forced
        plan = greedy(budget=0.5, initial="nearest")
    assert len(plan.cells) == 2
    stayed = greedy(budget=0.5, initial="start", stay=True)  # e.g. a replan at the route's end
    assert stayed.cells.tolist() == [START] and stayed.cost == 0
    with pytest.raises(PlanningError, match="stay"):
        greedy(budget=0.5, initial="start", stay="yes")
