"""Campaign-like sample designs on a region's observed cells: the sample sets every validated
choice draws (the calibration's fold-ins, ``temporal="auto"``, ``spatial="auto"``,
``select_dynamics``). A route (spatially clustered), a straight transect (``"line"``) or
scattered cells, in ``O(size)`` work each."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..errors import DataError, ModelError

__all__ = ["sample_sets", "flown_sets", "SET_KINDS", "ALL_KINDS"]

SET_KINDS = ("route", "scattered")
ALL_KINDS = ("route", "scattered", "line")  # line: a transect-like straight run of cells


def sample_sets(region: Any, observed: np.ndarray, size: int, kind: str,
                rng: np.random.Generator) -> np.ndarray:
    """Cells of one sample set among the ``observed`` cells (bool ``(L,)``): ``"scattered"``
    (uniformly at random), ``"route"`` (the ``size`` observed cells nearest, on the grid, to
    a random observed cell: a spatially clustered set like a short route) or ``"line"`` (the
    observed cells of the grid row or column (random) through a random observed cell, the
    ``size`` nearest to it: a straight transect). Ties in grid distance are broken at random.

    Sorted cell indices, at most ``size`` (all observed cells when fewer). The work is
    ``O(size)`` beside one count of ``observed`` (a route searches a growing grid window around
    its centre, a line reads one grid row or column): the model selection draws hundreds."""
    if kind not in ALL_KINDS:
        raise ModelError(f"kind must be one of {ALL_KINDS}, got {kind!r}")
    observed = np.asarray(observed, dtype=bool)
    if observed.shape != (region.n_cells,):
        raise DataError(f"observed must be a bool array of the region's {region.n_cells} "
                        f"cells, got shape {observed.shape}")
    n_obs = int(np.count_nonzero(observed))
    size = int(min(size, n_obs))
    if size <= 0:
        return np.zeros(0, dtype=np.int64)
    if kind == "scattered":
        return _scattered(observed, n_obs, size, rng)
    centre = _random_observed(observed, n_obs, rng)
    if kind == "line":
        return _line(region, observed, centre, int(rng.integers(2)), size, rng)
    return _route(region, observed, n_obs, centre, size, rng)


def flown_sets(region: Any, size: int, kind: str, rng: np.random.Generator) -> np.ndarray:
    """The cells a campaign's design visits: :func:`sample_sets` among **all** of the region's
    cells, not only the day's observed ones. A route or a transect does not know where the
    day's clouds are, so on a day with gaps some of its cells give no value (NaN, ignored by
    the updates), as they do in a campaign; the validations that score campaign-like maps
    (``temporal="auto"``, the calibration, ``select_dynamics``) draw their designs here. On a
    day without gaps it is :func:`sample_sets` itself (the same draws)."""
    return sample_sets(region, np.ones(region.n_cells, dtype=bool), size, kind, rng)


def _route(region: Any, observed: np.ndarray, n_obs: int, centre: int, size: int,
           rng: np.random.Generator) -> np.ndarray:
    """The ``size`` (<= ``n_obs``, the count of ``observed``) observed cells nearest to cell
    ``centre`` in squared grid distance, found in a square grid window around it that grows
    until no cell outside can be nearer than the ``size``-th inside."""
    lookup = region.cell_lookup  # (ny, nx) cell index or -1
    ny, nx = lookup.shape
    r0, c0 = (int(v) for v in region.grid_index[centre])
    # radius of a window holding about 2 size observed cells at the mean density
    R = max(1, int(np.ceil(0.7 * np.sqrt(size * ny * nx / n_obs))))
    while True:
        r_lo, c_lo = max(0, r0 - R), max(0, c0 - R)
        win = lookup[r_lo:r0 + R + 1, c_lo:c0 + R + 1]
        rr, cc = np.nonzero(win >= 0)
        cells = win[rr, cc]
        keep = observed[cells]
        cells, rr, cc = cells[keep], rr[keep] + (r_lo - r0), cc[keep] + (c_lo - c0)
        whole = win.shape == (ny, nx)
        if cells.size >= size or whole:
            m = min(size, cells.size)
            d = rr * rr + cc * cc
            dk = int(np.partition(d, m - 1)[m - 1])
            # a cell outside the window is at least (R + 1)^2 away: the nearest are inside
            if dk < (R + 1) ** 2 or whole:
                return _nearest(cells, d, m, rng)
            R = int(np.ceil(np.sqrt(dk)))  # the next window holds every cell within dk
        else:
            R *= 2


def _line(region: Any, observed: np.ndarray, centre: int, axis: int, size: int,
          rng: np.random.Generator) -> np.ndarray:
    """The observed cells of the grid row (``axis`` 0) or column (1) through cell ``centre``,
    the ``size`` nearest to it (``O(grid side)``)."""
    lookup = region.cell_lookup
    r0, c0 = (int(v) for v in region.grid_index[centre])
    run = lookup[r0, :] if axis == 0 else lookup[:, c0]
    pos = np.flatnonzero(run >= 0)
    pos = pos[observed[run[pos]]]
    d = np.abs(pos - (c0 if axis == 0 else r0))
    return _nearest(run[pos], d, min(size, pos.size), rng)


def _random_observed(observed: np.ndarray, n_obs: int, rng: np.random.Generator) -> int:
    """A uniformly random observed cell: the first observed one of uniform draws over all
    cells (``O(L / n_obs)`` expected), or from the list of observed cells when they are few."""
    L = observed.size
    if 16 * n_obs >= L:
        while True:
            draw = rng.integers(L, size=32)
            hit = draw[observed[draw]]
            if hit.size:
                return int(hit[0])
    return int(np.flatnonzero(observed)[rng.integers(n_obs)])


def _scattered(observed: np.ndarray, n_obs: int, size: int,
               rng: np.random.Generator) -> np.ndarray:
    """``size`` distinct observed cells uniformly at random (sorted): the first distinct
    observed cells of uniform draws over all cells (sampling without replacement), or a choice
    from the list of observed cells when they are few or ``size`` is most of them."""
    L = observed.size
    if not (16 * n_obs >= L and 4 * size <= n_obs):
        return np.sort(rng.choice(np.flatnonzero(observed), size=size, replace=False))
    chosen = np.zeros(0, dtype=np.int64)
    while chosen.size < size:
        draw = rng.integers(L, size=int(2 * (size - chosen.size) * L / n_obs) + 8)
        both = np.concatenate([chosen, draw[observed[draw]]])
        chosen = both[np.sort(np.unique(both, return_index=True)[1])]  # first occurrences
    return np.sort(chosen[:size])


def _nearest(cells: np.ndarray, d: np.ndarray, size: int,
             rng: np.random.Generator) -> np.ndarray:
    """The ``size`` of ``cells`` with the smallest ``d`` (sorted), the cells tied at the
    ``size``-th distance chosen uniformly at random."""
    if size <= 0:
        return np.zeros(0, dtype=np.int64)
    dk = np.partition(d, size - 1)[size - 1]
    inner = cells[d < dk]
    ties = cells[d == dk]
    ties = rng.choice(ties, size - inner.size, replace=False)
    return np.sort(np.concatenate([inner, ties])).astype(np.int64, copy=False)
