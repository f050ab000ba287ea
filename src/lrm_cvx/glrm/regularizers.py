"""Regularisers of the GLRM factors: one small class each, applied to columns of ``X`` or ``Y``.

A regulariser ``g`` is separable over the columns of its factor (each column a time of ``X`` or a
cell of ``Y``, shape ``(k,)``). Each class knows its value (``evaluate`` per column, vectorised),
its cvxpy expression and constraints (``cvxpy``), and, as fitting capabilities:

- ``ridge_coefficient``: ``lam`` when ``g(y) = lam ||y||^2`` (``0`` for no regulariser): the block
  problem of a quadratic (majorised) loss is then solved in closed form by normal equations;
- ``separable_prox``: True when ``g`` is a sum of scalar functions with a prox (``prox``), so the
  block problem is solved by exact coordinate descent on the k x k normal equations;
- ``minimizer``: ``argmin g`` (the value of a never-observed column), zero for all classes here.

Any other callable taking a cvxpy Variable is wrapped in :class:`CvxpyRegularizer` and only the
cvxpy path can fit it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import cvxpy as cp
import numpy as np

from .._validation import check_positive
from ..errors import ModelError
from ..registry import Registry

__all__ = [
    "Regularizer",
    "ZeroReg",
    "Ridge",
    "L1",
    "NonNegative",
    "CvxpyRegularizer",
    "get_regularizer",
    "REGULARIZERS",
    "REGULARIZER_REGISTRY",
]


class Regularizer:
    """Base class: a penalty ``g`` on each column of a ``(k, n)`` factor matrix."""

    name = "regularizer"
    ridge_coefficient: float | None = None
    separable_prox = False
    serializable = True

    def evaluate(self, F: np.ndarray) -> np.ndarray:
        """Penalty of each column of ``F (k, n)``: ``(n,)``."""
        raise NotImplementedError

    def value(self, F: np.ndarray) -> float:
        """Total penalty of ``F``."""
        return float(np.sum(self.evaluate(F)))

    def prox(self, v: np.ndarray, t: float | np.ndarray) -> np.ndarray:
        """Entry-wise ``argmin_y g(y) + (y - v)^2 / (2 t)``."""
        raise NotImplementedError

    def cvxpy(self, V: cp.Variable) -> tuple[cp.Expression, list[cp.Constraint]]:
        """Penalty of a ``(k, n)`` cvxpy variable and its constraints."""
        raise NotImplementedError

    def minimizer(self, k: int) -> np.ndarray:
        """``argmin g``: the column given to a never-observed time or cell."""
        return np.zeros(k)

    def get_params(self) -> dict[str, float]:
        return {}

    def spec(self) -> dict[str, Any]:
        return {"name": self.name, "params": self.get_params()}

    def __repr__(self) -> str:
        args = ", ".join(f"{v!r}" for v in self.get_params().values())
        return f"{type(self).__name__}({args})"

    def __eq__(self, other: object) -> bool:
        return type(self) is type(other) and self.get_params() == other.get_params()

    def __hash__(self) -> int:
        return hash((type(self).__name__, tuple(self.get_params().items())))


class ZeroReg(Regularizer):
    """No regulariser, ``g = 0`` (least squares normal equations; min-norm when singular)."""

    name = "none"
    ridge_coefficient = 0.0
    separable_prox = True

    def evaluate(self, F: np.ndarray) -> np.ndarray:
        return np.zeros(np.shape(F)[1])

    def prox(self, v: np.ndarray, t: float | np.ndarray) -> np.ndarray:
        return np.asarray(v, dtype=float)

    def cvxpy(self, V: cp.Variable) -> tuple[cp.Expression, list[cp.Constraint]]:
        return cp.Constant(0.0), []


class Ridge(Regularizer):
    """``g(y) = lam ||y||_2^2``; with a quadratic loss: ``(G + lam I) y = h`` exactly."""

    name = "ridge"
    separable_prox = True

    def __init__(self, lam: float = 1.0) -> None:
        self.lam = check_positive(lam, "Ridge weight", error=ModelError)

    @property
    def ridge_coefficient(self) -> float:  # type: ignore[override]
        return self.lam

    def get_params(self) -> dict[str, float]:
        return {"lam": self.lam}

    def evaluate(self, F: np.ndarray) -> np.ndarray:
        return self.lam * np.sum(np.square(F), axis=0)

    def prox(self, v: np.ndarray, t: float | np.ndarray) -> np.ndarray:
        return np.asarray(v, dtype=float) / (1.0 + 2.0 * self.lam * np.asarray(t))

    def cvxpy(self, V: cp.Variable) -> tuple[cp.Expression, list[cp.Constraint]]:
        return self.lam * cp.sum_squares(V), []


class L1(Regularizer):
    """``g(y) = lam ||y||_1`` (sparse factors); prox is soft thresholding."""

    name = "l1"
    separable_prox = True

    def __init__(self, lam: float = 1.0) -> None:
        self.lam = check_positive(lam, "L1 weight", error=ModelError)

    def get_params(self) -> dict[str, float]:
        return {"lam": self.lam}

    def evaluate(self, F: np.ndarray) -> np.ndarray:
        return self.lam * np.sum(np.abs(F), axis=0)

    def prox(self, v: np.ndarray, t: float | np.ndarray) -> np.ndarray:
        v = np.asarray(v, dtype=float)
        return np.sign(v) * np.maximum(np.abs(v) - self.lam * np.asarray(t), 0.0)

    def cvxpy(self, V: cp.Variable) -> tuple[cp.Expression, list[cp.Constraint]]:
        return self.lam * cp.sum(cp.abs(V)), []


class NonNegative(Regularizer):
    """Indicator of ``y >= 0`` (non-negative factors); prox is the projection."""

    name = "nonneg"
    separable_prox = True

    def evaluate(self, F: np.ndarray) -> np.ndarray:
        # tolerance for interior-point solutions (cvxpy path) that sit at -1e-10
        return np.where(np.any(np.asarray(F) < -1e-7, axis=0), np.inf, 0.0)

    def prox(self, v: np.ndarray, t: float | np.ndarray) -> np.ndarray:
        return np.maximum(np.asarray(v, dtype=float), 0.0)

    def cvxpy(self, V: cp.Variable) -> tuple[cp.Expression, list[cp.Constraint]]:
        return cp.Constant(0.0), [V >= 0]


class CvxpyRegularizer(Regularizer):
    """A user callable ``fn(V) -> expression`` (or ``(expression, constraints)``) on a cvxpy
    Variable ``V`` of shape ``(k, n)``: a batch of ``n`` columns.

    The callable must be a sum of per-column penalties (the fit splits the columns into batches)
    and must accept a ``cp.Constant`` too (used to evaluate it). Only the cvxpy path fits it; it
    cannot be saved (its ``repr`` is stored instead). Its minimiser is assumed to be 0.
    """

    name = "custom"
    serializable = False

    def __init__(self, fn: Callable[[Any], Any]) -> None:
        if not callable(fn):
            raise ModelError(f"a custom regulariser must be callable, got {fn!r}")
        self.fn = fn

    def _call(self, V: Any) -> tuple[cp.Expression, list[cp.Constraint]]:
        out = self.fn(V)
        if isinstance(out, tuple):
            expr, cons = out
            return cp.Constant(0.0) + expr, list(cons)
        return cp.Constant(0.0) + out, []

    def evaluate(self, F: np.ndarray) -> np.ndarray:
        F = np.asarray(F, dtype=float)
        vals = np.empty(F.shape[1])
        for j in range(F.shape[1]):  # small problems only (the cvxpy path)
            expr, cons = self._call(cp.Constant(F[:, j : j + 1]))
            # constraint violation, with the tolerance of NonNegative (interior-point solutions)
            feasible = all(np.all(np.asarray(c.violation()) <= 1e-7) for c in cons)
            vals[j] = float(expr.value) if feasible else np.inf
        return vals

    def cvxpy(self, V: cp.Variable) -> tuple[cp.Expression, list[cp.Constraint]]:
        return self._call(V)

    def __repr__(self) -> str:
        return f"CvxpyRegularizer({self.fn!r})"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, CvxpyRegularizer) and other.fn is self.fn

    def __hash__(self) -> int:
        return hash(id(self.fn))


REGULARIZER_REGISTRY = Registry("regulariser", ModelError)
"""Regulariser classes by name (constructed with weight 1 by :func:`get_regularizer`)."""
REGULARIZER_REGISTRY.register("none", ZeroReg, description="no penalty, `g = 0`",
                              aliases=(None,))
REGULARIZER_REGISTRY.register("ridge", Ridge, aliases=("l2",),
                              description="`lam ||y||_2^2` (`Ridge(lam)`)")
REGULARIZER_REGISTRY.register("l1", L1, aliases=("lasso",),
                              description="`lam ||y||_1`, sparse factors (`L1(lam)`)")
REGULARIZER_REGISTRY.register("nonneg", NonNegative, aliases=("nonnegative",),
                              description="indicator of `y >= 0`, non-negative factors")
REGULARIZERS: tuple[str, ...] = REGULARIZER_REGISTRY.choices()
"""Canonical regulariser names (``in`` accepts aliases); the registry's ``choices()``."""


def get_regularizer(reg: Any) -> Regularizer:
    """A :class:`Regularizer` from ``None``, a name (``"ridge"``/``"l2"``, ``"l1"``,
    ``"nonneg"``; weight 1), an instance, a spec dict, or a callable on a cvxpy Variable."""
    if reg is None:
        return ZeroReg()
    if isinstance(reg, Regularizer):
        return reg
    if isinstance(reg, dict):
        name, params = reg.get("name"), dict(reg.get("params", {}))
    else:
        name, params = reg, {}
    if isinstance(name, str):
        if name in REGULARIZER_REGISTRY:
            return REGULARIZER_REGISTRY.get(name)(**params)
        raise ModelError(
            REGULARIZER_REGISTRY.message(reg) + "; or None, a Regularizer instance "
            "(e.g. Ridge(0.1)) or a callable on a cvxpy Variable"
        )
    if callable(reg):
        return CvxpyRegularizer(reg)
    raise ModelError(f"regulariser must be None, a name, a Regularizer or a callable, got {reg!r}")
