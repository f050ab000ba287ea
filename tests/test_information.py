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


# --------------------------------------------------------------------------- gp-variance, trend
def _gp_setup(seed, sill, rng_range=1.5, ny=7, nx=8):
    from lrm_cvx import Region
    from lrm_cvx.spatial import ResidualCovariance

    rng = np.random.default_rng(seed)
    da = xr.DataArray(np.zeros((ny, nx)), dims=("lat", "lon"),
                      coords=dict(lat=np.arange(ny) * 1.0, lon=np.arange(nx) * 1.0))
    region = Region.from_dataarray(da, mask=rng.random((ny, nx)) > 0.15)
    L = region.n_cells
    Y = rng.normal(size=(2, L))
    B = rng.normal(size=(2, 2))
    S0 = B @ B.T + 0.3 * np.eye(2)
    cov = ResidualCovariance("exponential", sill=sill, range=rng_range, nugget=0.1)
    c = rng.uniform(0.5, 2.0, L)
    return rng, region, Y, S0, cov, c


@pytest.mark.parametrize("seed", range(3))
def test_gp_residual_share_equals_the_dense_numerators(seed):
    from scipy.spatial.distance import cdist

    from lrm_cvx.information import gp_residual_share

    rng, region, Y, S0, cov, c = _gp_setup(seed, sill=0.3)
    L = region.n_cells
    pool = np.sort(rng.choice(L, L // 2, replace=False))
    g = region.grid_index.astype(float)
    Kt = Y.T @ S0 @ Y
    K = Kt + cov.covariance(cdist(g, g), nugget=False)
    N = (c[:, None] * K[:, pool] ** 2).sum(0)
    Nt = (c[:, None] * Kt[:, pool] ** 2).sum(0)
    ref = float(np.max(np.abs(N - Nt) / N))
    got = gp_residual_share(Y, region, cov, S0, pool, target_weights=c)
    assert got == pytest.approx(ref, rel=1e-9)


@pytest.mark.parametrize("targets", ["all", "subset"])
def test_gp_variance_gains_equal_value_differences_for_any_pool_targets_and_candidates(targets):
    """The dense oracle's gains (whole pool, a shuffled subset of candidates; targets all cells
    or a subset, so views and copies of its covariance both run) equal the decrease of the
    brute-force total variance after each of a few picks."""
    import lrm_cvx.information as info

    rng, region, Y, S0, cov, c = _gp_setup(11, sill=0.5)
    L = region.n_cells
    T = None if targets == "all" else np.sort(rng.choice(L, L // 3, replace=False))
    pool = np.sort(rng.choice(L, L // 2, replace=False))
    o = info.GPVarianceOracle(Y, [int(pool[0])], region=region, spatial_cov=cov, prior_cov=S0,
                              pool=pool, targets=T, target_weights=c)
    picks = [int(pool[0])]
    for add in (pool[5], pool[9]):
        v0 = info.gp_variance_value(Y, region, cov, S0, picks, targets=T, target_weights=c)
        assert o.value == pytest.approx(v0, rel=1e-9)
        ref = np.array([v0 - info.gp_variance_value(Y, region, cov, S0, picks + [int(x)],
                                                     targets=T, target_weights=c)
                        if x not in picks else np.nan for x in pool])
        g = o.gains()
        ok = np.isfinite(ref)
        np.testing.assert_allclose(g[ok], ref[ok], rtol=1e-7, atol=1e-10)
        sub = rng.permutation(pool.size)[:7]
        np.testing.assert_allclose(o.gains(pool[sub]), g[sub], rtol=1e-12, atol=1e-14)
        o.add(int(add))
        picks.append(int(add))


def test_dense_gp_oracles_on_the_same_cells_share_one_residual_block(monkeypatch):
    """Two dense gp-variance set-ups on the same cells under different priors (two days of a
    campaign) compute the residual covariance once; each one's covariances are the latent
    prior covariance ``gp_latent_cov`` bit for bit, and the second set-up starts from the prior
    though the first one has picked cells."""
    import lrm_cvx.gp_structured as gp_structured
    import lrm_cvx.information as info

    rng, region, Y, S0, cov, c = _gp_setup(5, sill=0.5)
    L = region.n_cells
    pool = np.sort(rng.choice(L, L // 2, replace=False))
    calls = []
    kernel = gp_structured.gp_residual_cov

    def counted(*args):
        calls.append(1)
        return kernel(*args)

    monkeypatch.setattr(gp_structured, "gp_residual_cov", counted)
    gp_structured.GRID_TERMS.clear()
    for prior in (S0, 2.0 * S0 + 0.1 * np.eye(2)):
        o = info.GPVarianceOracle(Y, region=region, spatial_cov=cov, prior_cov=prior, pool=pool,
                                  target_weights=c)
        ref = info.gp_latent_cov(Y, 0.5 * (prior + prior.T), region, cov, np.arange(L), pool)
        np.testing.assert_array_equal(o.C, ref)
        o.add(int(pool[3]))  # updates its own copy, not the kept block
    assert len(calls) == 1


def test_trend_oracle_is_the_gp_criterion_with_the_residual_as_noise(monkeypatch):
    import lrm_cvx.information as info

    rng, region, Y, S0, cov, c = _gp_setup(5, sill=0.3)
    L = region.n_cells
    kw = dict(region=region, spatial_cov=cov, prior_cov=S0, target_weights=c)
    o = info.make_oracle("gp-variance", Y, 0.0, [0], gp_method="trend", **kw)
    assert isinstance(o, info.TrendGPVarianceOracle)
    picks = [0]
    for cell in (5, 11, 5):
        o.add(cell)
        picks.append(cell)
    # brute force: latent posterior under independent noise sill + nugget
    sig2 = cov.nugget + cov.sill
    P = np.array(picks)
    S = np.linalg.inv(np.linalg.inv(S0) + Y[:, P] @ Y[:, P].T / sig2)
    C = Y.T @ S @ Y
    ref = (c[:, None] * C ** 2).sum(0) / (np.diag(C) + sig2)
    np.testing.assert_allclose(o.gains(np.arange(L)), ref, rtol=1e-10)
    assert o.value == pytest.approx(float(c @ (np.diag(C) + cov.sill)), rel=1e-10)
    # auto: a negligible residual switches to it, a real one does not
    monkeypatch.setattr(info, "GP_STRUCTURED_MIN_ENTRIES", 0.0)
    from lrm_cvx.spatial import ResidualCovariance

    tiny = ResidualCovariance("exponential", sill=1e-14, range=1.5, nugget=0.1)
    auto = info.make_oracle("gp-variance", Y, 0.0, [0], **dict(kw, spatial_cov=tiny))
    assert isinstance(auto, info.TrendGPVarianceOracle)
    assert auto.prior_residual_share <= info.GP_RESIDUAL_TOL
    auto.add(3)
    assert 0 <= auto.residual_share() < 1e-3
    assert isinstance(info.make_oracle("gp-variance", Y, 0.0, [0], **kw),
                      info.StructuredGPVarianceOracle)


def test_structured_gp_lag_table_matches_the_exact_convolution():
    """Equal target weights, a pool far from the region's edge: g(p, x) from the lattice
    autocorrelation table (no per-pick FFT) gives the exact oracle's gains to ~1e-6."""
    import lrm_cvx.information as info
    from lrm_cvx import Region
    from lrm_cvx.spatial import ResidualCovariance

    rng = np.random.default_rng(0)
    ny, nx = 70, 80
    da = xr.DataArray(np.zeros((ny, nx)), dims=("lat", "lon"),
                      coords=dict(lat=np.arange(ny) * 1.0, lon=np.arange(nx) * 1.0))
    region = Region.from_dataarray(da)
    L = region.n_cells
    Y = rng.normal(size=(2, L))
    S0 = np.diag([1e-6, 2e-6])  # a pinned trend: the residual is the whole criterion
    cov = ResidualCovariance("exponential", sill=1.0, range=3.0, nugget=0.1)
    gi = region.grid_index
    pool = np.flatnonzero((np.abs(gi[:, 0] - 35) <= 8) & (np.abs(gi[:, 1] - 40) <= 8))
    start = int(pool[len(pool) // 2])
    kw = dict(region=region, spatial_cov=cov, prior_cov=S0, pool=pool)
    a = info.make_oracle("gp-variance", Y, 0.0, [start], gp_method="structured", **kw)
    b = info.StructuredGPVarianceOracle(Y, [start], **kw)  # the class default: exact
    assert a._k2 is not None and b._k2 is None and a.boundary_bound < 1e-6
    for c in pool[::7][:6]:
        a.add(int(c))
        b.add(int(c))
    ga, gb = a.gains(pool), b.gains(pool)
    assert np.max(np.abs(ga - gb)) <= 1e-6 * np.max(gb)
    assert a.value == pytest.approx(b.value, rel=1e-9)
    # a pool at the edge: the boundary term is not negligible, the exact convolution stays
    edge = np.flatnonzero((gi[:, 0] <= 6) & (gi[:, 1] <= 6))
    c = info.StructuredGPVarianceOracle(Y, [int(edge[0])], boundary_tol=1e-3,
                                        **dict(kw, pool=edge))
    assert c._k2 is None and c.boundary_bound > 1e-3


def test_structured_oracle_with_a_kernel_far_longer_than_the_grid_skips_the_lag_table():
    """A degenerate fitted residual (range 10,000 cells on a 30 x 40 grid, tiny sill) would need
    a kernel lattice of ~4e10 entries for the lag table: the oracle keeps the exact per-pick
    convolutions instead (``_k2`` None) and its gains equal the dense oracle's."""
    import lrm_cvx.information as info
    from lrm_cvx import Region
    from lrm_cvx.spatial import ResidualCovariance

    rng = np.random.default_rng(1)
    ny, nx = 30, 40
    da = xr.DataArray(np.zeros((ny, nx)), dims=("lat", "lon"),
                      coords=dict(lat=np.arange(ny) * 1.0, lon=np.arange(nx) * 1.0))
    region = Region.from_dataarray(da)
    Y = rng.normal(size=(2, region.n_cells))
    cov = ResidualCovariance("exponential", sill=1e-3, range=1e4, nugget=1e-4)
    kw = dict(region=region, spatial_cov=cov, prior_cov=np.diag([1.0, 0.5]))
    s = info.StructuredGPVarianceOracle(Y, [0], boundary_tol=1e-3, **kw)
    d = info.GPVarianceOracle(Y, [0], **kw)
    assert s._k2 is None and s.boundary_bound == np.inf
    for c in (123, 611, 1100):
        s.add(c)
        d.add(c)
    gs, gd = s.gains(), d.gains()
    np.testing.assert_allclose(gs, gd, rtol=1e-6, atol=1e-9 * np.max(np.abs(gd)))


def test_a_singular_information_matrix_is_one_line_naming_its_observations():
    import scipy.sparse as sps

    from lrm_cvx.oracles import FisherOracle, RowOracle

    Y = np.ones((3, 6))  # every column the same: rank 1 < k = 3
    with pytest.raises(PlanningError, match=r"^the information matrix of the 2 initial cells is "
                       r"singular \(rank 1 < k = 3\); pass a small ridge \(e\.g\. ridge=1e-6\) "
                       r"or start with more cells$"):
        FisherOracle(Y, 0.0, [0, 1])
    Y = np.random.default_rng(0).standard_normal((3, 6))
    legs = sps.identity(6, format="csr")[:3]
    oracle = RowOracle("fisher", Y, pool=np.arange(6), rows=sps.identity(6, format="csr"),
                       extra_rows=legs)
    with pytest.raises(PlanningError, match=r"^the information matrix of the 0 observations is "
                       r"singular \(rank 0 < k = 3\); pass a small ridge \(e\.g\. ridge=1e-6\)$"):
        oracle.set_extra(sps.csr_matrix((0, 6)))
