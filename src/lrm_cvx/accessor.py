"""The ``.lrm`` xarray accessor: thin wrappers so a notebook can stay in xarray.

>>> import lrm_cvx  # registers the accessor
>>> model = da.lrm.fit(rank=5)                       # doctest: +SKIP
>>> plan = da.lrm.plan(model, start=(0.0, 20.0), budget=50)   # doctest: +SKIP
>>> snapshot.lrm.complete(model)                    # doctest: +SKIP
"""

from __future__ import annotations

from typing import Any

import xarray as xr

from .region import Region

__all__ = ["LrmAccessor"]


@xr.register_dataarray_accessor("lrm")
class LrmAccessor:
    """Accessor on ``(time, lat, lon)`` data and ``(lat, lon)`` snapshots."""

    def __init__(self, da: xr.DataArray) -> None:
        self._da = da

    def region(self, mask: Any = None) -> Region:
        """The :class:`~lrm_cvx.region.Region` of valid cells (observed at least once)."""
        return Region.from_dataarray(self._da, mask=mask)

    def stack(self, region: Region | None = None):
        """The ``(time, L)`` float32 matrix view with NaN for missing entries."""
        return (region or self.region()).stack(self._da)

    def fit(self, rank: int = 5, **kwargs: Any):
        """Fit a :class:`~lrm_cvx.glrm.GLRM` (keyword arguments go to its constructor)."""
        from .glrm import GLRM

        return GLRM(rank=rank, **kwargs).fit(self._da)

    def plan(self, model: Any, start: Any, budget: float, **kwargs: Any):
        """Greedy plan on ``model`` (see :func:`lrm_cvx.planning.plan_greedy`): the
        recommended planner unless ``paper=True`` or explicit options say otherwise."""
        from .planning import plan_greedy

        return plan_greedy(model, model.region_, start, budget, **kwargs)

    def complete(self, model: Any, ridge: float = 0.0, **kwargs: Any) -> xr.Dataset:
        """Predict the full map(s) from this partially observed snapshot (NaN = unobserved)."""
        return model.complete(self._da, ridge=ridge, **kwargs)

    def evaluate(self, **kwargs: Any) -> xr.Dataset:
        """The evaluation protocol on this data (see :func:`lrm_cvx.evaluation.evaluate`:
        the recommended setting, ``paper=True`` the paper's)."""
        from .evaluation import evaluate

        return evaluate(self._da, **kwargs)

    def plot_map(self, **kwargs: Any):
        """Plot a ``(lat, lon)`` map (see :func:`lrm_cvx.plots.plot_map`)."""
        from .plots import plot_map

        return plot_map(self._da, **kwargs)
