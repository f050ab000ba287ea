"""spatial="auto": the residual kernel chosen by design-matched kriging cross-validation on the
training residuals (validation/kernel_selection.py), and the paired rule it shares with
temporal="auto"."""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import pytest
import xarray as xr
from scipy.spatial.distance import cdist

from lrm_cvx import GLRM
from lrm_cvx.errors import ModelError
from lrm_cvx.spatial import ResidualCovariance
from lrm_cvx.spatial.covariance import correlation
from lrm_cvx.validation.kernel_selection import _kriging_errors, format_kernel_selection
from lrm_cvx.validation.search import paired_choice


def _field(kernel: str, range_: float, T: int = 30, n: int = 18, seed: int = 0) -> xr.DataArray:
    """Rank-2 trend plus a GP residual of ``kernel`` (sill 1, ``range_`` cells) and white noise
    0.05^2 on an ``n x n`` grid, 5 % missing."""
    rng = np.random.default_rng(seed)
    ii, jj = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    xy = np.c_[ii.ravel(), jj.ravel()].astype(float)
    C = correlation(kernel, cdist(xy, xy) / range_) + 1e-8 * np.eye(n * n)
    Lc = np.linalg.cholesky(C)
    Y = rng.normal(size=(2, n * n))
    X = rng.normal(size=(2, T)) * 2
    D = X.T @ Y + (Lc @ rng.normal(size=(n * n, T))).T + 0.05 * rng.normal(size=(T, n * n))
    D[rng.random(D.shape) < 0.05] = np.nan
    return xr.DataArray(D.reshape(T, n, n), dims=("time", "lat", "lon"),
                        coords={"time": pd.date_range("2000-01-01", periods=T, freq="D"),
                                "lat": np.arange(n) * 1.0, "lon": np.arange(n) * 1.0})


def _fit(data, spatial):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return GLRM(rank=2, offset=True, spatial=spatial, random_state=0,
                    progress=False).fit(data)


@pytest.mark.parametrize("truth, expect", [("gaussian", {"gaussian", "matern52"}),
                                           ("exponential", {"exponential"})])
def test_auto_picks_the_family_of_the_residual(truth, expect):
    model = _fit(_field(truth, 4.0 if truth == "gaussian" else 3.0), "auto")
    table = model.kernel_selection_
    assert table.attrs["choice"] in expect
    assert model.spatial_cov_.model == table.attrs["choice"]
    np.testing.assert_allclose(table["ratio"].sel(kernel="exponential"), 1.0)
    if truth == "gaussian":  # a smooth residual: the smooth family interpolates it better
        assert float(table["ratio"].sel(kernel=table.attrs["choice"]).max()) < 0.9
    # the chosen covariance is the fixed-kernel fit of that family (same residuals, same fit)
    fixed = _fit(_field(truth, 4.0 if truth == "gaussian" else 3.0), table.attrs["choice"])
    assert model.spatial_cov_ == fixed.spatial_cov_
    assert "spatial='auto' chose" in format_kernel_selection(table)


def test_kriging_errors_match_a_naive_simple_kriging():
    """The scored MSE is simple kriging of the held-out residuals, solved here densely, from
    designs flown over the snapshot's gaps: drawn among all of the region's cells, a design cell
    in a gap gives no value (as in a campaign), and is not held out either."""
    from lrm_cvx.region import Region
    from lrm_cvx.validation.designs import sample_sets

    data = _field("matern32", 3.0, T=4, n=12, seed=1)
    region = Region.from_dataarray(data)
    R = region.stack(data).astype(float)
    covs = [ResidualCovariance("exponential", 1.0, 3.0, 0.1),
            ResidualCovariance("gaussian", 0.8, 2.5, 0.05)]
    sizes, designs = [5, 20], ["route", "scattered"]
    got = _kriging_errors(covs, R, region, sizes, designs, np.random.default_rng(7), 40)
    rng = np.random.default_rng(7)  # the same draws, in the same order
    xy = np.asarray(region.grid_index, dtype=float)
    every = np.ones(region.n_cells, dtype=bool)
    assert got.shape == (2, 2, 8)
    lost = 0
    for i, r in enumerate(R):
        ok = np.isfinite(r)
        for s_i, size in enumerate(sizes):
            for j, design in enumerate(designs):
                flown = sample_sets(region, every, size, design, rng)
                cells = flown[ok[flown]]
                lost += flown.size - cells.size
                held = ok & ~np.isin(np.arange(region.n_cells), flown)
                h = np.flatnonzero(held)
                if h.size > 40:
                    h = np.sort(rng.choice(h, 40, replace=False))
                for c_i, cov in enumerate(covs):
                    Coo = cov.covariance(cdist(xy[cells], xy[cells]))
                    Cho = cov.covariance(cdist(xy[h], xy[cells]), nugget=False)
                    pred = Cho @ np.linalg.solve(Coo, r[cells])
                    assert got[c_i, s_i, 2 * i + j] == pytest.approx(
                        np.mean((pred - r[h]) ** 2), rel=1e-6)
    assert lost > 0  # some designs did meet the gaps


def test_paired_rule_needs_confidence_not_only_a_lower_mean():
    rng = np.random.default_rng(0)
    base = 1.0 + 0.1 * rng.random((1, 200))
    E = np.stack([base,
                  base * 0.9,  # 10 % better on every case: admissible, chosen
                  base * (0.8 + 0.6 * rng.random((1, 200)))])  # better on average? noisy
    mse, ratio, ucb, admissible, best, n = paired_choice(E, 1.645, 0.0)
    assert n == 200 and best == 1 and admissible.tolist() == [True, True, False]
    np.testing.assert_allclose(ratio[1], 0.9)
    np.testing.assert_allclose(mse, E.mean(axis=-1))
    # a candidate that is never better stays out even at tolerance 0
    *_, admissible, best, _ = paired_choice(E[[0, 0]] * [[[1.0]], [[1.01]]], 1.645, 0.0)
    assert best == 0 and not admissible[1]
    with pytest.raises(ModelError, match="fewer than 2"):
        paired_choice(np.full((2, 1, 3), np.nan), 1.645, 0.0)


def test_auto_is_saved_and_loaded(tmp_path):
    model = _fit(_field("gaussian", 4.0, T=20, n=12), "auto")
    model.save(tmp_path / "m.nc")
    back = GLRM.load(tmp_path / "m.nc")
    assert back.spatial == "auto" and back.spatial_cov_ == model.spatial_cov_
    xr.testing.assert_identical(back.kernel_selection_, model.kernel_selection_)
    fixed = _fit(_field("gaussian", 4.0, T=20, n=12), "exponential")
    assert fixed.kernel_selection_ is None
    fixed.save(tmp_path / "f.nc")
    assert GLRM.load(tmp_path / "f.nc").kernel_selection_ is None


def test_bad_spatial_names_auto_in_the_error():
    with pytest.raises(ModelError, match="'auto'"):
        _fit(_field("exponential", 3.0, T=6, n=6), "spline")


def test_refits_keep_the_chosen_family():
    from lrm_cvx.validation.refits import clone_model

    model = _fit(_field("gaussian", 4.0, T=20, n=12), "auto")
    refit = clone_model(model)
    assert str(refit.spatial) == model.kernel_selection_.attrs["choice"] != "auto"
    assert clone_model(GLRM(2, spatial="auto")).spatial == "auto"  # unfitted: still auto
