"""The exact initial SVD of the fit (``glrm.fit._exact_svd``): the Gram route for wide or tall
matrices gives LAPACK's leading singular triplets; ill-conditioned ones take the plain SVD."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lrm_cvx.glrm.fit import _exact_svd


def _aligned(U, S, Vt, k, Z):
    U2, S2, Vt2 = np.linalg.svd(Z, full_matrices=False)
    sign = np.sign(np.sum(Vt * Vt2[:k], axis=1))
    return U * sign, S, Vt * sign[:, None], U2[:, :k], S2[:k], Vt2[:k]


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), short=st.integers(2, 12), ratio=st.integers(8, 40),
       k=st.integers(1, 2), tall=st.booleans())
def test_gram_route_matches_lapack(seed, short, ratio, k, tall):
    rng = np.random.default_rng(seed)
    shape = (short * ratio, short) if tall else (short, short * ratio)
    # distinct, well separated leading singular values (a generic data matrix)
    spread = np.diag(np.geomspace(10.0, 1.0, short))
    Z = rng.normal(size=shape) @ spread if tall else spread @ rng.normal(size=shape)
    U, S, Vt, U2, S2, Vt2 = _aligned(*_exact_svd(Z, k), k, Z)
    np.testing.assert_allclose(S, S2, rtol=1e-10)
    np.testing.assert_allclose(Vt, Vt2, atol=1e-8)
    np.testing.assert_allclose(U, U2, atol=1e-8)


def test_rank_deficient_matrix_takes_the_plain_svd():
    rng = np.random.default_rng(0)
    Z = np.outer(rng.normal(size=6), rng.normal(size=300))  # rank 1, asked for 3
    U, S, Vt = _exact_svd(Z, 3)
    U2, S2, Vt2 = np.linalg.svd(Z, full_matrices=False)
    np.testing.assert_array_equal(S, S2[:3])  # the plain SVD itself, not the Gram route
    np.testing.assert_array_equal(Vt, Vt2[:3])
    assert S[1] < 1e-10 * S[0]


@pytest.mark.parametrize("shape", [(30, 40), (40, 30)])
def test_square_ish_matrix_is_the_plain_svd(shape):
    Z = np.random.default_rng(1).normal(size=shape)
    U, S, Vt = _exact_svd(Z, 4)
    U2, S2, Vt2 = np.linalg.svd(Z, full_matrices=False)
    np.testing.assert_array_equal(S, S2[:4])
    np.testing.assert_array_equal(U, U2[:, :4])
