"""Every registered criterion: gains of the incremental oracle equal the criterion's value
recomputed from scratch, the value equals a brute-force reference, and the certificate bounds
the criteria it certifies (and refuses a gap for the others)."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import xarray as xr

from lrm_cvx.information import CRITERION_REGISTRY
from lrm_cvx.region import Region
from lrm_cvx.spatial import ResidualCovariance

NAMES = list(CRITERION_REGISTRY.choices())
RIDGE = 0.1


def tiny_region(ny: int = 4, nx: int = 5, seed: int = 0) -> Region:
    mask = np.random.default_rng(seed).random((ny, nx)) < 0.85
    mask[ny // 2, nx // 2] = True
    lat, lon = np.linspace(10, 10 - ny + 1, ny), np.linspace(0, nx - 1, nx)
    return Region(lat=xr.DataArray(lat, dims="lat", coords={"lat": lat}),
                  lon=xr.DataArray(lon, dims="lon", coords={"lon": lon}), mask=mask)


def _gp_kwargs(region: Region, k: int) -> dict:
    return dict(region=region, spatial_cov=ResidualCovariance("exponential", sill=0.7, range=1.5,
                                                              nugget=0.05),
                prior_cov=np.diag(np.linspace(1.0, 0.5, k)))


# the inputs each criterion needs beyond (Y, ridge, cells); a new criterion needing more adds a
# line here
EXTRA = {"gp-variance": _gp_kwargs}


# ---------------------------------------------------------------- brute-force references
def ref_fisher(Y, cells, ridge, **_):
    M = ridge * np.eye(Y.shape[0])
    for c in cells:
        M = M + np.outer(Y[:, c], Y[:, c])
    return math.log(np.linalg.det(M))


def ref_aopt(Y, cells, ridge, **_):
    M = ridge * np.eye(Y.shape[0])
    for c in cells:
        M = M + np.outer(Y[:, c], Y[:, c])
    Minv = np.linalg.inv(M)
    return float(sum(Y[:, i] @ Minv @ Y[:, i] for i in range(Y.shape[1])))


def ref_gp(Y, cells, ridge, *, region, spatial_cov, prior_cov, **_):
    """Posterior variance of f = Y^T x + r summed over every cell, from the dense joint
    covariance (Gaussian conditioning written out)."""
    g = region.grid_index.astype(float)
    d = np.sqrt(((g[:, None, :] - g[None, :, :]) ** 2).sum(-1))
    K = Y.T @ prior_cov @ Y + spatial_cov.sill * np.exp(-d / spatial_cov.range)
    P = list(cells)
    if not P:
        return float(np.trace(K))
    noise = max(spatial_cov.nugget, 1e-9 * spatial_cov.total_variance)
    A = K[np.ix_(P, P)] + noise * np.eye(len(P))
    post = K - K[:, P] @ np.linalg.inv(A) @ K[P, :]
    return float(np.trace(post))


REFERENCES = {"fisher": ref_fisher, "a-optimal": ref_aopt, "gp-variance": ref_gp}


def test_every_criterion_has_a_reference():
    assert set(REFERENCES) == set(NAMES), "add a brute-force reference for the new criterion"


def _problem(name: str, seed: int):
    region = tiny_region(seed=seed)
    rng = np.random.default_rng(seed)
    k = 2
    Y = rng.standard_normal((k, region.n_cells))
    kw = EXTRA.get(name, lambda r, k: {})(region, k)
    return region, Y, kw


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("name", NAMES)
def test_gains_equal_recomputed_values(name, seed):
    spec = CRITERION_REGISTRY.get(name)
    region, Y, kw = _problem(name, seed)
    L = region.n_cells
    P = [0, L - 1]
    oracle = spec.oracle(Y, RIDGE, P, **kw)
    sign = 1.0 if spec.maximize else -1.0
    for _ in range(4):
        value = spec.value(Y, P, RIDGE, **kw)
        assert value == pytest.approx(REFERENCES[name](Y, P, RIDGE, **kw), rel=1e-9, abs=1e-9)
        assert oracle.value == pytest.approx(value, rel=1e-8, abs=1e-9)
        cand = np.setdiff1d(np.arange(L), P)
        gains = oracle.gains(cand)
        expect = np.array([sign * (spec.value(Y, P + [int(c)], RIDGE, **kw) - value)
                           for c in cand])
        np.testing.assert_allclose(gains, expect, rtol=1e-7, atol=1e-9)
        assert np.all(gains >= -1e-12)  # monotone: observing more never hurts
        best = int(cand[np.argmax(gains)])
        oracle.add(best)
        P = P + [best]


@pytest.mark.parametrize("name", NAMES)
def test_posterior_options_when_supported(name):
    """A prior precision and per-cell noise (the fold-in's posterior) change the matrix, and the
    gains still equal the recomputed values."""
    import inspect

    spec = CRITERION_REGISTRY.get(name)
    if "prior_precision" not in inspect.signature(spec.oracle).parameters:
        pytest.skip(f"{name} has no posterior options")
    region, Y, kw = _problem(name, 3)
    rng = np.random.default_rng(3)
    A = rng.standard_normal((2, 2))
    kw = dict(kw, prior_precision=A @ A.T + 0.5 * np.eye(2),
              noise_var=rng.uniform(0.5, 2.0, region.n_cells))
    oracle = spec.oracle(Y, 0.0, [0], **kw)
    sign = 1.0 if spec.maximize else -1.0
    value = spec.value(Y, [0], 0.0, **kw)
    cand = np.arange(1, region.n_cells)
    expect = [sign * (spec.value(Y, [0, int(c)], 0.0, **kw) - value) for c in cand]
    np.testing.assert_allclose(oracle.gains(cand), expect, rtol=1e-7, atol=1e-9)


@pytest.mark.parametrize("name", NAMES)
def test_certificate_bounds_or_refuses(name):
    from lrm_cvx.planning import plan_greedy
    from lrm_cvx.planning.greedy import initial_cells

    spec = CRITERION_REGISTRY.get(name)
    region, Y, kw = _problem(name, 5)
    from lrm_cvx.planning import PriorTerms

    prior = PriorTerms(**{key: v for key, v in kw.items() if key != "region"})
    start = int(region.cell_grid[2, 2])
    budget = 2.0
    plan = plan_greedy(Y, region, start, budget, criterion=name, ridge=RIDGE, progress=False,
                       prior=prior)
    cert = plan.certify(tighten=False, criterion="fisher")
    assert cert.criterion == "fisher" and cert.plan_criterion == name
    # brute force: the best Fisher information of any set the certificate covers
    dist = np.hypot(*(region.grid_index - region.grid_index[start]).T)
    disk = np.flatnonzero(dist <= budget + 1e-9)
    best = ref_fisher(Y, initial_cells(region, start, Y.shape[0]), RIDGE)
    for m in range(1, cert.n_max + 1):
        for S in itertools.combinations(disk.tolist(), m):
            if start in S:
                best = max(best, ref_fisher(Y, S, RIDGE))
    assert cert.bound >= best - 1e-7
    assert cert.information == pytest.approx(ref_fisher(Y, plan.cells, RIDGE))
    if spec.certified:
        assert cert.comparable and 0 <= cert.gap == pytest.approx(cert.bound - cert.information)
    else:
        assert not cert.comparable and math.isnan(cert.gap) and math.isnan(cert.volume_ratio)
