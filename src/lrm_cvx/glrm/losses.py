"""Losses of the GLRM: one small class each, applied entry-wise to residuals ``r = x_t . y_j - d``.

Each loss knows (LowRankModels.jl style) its value (``evaluate``, vectorised numpy), its gradient
(``grad``), its prox, its cvxpy expression (``cvxpy``), and, as fitting capabilities:

- ``kernel_spec``: ``(code, p0, p1)`` of its compiled quadratic majoriser (see
  :func:`lrm_cvx.glrm.kernels.majorize`), or ``None`` when it has none (then only the cvxpy path
  fits it);
- ``is_quadratic``: the majoriser is the loss itself, so one weighted least-squares solve is the
  exact block minimiser;
- ``majorizer_exact``: the majoriser touches the loss at the current residual, so every MM step
  decreases the objective; when False the fit checks each column/row and keeps the old one if the
  objective went up (monotone safeguard).

The scale follows cvxpy: ``Quadratic`` is ``r^2`` (the paper's squared Frobenius norm), ``Huber``
is ``r^2`` inside ``[-delta, delta]`` and ``2 delta |r| - delta^2`` outside (``cp.huber``).
"""

from __future__ import annotations

from typing import Any

import cvxpy as cp
import numpy as np

from ..errors import ModelError
from ..registry import Registry

__all__ = ["Loss", "Quadratic", "Huber", "Absolute", "Quantile", "get_loss", "LOSSES",
           "LOSS_REGISTRY"]

_EPS = 1e-9  # floor of |r| in the L1-type majorisers, relative to the data's RMS (set in fit)
_START, _DECAY = 1e7, 0.5  # continuation: the floor starts at 1e7 * eps and halves every MM step


class Loss:
    """Base class: an entry-wise loss ``f(r)`` of the residual ``r = prediction - data``."""

    name = "loss"
    kernel_spec: tuple[int, float, float] | None = None
    is_quadratic = False
    majorizer_exact = False

    def evaluate(self, r: np.ndarray) -> np.ndarray:
        """Entry-wise loss values, same shape as ``r``."""
        raise NotImplementedError

    def grad(self, r: np.ndarray) -> np.ndarray:
        """Entry-wise (sub)gradient ``f'(r)``."""
        raise NotImplementedError

    def prox(self, v: np.ndarray, t: float | np.ndarray) -> np.ndarray:
        """``argmin_r f(r) + (r - v)^2 / (2 t)`` entry-wise."""
        raise NotImplementedError

    def cvxpy(self, r: cp.Expression) -> cp.Expression:
        """Scalar cvxpy expression: the sum of the loss over the entries of ``r``."""
        raise NotImplementedError

    def with_scale(self, scale: float) -> Loss:
        """The loss with its numerical floor set for data of RMS ``scale`` (default: itself)."""
        return self

    smoothing = False
    """True for L1-type losses whose majoriser floors ``|r|`` at ``eps``: the fit then starts
    from a large floor and shrinks it (continuation), which avoids IRLS sticking at zero
    residuals; see :meth:`smoothed`."""

    def smoothed(self, step: int) -> Loss:
        """The loss whose majoriser floor is used at MM step ``step`` (default: itself)."""
        return self

    def get_params(self) -> dict[str, float]:
        """Constructor parameters (for ``repr`` and saving)."""
        return {}

    def spec(self) -> dict[str, Any]:
        """JSON-serialisable description: ``{"name": ..., "params": {...}}``."""
        return {"name": self.name, "params": self.get_params()}

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.get_params().items())
        return f"{type(self).__name__}({args})"

    def __eq__(self, other: object) -> bool:
        return type(self) is type(other) and self.get_params() == other.get_params()

    def __hash__(self) -> int:
        return hash((type(self).__name__, tuple(self.get_params().items())))


class Quadratic(Loss):
    """``f(r) = r^2``: the paper's ``||P_Omega(X^T Y - D)||_F^2``. Block steps are exact."""

    name = "quadratic"
    kernel_spec = (0, 0.0, 0.0)
    is_quadratic = True
    majorizer_exact = True

    def evaluate(self, r: np.ndarray) -> np.ndarray:
        return np.square(r)

    def grad(self, r: np.ndarray) -> np.ndarray:
        return 2.0 * np.asarray(r)

    def prox(self, v: np.ndarray, t: float | np.ndarray) -> np.ndarray:
        return np.asarray(v) / (1.0 + 2.0 * np.asarray(t))

    def cvxpy(self, r: cp.Expression) -> cp.Expression:
        return cp.sum_squares(r)


class Huber(Loss):
    """Huber loss ``r^2`` for ``|r| <= delta``, ``2 delta |r| - delta^2`` beyond (``cp.huber``).

    Fitted by majorisation-minimisation: at residual ``r0`` with ``|r0| > delta`` the quadratic
    ``(delta/|r0|) r^2 + const`` majorises the loss and touches it at ``r0`` (IRLS weights).
    """

    name = "huber"
    is_quadratic = False
    majorizer_exact = True

    def __init__(self, delta: float = 1.0) -> None:
        delta = float(delta)
        if not np.isfinite(delta) or delta <= 0:
            raise ModelError(f"Huber delta must be > 0, got {delta!r}")
        self.delta = delta

    @property
    def kernel_spec(self) -> tuple[int, float, float]:  # type: ignore[override]
        return (1, self.delta, 0.0)

    def get_params(self) -> dict[str, float]:
        return {"delta": self.delta}

    def evaluate(self, r: np.ndarray) -> np.ndarray:
        a = np.abs(r)
        return np.where(a <= self.delta, np.square(r), 2.0 * self.delta * a - self.delta**2)

    def grad(self, r: np.ndarray) -> np.ndarray:
        return 2.0 * np.clip(r, -self.delta, self.delta)

    def prox(self, v: np.ndarray, t: float | np.ndarray) -> np.ndarray:
        v = np.asarray(v, dtype=float)
        t = np.asarray(t, dtype=float)
        inner = v / (1.0 + 2.0 * t)
        return np.where(np.abs(inner) <= self.delta, inner, v - 2.0 * t * self.delta * np.sign(v))

    def cvxpy(self, r: cp.Expression) -> cp.Expression:
        return cp.sum(cp.huber(r, self.delta))


class Absolute(Loss):
    """``f(r) = |r|`` (robust, median-type). Fitted by IRLS with ``|r|`` floored at ``eps``.

    The floor makes the majoriser inexact where ``|r| < eps``, so the fit keeps a column/row
    step only when it lowers the objective (monotone safeguard).
    """

    name = "absolute"
    is_quadratic = False
    majorizer_exact = False

    def __init__(self, eps: float | None = None) -> None:
        self.eps = None if eps is None else float(eps)

    smoothing = True

    @property
    def kernel_spec(self) -> tuple[int, float, float]:  # type: ignore[override]
        return (2, 0.0, self.eps if self.eps is not None else _EPS)

    def smoothed(self, step: int) -> Loss:
        floor = self.kernel_spec[2]
        return Absolute(eps=max(floor, floor * _START * _DECAY**step))

    def with_scale(self, scale: float) -> Loss:
        return self if self.eps is not None else Absolute(eps=_EPS * max(scale, 1e-300))

    def evaluate(self, r: np.ndarray) -> np.ndarray:
        return np.abs(r)

    def grad(self, r: np.ndarray) -> np.ndarray:
        return np.sign(r)

    def prox(self, v: np.ndarray, t: float | np.ndarray) -> np.ndarray:
        v = np.asarray(v, dtype=float)
        return np.sign(v) * np.maximum(np.abs(v) - t, 0.0)

    def cvxpy(self, r: cp.Expression) -> cp.Expression:
        return cp.sum(cp.abs(r))


class Quantile(Loss):
    """Quantile (pinball) loss of level ``tau``: ``tau max(d - u, 0) + (1 - tau) max(u - d, 0)``.

    With ``r = u - d``: ``0.5 |r| + (0.5 - tau) r``. Fitted like :class:`Absolute` (IRLS on the
    ``|r|`` part, the linear part exact), with the same monotone safeguard.
    """

    name = "quantile"
    is_quadratic = False
    majorizer_exact = False

    def __init__(self, tau: float = 0.5, eps: float | None = None) -> None:
        tau = float(tau)
        if not 0.0 < tau < 1.0:
            raise ModelError(f"Quantile tau must be in (0, 1), got {tau!r}")
        self.tau = tau
        self.eps = None if eps is None else float(eps)

    smoothing = True

    @property
    def kernel_spec(self) -> tuple[int, float, float]:  # type: ignore[override]
        return (3, self.tau, self.eps if self.eps is not None else _EPS)

    def smoothed(self, step: int) -> Loss:
        floor = self.kernel_spec[2]
        return Quantile(self.tau, eps=max(floor, floor * _START * _DECAY**step))

    def with_scale(self, scale: float) -> Loss:
        if self.eps is not None:
            return self
        return Quantile(self.tau, eps=_EPS * max(scale, 1e-300))

    def get_params(self) -> dict[str, float]:
        return {"tau": self.tau}

    def evaluate(self, r: np.ndarray) -> np.ndarray:
        r = np.asarray(r)
        return self.tau * np.maximum(-r, 0.0) + (1.0 - self.tau) * np.maximum(r, 0.0)

    def grad(self, r: np.ndarray) -> np.ndarray:
        r = np.asarray(r)
        return np.where(r > 0, 1.0 - self.tau, np.where(r < 0, -self.tau, 0.0))

    def prox(self, v: np.ndarray, t: float | np.ndarray) -> np.ndarray:
        v = np.asarray(v, dtype=float)
        t = np.asarray(t, dtype=float)
        up = v + self.tau * t  # r < 0 branch
        down = v - (1.0 - self.tau) * t  # r > 0 branch
        return np.where(down > 0, down, np.where(up < 0, up, 0.0))

    def cvxpy(self, r: cp.Expression) -> cp.Expression:
        return cp.sum(self.tau * cp.pos(-r) + (1.0 - self.tau) * cp.pos(r))


LOSS_REGISTRY = Registry("loss", ModelError)
"""Loss classes by name (constructed with their default parameters by :func:`get_loss`)."""
LOSS_REGISTRY.register("quadratic", Quadratic, aliases=("l2",),
                       description="`r^2`, the paper's squared Frobenius norm")
LOSS_REGISTRY.register("huber", Huber, description="`r^2` for `|r| <= delta`, "
                       "`2 delta |r| - delta^2` beyond (`Huber(delta=1.0)`)")
LOSS_REGISTRY.register("absolute", Absolute, aliases=("l1",),
                       description="`|r|`, robust (median-type)")
LOSS_REGISTRY.register("quantile", Quantile, description="pinball loss of level `tau` "
                       "(`Quantile(tau=0.5)`)")
LOSSES: tuple[str, ...] = LOSS_REGISTRY.choices()
"""Canonical loss names (``in`` accepts aliases); the registry's ``choices()``."""


def get_loss(loss: Any) -> Loss:
    """A :class:`Loss` from a name (``"quadratic"``, ``"huber"``, ``"absolute"``/``"l1"``,
    ``"quantile"``), an instance, or a spec dict ``{"name": ..., "params": {...}}``."""
    if isinstance(loss, Loss):
        return loss
    if isinstance(loss, dict):
        name, params = loss.get("name"), dict(loss.get("params", {}))
    else:
        name, params = loss, {}
    if isinstance(name, str) and name in LOSS_REGISTRY:
        return LOSS_REGISTRY.get(name)(**params)
    raise ModelError(LOSS_REGISTRY.message(loss) + "; or pass a Loss instance "
                     "(e.g. Huber(delta=1.0))")
