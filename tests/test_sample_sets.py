"""``sample_sets`` (the validation days' sample designs) against the former ``O(L)``
implementation, kept here as the brute-force reference."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest
import xarray as xr
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import chi2_contingency

from lrm_cvx.errors import DataError, ModelError
from lrm_cvx.region import Region
from lrm_cvx.validation.designs import _line, _route, flown_sets, sample_sets


def naive_sample_sets(region, observed, size, kind, rng, centre=None, axis=None):
    """The former implementation (a distance pass over every observed cell); ``centre`` and
    ``axis`` fix what it draws at random."""
    pool = np.flatnonzero(observed)
    size = int(min(size, pool.size))
    if size == 0:
        return pool
    if kind == "scattered":
        return np.sort(rng.choice(pool, size=size, replace=False))
    if kind == "route":
        g = np.asarray(region.grid_index, dtype=np.float64)[pool]
        c = g[rng.integers(pool.size)] if centre is None else region.grid_index[centre]
        d = ((g - c) ** 2).sum(axis=1) + 1e-6 * rng.random(pool.size)  # random tie-break
        return np.sort(pool[np.argpartition(d, size - 1)[:size]])
    if kind == "line":
        g = np.asarray(region.grid_index, dtype=np.int64)[pool]
        c = g[rng.integers(pool.size)] if centre is None else region.grid_index[centre]
        axis = int(rng.integers(2)) if axis is None else axis
        on = np.flatnonzero(g[:, axis] == c[axis])
        d = np.abs(g[on, 1 - axis] - c[1 - axis]) + 1e-6 * rng.random(on.size)
        m = min(size, on.size)
        return np.sort(pool[on[np.argpartition(d, m - 1)[:m]]])
    raise AssertionError(kind)


def _region(mask: np.ndarray) -> Region:
    ny, nx = mask.shape
    da = xr.DataArray(np.zeros((ny, nx)), dims=("lat", "lon"),
                      coords={"lat": np.arange(ny, dtype=float),
                              "lon": np.arange(nx, dtype=float)})
    return Region.from_dataarray(da, mask=mask)


def _sq_dist(region, cells, centre):
    g = region.grid_index
    return np.sort(((g[cells] - g[centre]) ** 2).sum(axis=1))


def _line_dist(region, cells, centre, axis):
    g = region.grid_index
    assert (g[cells, axis] == g[centre, axis]).all()  # on the centre's row / column
    return np.sort(np.abs(g[cells, 1 - axis] - g[centre, 1 - axis]))


def _unique_cutoff(dist_all: np.ndarray, size: int) -> bool:
    """No tie across the ``size``-th smallest of ``dist_all`` (the nearest set is unique)."""
    d = np.sort(dist_all)
    return size >= d.size or d[size - 1] < d[size]


def _check_fixed_centre(region, observed, size, centre, axis, seed):
    rng = np.random.default_rng(seed)
    n_obs = int(observed.sum())
    g = region.grid_index
    pool = np.flatnonzero(observed)
    # route
    got = _route(region, observed, n_obs, centre, min(size, n_obs), rng)
    ref = naive_sample_sets(region, observed, size, "route", rng, centre=centre)
    assert got.size == ref.size == min(size, n_obs)
    assert np.all(np.diff(got) > 0) and observed[got].all()
    np.testing.assert_array_equal(_sq_dist(region, got, centre), _sq_dist(region, ref, centre))
    if _unique_cutoff(((g[pool] - g[centre]) ** 2).sum(axis=1), got.size):
        np.testing.assert_array_equal(got, ref)
    # line
    got = _line(region, observed, centre, axis, min(size, n_obs), rng)
    ref = naive_sample_sets(region, observed, size, "line", rng, centre=centre, axis=axis)
    assert got.size == ref.size
    assert np.all(np.diff(got) > 0) and observed[got].all() and centre in got
    np.testing.assert_array_equal(_line_dist(region, got, centre, axis),
                                  _line_dist(region, ref, centre, axis))
    on = pool[g[pool, axis] == g[centre, axis]]
    if _unique_cutoff(np.abs(g[on, 1 - axis] - g[centre, 1 - axis]), got.size):
        np.testing.assert_array_equal(got, ref)


@settings(max_examples=150, deadline=None)
@given(ny=st.integers(1, 25), nx=st.integers(1, 25), p_mask=st.floats(0.2, 1.0),
       p_obs=st.floats(0.02, 1.0), size=st.integers(1, 80), axis=st.integers(0, 1),
       seed=st.integers(0, 2**32 - 1))
def test_route_and_line_match_the_brute_force_with_the_centre_fixed(ny, nx, p_mask, p_obs,
                                                                    size, axis, seed):
    rng = np.random.default_rng(seed)
    mask = rng.random((ny, nx)) < p_mask
    mask.flat[rng.integers(ny * nx)] = True
    region = _region(mask)
    observed = rng.random(region.n_cells) < p_obs
    observed[rng.integers(region.n_cells)] = True
    centre = int(rng.choice(np.flatnonzero(observed)))
    _check_fixed_centre(region, observed, size, centre, axis, seed)


def test_route_far_from_the_observed_cells():
    """The window grows from a lone centre across an empty grid to a distant block."""
    mask = np.ones((300, 280), bool)
    mask[100:140, 20:200] = False  # a hole between them
    region = _region(mask)
    lookup = region.cell_lookup
    observed = np.zeros(region.n_cells, bool)
    observed[lookup[250:260, 250:262].ravel()] = True
    observed[lookup[0, 0]] = True
    for size, axis in ((5, 0), (37, 1), (121, 0), (500, 1)):
        _check_fixed_centre(region, observed, size, int(lookup[0, 0]), axis, size)
        _check_fixed_centre(region, observed, size, int(lookup[255, 251]), axis, size)


@settings(max_examples=150, deadline=None)
@given(n_clusters=st.integers(1, 8), block=st.booleans(), size=st.integers(1, 40),
       axis=st.integers(0, 1), seed=st.integers(0, 2**32 - 1))
def test_route_and_line_among_sparse_clusters(n_clusters, block, size, axis, seed):
    """Few small clusters on a large grid (a dense far block makes the first window small):
    the nearest cells are often just outside the window that first holds ``size`` cells."""
    rng = np.random.default_rng(seed)
    region = _region(np.ones((150, 140), bool))
    lookup = region.cell_lookup
    observed = np.zeros(region.n_cells, bool)
    for r, c, h, w in zip(rng.integers(0, 100, n_clusters), rng.integers(0, 100, n_clusters),
                          rng.integers(1, 4, n_clusters), rng.integers(1, 4, n_clusters),
                          strict=True):
        observed[lookup[r:r + h, c:c + w].ravel()] = True
    if block:
        observed[lookup[120:150, 110:140].ravel()] = True
    pool = np.flatnonzero(observed)
    centre = int(pool[rng.integers(min(pool.size, 4 * n_clusters))])
    _check_fixed_centre(region, observed, size, centre, axis, seed)


def test_public_sets_are_observed_sorted_and_deterministic():
    rng = np.random.default_rng(3)
    mask = rng.random((40, 50)) < 0.85
    region = _region(mask)
    for p_obs in (0.9, 0.03):  # dense: rejection draws; sparse: the list of observed cells
        observed = rng.random(region.n_cells) < p_obs
        n_obs = int(observed.sum())
        for kind in ("route", "line", "scattered"):
            for size in (1, 5, 50, n_obs, n_obs + 7):
                a = sample_sets(region, observed, size, kind, np.random.default_rng(11))
                b = sample_sets(region, observed, size, kind, np.random.default_rng(11))
                np.testing.assert_array_equal(a, b)
                assert a.dtype == np.int64 and np.all(np.diff(a) > 0) and observed[a].all()
                if kind != "line":
                    assert a.size == min(size, n_obs)
                if kind == "line":
                    g = region.grid_index[a]
                    assert (g[:, 0] == g[0, 0]).all() or (g[:, 1] == g[0, 1]).all()
            assert sample_sets(region, observed, 0, kind, rng).size == 0
        np.testing.assert_array_equal(  # more than observed: every observed cell
            sample_sets(region, observed, n_obs + 1, "route", rng), np.flatnonzero(observed))
    none = np.zeros(region.n_cells, bool)
    assert sample_sets(region, none, 5, "route", rng).size == 0
    with pytest.raises(ModelError, match="kind"):
        sample_sets(region, observed, 5, "zigzag", rng)
    with pytest.raises(DataError, match="observed"):
        sample_sets(region, observed[:-1], 5, "route", rng)


@pytest.mark.parametrize("kind", ["route", "line", "scattered"])
@pytest.mark.parametrize("p_obs", [0.75, 0.04])
def test_the_sets_have_the_brute_force_distribution(kind, p_obs):
    """Random centre, axis, tie-breaks and scattered draws: the frequencies of the sets
    match the former implementation's (a two-sample chi-square test)."""
    mask = np.ones((9, 10), bool)
    mask[3:5, 2:7] = False
    region = _region(mask)
    observed = np.random.default_rng(1).random(region.n_cells) < p_obs
    observed[[0, 17, 40, 63]] = True
    n = 6000
    rng_new, rng_old = np.random.default_rng(5), np.random.default_rng(6)
    new = Counter(tuple(sample_sets(region, observed, 3, kind, rng_new)) for _ in range(n))
    old = Counter(tuple(naive_sample_sets(region, observed, 3, kind, rng_old))
                  for _ in range(n))
    keys = sorted(set(new) | set(old))
    table = np.array([[new[k] for k in keys], [old[k] for k in keys]])
    if len(keys) > 1:
        assert chi2_contingency(table)[1] > 1e-3
    if kind == "route":  # every observed cell can be a centre
        assert len({c for k in new for c in k}) == int(observed.sum())


def test_route_of_one_is_a_uniform_random_observed_cell():
    region = _region(np.ones((20, 30), bool))
    observed = np.random.default_rng(2).random(region.n_cells) < 0.5
    rng = np.random.default_rng(0)
    n_obs, n = int(observed.sum()), 60 * int(observed.sum())
    hits = np.concatenate([sample_sets(region, observed, 1, "route", rng) for _ in range(n)])
    counts = np.bincount(hits, minlength=region.n_cells)[observed]
    assert counts.size == n_obs and counts.min() > 0
    chi2 = ((counts - n / n_obs) ** 2 / (n / n_obs)).sum()
    assert chi2 < n_obs + 6 * np.sqrt(2 * n_obs)  # ~ chi-square with n_obs - 1 dof


def test_flown_sets_ignore_the_days_gaps():
    """A campaign's design does not know where the day's clouds are: ``flown_sets`` draws as
    ``sample_sets`` does among every cell of the region (the same cells for the same seed), so
    on a day with gaps some of its cells are unobserved."""
    rng = np.random.default_rng(4)
    region = _region(rng.random((30, 40)) < 0.9)
    observed = rng.random(region.n_cells) < 0.7
    every = np.ones(region.n_cells, bool)
    hit = 0
    for kind in ("route", "line", "scattered"):
        for seed in range(5):
            a = flown_sets(region, 20, kind, np.random.default_rng(seed))
            b = sample_sets(region, every, 20, kind, np.random.default_rng(seed))
            np.testing.assert_array_equal(a, b)
            hit += int((~observed[a]).any())
    assert hit >= 12  # of 15 designs of 20 cells with 30 % of the cells in gaps
