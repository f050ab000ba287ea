"""Every registered spatial covariance model: positive semidefinite on random points, equal to
its closed form at a few distances, and what ResidualCovariance uses."""

from __future__ import annotations

import numpy as np
import pytest

from lrm_cvx.spatial import KERNEL_REGISTRY, ResidualCovariance

NAMES = list(KERNEL_REGISTRY.choices())
S3, S5 = np.sqrt(3.0), np.sqrt(5.0)
CLOSED_FORMS = {
    "exponential": lambda h: np.exp(-h),
    "matern32": lambda h: (1 + S3 * h) * np.exp(-S3 * h),
    "matern52": lambda h: (1 + S5 * h + 5 * h**2 / 3) * np.exp(-S5 * h),
    "gaussian": lambda h: np.exp(-(h**2)),
}
H = np.array([0.0, 0.1, 0.5, 1.0, 2.5, 7.0])


def test_every_kernel_has_a_closed_form():
    assert set(CLOSED_FORMS) == set(NAMES), "add the closed form of the new kernel"


@pytest.mark.parametrize("name", NAMES)
def test_closed_form(name):
    rho = KERNEL_REGISTRY.get(name)
    np.testing.assert_allclose(rho(H), CLOSED_FORMS[name](H), rtol=1e-13, atol=1e-15)
    assert rho(0.0) == 1.0 and np.all(np.diff(rho(H)) < 0)


@pytest.mark.parametrize("name", NAMES)
def test_covariance_is_psd_and_uses_the_kernel(name):
    rng = np.random.default_rng(1)
    pts = rng.uniform(0, 10, (40, 2))
    d = np.sqrt(((pts[:, None] - pts[None]) ** 2).sum(-1))
    cov = ResidualCovariance(name.upper(), sill=2.0, range=1.7, nugget=0.3)  # any case
    assert cov.model == name
    K = cov.covariance(d)
    np.testing.assert_allclose(K, 2.0 * CLOSED_FORMS[name](d / 1.7) + 0.3 * np.eye(40),
                               rtol=1e-12, atol=1e-14)
    Kc = cov.covariance(d, nugget=False)
    assert np.linalg.eigvalsh(Kc).min() >= -1e-9 * np.abs(Kc).max()
