"""Geometric anisotropy of the spatial residual (east-west range != north-south range).

Every computation of an anisotropic covariance (kriging, the FFT kriging of a grid, the
gp-variance oracles) is checked against a brute force that builds the dense covariance from
``sqrt(dr^2 + (dc / a)^2)`` by hand (the grid convolution and the static placement's windows
in test_reconstruction.py and test_static_default.py); the estimate against a field with a
planted anisotropy; the persistence and the bad inputs as for the other covariance fields.
"""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr
from scipy.spatial.distance import cdist

from lrm_cvx import GLRM, Region, SpatialOptions
from lrm_cvx.errors import ModelError
from lrm_cvx.spatial import ResidualCovariance, estimate_anisotropy, krige
from lrm_cvx.spatial.covariance import correlation


def _region(ny, nx, mask=None):
    da = xr.DataArray(np.zeros((ny, nx)), dims=("lat", "lon"),
                      coords=dict(lat=np.arange(ny) * 1.0, lon=np.arange(nx) * 1.0))
    return Region.from_dataarray(da, mask=mask)


def _dense(cov, region, rows=None, cols=None):
    """The spatial covariance (no nugget) between cells, from grid offsets by hand."""
    g = region.grid_index.astype(float)
    a = g if rows is None else g[rows]
    b = g if cols is None else g[cols]
    dr = a[:, None, 0] - b[None, :, 0]
    dc = (a[:, None, 1] - b[None, :, 1]) / cov.anisotropy
    return cov.sill * correlation(cov.model, np.sqrt(dr ** 2 + dc ** 2) / cov.range)


def test_covariance_is_longer_east_west_by_the_anisotropy():
    cov = ResidualCovariance("exponential", sill=2.0, range=1.5, nugget=0.1, anisotropy=3.0)
    # three cells east-west are one cell north-south
    assert cov.lattice(0, 3) == pytest.approx(cov.lattice(1, 0), rel=1e-15)
    assert cov.lattice(0, 3) == pytest.approx(2.0 * np.exp(-1 / 1.5), rel=1e-15)
    assert cov.reach(1e-6) == pytest.approx((cov.cutoff_distance(1e-6),
                                             3.0 * cov.cutoff_distance(1e-6)))
    region = _region(5, 7)
    xyz = cov.points(region)
    np.testing.assert_allclose(cov.covariance(cdist(xyz, xyz), nugget=False),
                               _dense(cov, region), rtol=1e-13)
    assert "anisotropy=3" in repr(cov)
    assert ResidualCovariance("exponential", sill=2.0, range=1.5).is_isotropic


@pytest.mark.parametrize("method", ["direct", "neighbors"])
@pytest.mark.parametrize("a", [0.4, 2.5])
def test_kriging_equals_the_dense_gp(method, a):
    rng = np.random.default_rng(3)
    mask = np.ones((12, 15), bool)
    mask[4:6, 5:9] = False
    region = _region(12, 15, mask)
    cov = ResidualCovariance("matern32", sill=1.2, range=1.7, nugget=0.15, anisotropy=a)
    cells = np.sort(rng.choice(region.n_cells, 30, replace=False))
    z = rng.standard_normal(30)
    K = _dense(cov, region)
    C = K[np.ix_(cells, cells)] + cov.nugget * np.eye(30)
    k = K[:, cells]
    ref_m = k @ np.linalg.solve(C, z)
    ref_s = np.sqrt(np.maximum(cov.sill - np.einsum("ij,ji->i", k, np.linalg.solve(C, k.T)), 0))
    mean, std = krige(cov, region, cells, z, method=method, neighbors=1000, cutoff=None)
    np.testing.assert_allclose(mean, ref_m, atol=1e-9)
    np.testing.assert_allclose(std, ref_s, atol=1e-8)
    # the isotropic covariance gives another map: the anisotropy is used, not dropped
    iso = ResidualCovariance("matern32", sill=1.2, range=1.7, nugget=0.15)
    assert np.abs(krige(iso, region, cells, z, method=method, neighbors=1000,
                        cutoff=None)[0] - ref_m).max() > 1e-2


def test_grid_fft_kriging_equals_direct():
    from lrm_cvx.spatial import krige_grid_fft

    rng = np.random.default_rng(5)
    region = _region(20, 26)
    cov = ResidualCovariance("exponential", sill=1.0, range=1.2, nugget=0.2, anisotropy=3.0)
    cells = np.sort(rng.choice(region.n_cells, 25, replace=False))
    z = rng.standard_normal(25)
    mean, var, _ = krige_grid_fft(cov, region, cells, z, var_tol=0.0)
    ref_m, ref_s = krige(cov, region, cells, z, method="direct", cutoff=None)
    np.testing.assert_allclose(mean, ref_m, atol=1e-9)
    np.testing.assert_allclose(var, ref_s ** 2, atol=1e-8)


@pytest.mark.parametrize("a", [0.5, 3.0])
def test_structured_gp_oracle_equals_dense_and_brute_force(a):
    from lrm_cvx.information import GPVarianceOracle, StructuredGPVarianceOracle

    rng = np.random.default_rng(1)
    region = _region(11, 14, rng.random((11, 14)) > 0.2)
    L, k = region.n_cells, 2
    Y = rng.normal(size=(k, L))
    S0 = np.diag([0.5, 0.8])
    cov = ResidualCovariance("exponential", sill=0.8, range=1.1, nugget=0.05, anisotropy=a)
    pool = np.sort(rng.choice(L, L // 2, replace=False))
    kw = dict(region=region, spatial_cov=cov, prior_cov=S0, pool=pool)
    d = GPVarianceOracle(Y, [int(pool[0])], **kw)
    s = StructuredGPVarianceOracle(Y, [int(pool[0])], **kw)
    cells = [int(pool[0])]
    for _ in range(5):
        K = Y.T @ S0 @ Y + _dense(cov, region)
        P = np.asarray(cells)
        K = K - K[:, P] @ np.linalg.solve(K[np.ix_(P, P)] + cov.nugget * np.eye(P.size),
                                          K[P, :])
        C = K[:, pool]
        ref = (C * C).sum(0) / (C[pool, np.arange(pool.size)] + cov.nugget)
        new = ~np.isin(pool, cells)
        np.testing.assert_allclose(s.gains(pool)[new], ref[new], rtol=1e-9)
        np.testing.assert_allclose(d.gains(pool)[new], ref[new], rtol=1e-9)
        best = int(pool[new][np.argmax(ref[new])])
        for o in (d, s):
            o.add(best)
        cells.append(best)


def _planted_field(a, n=12, seed=0, ny=40, nx=48):
    region = _region(ny, nx)
    cov = ResidualCovariance("exponential", sill=1.0, range=2.0, nugget=0.05, anisotropy=a)
    K = _dense(cov, region) + cov.nugget * np.eye(region.n_cells)
    Lc = np.linalg.cholesky(K)
    R = (Lc @ np.random.default_rng(seed).standard_normal((region.n_cells, n))).T
    return region, R


@pytest.mark.parametrize("a", [0.5, 1.0, 3.0])
def test_estimate_recovers_a_planted_anisotropy(a):
    region, R = _planted_field(a)
    est = estimate_anisotropy(R, region)
    assert est == pytest.approx(a, rel=0.25)


def test_spatial_auto_chooses_the_anisotropy_and_refits_keep_it():
    from lrm_cvx.validation.kernel_selection import select_kernel
    from lrm_cvx.validation.refits import clone_model

    region, R = _planted_field(3.0, n=20, seed=1)
    cov, table = select_kernel(R, region, seed=0)
    assert cov.anisotropy == pytest.approx(3.0, rel=0.25)
    assert table.attrs["choice"].endswith(f"x{cov.anisotropy:.3g}")
    assert float(table["anisotropy"].sel(kernel="exponential")) == 1.0
    iso, table = select_kernel(R, region, seed=0, anisotropic=False)
    assert iso.is_isotropic and np.all(table["anisotropy"].values == 1.0)
    # a GLRM on the planted field (a constant trend): spatial="auto" picks it, a clone keeps it
    times = np.arange(R.shape[0])
    da = xr.DataArray(np.stack([region.unstack(r).values for r in R]),
                      dims=("time", "lat", "lon"),
                      coords=dict(time=times, lat=region.lat.values, lon=region.lon.values))
    model = GLRM(rank=1, offset=True, spatial="auto", random_state=0, progress=False).fit(da)
    assert model.spatial_cov_.anisotropy > 2.0
    clone = clone_model(model)
    assert clone.spatial == SpatialOptions(model.spatial_cov_.model,
                                           model.spatial_cov_.anisotropy)


@pytest.mark.parametrize("auto", ["auto", SpatialOptions("auto")])
def test_a_clone_keeps_the_chosen_kernel_however_auto_is_written(auto):
    from lrm_cvx.validation.refits import clone_model

    model = GLRM(rank=1, spatial=auto, progress=False)
    model.spatial_cov_ = ResidualCovariance("matern32", sill=1.0, range=2.0, anisotropy=2.5)
    assert clone_model(model).spatial == SpatialOptions("matern32", anisotropy=2.5)


def test_persistence_and_old_files(tmp_path):
    cov = ResidualCovariance("gaussian", sill=1.0, range=2.0, nugget=0.1, anisotropy=2.2)
    assert ResidualCovariance.from_attrs(cov.to_attrs()) == cov
    old = {k: v for k, v in cov.to_attrs().items() if k != "spatial_anisotropy"}
    assert ResidualCovariance.from_attrs(old).anisotropy == 1.0
    region, R = _planted_field(2.0, n=10, ny=16, nx=18)
    da = xr.DataArray(np.stack([region.unstack(r).values for r in R]),
                      dims=("time", "lat", "lon"),
                      coords=dict(time=np.arange(10), lat=region.lat.values,
                                  lon=region.lon.values))
    model = GLRM(rank=1, offset=True, spatial=SpatialOptions("exponential", anisotropy=2.0),
                 random_state=0, progress=False).fit(da)
    assert model.spatial_cov_.anisotropy == 2.0
    path = tmp_path / "m.nc"
    model.save(path)
    back = GLRM.load(path)
    assert back.spatial_cov_ == model.spatial_cov_
    assert back.spatial == SpatialOptions("exponential", anisotropy=2.0)


@pytest.mark.parametrize("bad", [0.0, -1.0, np.nan, np.inf, "wide", True])
def test_bad_anisotropy_is_a_one_line_error(bad):
    with pytest.raises(ModelError, match="anisotropy"):
        ResidualCovariance("exponential", sill=1.0, range=2.0, anisotropy=bad)
    da = xr.DataArray(np.random.default_rng(0).normal(size=(6, 5, 4)),
                      dims=("time", "lat", "lon"),
                      coords=dict(time=np.arange(6), lat=np.arange(5.0), lon=np.arange(4.0)))
    with pytest.raises(ModelError, match="anisotropy"):
        GLRM(rank=1, spatial=SpatialOptions("exponential", anisotropy=bad),
             progress=False).fit(da)


def test_anisotropy_needs_a_fixed_family():
    da = xr.DataArray(np.random.default_rng(0).normal(size=(6, 5, 4)),
                      dims=("time", "lat", "lon"),
                      coords=dict(time=np.arange(6), lat=np.arange(5.0), lon=np.arange(4.0)))
    with pytest.raises(ModelError, match="fixed spatial family"):
        GLRM(rank=1, spatial=SpatialOptions("auto", anisotropy=2.0), progress=False).fit(da)


def test_white_noise_has_no_anisotropy():
    region = _region(20, 24)
    R = np.random.default_rng(2).standard_normal((10, region.n_cells))
    assert estimate_anisotropy(R, region) == 1.0


def test_anisotropy_needs_the_grid_metric():
    with pytest.raises(ModelError, match="metric='grid'"):
        ResidualCovariance("exponential", sill=1.0, range=200.0, metric="km", anisotropy=2.0)
    ResidualCovariance("exponential", sill=1.0, range=200.0, metric="km", anisotropy=1.0)


def test_cli_fits_a_fixed_anisotropy(tmp_path, capsys):
    from lrm_cvx.cli import main

    out = tmp_path / "m.nc"
    assert main(["-q", "fit", "sample:sst", "--rank", "3", "--offset", "--spatial",
                 "exponential", "--anisotropy", "2.5", "--temporal", "none",
                 "-o", str(out)]) == 0
    model = GLRM.load(out)
    assert model.spatial.anisotropy == 2.5 and model.spatial_cov_.anisotropy == 2.5
    assert main(["-q", "fit", "sample:sst", "--rank", "3", "--spatial", "auto",
                 "--anisotropy", "2.5", "-o", str(tmp_path / "n.nc")]) != 0
    assert "fixed spatial family" in capsys.readouterr().err
    assert main(["-q", "fit", "sample:sst", "--paper", "--anisotropy", "2.5",
                 "-o", str(tmp_path / "p.nc")]) == 2
    assert "--anisotropy needs --spatial KERNEL" in capsys.readouterr().err
    assert not (tmp_path / "p.nc").exists()


def test_an_anisotropic_fit_validated_worse_does_not_compete(monkeypatch):
    """The rule: the anisotropic fit replaces its family's isotropic one unless its paired
    errors are worse with confidence at some size; then the isotropic fit competes."""
    import lrm_cvx.validation.kernel_selection as ks
    from lrm_cvx.validation.search import FamilyVariants, PairedGuard

    not_worse = FamilyVariants(PairedGuard(1.645)).not_worse
    assert not_worse(np.full((2, 30), 1.0), np.full((2, 30), 1.0))
    rng = np.random.default_rng(0)
    base = rng.uniform(1, 2, (2, 30))
    assert not_worse(base + rng.normal(0, 0.01, (2, 30)), base)  # noise: kept
    worse = base.copy()
    worse[1] += 0.05  # worse at the second size only
    assert not not_worse(worse, base)
    region, R = _planted_field(3.0, n=20, seed=1)
    real = ks._kriging_errors

    def penalised(covs, *args, **kw):  # every anisotropic fit made 10 % worse
        E = real(covs, *args, **kw)
        for i, c in enumerate(covs):
            if not c.is_isotropic:
                E[i] *= 1.1
        return E

    monkeypatch.setattr(ks, "_kriging_errors", penalised)
    cov, table = ks.select_kernel(R, region, seed=0)
    assert cov.is_isotropic
    aniso = table["anisotropy"].values != 1.0
    assert aniso.any() and not table["competes"].values[aniso].any()
    assert table["competes"].values[~aniso].all()
