"""One structured gp-variance set-up per plan: the greedy, its gentler rival and the routes of
the check against straight lines share it (forks, and each cell's convolution computed once),
with the same plans and values as an oracle set up for each of them."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import lrm_cvx.gp_structured as gp_structured
import lrm_cvx.information as information
import lrm_cvx.planning.lines as lines
from lrm_cvx.information import StructuredGPVarianceOracle
from lrm_cvx.planning import PriorTerms, plan_greedy, transect
from lrm_cvx.planning.baselines import DIRECTIONS
from lrm_cvx.region import Region
from lrm_cvx.spatial import ResidualCovariance
from lrm_cvx.spatial.kriging import GridConv


def grid_region(ny: int, nx: int) -> Region:
    da = xr.DataArray(np.zeros((ny, nx)), dims=("lat", "lon"),
                      coords={"lat": np.arange(ny, dtype=float),
                              "lon": np.arange(nx, dtype=float)})
    return Region.from_dataarray(da)


def problem(seed: int, ny: int = 11, nx: int = 12, k: int = 3) -> tuple:
    """A random factor matrix, its region and gp-variance terms with unequal target weights
    (so every pick is an exact convolution, not a lag-table gather)."""
    rng = np.random.default_rng(seed)
    region = grid_region(ny, nx)
    Y = rng.normal(size=(k, region.n_cells)) * 0.5
    A = rng.normal(size=(k, k))
    terms = dict(prior_cov=A @ A.T / k + 0.1 * np.eye(k),
                 spatial_cov=ResidualCovariance("exponential", sill=1.0,
                                                range=float(rng.uniform(1.0, 4.0)),
                                                nugget=0.1),
                 target_weights=rng.uniform(0.5, 2.0, region.n_cells))
    return Y, region, terms


@pytest.fixture
def structured(monkeypatch):
    """The structured oracle at these tiny sizes (the paper-scale path)."""
    monkeypatch.setattr(information, "GP_STRUCTURED_MIN_ENTRIES", 0.0)
    monkeypatch.setattr(lines, "GP_STRUCTURED_MIN_ENTRIES", 0.0)


def count_convolutions(monkeypatch) -> list:
    """A list that grows by one at each FFT convolution over the grid."""
    calls = []
    call, product = GridConv.__call__, GridConv.product
    monkeypatch.setattr(GridConv, "__call__", lambda self, f: calls.append(1) or call(self, f))
    monkeypatch.setattr(GridConv, "product", lambda self, f1, f2: calls.append(1)
                        or product(self, f1, f2))
    return calls


def own_oracle_value(Y, region, cells, terms) -> float:
    """A route's value by its own exact structured oracle, set up on its cells alone."""
    cells = np.unique(np.asarray(cells, dtype=np.int64))
    return StructuredGPVarianceOracle(Y, cells, pool=cells, region=region,
                                      **{k: v for k, v in terms.items()}).value


@settings(max_examples=8, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])  # constants only
@given(seed=st.integers(0, 10_000), start=st.integers(0, 131),
       budget=st.sampled_from([4.0, 6.0, 9.0]))
def test_rivals_from_one_set_up_plan_as_separate_oracles(structured, seed, start, budget):
    """``refine="rivals"`` with the shared set-up: the route chosen is the best of the greedy,
    the gentler greedy (each planned alone, with its own oracle) and the transects by their
    own exact oracles' values; the values recorded equal those to 1e-10 relative, and a kept
    greedy is the lone greedy's plan bit for bit."""
    Y, region, terms = problem(seed)
    kw = dict(criterion="gp-variance", initial="start", progress=False,
              prior=PriorTerms(**terms))
    plan = plan_greedy(Y, region, start, budget, refine="rivals", **kw)
    gp_structured.GRID_TERMS.clear()  # the lone plans set up on their own
    greedy = plan_greedy(Y, region, start, budget, **kw)
    gp_structured.GRID_TERMS.clear()
    gentle = plan_greedy(Y, region, start, budget, cost_exponent=0.5, **kw)
    routes = {"greedy": greedy, "greedy-cost^0.5": gentle}
    routes.update({f"transect-{d}": transect(region, start, budget, d) for d in DIRECTIONS})
    want = {name: own_oracle_value(Y, region, p.cells, terms) for name, p in routes.items()}
    got = plan.rivals["values"]
    assert got.keys() == want.keys()
    for name, v in want.items():
        assert got[name] == pytest.approx(v, rel=1e-10), name
    best = "greedy"
    for name, v in want.items():  # the check's rule: strictly better by more than 1e-9
        if v < want[best] - 1e-9 * max(1.0, abs(want[best])):
            best = name
    assert plan.rivals["chosen"] == best
    np.testing.assert_array_equal(plan.route, routes[best].route)
    if best == "greedy":
        for key, v in greedy.history.items():
            np.testing.assert_array_equal(plan.history[key], v)


def count_direct_rows(monkeypatch) -> list:
    """A list that grows by the rows each direct sum of a route's fork computes."""
    rows = []
    direct = StructuredGPVarianceOracle._direct_rows

    def counted(self):
        rows.append(sum(self._gcache.get(j) is None for j in range(self._X.size)))
        return direct(self)

    monkeypatch.setattr(StructuredGPVarianceOracle, "_direct_rows", counted)
    return rows


def test_one_set_up_and_one_convolution_per_cell(structured, monkeypatch):
    """A plan with its rivals sets the structured oracle up once and convolves each cell that
    the greedy or the gentler greedy conditions on once; each route's other cells are summed
    directly, once, by the route's fork."""
    Y, region, terms = problem(4, 13, 14)
    built = []
    init = StructuredGPVarianceOracle.__init__
    monkeypatch.setattr(StructuredGPVarianceOracle, "__init__",
                        lambda self, *a, **k: built.append(1) or init(self, *a, **k))
    convolved = count_convolutions(monkeypatch)
    summed = count_direct_rows(monkeypatch)
    kw = dict(criterion="gp-variance", initial="start", progress=False,
              prior=PriorTerms(**terms))
    gp_structured.GRID_TERMS.clear()
    plan = plan_greedy(Y, region, 90, 8.0, refine="rivals", **kw)
    assert len(built) == 1
    n_convolved = len(convolved)
    gentle = plan_greedy(Y, region, 90, 8.0, cost_exponent=0.5, **kw)
    greedy = plan_greedy(Y, region, 90, 8.0, **kw)
    picked = set(greedy.cells.tolist()) | set(gentle.cells.tolist())
    assert n_convolved == Y.shape[0] + 1 + len(picked)  # the set-up's u (k) and s, then cells
    lines = [set(transect(region, 90, 8.0, d).cells.tolist()) - picked for d in DIRECTIONS]
    assert sum(summed) == sum(len(c) for c in lines) > 0  # each route's own cells, once
    assert len(plan.rivals["values"]) == 6


@pytest.mark.parametrize("seed", [0, 3, 7])
def test_a_routes_fork_sums_its_rows_as_the_convolution_would(seed, monkeypatch):
    """A restricted fork's rows ``g(p, .)`` summed directly equal the FFT convolution's to
    rounding (1e-12 of the largest), and the route's value equals the value its fork gets
    from the convolutions (``GP_DIRECT_MAX_CELLS = 0``) to 1e-12 relative."""
    Y, region, terms = problem(seed)
    base = StructuredGPVarianceOracle(Y, [5], region=region, **terms)
    cells = np.array([7, 8, 20, 33, 34, 35, 60, 61, 100])
    fork = base.restricted(cells)
    assert fork._direct
    fork._direct_rows()
    g_direct = np.array([fork._gcache.get(j) for j in range(cells.size)])
    g_fft = np.array([fork._gconv.product(fork._window_of(j), fork._cwin)[fork._oidx]
                      for j in range(cells.size)])
    assert np.abs(g_direct - g_fft).max() <= 1e-12 * np.abs(g_fft).max()
    direct = lines.forked_values(base.restricted(cells[::-1]), {"r": cells})["r"]
    monkeypatch.setattr(gp_structured, "GP_DIRECT_MAX_CELLS", 0)
    gp_structured.GRID_TERMS.clear()
    base = StructuredGPVarianceOracle(Y, [5], region=region, **terms)
    fft = lines.forked_values(base.restricted(cells[::-1]), {"r": cells})["r"]
    assert direct == pytest.approx(fft, rel=1e-12)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), picks=st.lists(st.integers(0, 131), min_size=1,
                                                   max_size=8))
def test_forks_and_fresh_forks_are_set_up_oracles_bit_for_bit(seed, picks):
    """A fork (sharing the set-up and the cells' convolutions) gives the same gains and value,
    bit for bit, as an oracle set up for it; ``fresh()`` is the oracle of no observation."""
    Y, region, terms = problem(seed)
    kw = dict(region=region, pool=np.arange(0, region.n_cells), **terms)
    base = StructuredGPVarianceOracle(Y, [5], **kw)
    a, b = base.fork(), base.fork()
    gp_structured.GRID_TERMS.clear()  # set up on its own
    alone = StructuredGPVarianceOracle(Y, [5], **kw)
    for c in picks:
        a.add(c)
        alone.add(c)
    for c in picks:  # the second fork reads every convolution from the first's
        b.add(c)
    for o in (a, b):
        np.testing.assert_array_equal(o.gains(), alone.gains())
        assert o.value == alone.value
    zero = base.fresh()
    gp_structured.GRID_TERMS.clear()
    empty = StructuredGPVarianceOracle(Y, [], **kw)
    assert zero.cells == [] and zero.value == empty.value
    np.testing.assert_array_equal(zero.gains(), empty.gains())
    for c in picks:
        zero.add(c)
        empty.add(c)
    np.testing.assert_array_equal(zero.gains(), empty.gains())
    assert zero.value == empty.value
    assert base.cells == [5]  # the original is untouched


def test_a_set_up_adds_its_initial_cells_but_not_others(structured):
    """``add`` conditions on a pool or initial cell; another cell is still refused."""
    Y, region, terms = problem(1)
    o = StructuredGPVarianceOracle(Y, [0], region=region, pool=np.arange(10, 40), **terms)
    assert o.covers([0, 10, 39]) and not o.covers([5])
    o.fresh().add(0)
    with pytest.raises(information.PlanningError, match="pool"):
        o.add(5)


def test_a_second_plan_of_the_same_set_up_convolves_only_new_cells(structured, monkeypatch):
    """The next day's plan (same factors, weights, grid and start; another prior covariance)
    reuses the set-up and the cells already convolved, and plans as a plan set up alone."""
    Y, region, terms = problem(8, 12, 12)
    convolved = count_convolutions(monkeypatch)
    kw = dict(criterion="gp-variance", initial="start", progress=False, refine="rivals")
    gp_structured.GRID_TERMS.clear()
    plan_greedy(Y, region, 66, 7.0, **kw, prior=PriorTerms(**terms))
    first = len(convolved)
    day2 = {**terms, "prior_cov": 0.5 * terms["prior_cov"]}
    plan = plan_greedy(Y, region, 66, 7.0, **kw, prior=PriorTerms(**day2))
    second = len(convolved) - first

    def picked(prior):  # the cells the greedy and the gentler greedy condition on
        kw1 = {**kw, "refine": None, "prior": PriorTerms(**prior)}
        return (set(plan_greedy(Y, region, 66, 7.0, **kw1).cells.tolist())
                | set(plan_greedy(Y, region, 66, 7.0, cost_exponent=0.5, **kw1).cells.tolist()))

    assert first == Y.shape[0] + 1 + len(picked(terms))
    assert second == len(picked(day2) - picked(terms))  # no set-up, only the new cells
    gp_structured.GRID_TERMS.clear()
    alone = plan_greedy(Y, region, 66, 7.0, **kw, prior=PriorTerms(**day2))
    np.testing.assert_array_equal(plan.route, alone.route)
    assert plan.rivals["values"] == alone.rivals["values"]


@settings(max_examples=10, deadline=None)
@given(shape=st.tuples(st.integers(1, 30), st.integers(1, 30)),
       out=st.tuples(st.integers(0, 20), st.integers(0, 20), st.integers(1, 12),
                     st.integers(1, 12)), seed=st.integers(0, 1000))
def test_a_convolution_of_a_product_is_the_convolution_bit_for_bit(shape, out, seed):
    rng = np.random.default_rng(seed)
    conv = GridConv((0, 0, *shape), out, lambda d: np.exp(-d / 3.0), anisotropy=1.5)
    f1, f2 = rng.normal(size=shape), rng.normal(size=shape)
    np.testing.assert_array_equal(conv.product(f1, f2), conv(f1 * f2))
