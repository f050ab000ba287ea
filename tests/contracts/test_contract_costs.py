"""Every registered path cost: each candidate's incremental cost equals the cost recomputed
from scratch (a naive reference per cost), and adding it gives that route."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
from references import naive_tour

from lrm_cvx.planning.routecost import COST_REGISTRY, route_length

NAMES = list(COST_REGISTRY.choices())


def ref_nearest_neighbor(g, route, x):
    """Cost of the nearest-neighbour tour of route's cells plus x, from scratch."""
    return naive_tour(g, list(route) + [x])[0]


def ref_insertion(g, route, x):
    """Cheapest way to put x into the route (between two stops or after the last), from
    scratch: the shortest of every candidate route."""
    route = list(route)
    options = [route[: i + 1] + [x] + route[i + 1:] for i in range(len(route))]
    return min(math.fsum(math.dist(g[a], g[b]) for a, b in zip(r, r[1:], strict=False))
               for r in options)


REFERENCES = {"nearest-neighbor": ref_nearest_neighbor, "insertion": ref_insertion}


def test_every_cost_has_a_reference():
    assert set(REFERENCES) == set(NAMES), "add a from-scratch reference for the new cost"


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("name", NAMES)
def test_incremental_cost_equals_recomputed(name, seed):
    rng = np.random.default_rng(seed)
    g = np.argwhere(rng.random((6, 7)) < 0.7).astype(np.int64)  # (L, 2) distinct positions
    L = g.shape[0]
    P = [int(c) for c in rng.choice(L, 3, replace=False)]
    pool = np.setdiff1d(np.arange(L), P[1:])  # the start may sit in the pool too (inactive)
    coster = COST_REGISTRY.get(name)(g, P, pool)
    assert coster.cost == pytest.approx(route_length(g, coster.route), abs=1e-12)
    for _ in range(5):
        inc = coster.increases()
        act = np.flatnonzero(coster.active)
        assert np.all(np.isnan(inc[~coster.active]))
        for j in act:
            x = int(pool[j])
            expect = REFERENCES[name](g, coster.route, x) - coster.cost
            assert inc[j] == pytest.approx(expect, abs=1e-9), (name, x)
            # generic: adding x makes the route whose length is the predicted cost
            trial = copy.deepcopy(coster)
            trial.add(x)
            assert trial.cost == pytest.approx(coster.cost + inc[j], abs=1e-9)
            assert trial.cost == pytest.approx(route_length(g, trial.route), abs=1e-12)
            assert sorted(trial.route.tolist()) == sorted(coster.route.tolist() + [x])
            assert trial.route[0] == P[0]
        coster.add(int(pool[act[rng.integers(act.size)]]))
