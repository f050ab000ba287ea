"""One search for every validated choice: candidates x splits, a scorer, a rule, one table.

A validated choice (``temporal="auto"``, ``spatial="auto"``, ``rank="auto"``, ...) is a
specification of :func:`search`, as scikit-learn's grid search validates any setting of any
estimator with one loop:

* **candidates**: labelled settings (a temporal model, a kernel, a rank);
* **a splitter** (:class:`RollingOrigin`: forward windows trained on the snapshots before
  them; :class:`ForwardBlocks`: the second half's blocks, each after the snapshots before
  it; :class:`InterleavedBlocks`: every ``k``-th snapshot held out;
  :class:`HeldOutCells`: the cells a campaign design samples against the observed cells it
  leaves, scored on at most ``max_scored`` of them), each with a ``split(...)`` method;
* **a scorer**: a callable that scores every candidate on one split, on the same sample cells
  (paired), returning errors ``(n_sizes, n_cases)`` per label (day-map MSE, kriging MSE, ...);
* **a rule** (:class:`Best`: the lowest mean error, or the highest log-likelihood;
  :class:`PairedGuard`: the lowest worst
  ratio among candidates whose paired bootstrap bound against the reference (candidate 0) is
  at most ``tolerance``;
  :class:`OneStandardError`: then the most cautious candidate within one standard error of
  it; :class:`FamilyVariants`: a fitted variant of a candidate replaces it unless validated
  worse; :class:`BlockGuard`: the reference unless another is surely better, counted in
  blocks of cases);
* **one table** (:func:`selection_table`): an ``xarray.Dataset`` over the candidates and the
  sample sizes with ``mse``, ``ratio``, ``ucb`` and ``admissible``, the choice in
  ``attrs["choice"]``; the models save it with their other fitted state.

A new validated choice is a new scorer and a call of :func:`search`, never a new loop.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import xarray as xr

from ..errors import ModelError
from .paired import MAX_SCORED, bootstrap_upper, paired_difference, shared_cases

__all__ = ["RollingOrigin", "ForwardBlocks", "InterleavedBlocks", "HeldOutCells", "Best",
           "PairedGuard", "OneStandardError", "FamilyVariants", "BlockGuard", "Decision",
           "paired_choice", "search", "selection_table"]


# ------------------------------------------------------------------------------ splitters
@dataclass(frozen=True)
class RollingOrigin:
    """Forward-chaining windows of ``n_val`` snapshots ending at the last one, each validated
    after a refit on the snapshots before it.

    Parameters
    ----------
    n_val : int
        Snapshots per window.
    n_folds : int
        Most windows.
    """

    n_val: int
    n_folds: int = 2

    def split(self, n: int, carries: Callable[[int], bool] | None = None
              ) -> list[tuple[int, int]] | None:
        """Windows ``[(lo, end)]`` of ``n`` snapshots, earliest first (it has the shortest
        history); the training snapshots of a window are those before ``lo``.

        Parameters
        ----------
        n : int
            Snapshots of the record.
        carries : callable, optional
            ``carries(lo)``: whether a refit on the snapshots before ``lo`` is possible. With
            it, the most windows (up to ``n_folds``) whose earliest history carries a refit,
            else one shorter window (down to 2 snapshots); None when none does.

        Returns
        -------
        list of (int, int) or None
        """
        n_val, n_folds = int(self.n_val), int(self.n_folds)
        if carries is not None:
            fold = next((f for f in range(n_folds, 0, -1) if carries(n - f * n_val)), None)
            if fold is None:
                short = next((v for v in range(n_val - 1, 1, -1) if carries(n - v)), None)
                if short is None:
                    return None
                n_val, fold = short, 1
            n_folds = fold
        return [(n - f * n_val, n - (f - 1) * n_val) for f in range(n_folds, 0, -1)]


@dataclass(frozen=True)
class InterleavedBlocks:
    """Every ``n_folds``-th snapshot held out, in turn, after a refit on all the others.

    Parameters
    ----------
    n_folds : int
        Folds.
    """

    n_folds: int

    def split(self, n: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """``[(train, test)]`` index arrays over ``n`` snapshots, one pair per fold."""
        fold = np.arange(n) % int(self.n_folds)
        return [(np.flatnonzero(fold != f), np.flatnonzero(fold == f))
                for f in range(int(self.n_folds))]


@dataclass(frozen=True)
class ForwardBlocks:
    """The record cut into ``n_blocks`` contiguous blocks; each block of the second half is
    held out after a refit on the snapshots before it (forward chaining).

    Parameters
    ----------
    n_blocks : int
        Blocks of the record.
    """

    n_blocks: int

    def split(self, n: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """``[(train, test)]`` index arrays over ``n`` snapshots, earliest block first."""
        blocks = np.array_split(np.arange(n), int(self.n_blocks))[int(self.n_blocks) // 2:]
        return [(np.arange(block[0]), block) for block in blocks]


@dataclass(frozen=True)
class HeldOutCells:
    """The cells a campaign's design flies, and the observed cells it leaves to score.

    Parameters
    ----------
    max_scored : int
        Most held-out cells scored (a random subset of them beyond).
    """

    max_scored: int = MAX_SCORED

    def split(self, region: Any, observed: np.ndarray, size: int, design: str,
              rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """``(flown, held)``: the ``size`` cells of ``design`` among all of ``region``'s cells
        (:func:`~lrm_cvx.validation.designs.flown_sets`: some may be unobserved, as under clouds)
        and the sorted ``observed`` cells not flown, at most ``max_scored`` of them.

        Parameters
        ----------
        region : Region
            The grid.
        observed : numpy.ndarray
            Bool ``(L,)``: the cells with a value.
        size : int
            Cells the design flies.
        design : str
            ``"route"``, ``"line"`` or ``"scattered"``.
        rng : numpy.random.Generator
            The draws (the design first, then the subset scored).

        Returns
        -------
        tuple of numpy.ndarray
        """
        from .designs import flown_sets

        flown = flown_sets(region, size, design, rng)
        held = np.array(observed, dtype=bool)
        held[flown] = False
        h = np.flatnonzero(held)
        if h.size > self.max_scored:
            h = np.sort(rng.choice(h, self.max_scored, replace=False))
        return flown, h


# ------------------------------------------------------------------------------ rules
@dataclass(frozen=True)
class Decision:
    """What a rule decides on paired errors ``E (n_candidates, n_sizes, n_cases)``.

    ``mse``, ``ratio`` (to the reference) and ``ucb`` per candidate and size, ``admissible``
    and ``competes`` per candidate, ``best`` (the validated best) and ``choice`` (after any
    step toward caution) as candidate indices, ``n_cases`` the cases every candidate scored.
    """

    mse: np.ndarray
    ratio: np.ndarray
    ucb: np.ndarray
    admissible: np.ndarray
    best: int
    choice: int
    n_cases: int
    competes: np.ndarray | None = None


def paired_choice(E: np.ndarray, confidence: float, tolerance: float,
                  what: str = "the selection") -> tuple:
    """The paired guard on errors ``E (n_candidates, n_sizes, n_cases)``.

    Candidate 0 is the reference; a case NaN for any candidate is left out. Per candidate and
    size: the mean error ``mse``, its ``ratio`` to the reference's and ``ucb``, the one-sided
    upper confidence bound of the relative change at the normal level of ``confidence``
    standard errors (a paired bootstrap over the cases,
    :func:`~lrm_cvx.validation.paired.bootstrap_upper`). A candidate is ``admissible`` when its
    ``ucb`` is at most ``tolerance`` at every size (the reference always is); ``best`` is the
    admissible one with the lowest worst ratio.

    Parameters
    ----------
    E : numpy.ndarray
        Paired errors.
    confidence : float
        Standard errors of the one-sided bound.
    tolerance : float
        Largest relative change of an admissible candidate.
    what : str
        The choice, named in the error.

    Returns
    -------
    tuple
        ``(mse, ratio, ucb, admissible, best, n_cases)``.

    Raises
    ------
    ModelError
        When fewer than 2 cases were scored.
    """
    E = shared_cases(E)
    n_cases = int(np.isfinite(E[0]).all(axis=0).sum())
    if n_cases < 2:
        raise ModelError(f"{what} scored fewer than 2 validation cases (is the data mostly "
                         "missing?)")
    mse = np.nanmean(E, axis=-1)
    ucb = bootstrap_upper(E, confidence)
    ratio = mse / mse[0]
    admissible = ucb.max(axis=1) <= float(tolerance)
    admissible[0] = True
    best = int(np.argmin(np.where(admissible, ratio.max(axis=1), np.inf)))
    return mse, ratio, ucb, admissible, best, n_cases


@dataclass(frozen=True)
class Best:
    """The candidate with the lowest worst ratio (over the sizes) of its mean error to the
    reference's; no guard (every candidate admissible, ``ucb`` NaN).

    Parameters
    ----------
    log_likelihood : bool
        The scores are log-likelihoods, higher is better (not errors): the best has the
        highest worst mean (over the sizes; a NaN mean never wins, the first of equal ones
        does) and ``ratio`` is the likelihood ratio to the reference per case,
        ``exp(mean - reference's mean)``.
    """

    log_likelihood: bool = False

    def __call__(self, E: np.ndarray, labels: Sequence[str] = ()) -> Decision:
        """The decision on errors (or log-likelihoods) ``E (n_candidates, n_sizes,
        n_cases)``."""
        mse = np.nanmean(E, axis=-1)
        if self.log_likelihood:
            ratio = np.exp(mse - mse[0])
            best = int(np.argmax(np.where(np.isnan(mse), -np.inf, mse).min(axis=1)))
        else:
            ratio = mse / mse[0]
            best = int(np.argmin(ratio.max(axis=1)))
        return Decision(mse, ratio, np.full_like(mse, np.nan), np.ones(E.shape[0], bool),
                        best, best, int(np.isfinite(E).all(axis=(0, 1)).sum()))


@dataclass(frozen=True)
class PairedGuard:
    """The lowest worst ratio among the candidates not worse than the reference (candidate 0)
    by more than ``tolerance`` with confidence (:func:`paired_choice`).

    Parameters
    ----------
    confidence : float
        Standard errors of the one-sided bootstrap bound.
    tolerance : float
        Largest relative change an admissible candidate may show (negative: a gain needed).
    what : str
        The choice, named in errors.
    """

    confidence: float = 1.645
    tolerance: float = 0.01
    what: str = "the selection"

    def __call__(self, E: np.ndarray, labels: Sequence[str] = ()) -> Decision:
        """The decision on paired errors ``E (n_candidates, n_sizes, n_cases)``."""
        mse, ratio, ucb, admissible, best, n = paired_choice(E, self.confidence,
                                                             self.tolerance, self.what)
        return Decision(mse, ratio, ucb, admissible, best, best, n)


@dataclass(frozen=True)
class OneStandardError:
    """The guard's best, then the most cautious admissible candidate of the same ``group``
    whose paired mean error exceeds the best's by at most ``n_se`` standard errors at every
    size (the one-standard-error rule of cross-validation).

    Parameters
    ----------
    guard : PairedGuard
        The rule that finds the best.
    group : callable
        ``group(label)``: candidates of one group may replace each other.
    caution : callable
        ``caution(label)``: a sortable key, larger is more cautious.
    n_se : float
        Standard errors of the tie.
    """

    guard: PairedGuard
    group: Callable[[int], Hashable]
    caution: Callable[[int], Any]
    n_se: float = 1.0

    def __call__(self, E: np.ndarray, labels: Sequence[str]) -> Decision:
        """The decision on paired errors ``E (n_candidates, n_sizes, n_cases)`` of the
        candidates ``labels``."""
        d = self.guard(E)
        E = shared_cases(E)
        pick = d.best
        for c, lab in enumerate(labels):
            if (self.group(lab) != self.group(labels[d.best]) or not d.admissible[c]
                    or self.caution(lab) <= self.caution(labels[pick])):
                continue
            diff, se = paired_difference(E, c, d.best)  # (size,)
            if np.all(diff <= self.n_se * se):
                pick = c
        return Decision(d.mse, d.ratio, d.ucb, d.admissible, d.best, pick, d.n_cases)


@dataclass(frozen=True)
class FamilyVariants:
    """Candidates with fitted variants (``variants``: candidate -> its variant's index, after
    the candidates): a variant replaces its candidate unless its paired errors are worse with
    confidence at some size; the guard then decides among those that compete. ``mse`` is over
    the cases every candidate and variant scored, ``ratio`` to the reference as it competes.

    Parameters
    ----------
    guard : PairedGuard
        The rule among the competing candidates.
    variants : mapping
        Candidate index -> the index of its variant.
    """

    guard: PairedGuard
    variants: Mapping[int, int] = field(default_factory=dict)

    def __call__(self, E: np.ndarray, labels: Sequence[str] = ()) -> Decision:
        """The decision on paired errors ``E (n_candidates, n_sizes, n_cases)``."""
        mse, _, _, _, _, n_cases = paired_choice(E, self.guard.confidence,
                                                 self.guard.tolerance, self.guard.what)
        use = [i for i in range(E.shape[0]) if i not in self.variants.values()]
        for i, j in self.variants.items():
            if self.not_worse(E[j], E[i]):
                use[use.index(i)] = j
        d = self.guard(E[use])
        ucb = np.full_like(mse, np.nan)
        ucb[use] = d.ucb
        admissible = np.zeros(E.shape[0], dtype=bool)
        admissible[use] = d.admissible
        competes = np.isin(np.arange(E.shape[0]), use)
        return Decision(mse, mse / mse[use[0]], ucb, admissible, use[d.best], use[d.choice],
                        n_cases, competes)

    def not_worse(self, Ea: np.ndarray, Ei: np.ndarray) -> bool:
        """Whether errors ``Ea (n_sizes, n_cases)`` are not worse than the paired ``Ei`` with
        confidence at any size: the upper bound of ``Ei``'s change against ``Ea`` is >= 0."""
        ucb = paired_choice(np.stack([Ea, Ei]), self.guard.confidence, 0.0,
                            self.guard.what)[2][1]
        return bool(np.all(ucb >= 0))


@dataclass(frozen=True)
class BlockGuard:
    """The reference (candidate 0) unless another candidate is surely better, counted in
    blocks of cases (a placement's validation window: its cases share one draw of each
    candidate, so their spread says nothing about the candidate's).

    The errors are averaged per block; the change against the reference is paired per block
    and its one-sided upper bound (``confidence`` standard errors of the changes' spread over
    the blocks, relative to the reference's mean) must be below ``tolerance``; among those
    candidates, the lowest mean over the blocks. With fewer than two blocks the bound is
    +inf and the reference stays. The decision's ``mse`` is per candidate and block.

    Parameters
    ----------
    blocks : sequence of (int, int)
        Case ranges ``(start, stop)``.
    confidence : float
        Standard errors of the one-sided bound.
    tolerance : float
        The bound a candidate must stay below.
    """

    blocks: Sequence[tuple[int, int]]
    confidence: float = 1.645
    tolerance: float = 0.0

    def __call__(self, E: np.ndarray, labels: Sequence[str] = ()) -> Decision:
        """The decision on paired errors ``E (n_candidates, 1, n_cases)``."""
        import warnings

        mse = np.array([[float(np.nanmean(row[a:b])) for a, b in self.blocks]
                        for row in E[:, 0]]).reshape(E.shape[0], len(self.blocks))
        score = mse.mean(axis=1) if self.blocks else np.full(E.shape[0], np.nan)
        ucb = np.zeros(E.shape[0])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            diff, se = paired_difference(mse, slice(1, None), 0)
            ub = (diff + self.confidence * se) / np.nanmean(mse[0])
        n = np.isfinite(mse[1:] - mse[0]).sum(axis=1)
        ucb[1:] = np.where((n >= 2) & np.isfinite(ub), ub, np.inf)
        admissible = ucb < self.tolerance
        admissible[0] = True
        best = 0
        for c in range(1, E.shape[0]):
            if admissible[c] and score[c] < score[best]:
                best = c
        return Decision(mse, score / score[0], ucb, admissible, best, best, E.shape[-1])


# ------------------------------------------------------------------------------ the search
def search(score: Callable[[Any], Mapping[str, np.ndarray]], splits: Iterable[Any],
           rule: Callable[[np.ndarray, list[str]], Decision], *,
           drop: Callable[[str], bool] | None = None) -> tuple[list[str], np.ndarray, Decision]:
    """Score every candidate on every split and decide.

    Parameters
    ----------
    score : callable
        ``score(split)``: errors ``(n_sizes, n_cases)`` per candidate label, every candidate
        on the same sample sets; the reference first.
    splits : iterable
        What a splitter's ``split`` gave.
    rule : callable
        ``rule(E, labels)``: a :class:`Decision` on the errors ``E (n_candidates, n_sizes,
        n_cases)`` of the candidates ``labels``.
    drop : callable, optional
        ``drop(label)``: leave a candidate out (one the record turned out not to carry).

    Returns
    -------
    tuple
        ``(labels, E, decision)``: the candidates scored on every split (in the first
        split's order), their errors with the splits' cases concatenated, the decision.
    """
    scored = [dict(score(s)) for s in splits]
    labels = [lab for lab in scored[0] if all(lab in e for e in scored)
              and not (drop is not None and drop(lab))]
    E = np.stack([np.concatenate([e[lab] for e in scored], axis=-1) for lab in labels])
    return labels, E, rule(E, labels)


def selection_table(decision: Decision, labels: Sequence[str], sizes: Sequence[int], *,
                    dim: str = "candidate", reference: str = "the reference",
                    what: str = "MSE", data_vars: Mapping[str, Any] | None = None,
                    coords: Mapping[str, Any] | None = None, **attrs: Any) -> xr.Dataset:
    """The table of a validated choice: ``mse``, ``ratio``, ``ucb`` over ``(dim, size)`` and
    ``admissible`` (with ``competes`` when the rule has variants) over ``dim``; attributes
    ``choice`` (the chosen label) and ``attrs``.

    Parameters
    ----------
    decision : Decision
        The rule's.
    labels : sequence of str
        Candidate labels.
    sizes : sequence of int
        Sample sizes (``[0]``: a choice not scored per sample size, as the calibration's and
        ``GLRM.select_rank``'s).
    dim : str
        The candidates' dim.
    reference : str
        The reference, named in the ratio's ``long_name``.
    what : str
        The error scored, named in the mean's ``long_name``.
    data_vars, coords : mapping, optional
        More per-candidate variables and coordinates.
    **attrs
        More attributes.

    Returns
    -------
    xarray.Dataset
    """
    d = decision
    ds = xr.Dataset({"mse": ((dim, "size"), d.mse), "ratio": ((dim, "size"), d.ratio),
                     "ucb": ((dim, "size"), d.ucb), "admissible": ((dim,), d.admissible)},
                    coords={dim: list(labels), "size": list(sizes), **(coords or {})})
    if d.competes is not None:
        ds["competes"] = ((dim,), d.competes)
    for name, value in (data_vars or {}).items():
        ds[name] = value
    ds["mse"].attrs["long_name"] = what
    ds["ratio"].attrs["long_name"] = f"MSE ratio to {reference}"
    ds["ucb"].attrs["long_name"] = "upper confidence bound of the relative MSE change"
    ds.attrs.update(choice=labels[d.choice], **attrs)
    return ds
