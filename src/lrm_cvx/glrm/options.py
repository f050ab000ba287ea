"""The settings records of :class:`~lrm_cvx.glrm.model.GLRM`: one constructor argument per idea.

:class:`SolverOptions` (``GLRM(solver=)``: which path fits the factors and how they start) and
:class:`SpatialOptions` (``GLRM(spatial=)``: the residual's covariance family and its
anisotropy) are frozen and validated once when built, as
:class:`~lrm_cvx.planning.request.PathOptions` is; a plain string still names the solver or the
family. :func:`solver_options`, :func:`spatial_options` and :func:`regularizer_pair` read a
``GLRM`` argument in any accepted form; :func:`dask_options` reads ``GLRM(dask=)``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import ModelError

__all__ = ["SolverOptions", "SpatialOptions", "solver_options", "spatial_options",
           "regularizer_pair", "dask_options", "SOLVERS", "INITS", "DASK_KEYS"]

SOLVERS = ("auto", "fast", "cvxpy")
"""``SolverOptions.name``: the compiled path when the loss and regularisers allow it, that
path required, or every block subproblem in cvxpy."""
INITS = ("svd", "random")
"""``SolverOptions.init``: the factors' initialisation."""
DASK_KEYS = ("keep_dask", "chunk_mb", "scratch_dir", "block_mb", "staging_options", "timings")
"""The keys of ``GLRM(dask=)``: :func:`~lrm_cvx.glrm.chunked.fit_chunked`'s options."""


@dataclass(frozen=True)
class SolverOptions:
    """How :class:`~lrm_cvx.glrm.model.GLRM` fits its factors (``GLRM(solver=)``); validated
    when built.

    ``name``: ``"auto"`` (the compiled fast path whenever the loss and regularisers allow it),
    ``"fast"`` (require it) or ``"cvxpy"`` (every block subproblem in cvxpy with Clarabel/SCS);
    ``init``: ``"svd"`` (SVD of the mean-filled matrix; randomized for large data) or
    ``"random"``. ``GLRM(solver="cvxpy")`` is ``SolverOptions("cvxpy")``. A bad value raises
    ModelError naming the field.

    >>> SolverOptions(init="random").name
    'auto'
    """

    name: str = "auto"
    init: str = "svd"

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or self.name not in SOLVERS:
            raise ModelError(f"solver name must be 'auto', 'fast' or 'cvxpy', got {self.name!r}")
        if not isinstance(self.init, str) or self.init not in INITS:
            raise ModelError(f"init must be 'svd' or 'random', got {self.init!r}")


@dataclass(frozen=True)
class SpatialOptions:
    """The GP residual of :class:`~lrm_cvx.glrm.model.GLRM` (``GLRM(spatial=)``); validated
    when built.

    ``model``: a covariance family (``"exponential"``, ``"matern32"``, ...) or ``"auto"`` (the
    family validated on the training residuals); ``anisotropy``: a fixed family's east-west
    over north-south range (grid cells; 1: isotropic). ``"auto"`` validates its own
    anisotropy, so it takes none. ``GLRM(spatial="exponential")`` is
    ``SpatialOptions("exponential")``; ``str()`` is the family, with ``" x<anisotropy>"`` when
    anisotropic (as ``kernel_selection_`` labels its candidates). A bad value raises ModelError
    naming the field.

    >>> str(SpatialOptions("exponential", anisotropy=2.5))
    'exponential x2.5'
    """

    model: str
    anisotropy: float = 1.0

    def __post_init__(self) -> None:
        from ..spatial import MODELS
        from ..spatial.covariance import check_anisotropy

        if not isinstance(self.model, str) or self.model not in (*MODELS, "auto"):
            raise ModelError(f"spatial model must be 'auto' or one of {MODELS}, got "
                             f"{self.model!r}")
        a = check_anisotropy(self.anisotropy)  # the residual's grid metric
        if a != 1 and self.model == "auto":
            raise ModelError(f"anisotropy={a!r} applies to a fixed spatial family (spatial="
                             "'exponential', ...); spatial='auto' estimates and validates its own")
        object.__setattr__(self, "anisotropy", a)

    def __str__(self) -> str:
        return self.model if self.anisotropy == 1.0 else f"{self.model} x{self.anisotropy:.3g}"


def solver_options(value: Any) -> SolverOptions:
    """``GLRM(solver=)`` as a :class:`SolverOptions`: a record as given, a string its
    ``name`` (ModelError naming ``solver`` otherwise)."""
    if isinstance(value, SolverOptions):
        return value
    if isinstance(value, str):
        return SolverOptions(value)
    raise ModelError(f"solver must be 'auto', 'fast', 'cvxpy' or a SolverOptions, got "
                     f"{value!r}")


def spatial_options(value: Any) -> SpatialOptions | None:
    """``GLRM(spatial=)`` as a :class:`SpatialOptions` (None: no GP residual): a record as
    given, a string its ``model`` (ModelError naming ``spatial`` otherwise)."""
    from ..spatial import MODELS

    if value is None or isinstance(value, SpatialOptions):
        return value
    if isinstance(value, str) and value in (*MODELS, "auto"):
        return SpatialOptions(value)
    raise ModelError(f"spatial must be None, 'auto', one of {MODELS} or a SpatialOptions, got "
                     f"{value!r}")


def regularizer_pair(value: Any) -> tuple[Any, Any]:
    """``GLRM(reg=)`` as ``(reg_x, reg_y)``, the regularisers of the columns of ``X`` and of
    ``Y``: a tuple or list is the pair, anything else is one regulariser for both (ModelError
    naming ``reg`` for a sequence of another length)."""
    if isinstance(value, (tuple, list)):
        if len(value) != 2:
            raise ModelError(f"reg must be one regulariser or a pair (reg_x, reg_y), got a "
                             f"{type(value).__name__} of {len(value)}")
        return value[0], value[1]
    return value, value


def dask_options(value: Any) -> tuple[dict[str, Any], bool]:
    """``GLRM(dask=)`` as ``(fit_chunked options, keep_dask)``: None or False for the
    defaults, else a mapping with keys among :data:`DASK_KEYS` (ModelError naming ``dask``
    otherwise)."""
    if value is None or value is False:
        return {}, False
    if not isinstance(value, Mapping):
        raise ModelError(f"dask must be None or a mapping of the dask fit's options (keys "
                         f"among {list(DASK_KEYS)}), got {value!r}")
    bad = sorted(set(value) - set(DASK_KEYS))
    if bad:
        raise ModelError(f"dask: unknown option(s) {bad}; choose from {list(DASK_KEYS)}")
    opts = dict(value)
    keep = opts.pop("keep_dask", False)
    if not isinstance(keep, (bool, np.bool_)):
        raise ModelError(f"dask['keep_dask'] must be True or False, got {keep!r}")
    return opts, bool(keep)
