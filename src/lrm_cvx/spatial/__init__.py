"""Spatial residual model: low-rank trend plus a stationary Gaussian-process residual.

The paper's completion predicts a new snapshot by the least-squares fold-in ``Y^T x`` and
leaves spatial locality as future work. This module adds it: the residuals of
the low-rank model are modelled as a zero-mean stationary Gaussian process with an isotropic
covariance of the distance between cells,

``C(d) = sill * rho(d / range) + nugget * [d == 0]``,

with ``rho`` one of ``exponential``, ``matern32``, ``matern52``, ``gaussian`` (``range`` is the
scale parameter, not the "practical range"; ``sill`` is the partial sill, ``nugget`` the
variance that no neighbour can predict: noise and sub-cell variation). The parameters come from
a binned empirical semivariogram of the training residuals fitted by weighted least squares
(:func:`fit_residual_covariance`). A new snapshot is predicted as trend + kriged residual
(:func:`~lrm_cvx.belief.foldin.residual_correction`), with the trend estimated either by the
paper's fold-in ("ols", regression kriging) or by generalised least squares under the GP
covariance ("gls", universal kriging, :func:`~lrm_cvx.belief.foldin.gls_fold_in`).

Scaling (L up to ~2M cells): no dense ``L x L`` matrix is ever built. :func:`krige` factors the
``n x n`` observation covariance once and streams targets in chunks of bounded memory
(``"direct"``), or solves a small system per target over its ``neighbors`` nearest observations
(``"neighbors"``, Vecchia-style local kriging, for many observations). Targets farther than the
covariance's cut-off distance (where ``rho < cutoff``) from every observation get the prior
(mean 0, variance ``sill``) without any solve: this is what makes 2M targets cheap.

Distances are in grid units (``metric="grid"``, the paper's) or great-circle kilometres
(``metric="km"``: cells are placed on a sphere and chord distances in the KD-tree are mapped to
arc lengths, which preserves neighbour order). Predictions are of the latent (noise-free)
residual; ``include_nugget=True`` adds the nugget to the variance to predict a new measurement.

Modules: :mod:`.covariance` (the covariance model and its fit), :mod:`.kriging` (kriging, the FFT
convolution, the GP criterion's model). The fold-ins that use the GP residual
(``gls_fold_in``, ``residual_correction``) live with the other fold-ins in
:mod:`lrm_cvx.belief.foldin`: the model layer sits above this one.
"""

from __future__ import annotations

from .covariance import (
    KERNEL_REGISTRY,
    MODELS,
    EmpiricalVariogram,
    ResidualCovariance,
    arc_distance,
    cell_xyz,
    correlation,
    empirical_variogram,
    estimate_anisotropy,
    fit_residual_covariance,
)
from .covariance import cell_xyz as _coords  # noqa: F401  (old private names, kept for tests)
from .kriging import (
    FFT_KRIGE_MIN_WORK,
    FFT_KRIGE_VAR_TOL,
    MAX_DIRECT,
    GridConv,
    check_gp_inputs,
    gp_latent_cov,
    gp_noise,
    jittered_cholesky,
    krige,
    krige_core,
    krige_grid_fft,
    krige_many,
)
from .kriging import krige_core as _krige_core  # noqa: F401

__all__ = [
    "MODELS",
    "KERNEL_REGISTRY",
    "ResidualCovariance",
    "EmpiricalVariogram",
    "correlation",
    "empirical_variogram",
    "estimate_anisotropy",
    "fit_residual_covariance",
    "krige",
    "krige_many",
    "krige_grid_fft",
    "krige_core",
    "cell_xyz",
    "arc_distance",
    "jittered_cholesky",
    "MAX_DIRECT",
    "FFT_KRIGE_MIN_WORK",
    "FFT_KRIGE_VAR_TOL",
    "GridConv",
    "gp_noise",
    "gp_latent_cov",
    "check_gp_inputs",
]

