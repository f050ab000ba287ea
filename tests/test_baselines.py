"""Transects and the random walk, hand-checked on small grids."""

import math
from itertools import pairwise

import numpy as np
import pytest
import xarray as xr

from lrm_cvx import Region
from lrm_cvx.errors import PlanningError
from lrm_cvx.information import fisher_information
from lrm_cvx.planning import random_walk, transect


def make_region(mask, lat_descending=True, lon_descending=False):
    ny, nx = mask.shape
    lat = np.arange(ny, dtype=float)
    lon = np.arange(nx, dtype=float)
    lat = lat[::-1].copy() if lat_descending else lat
    lon = lon[::-1].copy() if lon_descending else lon
    return Region(lat=xr.DataArray(lat, dims="lat", coords={"lat": lat}),
                  lon=xr.DataArray(lon, dims="lon", coords={"lon": lon}), mask=mask)


def positions(region, plan):
    return [tuple(p) for p in region.grid_index[plan.route].tolist()]


def test_transect_up_turns_east_at_the_edge():
    region = make_region(np.ones((4, 5), dtype=bool))  # row 0 is north
    start = int(region.cell_grid[1, 1])
    plan = transect(region, start, 5, "up")
    # north to row 0, one step east, then south for the rest of the budget
    assert positions(region, plan) == [(1, 1), (0, 1), (0, 2), (1, 2), (2, 2), (3, 2)]
    assert plan.cost == 5 and plan.method == "transect-up" and len(plan) == 6
    assert plan.cells.tolist() == plan.route.tolist()
    # a second edge: east again (lawnmower)
    plan = transect(region, start, 8, "up")
    assert positions(region, plan)[5:] == [(3, 2), (3, 3), (2, 3), (1, 3)]


def test_transect_directions_follow_coordinates_not_rows():
    region = make_region(np.ones((4, 5), dtype=bool), lat_descending=False)  # row 0 is south
    start = int(region.cell_grid[1, 1])
    assert positions(region, transect(region, start, 2, "up")) == [(1, 1), (2, 1), (3, 1)]
    assert positions(region, transect(region, start, 2, "down")) == [(1, 1), (0, 1), (0, 2)]
    # columns always run eastward now (Region refuses a descending longitude axis)


def test_transect_left_right_turn_south_and_corner_turns_back():
    region = make_region(np.ones((3, 4), dtype=bool))
    start = int(region.cell_grid[2, 1])  # bottom (south) row
    # west to col 0, south is off the grid -> north, then east
    assert positions(region, transect(region, start, 4, "left")) == [
        (2, 1), (2, 0), (1, 0), (1, 1), (1, 2)]
    start = int(region.cell_grid[0, 2])
    assert positions(region, transect(region, start, 3, "right")) == [
        (0, 2), (0, 3), (1, 3), (1, 2)]


def test_transect_crosses_masked_cells_and_counts_their_steps():
    mask = np.ones((5, 3), dtype=bool)
    mask[1:3, 1] = False
    region = make_region(mask)
    start = int(region.cell_grid[4, 1])
    plan = transect(region, start, 3.9999999999, "up")  # floor(budget + 1e-9) = 4 steps
    assert positions(region, plan) == [(4, 1), (3, 1), (0, 1)]
    assert plan.cost == 4
    # 2 steps, the second onto a masked position: the plan ends at the last observed cell
    short = transect(region, start, 2.5, "up")
    assert short.cost == 1 and short.to_dataframe()["cumulative_cost"].tolist() == [0, 1]
    assert plan.to_dataframe()["cumulative_cost"].tolist() == [0, 1, 4]


def test_transect_information_and_errors():
    region = make_region(np.ones((6, 6), dtype=bool))
    Y = np.random.default_rng(0).standard_normal((3, region.n_cells))
    plan = transect(region, 14, 7, "down", Y=Y, ridge=0.1)
    assert plan.information == pytest.approx(fisher_information(Y, plan.cells, 0.1))
    assert np.isnan(transect(region, 14, 7, "down").information)
    with pytest.raises(PlanningError, match="direction"):
        transect(region, 14, 7, "north")
    with pytest.raises(PlanningError, match="budget"):
        transect(region, 14, -1, "up")


def _check_walk(region, plan, budget):
    g = region.grid_index[plan.route]
    steps = np.abs(np.diff(g, axis=0))
    assert np.all(steps.max(axis=1) == 1)  # 8-neighbours, never standing still
    assert plan.cost == pytest.approx(np.hypot(*steps.T).sum())
    assert plan.cost <= budget + 1e-9
    assert plan.cells.tolist() == list(dict.fromkeys(plan.route.tolist()))


def test_random_walk_properties_and_determinism():
    rng = np.random.default_rng(5)
    for trial in range(30):
        mask = rng.random((8, 9)) < 0.75
        mask[4, 4] = True
        region = make_region(mask)
        start = int(region.cell_grid[4, 4])
        budget = float(rng.uniform(0, 25))
        plan = random_walk(region, start, budget, trial)
        _check_walk(region, plan, budget)
        assert plan == random_walk(region, start, budget, trial)  # deterministic by seed
        grid = region.cell_grid
        visited = set()
        cost = 0.0
        for a, b in pairwise(plan.route):
            visited.add(int(a))
            r, c = region.grid_index[a]
            fitting = [
                int(grid[r + dr, c + dc]) for dr in (-1, 0, 1) for dc in (-1, 0, 1)
                if (dr or dc) and 0 <= r + dr < 8 and 0 <= c + dc < 9
                and grid[r + dr, c + dc] >= 0 and cost + math.hypot(dr, dc) <= budget + 1e-9
            ]
            if int(b) in visited:  # a revisit only when every fitting neighbour was visited
                assert all(n in visited for n in fitting)
            cost += math.dist(region.grid_index[a], region.grid_index[b])
        # it stopped because no neighbour fits the remaining budget
        r, c = region.grid_index[plan.route[-1]]
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                if (dr or dc) and 0 <= r + dr < 8 and 0 <= c + dc < 9 and grid[r + dr, c + dc] >= 0:
                    assert plan.cost + math.hypot(dr, dc) > budget + 1e-9


def test_random_walk_seeds_differ_and_information():
    region = make_region(np.ones((10, 10), dtype=bool))
    Y = np.random.default_rng(0).standard_normal((2, 100))
    walks = {tuple(random_walk(region, 55, 20, s).route.tolist()) for s in range(5)}
    assert len(walks) > 1
    plan = random_walk(region, 55, 20, np.random.default_rng(1), Y=Y)
    assert plan.information == pytest.approx(fisher_information(Y, plan.cells))
    assert plan.method == "random" and plan.criterion is None
    isolated = make_region(np.eye(3, dtype=bool)[:, ::-1] | np.eye(3, dtype=bool))
    assert random_walk(isolated, 0, 0.5, 0).route.tolist() == [0]
