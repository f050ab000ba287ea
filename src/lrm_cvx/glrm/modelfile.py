"""The GLRM model file: its format constants and the validated reader ``GLRM.load`` uses.

``GLRM.save`` writes ``X``, ``Y``, ``objective``, ``unobserved_cells`` and the attributes below
to NetCDF; :func:`read_model_file` opens one and refuses a file that is not a model, is newer
than this version or is inconsistent (DataError naming the file and what is wrong).
"""

from __future__ import annotations

import dataclasses
import json
import os
import warnings
from dataclasses import replace
from typing import Any

import numpy as np
import xarray as xr

from .._validation import read_netcdf
from ..errors import DataError
from .options import SolverOptions, SpatialOptions

__all__ = ["MODEL_FORMAT", "MODEL_FORMAT_VERSION", "MODEL_VARS", "MODEL_ATTRS",
           "read_model_file", "params_to_json", "params_from_json", "validation_tables",
           "restore_validation_tables"]

MODEL_FORMAT = "lrm-cvx GLRM"
MODEL_FORMAT_VERSION = 1
MODEL_VARS = ("X", "Y", "objective", "unobserved_cells")
MODEL_ATTRS = ("params", "noise_std", "n_iter", "converged", "n_observed")

_RECORDS = (SolverOptions, SpatialOptions)
"""The settings records a model's parameters may hold, saved as their fields."""
_RECORD_NAMES = {cls.__name__: cls for cls in _RECORDS}


_TABLES = (  # (attribute, file prefix, its variables and coords, int attrs, float attrs)
    ("selection_", "selection_",
     ("mse", "ratio", "ucb", "admissible", "candidate", "size", "kind", "alpha", "inflation",
      "rank"),  # rank: GLRM(rank="auto")'s tables only
     ("n_days",), ("choice_alpha", "choice_inflation", "confidence", "tolerance")),
    ("kernel_selection_", "kernel_selection_",
     ("mse", "ratio", "ucb", "admissible", "sill", "range", "nugget", "anisotropy", "competes",
      "kernel", "size"),
     ("n_rows", "n_cases"), ("confidence", "tolerance")),
    ("dynamics_selection_", "dynamics_selection_",
     ("mse", "ratio", "ucb", "admissible", "total", "candidate", "size", "alpha"),
     ("n_days",), ("choice_alpha", "confidence", "tolerance")),
    ("calibration_.selection", "calibration_selection_",
     ("mse", "ratio", "ucb", "admissible", "candidate", "size", "residual_scale",
      "local_power", "scale"),
     ("n_residuals",), ()),
)
"""The validated choices' tables a model file carries, each made by
:func:`~lrm_cvx.validation.search.selection_table`: ``temporal="auto"``'s (and
``rank="auto"``'s) ``selection_`` (validation/selection.py), ``spatial="auto"``'s
``kernel_selection_`` (validation/kernel_selection.py), ``select_dynamics``'
``dynamics_selection_`` (validation/blending.py) and the calibration's choice,
``calibration_.selection`` (validation/calibration.py)."""


def _table_of(model: object, attr: str) -> xr.Dataset | None:
    """The table at ``attr`` of ``model`` (``"a.b"``: attribute ``b`` of its ``a``), or None."""
    for name in attr.split("."):
        model = getattr(model, name, None)
    return model


def validation_tables(model: object) -> list[xr.Dataset]:
    """The validated choices' tables of a fitted model, renamed for its file (variables, dims
    and attributes prefixed, :data:`_TABLES`)."""
    out = []
    for attr, prefix, *_ in _TABLES:
        table = _table_of(model, attr)
        if table is not None:
            renamed = table.rename({v: prefix + str(v)
                                    for v in [*table.data_vars, *table.coords]})
            renamed.attrs = {prefix + k: v for k, v in table.attrs.items()}
            out.append(renamed)
    return out


def restore_validation_tables(model: object, ds: xr.Dataset) -> None:
    """Set each table of :data:`_TABLES` on ``model`` from its file ``ds`` (None when
    absent), with its attributes' types restored; the calibration's on ``model.calibration_``
    (read before)."""
    for attr, prefix, variables, ints, floats in _TABLES:
        table = None
        if prefix + "mse" in ds:
            present = [v for v in variables if prefix + v in ds.variables]
            table = ds[[prefix + v for v in present]].rename({prefix + v: v for v in present})
            table = table.drop_vars([v for v in table.variables if v not in variables])
            for flag in ("admissible", "competes"):  # older files have no "competes"
                if flag in table:
                    table[flag] = table[flag].astype(bool)
            table.attrs = {k[len(prefix):]: v for k, v in ds.attrs.items()
                           if k.startswith(prefix)}
            table.attrs.update({k: int(table.attrs[k]) for k in ints})
            if "choice_rank" in table.attrs:
                table.attrs["choice_rank"] = int(table.attrs["choice_rank"])
            table.attrs.update({k: float(table.attrs[k]) for k in floats  # older files
                                if k in table.attrs})
            table = table.load()
        if "." not in attr:
            setattr(model, attr, table)
            continue
        owner, name = attr.split(".")
        if getattr(model, owner, None) is not None:  # a frozen record: replaced
            setattr(model, owner, replace(getattr(model, owner), **{name: table}))


def params_to_json(params: dict) -> tuple[str, list[str]]:
    """``(json text, names)`` of a model's ``get_params()``: the loss and the regularisers as
    their specs (``reg``'s pair as a list of two), the settings records
    (:mod:`~lrm_cvx.glrm.options`) as their fields under ``"record"``; ``names`` the custom
    callables that cannot be saved (their repr is stored)."""
    from .losses import get_loss
    from .options import regularizer_pair

    out, custom = {}, []
    for key, value in params.items():
        if key == "loss":
            out[key] = _spec(get_loss(value), key, custom)
        elif key == "reg":
            pair = isinstance(value, (tuple, list))
            specs = [_spec(r, f"{key}[{i}]" if pair else key, custom)
                     for i, r in enumerate(regularizer_pair(value)[:1 + pair])]
            out[key] = specs if pair else specs[0]
        elif isinstance(value, _RECORDS):
            out[key] = {"record": type(value).__name__, **dataclasses.asdict(value)}
        elif key == "random_state":
            out[key] = value if isinstance(value, (int, type(None))) else repr(value)
        else:
            out[key] = value
    return json.dumps(out, default=str), custom


def _spec(value: Any, name: str, custom: list[str]) -> dict:
    """The spec of a loss or regulariser (``custom`` gains ``name`` for a custom callable)."""
    from .regularizers import get_regularizer

    obj = value if name == "loss" else get_regularizer(value)
    if getattr(obj, "serializable", True):
        return obj.spec()
    custom.append(name)
    return {"name": "custom", "repr": repr(obj)}


def params_from_json(params: dict) -> dict:
    """The parameters of :func:`params_to_json` read back (``read_model_file``'s ``params``):
    loss and regulariser specs and settings records rebuilt; a custom callable becomes None
    with a warning. A file that stores the regularisers, the initialisation, the anisotropy
    and the dask options as separate keys (``reg_x``, ``reg_y``, ``init``, ``anisotropy``,
    ``keep_dask``, ``dask_options``) reads back as ``reg``, ``solver``, ``spatial`` and
    ``dask``."""
    from .losses import get_loss
    from .regularizers import get_regularizer

    params = _merged_keys(dict(params))
    for key in ("loss", "reg"):
        if key not in params:
            continue
        spec = params[key]
        specs = spec if isinstance(spec, list) else [spec]
        for i, one in enumerate(specs):
            if isinstance(one, dict) and one.get("name") == "custom":
                warnings.warn(f"{key} was a custom callable ({one.get('repr')}) and cannot be "
                              "restored; it is set to None", UserWarning, stacklevel=3)
                specs[i] = None
            elif isinstance(one, dict):
                specs[i] = get_loss(one) if key == "loss" else get_regularizer(one)
        params[key] = tuple(specs) if isinstance(spec, list) else specs[0]
    for key, value in params.items():
        if isinstance(value, dict) and value.get("record") in _RECORD_NAMES:
            fields = {k: v for k, v in value.items() if k != "record"}
            params[key] = _RECORD_NAMES[value["record"]](**fields)
    return params


def _merged_keys(params: dict) -> dict:
    """``params`` with the separate keys of :func:`params_from_json` merged into ``reg``,
    ``solver``, ``spatial`` and ``dask`` (their defaults dropped: the same model)."""
    from .options import SolverOptions, SpatialOptions

    if "reg_x" in params or "reg_y" in params:
        params["reg"] = [params.pop("reg_x", None), params.pop("reg_y", None)]
    init = params.pop("init", "svd")
    if init != "svd":
        params["solver"] = SolverOptions(params.get("solver", "auto"), init)
    anisotropy = params.pop("anisotropy", 1.0)
    if anisotropy != 1.0 and params.get("spatial") is not None:
        params["spatial"] = SpatialOptions(params.get("spatial"), anisotropy)
    keep, options = params.pop("keep_dask", False), params.pop("dask_options", None)
    if keep or options:
        params["dask"] = {**(options or {}), **({"keep_dask": True} if keep else {})}
    return params


def read_model_file(path: str | os.PathLike) -> tuple[xr.Dataset, dict]:
    """``(dataset, params)`` of a GLRM model file, validated (DataError naming the file and
    what is wrong)."""
    name = repr(os.fspath(path))
    ds = read_netcdf(path, "model file", "GLRM.save")
    if ds.attrs.get("format") != MODEL_FORMAT:
        raise DataError(f"{name} is not an lrm-cvx GLRM model file (no format attribute "
                        f"{MODEL_FORMAT!r})")
    try:
        version = int(ds.attrs.get("format_version", 1))
    except (TypeError, ValueError):
        raise DataError(f"model file {name} has an unreadable format_version "
                        f"{ds.attrs.get('format_version')!r}") from None
    if version > MODEL_FORMAT_VERSION:
        raise DataError(f"model file {name} has format_version {version}, written by a newer "
                        f"lrm-cvx; this version reads up to {MODEL_FORMAT_VERSION}: upgrade "
                        "lrm-cvx")
    missing = [v for v in MODEL_VARS if v not in ds.variables]
    if missing:
        raise DataError(f"model file {name} is missing the variable(s) {missing}")
    missing = [a for a in MODEL_ATTRS if a not in ds.attrs]
    if missing:
        raise DataError(f"model file {name} is missing the attribute(s) {missing}")
    tdim = ds.attrs.get("time_dim", "time")
    X, Y = ds["X"], ds["Y"]
    if X.ndim != 2 or Y.ndim != 2 or X.shape[0] != Y.shape[0] or X.dims[1] != tdim:
        raise DataError(f"model file {name} has inconsistent factors: X {X.dims} {X.shape}, "
                        f"Y {Y.dims} {Y.shape} (expected (component, {tdim}) and "
                        "(component, cell) with the same number of components)")
    for key, factor in (("X", X), ("Y", Y)):
        if not np.issubdtype(factor.dtype, np.number):
            raise DataError(f"model file {name}: the factor {key} holds {factor.dtype} values, "
                            "expected numbers")
        bad = int(np.count_nonzero(~np.isfinite(np.asarray(factor.values, dtype=np.float64))))
        if bad:
            raise DataError(f"model file {name} has {bad} non-finite value(s) (NaN or inf) in "
                            f"the factor {key}; a fitted model's factors are finite: refit it")
    if tdim not in ds.variables:
        raise DataError(f"model file {name} is missing the variable {tdim!r} (the time "
                        "coordinate)")
    key = "params"
    try:
        params = json.loads(ds.attrs["params"])
        key = "region_attrs"
        json.loads(ds.attrs.get("region_attrs", "{}"))
        noise = float(ds.attrs["noise_std"])
        int(ds.attrs["n_iter"]), int(ds.attrs["converged"]), int(ds.attrs["n_observed"])
    except (TypeError, ValueError) as exc:
        raise DataError(f"model file {name} has a corrupt attribute: {exc}") from None
    except RecursionError:
        raise DataError(f"model file {name} has a corrupt attribute: {key!r} is JSON nested "
                        "too deeply to read") from None
    if not isinstance(params, dict):
        raise DataError(f"model file {name} has a corrupt 'params' attribute (not a mapping)")
    if not np.isfinite(noise) or noise < 0:
        raise DataError(f"model file {name} has noise_std {noise}, expected a finite number "
                        ">= 0")
    if noise == 0:
        warnings.warn(f"model file {name} has noise_std 0: the noise was not identifiable at "
                      "its rank (fitted by an older lrm-cvx?), so every std map is 0; refit "
                      "with a lower rank", UserWarning, stacklevel=3)
    if int(ds.attrs.get("has_region", 0)):
        if "region_mask" not in ds.variables:
            raise DataError(f"model file {name} is missing the variable(s) ['region_mask']")
        n_valid = int(np.count_nonzero(ds["region_mask"].values))
        if n_valid != Y.shape[1]:
            raise DataError(f"model file {name}: the region has {n_valid} valid cells but Y has "
                            f"{Y.shape[1]}")
    for key in [k for k in ds.variables if str(k).startswith("predictive_")]:
        if ds[key].shape != (Y.shape[1],):
            raise DataError(f"model file {name}: {key} has shape {ds[key].shape}, expected "
                            f"({Y.shape[1]},) (one value per cell)")
    return ds, params
