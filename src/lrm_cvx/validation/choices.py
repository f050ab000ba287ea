"""The choices :meth:`GLRM.fit <lrm_cvx.glrm.model.GLRM.fit>` validates on its training data.

``rank="auto"`` (:func:`choose_rank`, before the fit), then ``temporal="auto"`` and
``calibration=`` (:func:`validate_choices`, after it). The estimator reaches them through
:data:`~lrm_cvx.glrm.hooks.HOOKS`, so the model's package never imports this one.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
import xarray as xr

from .._validation import check_ranks
from ..errors import ModelError
from ..glrm.dynamics import temporal_value
from ..region import Region
from . import refits
from .calibration import calibrate_with
from .search import Best, search, selection_table
from .selection import (
    AUTO_INFLATIONS,
    AUTO_RANKS,
    REFERENCE_RANK,
    apply_selection,
    check_auto_data,
    select_temporal,
)

__all__ = ["choose_rank", "validate_choices", "window_of", "clone", "select_rank"]


def choose_rank(model: Any, data: Any, mask: Any, region: Any,
                is_dask: bool) -> tuple[int, Any, Any]:
    """``rank="auto"``: ``(rank, selection, region)`` from
    :func:`~.selection.select_temporal` with ``ranks`` on a reference fit (rank
    :data:`~.selection.REFERENCE_RANK`, no dynamics or calibration: its region, kernel and
    refits), before the real fit of ``model``.

    Above ``refits.VALIDATION_MAX_CELLS`` cells the reference model is fitted on the window the
    validations read (:func:`~.refits.validation_data`), not on the whole region. ``region``:
    the data's, found once for the reference and the real fit. ``is_dask``: ``data`` or
    ``mask`` is dask-backed (refused: the choice refits in memory).
    """
    if model.rank != "auto":
        raise ModelError(f"rank must be an integer or 'auto', got {model.rank!r}")
    temporal = temporal_value(model.temporal)
    if temporal not in (None, "auto"):
        raise ModelError(f"rank='auto' is validated with temporal='auto' or None, got "
                         f"temporal={model.temporal!r}")
    if mask is not None or is_dask:
        raise ModelError("rank='auto' refits in memory on a (time, lat, lon) DataArray: "
                         "pass an integer rank for masked arrays or dask data")
    check_auto_data(data)
    ref_rank = int(min(REFERENCE_RANK, max(1, data.shape[0] // 4)))
    # a large region's reference model is fitted on the validations' window only
    region = Region.from_dataarray(data) if region is None else region
    ref_data, ref_region = refits.validation_data(data, region)
    ref = refits.clone_model(model, rank=ref_rank, temporal=None).fit(ref_data, region=ref_region)
    auto = temporal == "auto"
    selection = select_temporal(
        ref, ref_data, ranks=AUTO_RANKS, kinds=("ar1", "seasonal") if auto else (),
        inflations=AUTO_INFLATIONS if auto else (1.0,), seed=model.random_state)
    return int(selection.attrs["choice_rank"]), selection, region


def clone(model: Any, **override: Any) -> Any:
    """An unfitted copy of ``model`` for a refit (:func:`~.refits.clone_model`, looked up when
    called): ``GLRM.select_rank``'s."""
    return refits.clone_model(model, **override)


def window_of(region: Any) -> Any:
    """The window of ``region`` the validations read (:func:`~.refits.validation_window` at
    ``refits.VALIDATION_MAX_CELLS``, read when called), None for the whole region."""
    return refits.validation_window(region, refits.VALIDATION_MAX_CELLS)


def validate_choices(model: Any, data: Any, stacked: np.ndarray | None = None,
                     selection: Any = None) -> None:
    """The choices validated on the training ``data`` of the fitted ``model``:
    ``temporal="auto"``'s ``dynamics_`` (:mod:`.selection`; ``selection``: the one
    ``rank="auto"`` made already), then ``calibration``'s ``calibration_``
    (:mod:`.calibration`). ``stacked``: ``data`` as the fit stacked it ``(T, L)``, when it
    still holds it."""
    if selection is not None:
        apply_selection(model, selection)
    elif temporal_value(model.temporal) == "auto":
        apply_selection(model, select_temporal(model, data, seed=model.random_state,
                                               values=stacked))
    if model.calibration is not None:
        calibrate_with(model, data, model.calibration)


def select_rank(model: Any, data: Any, ranks: Any, fraction: float = 0.1,
                seed: Any = 0) -> xr.Dataset:
    """:meth:`GLRM.select_rank <lrm_cvx.glrm.model.GLRM.select_rank>`: the held-out error of
    each rank, from copies of ``model`` fitted on a random training split of the observed
    entries (``fraction`` held out, ``seed``) and scored on the rest, through the one search
    (:func:`~.search.search`, one split, the :class:`~.search.Best` rule).

    Returns the table of every validated choice (:func:`~.search.selection_table`) over
    ``rank`` (the reference, for ``ratio``, is the first rank) and one ``size`` (0: not scored
    per sample size): ``mse`` (the held-out MSE in data units), ``ratio``, ``ucb`` (NaN: no
    guard), ``admissible`` and ``rmse`` (its square root); ``attrs["choice"]`` is the rank of
    the lowest held-out error, ``attrs["fraction"]`` the share held out."""
    ranks = check_ranks(ranks)
    if isinstance(data, xr.DataArray) and data.ndim == 3:
        region = Region.from_dataarray(data)
        data = xr.DataArray(region.stack(data), dims=(data.dims[0], "cell"))
    train, test = model.holdout(data, fraction, seed)
    train = np.asarray(getattr(train, "values", train))
    mask = ~np.isnan(train)
    np.copyto(train, 0, where=~mask)  # ours: zero-filled once, so no fit copies it
    test = np.asarray(getattr(test, "values", test))

    def mse_by_rank(split: tuple) -> dict[int, np.ndarray]:  # one split: (1, 1) each
        out = {}
        for r in ranks:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                fit = refits.clone_model(model, rank=int(r)).fit(split[0], mask=split[1])
            out[int(r)] = np.array([[fit.score(split[2])]])
        return out

    labels, E, decision = search(mse_by_rank, [(train, mask, test)], Best())
    table = selection_table(
        decision, labels, [0], dim="rank", reference=f"rank {labels[0]}",
        what="held-out MSE (data units)",
        data_vars={"rmse": (("rank",), [float(np.sqrt(e[0, 0])) for e in E])},
        fraction=float(fraction))
    table["rmse"].attrs["long_name"] = "held-out RMSE (data units)"
    return table
