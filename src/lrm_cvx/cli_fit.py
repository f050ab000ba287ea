"""``lrm-cvx fit``: the data a command reads and the GLRM it fits.

The data arguments (files, globs, folders, ``sample:NAME``; ``--var``, ``--bbox``), the model
options (``--offset`` ... ``--temporal``, over the recommended or the paper's setting) and the fit
itself (``--hold-out`` / ``--until``; the recommended ``temporal='auto'`` and calibration fall
back with a note where the data cannot take them); ``evaluate`` and ``place`` read their data
and fit their models with the same helpers.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .cli_common import (
    UsageError,
    add_output,
    add_setting,
    check_lat,
    finite_number,
    first,
    guard_paths,
    int_at_least,
    none_value,
    note,
    paper_setting,
    parse_floats,
)
from .recommended import RECOMMENDED

__all__ = ["rank_value", "input_files", "load_data", "MODEL_FLAGS", "recommended_glrm",
           "model_params", "cmd_fit", "fit_model", "add_data", "add_model_options",
           "recommended_fit", "add_fit_parser"]


def _bbox(text: str | None) -> tuple[float, float, float, float] | None:
    """``--bbox S,W,N,E`` as ``(south, west, north, east)`` (None when not given)."""
    if text is None:
        return None
    south, west, north, east = parse_floats(text, 4, "--bbox S,W,N,E")
    check_lat(south, "--bbox south")
    check_lat(north, "--bbox north")
    if south >= north:
        raise UsageError(f"--bbox south ({south:g}) must be below north ({north:g}); the order "
                         "is S,W,N,E")
    return (south, west, north, east)


def rank_value(text: str) -> int | str:
    """``--rank``: an integer >= 1 or ``auto`` (chosen on the training snapshots)."""
    if text == "auto":
        return text
    try:
        return int_at_least(1)(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1 or 'auto', got {text!r}") \
            from None


def input_files(items: Sequence[str]) -> list[Path]:
    """Every file a data argument reads: globs expanded (as ``open_data`` does), a folder and
    every file in it, and the package file behind ``sample:NAME``."""
    from .io.generic import expand_paths

    files: list[Path] = []
    plain = []
    for item in items:
        text = str(item)
        if text.startswith("sample:"):
            from importlib import resources

            name = text.split(":", 1)[1]
            files.append(Path(str(resources.files("lrm_cvx") / "data" / f"{name}.nc")))
        else:
            plain.append(text)
    for path in expand_paths(plain) if plain else []:
        files.append(path)
        if path.is_dir():
            files.extend(q for q in sorted(path.iterdir()) if q.is_file())
    return files


def load_data(args: argparse.Namespace) -> Any:
    """The snapshots of ``DATA`` (``--var``, ``--bbox``), read by :func:`lrm_cvx.io.open_data`."""
    from .io import open_data

    return open_data(args.data, var=args.var, bbox=_bbox(args.bbox))


MODEL_FLAGS = ("offset", "scale", "noise", "spatial", "temporal")
"""The GLRM parameters the CLI has an option for (``--offset`` ...)."""


def recommended_glrm() -> dict:
    """``GLRM.recommended_params()``: the GLRM parameters of ``RECOMMENDED``."""
    from .glrm import GLRM

    return GLRM.recommended_params()


def model_params(args: argparse.Namespace) -> dict:
    """The GLRM parameters of ``fit`` / ``evaluate``: the explicit model options over the
    paper's defaults (``--paper``) or over the recommended ones (every GLRM parameter in
    ``RECOMMENDED``, so a key the recommended setting gains reaches the fit)."""
    from .glrm.options import SpatialOptions
    from .glrm.predictive import NOISE_MODELS

    params: dict = {"offset": False, "spatial": None, "scale": False,
                    "noise": first(NOISE_MODELS), "temporal": None}  # the paper's
    if not paper_setting(args):
        params.update(recommended_glrm())
    explicit = {"offset": True if args.offset else None,
                "scale": _scale_option(args),
                "noise": args.noise, "spatial": args.spatial, "temporal": args.temporal}
    params.update({k: v for k, v in explicit.items() if v is not None})
    if args.anisotropy is not None:  # --spatial KERNEL --anisotropy A: one spatial setting
        if params["spatial"] is None:
            raise UsageError("--anisotropy needs --spatial KERNEL (a fixed covariance family)")
        params["spatial"] = SpatialOptions(params["spatial"], args.anisotropy)
    params["temporal"] = none_value(params["temporal"])  # --temporal none: no dynamics
    return params


def _scale_option(args: argparse.Namespace) -> Any:
    """GLRM's ``scale`` from ``--scale`` (True) / ``--residual-scale`` (``"residual"``); None
    when neither is given."""
    if args.scale and args.residual_scale:
        raise UsageError("--scale and --residual-scale exclude each other: choose one")
    return True if args.scale else "residual" if args.residual_scale else None


def cmd_fit(args: argparse.Namespace) -> int:
    """``lrm-cvx fit``: fit a GLRM to the snapshots of ``DATA`` and save it to ``-o``."""
    from .validation.selection import AutoUnavailable

    params = model_params(args)
    (out,) = guard_paths([args.output], input_files(args.data), args)
    data = _hold_out(load_data(args), args)
    default_auto = params["temporal"] == "auto" and args.temporal is None

    def without_dynamics(why: str) -> None:  # the recommended default cannot run here
        note(f"the recommended temporal='auto' cannot run on these data ({why.split(';')[0]}); "
             "fitting without dynamics (--temporal ar1|seasonal asks for them)")
        params["temporal"] = None

    if default_auto:
        from .validation.selection import auto_unavailable

        if (why := auto_unavailable(data)) is not None:  # found before any fit
            without_dynamics(why)
    fit_kw = dict(rank=args.rank, loss=args.loss, max_iter=args.max_iter, tol=args.tol,
                  random_state=args.seed, progress=not args.quiet)
    try:
        model = fit_model(data, params, **fit_kw)
    except AutoUnavailable as exc:  # a record too short for the validation's refits
        if not default_auto:
            raise
        without_dynamics(str(exc))
        model = fit_model(data, params, **fit_kw)
    model.save(out)
    extras = [name if getattr(model, name) is True else f"{name}={getattr(model, name)}"
              for name in ("offset", "scale") if getattr(model, name)]
    if model.spatial:
        extras.append(f"spatial={model.spatial}")
    print(f"fitted rank-{model.rank_} GLRM{' (' + ', '.join(extras) + ')' if extras else ''} on "
          f"{data.sizes['time']} snapshots x {model.region_.n_cells} cells in {model.n_iter_} "
          f"iterations (noise std {model.noise_std_:.4g}); saved {out}")
    if getattr(model, "selection_", None) is not None:
        from .validation.selection import format_selection

        print(format_selection(model.selection_))
    if getattr(model, "kernel_selection_", None) is not None:
        from .validation.kernel_selection import format_kernel_selection

        print(format_kernel_selection(model.kernel_selection_))
    return 0


def fit_model(data, params: dict, **kw):
    """``GLRM(**kw, **params).fit(data)``; the recommended ``calibration`` (the only way the CLI
    asks for one) runs after the fit and, on a record too short for its refits, is left out with
    one note instead of failing the fit."""
    from .glrm import GLRM
    from .validation.calibration import fit_then_try_calibrate

    model = GLRM(**kw, **params)
    if (why := fit_then_try_calibrate(model, data)) is not None:
        note(f"the recommended conformal calibration cannot run on these data ({why}); the "
             "intervals are uncalibrated")
    return model


def _hold_out(data, args: argparse.Namespace):
    """The snapshots ``fit`` trains on: all, all but the last ``--hold-out N``, or those at or
    before ``--until DATE`` (any calendar of the data); says what was held out."""
    n_all = data.sizes["time"]
    if args.hold_out is not None and args.until is not None:
        raise UsageError("--hold-out and --until exclude each other")
    if args.hold_out is not None:
        keep = n_all - args.hold_out
        if keep < 2:
            raise UsageError(f"--hold-out {args.hold_out} leaves {max(keep, 0)} of {n_all} "
                             "snapshots to fit on; at least 2 are needed")
    elif args.until is not None:
        from .belief.filter import parse_time

        until = parse_time(args.until, data["time"], "--until")
        keep = int(np.count_nonzero(data["time"].values <= until))
        if keep < 2:
            raise UsageError(f"--until {args.until} keeps {keep} of {n_all} snapshots (the "
                             f"first is {data['time'].values[0]}); at least 2 are needed")
    else:
        return data
    if keep < n_all:
        from .belief.filter import time_label

        times = data["time"].values
        print(f"held out the last {n_all - keep} of {n_all} snapshots ({time_label(times[keep])}"
              f" .. {time_label(times[-1])}); fitting on {keep}")
    return data.isel(time=slice(0, keep))


def add_data(p: argparse.ArgumentParser) -> None:
    """``DATA`` (files, globs, folders, ``sample:NAME``), ``--var`` and ``--bbox``."""
    p.add_argument("data", nargs="+", help="NOAA NDVI CDR files, an image folder, a NetCDF "
                   "file with a (time, lat, lon) variable, or sample:NAME")
    p.add_argument("--var", help="variable name in a generic NetCDF file")
    p.add_argument("--bbox", help="region S,W,N,E in degrees (or S W N E; negative = south / "
                   "west; W > E crosses the antimeridian; required for images)")


def add_model_options(p: argparse.ArgumentParser, *, fit: bool = True) -> None:
    """The GLRM options (``--offset`` ... ``--temporal``; read with :func:`model_params`);
    ``fit=False``: ``evaluate``'s help for ``--temporal``."""
    from .glrm.dynamics import TEMPORAL
    from .glrm.predictive import NOISE_MODELS
    from .spatial import MODELS

    def default(key: str, paper: str, recommended: str | None = None) -> str:
        rec = recommended or str(RECOMMENDED.get(key, paper))
        return f"default: {rec}; {paper} with --paper" if rec != paper else f"default: {paper}"

    p.add_argument("--offset", action="store_true",
                   help="fit a per-cell mean (offset) (default: on; off with --paper)"
                   if RECOMMENDED.get("offset") else "fit a per-cell mean (offset)")
    p.add_argument("--scale", action="store_true",
                   help="divide the data by a per-cell std before the fit (floored at 0.1 x the "
                   "median cell's)")
    p.add_argument("--residual-scale", action="store_true",
                   help="a heteroscedastic residual: a per-cell scale of the training "
                   "residuals, after the fit (scale='residual')")
    p.add_argument("--noise", choices=NOISE_MODELS, default=None,
                   help=f"noise model ({default('noise', first(NOISE_MODELS))})")
    p.add_argument("--spatial", choices=(*MODELS, "auto"), default=None, metavar="KERNEL",
                   help=f"also fit a GP covariance of the residuals ({', '.join(MODELS)}, or "
                   "auto: the family validated on the training residuals; "
                   f"{default('spatial', 'none')})")
    p.add_argument("--anisotropy", type=float, default=None, metavar="A",
                   help="a fixed --spatial kernel's east-west over north-south range (grid "
                   "cells; default 1: isotropic; --spatial auto validates its own)")
    p.add_argument("--temporal", choices=[t or "none" for t in TEMPORAL], default=None,
                   help="latent dynamics for persistent monitoring (docs/monitoring.md): auto "
                   "chooses none, ar1 or seasonal on the training snapshots by rolling-origin "
                   "validation and prints its table (" + (
                       f"{default('temporal', 'none')}; where auto cannot run on the data, "
                       "e.g. fewer than 8 regularly spaced snapshots, a note says so and none "
                       "is fitted)" if fit else "default: none, the protocol is memoryless, "
                       "with or without --paper; with it, each start's route is flown day "
                       "after day and the filter is scored beside the memoryless fold-in)"))


def recommended_fit(fit: bool = True) -> str:
    """The GLRM parameters of ``RECOMMENDED`` as flags, for the help texts (``evaluate``
    fits no dynamics unless ``--temporal`` is given)."""
    flags = []
    params = recommended_glrm()
    for key, value in params.items():
        if key in MODEL_FLAGS and (fit or key != "temporal") and value not in (None, False):
            flag = f"--{key.replace('_', '-')}"
            if key == "scale" and value == "residual":
                flags.append("--residual-scale")
                continue
            flags.append(flag if value is True else f"{flag} {value}")
    if params.get("calibration") is not None:  # no flag: the recommended fit's own step
        flags.append("and the conformal interval calibration")
    return " ".join(flags)


def add_fit_parser(sub: Any) -> None:
    """Add ``fit`` to ``lrm-cvx``'s subcommands."""
    from .glrm.losses import LOSSES

    p = sub.add_parser("fit", help="fit a GLRM to gridded snapshots")
    add_data(p)
    p.add_argument("--rank", type=rank_value, default=5,
                   help="components (default 5), or auto: chosen with the temporal model "
                        "(--temporal auto or none) by rolling-origin validation on the "
                        "training snapshots")
    p.add_argument("--loss", default="quadratic", choices=LOSSES)
    p.add_argument("--max-iter", type=int_at_least(1), default=100)
    p.add_argument("--tol", type=finite_number, default=1e-4)
    p.add_argument("--seed", type=int_at_least(0), default=0)
    add_model_options(p)
    add_setting(p, recommended_fit(), "no offset, no spatial residual, no dynamics")
    p.add_argument("--hold-out", type=int_at_least(0), default=None, metavar="N",
                   help="leave the last N snapshots out of the fit (to test or monitor on)")
    p.add_argument("--until", default=None, metavar="DATE",
                   help="fit on the snapshots at or before DATE only (YYYY-MM-DD[THH:MM], in "
                   "the data's calendar: 2093-02-30 is a 360-day date)")
    p.add_argument("-o", "--output", required=True, help="model file (.nc)")
    add_output(p)
    p.set_defaults(func=cmd_fit)
