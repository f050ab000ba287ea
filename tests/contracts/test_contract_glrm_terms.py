"""Every registered loss and regulariser: value against its cvxpy expression, prox against a
cvxpy solve of the same small problem, gradient against finite differences."""

from __future__ import annotations

import cvxpy as cp
import numpy as np
import pytest

from lrm_cvx.glrm.losses import LOSS_REGISTRY, get_loss
from lrm_cvx.glrm.regularizers import REGULARIZER_REGISTRY, get_regularizer

LOSSES = list(LOSS_REGISTRY.choices())
REGS = list(REGULARIZER_REGISTRY.choices())
RNG = np.random.default_rng(0)
R = np.concatenate([RNG.normal(0, 2, 9), [0.0, 0.3, -0.3, 5.0, -5.0]])


def _solve(prob: cp.Problem) -> None:
    prob.solve(solver="CLARABEL")
    assert prob.status == "optimal", prob.status


@pytest.mark.parametrize("name", LOSSES)
def test_loss_value_matches_cvxpy(name):
    loss = get_loss(name)
    assert type(loss) is LOSS_REGISTRY.get(name)
    vals = loss.evaluate(R)
    assert vals.shape == R.shape and np.all(vals >= 0) and loss.evaluate(np.zeros(1))[0] == 0
    assert float(loss.cvxpy(cp.Constant(R)).value) == pytest.approx(vals.sum(), rel=1e-9)


@pytest.mark.parametrize("t", [0.1, 0.7, 3.0])
@pytest.mark.parametrize("name", LOSSES)
def test_loss_prox_matches_cvxpy(name, t):
    loss = get_loss(name)
    x = cp.Variable(R.size)
    _solve(cp.Problem(cp.Minimize(loss.cvxpy(x) + cp.sum_squares(x - R) / (2 * t))))
    np.testing.assert_allclose(loss.prox(R, t), x.value, atol=2e-5)


@pytest.mark.parametrize("name", LOSSES)
def test_loss_gradient_matches_finite_differences(name):
    loss = get_loss(name)
    r = R[np.abs(R) > 0.05]  # away from the kinks at 0 (and Huber's at +-1)
    r = r[np.abs(np.abs(r) - getattr(loss, "delta", 99.0)) > 0.05]
    h = 1e-6
    fd = (loss.evaluate(r + h) - loss.evaluate(r - h)) / (2 * h)
    np.testing.assert_allclose(loss.grad(r), fd, rtol=1e-5, atol=1e-6)


F = RNG.normal(0, 1, (3, 5))


@pytest.mark.parametrize("name", REGS)
def test_regularizer_value_matches_cvxpy(name):
    reg = get_regularizer(name)
    assert type(reg) is REGULARIZER_REGISTRY.get(name)
    for M in (F, np.abs(F)):  # the second one is feasible for constraint regularisers
        expr, cons = reg.cvxpy(cp.Constant(M))
        feasible = all(np.all(np.asarray(c.violation()) <= 1e-9) for c in cons)
        expect = float(expr.value) if feasible else np.inf
        assert reg.value(M) == pytest.approx(expect, rel=1e-9)
        assert reg.evaluate(M).shape == (M.shape[1],)
    if reg.ridge_coefficient is not None:  # the closed form the fast path relies on
        assert reg.value(F) == pytest.approx(reg.ridge_coefficient * np.sum(F**2))
    np.testing.assert_array_equal(reg.minimizer(3), np.zeros(3))


@pytest.mark.parametrize("t", [0.2, 1.5])
@pytest.mark.parametrize("name", REGS)
def test_regularizer_prox_matches_cvxpy(name, t):
    reg = get_regularizer(name)
    V = cp.Variable(F.shape)
    expr, cons = reg.cvxpy(V)
    _solve(cp.Problem(cp.Minimize(expr + cp.sum_squares(V - F) / (2 * t)), cons))
    np.testing.assert_allclose(reg.prox(F, t), V.value, atol=2e-5)


def test_custom_regularizer_is_infinite_outside_its_constraints():
    from lrm_cvx.glrm.regularizers import CvxpyRegularizer

    reg = CvxpyRegularizer(lambda V: (cp.sum(V), [V >= 0]))
    np.testing.assert_array_equal(reg.evaluate(np.array([[-1.0, 1.0], [2.0, 3.0]])),
                                  [np.inf, 4.0])
