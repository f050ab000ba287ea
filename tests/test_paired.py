"""The paired rule's upper bound (validation/paired.py): a paired bootstrap of the MSE ratio."""

from itertools import product

import numpy as np
import pytest
from scipy.stats import norm

from lrm_cvx.errors import ModelError
from lrm_cvx.validation.paired import BOOTSTRAP_SEED, bootstrap_upper
from lrm_cvx.validation.search import paired_choice


def _naive_bootstrap(E: np.ndarray, confidence: float, n_boot: int) -> np.ndarray:
    """The same draws as bootstrap_upper, written out: each draw's cases repeated by their
    counts, then the ratio of the two means."""
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    out = np.zeros(E.shape[:2])
    for s in range(E.shape[1]):
        n = E.shape[2]
        counts = rng.multinomial(n, np.full(n, 1.0 / n), size=n_boot)
        for c in range(E.shape[0]):
            draws = []
            for row in counts:
                picked = np.repeat(np.arange(n), row)
                draws.append(E[c, s, picked].mean() / E[0, s, picked].mean() - 1.0)
            out[c, s] = np.quantile(draws, norm.cdf(confidence))
    return out


def test_bootstrap_bound_against_a_naive_resampling(monkeypatch):
    import lrm_cvx.validation.paired as paired

    rng = np.random.default_rng(3)
    E = 1.0 + rng.random((3, 2, 9))
    naive = _naive_bootstrap(E, 1.645, 300)
    np.testing.assert_allclose(bootstrap_upper(E, 1.645, n_boot=300), naive,
                               rtol=1e-12, atol=1e-12)
    monkeypatch.setattr(paired, "BOOTSTRAP_BLOCK", 20)  # the draws in blocks of 2: the same
    np.testing.assert_allclose(bootstrap_upper(E, 1.645, n_boot=300), naive,
                               rtol=1e-12, atol=1e-12)


def test_bootstrap_bound_lies_within_the_exact_bootstrap_quantiles():
    """On 5 cases every one of the 5^5 resamples is enumerated: the Monte Carlo bound lies
    between the exact bootstrap distribution's 93 % and 97 % quantiles (a lower bound, an
    unpaired or an inverted ratio would not)."""
    rng = np.random.default_rng(1)
    ref = 1.0 + rng.random(5)
    cand = ref * (0.7 + 0.6 * rng.random(5))
    exact = [cand[list(i)].mean() / ref[list(i)].mean() - 1.0 for i in product(range(5), repeat=5)]
    got = bootstrap_upper(np.stack([ref, cand])[:, None, :], 1.645, n_boot=20000)[1, 0]
    assert np.quantile(exact, 0.93) <= got <= np.quantile(exact, 0.97)
    assert bootstrap_upper(np.stack([ref, cand])[:, None, :], 1.645)[0, 0] == 0.0


def test_an_outlier_day_widens_the_bound_only_on_its_side():
    """One day where the reference fails badly no longer rejects a candidate that is 10 %
    better on every other day (the normal bound did); the same day against the candidate
    still rejects it."""
    rng = np.random.default_rng(0)
    ref = 1.0 + 0.1 * rng.random(48)
    cand = 0.9 * ref
    ref_bad = ref.copy()
    ref_bad[7] = 30.0
    E = np.stack([ref_bad, cand])[:, None, :]
    d = E[1, 0] - E[0, 0]
    normal = (d.mean() + 1.645 * d.std(ddof=1) / np.sqrt(d.size)) / E[0, 0].mean()
    assert normal > 0.01  # the old bound rejected it
    *_, admissible, best, _ = paired_choice(E, 1.645, 0.01)
    assert admissible[1] and best == 1
    cand_bad = cand.copy()
    cand_bad[7] = 30.0
    E = np.stack([ref, cand_bad])[:, None, :]
    *_, ucb, admissible, best, _ = paired_choice(E, 1.645, 0.01)
    assert ucb[1, 0] > 0.01 and not admissible[1] and best == 0


def test_a_case_left_out_is_a_case_dropped():
    rng = np.random.default_rng(2)
    E = 1.0 + rng.random((2, 1, 12))
    holed = E.copy()
    holed[1, 0, 4] = np.nan  # not scored for one candidate: left out for both
    np.testing.assert_array_equal(bootstrap_upper(holed, 1.645),
                                  bootstrap_upper(np.delete(E, 4, axis=2), 1.645))


def test_no_draws_is_a_clear_error():
    with pytest.raises(ModelError, match="n_boot"):
        bootstrap_upper(np.ones((2, 1, 4)), 1.645, n_boot=0)
