"""Information measures and the incremental gain oracles, against from-scratch linear algebra."""

import numpy as np
import pytest
import xarray as xr

from lrm_cvx.errors import DataError, PlanningError
from lrm_cvx.information import (
    AOptimalOracle,
    FisherOracle,
    a_optimal_value,
    fisher_information,
    make_oracle,
)


def _logdet(Y, cells, ridge):
    M = ridge * np.eye(Y.shape[0]) + sum(np.outer(Y[:, c], Y[:, c]) for c in cells)
    return np.log(np.linalg.det(M))


def _total_variance(Y, cells, ridge):
    M = ridge * np.eye(Y.shape[0]) + sum(np.outer(Y[:, c], Y[:, c]) for c in cells)
    Minv = np.linalg.inv(M)
    return sum(Y[:, i] @ Minv @ Y[:, i] for i in range(Y.shape[1]))


@pytest.fixture
def Y():
    return np.random.default_rng(0).standard_normal((4, 30))


def test_fisher_information_matches_determinant(Y):
    cells = [0, 3, 7, 11, 20]
    assert fisher_information(Y, cells) == pytest.approx(_logdet(Y, cells, 0.0), rel=1e-12)
    assert fisher_information(Y, cells, ridge=0.5) == pytest.approx(_logdet(Y, cells, 0.5))
    # a DataArray (component, cell) gives the same
    da = xr.DataArray(Y, dims=("component", "cell"))
    assert fisher_information(da, cells) == fisher_information(Y, cells)


def test_fisher_information_singular_is_minus_inf(Y):
    assert fisher_information(Y, [0, 1]) == -np.inf  # 2 cells, rank 4
    assert fisher_information(Y, []) == -np.inf
    Z = Y.copy()
    Z[3] = 0.0  # a zero row: singular whatever the cells
    assert fisher_information(Z, range(30)) == -np.inf
    # the ridge makes it finite: log det(ridge I) for no cell
    assert fisher_information(Y, [], ridge=2.0) == pytest.approx(4 * np.log(2.0))


def test_fisher_information_bad_input(Y):
    with pytest.raises(PlanningError):
        fisher_information(Y, [0, 30])
    with pytest.raises(PlanningError):
        fisher_information(Y, [0], ridge=-1)
    with pytest.raises(DataError):
        fisher_information(np.ones(3), [0])


def test_a_optimal_value_matches_definition(Y):
    cells = [1, 2, 5, 8]
    assert a_optimal_value(Y, cells, 0.1) == pytest.approx(_total_variance(Y, cells, 0.1))
    with pytest.raises(PlanningError, match="ridge > 0"):
        a_optimal_value(Y, cells, 0.0)


@pytest.mark.parametrize("ridge", [0.0, 1e-3, 1.0])
def test_fisher_gains_equal_logdet_differences_after_updates(Y, ridge):
    rng = np.random.default_rng(1)
    P = [0, 1, 2, 3, 4]
    oracle = FisherOracle(Y, ridge, P)
    for _ in range(12):
        gains = oracle.gains()
        assert gains.shape == (30,) and gains.dtype == np.float64
        base = _logdet(Y, P, ridge)
        ref = np.array([_logdet(Y, P + [x], ridge) - base for x in range(30)])
        np.testing.assert_allclose(gains, ref, rtol=1e-9, atol=1e-11)
        sub = np.array([29, 3, 17])
        np.testing.assert_array_equal(oracle.gains(sub), gains[sub])
        assert oracle.value == pytest.approx(base, rel=1e-10, abs=1e-10)
        x = int(rng.integers(30))
        oracle.add(x)
        P.append(x)
    assert oracle.cells == P
    # the Sherman-Morrison inverse stays close to a fresh inverse
    M = ridge * np.eye(4) + Y[:, P] @ Y[:, P].T
    np.testing.assert_allclose(oracle.S, np.linalg.inv(M), rtol=1e-8, atol=1e-10)


def test_a_optimal_gains_equal_value_differences(Y):
    rng = np.random.default_rng(2)
    P = [5, 6]
    oracle = make_oracle("a-optimal", Y, 0.05, P)
    assert isinstance(oracle, AOptimalOracle)
    for _ in range(8):
        base = _total_variance(Y, P, 0.05)
        assert oracle.value == pytest.approx(base, rel=1e-9)
        ref = np.array([base - _total_variance(Y, P + [x], 0.05) for x in range(30)])
        np.testing.assert_allclose(oracle.gains(), ref, rtol=1e-8, atol=1e-10)
        x = int(rng.integers(30))
        oracle.add(x)
        P.append(x)


def test_oracle_errors(Y):
    with pytest.raises(PlanningError, match="ridge"):
        FisherOracle(Y, 0.0, [0, 1])  # singular initial set: suggests a ridge
    with pytest.raises(PlanningError, match="ridge > 0"):
        AOptimalOracle(Y, 0.0, [0, 1, 2, 3, 4])
    with pytest.raises(PlanningError, match="criterion"):
        make_oracle("e-optimal", Y, 1.0)
    oracle = FisherOracle(Y, 1.0)
    with pytest.raises(PlanningError):
        oracle.gains([30])
    assert isinstance(make_oracle("fisher", Y, 1.0), FisherOracle)
