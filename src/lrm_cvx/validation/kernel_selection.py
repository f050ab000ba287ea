"""A spatial residual kernel that validates itself: ``GLRM(spatial="auto")``.

Which covariance family interpolates a record's residual best (the rough exponential, the
smoother Matern 3/2 and 5/2, the very smooth Gaussian) is an empirical question, answered here
on the training residuals the fit already holds (``residual_sample``: up to 20 evenly spaced
snapshots of data minus the low-rank reconstruction), the way campaigns use the kernel:

* every family is fitted to the same residuals' variogram (:func:`~lrm_cvx.spatial.
  fit_residual_covariance`, the nugget bounded below by the sub-cell variation, as for a fixed
  kernel), isotropic and, where the directional variograms differ by at least
  :data:`MIN_ANISOTROPY`, also at their anisotropy (:func:`~lrm_cvx.spatial.
  estimate_anisotropy`: zonal bands make the residuals of monthly winds and sea-surface
  temperatures correlate 2-6 times further east-west than north-south);
* each residual snapshot is sampled as campaigns sample (a clustered route, a straight transect
  and scattered cells, drawn among all of the region's cells as they are flown:
  :func:`~lrm_cvx.validation.designs.flown_sets`; a design cell in one of the snapshot's gaps gives
  no value, so under clouds the kernel interpolates across the gaps a campaign meets), once per
  design and size of :data:`~lrm_cvx.validation.selection.AUTO_SIZES`, the same cells for every
  family (paired);
* the score is the MSE of the kriged residual at (at most :data:`~lrm_cvx.validation.selection.
  MAX_SCORED` random) held-out observed cells: the part of the map the kernel decides;
* rule (the paired guard of the one search, :func:`~lrm_cvx.validation.search.search` on
  one split, the residual snapshots, with :class:`~lrm_cvx.validation.search.
  FamilyVariants` and :class:`~lrm_cvx.validation.search.PairedGuard`): a
  family is admissible when the upper confidence bound of its MSE change against the
  exponential (the recommended default) is at most ``-MIN_GAIN`` (2 %) at every size; the
  admissible family with the lowest worst ratio wins.

The residuals are those of the fit itself, so no refit is needed (a few kriging calls: cheap
beside the fit); the factors saw these snapshots, but every family is scored on the same
residuals, whose spatial structure is what the kernel models. The result is an
``xarray.Dataset`` (``model.kernel_selection_``, saved with the model).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import xarray as xr

from .._validation import as_generator
from ..errors import DataError
from .search import FamilyVariants, HeldOutCells, PairedGuard, search, selection_table

__all__ = ["select_kernel", "AUTO_KERNELS", "DEFAULT_KERNEL", "MIN_GAIN", "MIN_ANISOTROPY",
           "format_kernel_selection"]

AUTO_KERNELS = ("exponential", "matern32", "matern52", "gaussian")
"""The covariance families ``spatial="auto"`` compares."""
DEFAULT_KERNEL = "exponential"
"""The reference family (the recommended one): another must beat it with confidence."""
MIN_GAIN = 0.02
"""The relative gain (kriged residual MSE, upper confidence bound, at every size) another family
must show over the exponential to replace it: a switch changes the planner's routes too, and
on the monthly SST record a 1 % validated gain of Matern 3/2 came with a 9 % loss at budget 15
in the campaigns (docs/spatial.md)."""
MIN_ANISOTROPY = 1.25
"""An anisotropic candidate is compared only when the estimated anisotropy (or its inverse) is
at least this: closer to 1 it is the isotropic family again."""


def _kriging_errors(covs: list[Any], R: np.ndarray, region: Any, sizes: Sequence[int],
                    designs: Sequence[str], rng: np.random.Generator,
                    max_scored: int) -> np.ndarray:
    """MSE ``(n_kernels, n_sizes, n_rows * n_designs)`` of the simple-kriged residual at
    held-out cells of each row of ``R (n_rows, L)`` (NaN: unobserved), from one sample set
    per row, size and design (case ``i * n_designs + j``: row ``i``, ``designs[j]``), the same
    cells for every covariance of ``covs``."""
    from .. import spatial as sp

    nd, holdout = len(designs), HeldOutCells(max_scored)
    err = np.full((len(covs), len(sizes), R.shape[0] * nd), np.nan)
    for i, r in enumerate(R):  # a loop over the (at most 20) residual snapshots
        ok = np.isfinite(r)
        for s_i, size in enumerate(sizes):
            for j, design in enumerate(designs):
                flown, h = holdout.split(region, ok, size, design, rng)  # over the day's gaps
                cells = flown[ok[flown]]  # the design's cells that gave a value
                if cells.size == 0 or h.size == 0:
                    continue
                z = r[cells].astype(np.float64)[:, None]
                truth = r[h].astype(np.float64)
                meth = "direct" if cells.size <= sp.MAX_DIRECT else "neighbors"
                for c_i, cov in enumerate(covs):
                    mu, _ = sp.krige_core(cov, cov.points(region, cells), z,
                                          cov.points(region, h), method=meth, neighbors=32,
                                          cutoff=1e-6, want_var=False)
                    err[c_i, s_i, i * nd + j] = float(np.mean((mu[0] - truth) ** 2))
    return err


def select_kernel(sample: Any, region: Any, *, kernels: Sequence[str] = AUTO_KERNELS,
                  sizes: Sequence[int] | None = None, designs: Sequence[str] | None = None,
                  confidence: float = 1.645, tolerance: float = -MIN_GAIN,
                  anisotropic: bool = True, seed: Any = 0) -> tuple[Any, xr.Dataset]:
    """Fit each of ``kernels`` to the residual ``sample`` ``(n_rows, L)`` (data minus the
    low-rank reconstruction, fit units, NaN unobserved; ``region`` its grid) and choose one by
    design-matched kriging cross-validation (module docstring). Returns ``(covariance,
    table)``: the chosen :class:`~lrm_cvx.spatial.ResidualCovariance` and a Dataset over
    ``kernel`` and ``size`` with ``mse``, ``ratio`` (to :data:`DEFAULT_KERNEL`'s fit that
    competes), ``ucb`` and ``admissible`` (of the fits that compete), the fitted ``sill``,
    ``range``, ``nugget``, ``anisotropy`` per kernel
    (an anisotropic fit is labelled ``"<family> x<anisotropy>"``; it replaces its family's
    isotropic fit, ``competes``, unless it is worse with confidence at some size: the
    anisotropy is a fitted parameter like the range; ``anisotropic=False`` compares the
    isotropic families only); attributes
    ``choice``, ``n_rows`` (residual snapshots), ``n_cases`` (sample sets per size),
    ``designs``. ``tolerance`` (default ``-MIN_GAIN``): another family must be better by
    :data:`MIN_GAIN` with confidence, not only as good."""
    from ..spatial import fit_residual_covariance
    from ..spatial.covariance import anisotropy_from_variograms, axis_variograms
    from .paired import AUTO_DESIGNS, AUTO_SIZES, MAX_SCORED

    kernels = list(dict.fromkeys([DEFAULT_KERNEL, *kernels]))  # the reference first
    R = np.asarray(sample)  # float32 from the fit: no float64 copy of (rows, L)
    if R.ndim != 2 or not np.isfinite(R).any():
        raise DataError("spatial='auto' needs finite training residuals to compare kernels")
    designs = list(AUTO_DESIGNS if designs is None else designs)
    n_obs = float(np.median(np.isfinite(R).sum(axis=1)))
    sizes = [int(s) for s in (AUTO_SIZES if sizes is None else sizes) if int(s) <= n_obs / 2]
    sizes = sizes or [max(1, int(n_obs / 4))]
    covs = [fit_residual_covariance(R, region, model=k, random_state=0, min_nugget="cell")
            for k in kernels]
    labels = list(kernels)
    variants = {}  # family index -> index of its anisotropic fit
    if anisotropic:
        axes = axis_variograms(R, region)  # once for every family
        for i, k in enumerate(kernels):
            a = anisotropy_from_variograms(*axes, model=k)
            if abs(np.log(a)) >= np.log(MIN_ANISOTROPY) - 1e-12:
                covs.append(fit_residual_covariance(R, region, model=k, random_state=0,
                                                    min_nugget="cell", anisotropy=a))
                labels.append(f"{k} x{a:.3g}")
                variants[i] = len(covs) - 1
    rng = as_generator(seed)

    def kriging_errors(rows: np.ndarray) -> dict[str, np.ndarray]:
        """The kriging MSE ``(n_sizes, n_rows * n_designs)`` of each fit on one split."""
        return dict(zip(labels, _kriging_errors(covs, rows, region, sizes, designs, rng,
                                                MAX_SCORED), strict=True))

    # one split (the residual snapshots); the anisotropy is a fitted parameter of its family
    # (as the range is): the family competes with it unless the validation finds it worse,
    # with confidence, at some size
    _, _, decision = search(kriging_errors, [R], FamilyVariants(
        PairedGuard(confidence, tolerance, "spatial='auto'"), variants))
    ds = selection_table(
        decision, labels, sizes, dim="kernel", reference=f"the {DEFAULT_KERNEL} family (as it "
        "competes)", what="mean MSE of the kriged residual at held-out cells",
        data_vars={name: (("kernel",), [getattr(c, name) for c in covs])
                   for name in ("sill", "range", "nugget", "anisotropy")},
        n_rows=R.shape[0], n_cases=int(decision.n_cases), designs=",".join(designs),
        confidence=float(confidence), tolerance=float(tolerance))
    ds["competes"].attrs["long_name"] = ("the variant of its family in the choice (the "
                                         "anisotropic one unless validated worse)")
    return covs[decision.choice], ds



def format_kernel_selection(table: xr.Dataset) -> str:
    """The kernel validation table as text (the CLI prints it)."""
    sizes = [int(s) for s in table["size"].values]
    lines = [f"spatial='auto' chose {table.attrs['choice']!r} (kriged residual MSE on "
             f"{table.attrs['n_rows']} training snapshots, designs {table.attrs['designs']})",
             f"{'kernel':<18}" + "".join(f"{'MSE@' + str(s):>12}" for s in sizes)
             + f"{'range':>10}{'worst ratio':>13}  admissible"]
    for i, k in enumerate(table["kernel"].values):
        mark = " *" if k == table.attrs["choice"] else ""
        ok = "yes" if bool(table["admissible"].values[i]) else "no"
        if "competes" in table and not bool(table["competes"].values[i]):
            ok = "-"  # its family competes with its other fit
        lines.append(f"{k:<18}" + "".join(f"{v:12.4g}" for v in table["mse"].values[i])
                     + f"{float(table['range'].values[i]):10.3g}"
                     + f"{float(table['ratio'].values[i].max()):13.3f}  {ok}{mark}")
    if "anisotropy" in table and np.any(table["anisotropy"].values != 1.0):
        lines.append("'xA': the east-west range A times the north-south one ('range'); '-': "
                     "the family competes with its other fit")
    return "\n".join(lines)
