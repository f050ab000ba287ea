"""GLRM fit at paper scale: quadratic (20 iterations), Huber to convergence, naive cvxpy estimate.

Run under the shared lock:  flock /tmp/lrm-bench.lock python benchmarks/bench_glrm.py
``--small`` runs a quick smoke version (60 x 200 x 150).
"""

from __future__ import annotations

import argparse
import gc
import resource
import threading
import time
import warnings

import cvxpy as cp
import numpy as np

from lrm_cvx.glrm import GLRM
from lrm_cvx.glrm import quadratic as Q
from lrm_cvx.glrm.fit import _quad_x, check_data, initialize, quadratic_y_step
from lrm_cvx.io.samples import synthetic_field
from lrm_cvx.region import Region


def rss_gib() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 2**20
    return float("nan")


class PeakRSS:
    """Sample VmRSS every 20 ms in a thread: the peak during a block of code."""

    def __enter__(self):
        self.peak = rss_gib()
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()
        return self

    def _run(self):
        while not self._stop.wait(0.02):
            self.peak = max(self.peak, rss_gib())

    def __exit__(self, *exc):
        self._stop.set()
        self._t.join()
        self.peak = max(self.peak, rss_gib())


def make_data(n_times, shape, seed=0, land_fraction=1.0):
    da = synthetic_field(n_times, shape, rank=5, missing=0.5, noise=0.05,
                         land_fraction=land_fraction, seed=seed)
    region = Region.from_dataarray(da)
    D = region.stack(da)  # (T, L) float32, NaN missing
    del da
    gc.collect()
    M = ~np.isnan(D)
    np.nan_to_num(D, copy=False, nan=0.0)
    return D, M, region


def naive_y_step_seconds(D, M, X, n_cols):
    """One cvxpy problem per column (the naive Y step), timed on ``n_cols`` columns."""
    k = X.shape[0]
    t0 = time.perf_counter()
    for j in range(n_cols):
        obs = M[:, j]
        y = cp.Variable(k)
        prob = cp.Problem(cp.Minimize(cp.sum_squares(X[:, obs].T @ y - D[obs, j])))
        prob.solve(solver=cp.CLARABEL)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--small", action="store_true")
    ap.add_argument("--land-fraction", type=float, default=1.0,
                    help="land fraction of the grid (1.0: all 2.1M cells at paper scale)")
    args = ap.parse_args()
    n_times, shape = (60, (200, 150)) if args.small else (310, (1500, 1400))
    print(f"data: {n_times} times x {shape} grid, land fraction {args.land_fraction}, rank 5, "
          "50% missing, float32")
    t0 = time.perf_counter()
    D, M, region = make_data(n_times, shape, land_fraction=args.land_fraction)
    print(f"  generated + stacked in {time.perf_counter() - t0:.1f} s: T={D.shape[0]}, "
          f"L={D.shape[1]}, observed {M.mean():.3f}; RSS {rss_gib():.2f} GiB")

    # warm-up compile on tiny data (numba cache)
    w = np.random.default_rng(0).random((6, 40)).astype(np.float32)
    for loss in ("quadratic", "huber"):
        GLRM(rank=2, loss=loss, max_iter=2, progress=False).fit(w, mask=w > 0.2)

    base = rss_gib()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with PeakRSS() as pk:
            Q.PASSES.reset()  # full reads of D by the kernels (checks, packing, init, rounds)
            t0 = time.perf_counter()
            m = GLRM(rank=5, max_iter=20, tol=0.0, random_state=0, progress=False)
            m.fit(D, mask=M)
            t_quad = time.perf_counter() - t0
            passes = Q.PASSES.passes(D.shape)
    print(f"quadratic, 20 iterations: {t_quad:.1f} s, {passes:.0f} passes over the data "
          f"(2 a round + {passes - 40:.0f} for checks, mask packing and init); fit peak RSS "
          f"{pk.peak:.2f} GiB (+{pk.peak - base:.2f} GiB over data {base:.2f} GiB); objective "
          f"{m.objective_[0]:.4g} -> {m.objective_[-1]:.4g}; noise_std {m.noise_std_:.4f}")
    t_iter = t_quad / 20

    # breakdown: the data pass, the init and one round measured alone
    k = 5
    t0 = time.perf_counter()
    st = check_data(D, M, k)
    t_chk = time.perf_counter() - t0
    rows, cols = st
    mu = np.where(cols > 0, st.colsum / np.maximum(cols, 1), 0.0)
    t0 = time.perf_counter()
    md = Q.prepare(D, M)
    t_prep = time.perf_counter() - t0
    t0 = time.perf_counter()
    X, Y = initialize(md, k, "svd", np.random.default_rng(0), mu, 1.0)
    t_init = time.perf_counter() - t0
    t0 = time.perf_counter()
    Y, _, _ = quadratic_y_step(md, X, Y, 0.0, Y)
    t_y = time.perf_counter() - t0
    t0 = time.perf_counter()
    X, _, _ = _quad_x(md, X, Y, 0.0)
    t_x = time.perf_counter() - t0
    print(f"  breakdown: check_data (stats pass) {t_chk:.2f} s, mask packing {t_prep:.2f} s, "
          f"randomized-SVD init {t_init:.2f} s, one Y step {t_y:.2f} s, one X step {t_x:.2f} s")
    del md
    del X, Y

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with PeakRSS() as pk:
            t0 = time.perf_counter()
            mh = GLRM(rank=5, loss="huber", max_iter=200, tol=1e-4, random_state=0,
                      progress=False).fit(D, mask=M)
            t_hub = time.perf_counter() - t0
    print(f"huber (delta=1), tol 1e-4: {t_hub:.1f} s, {mh.n_iter_} iterations, converged "
          f"{mh.converged_}; peak RSS {pk.peak:.2f} GiB")

    n_cols = 200 if args.small else 1000
    X = np.asarray(m.X_)
    t_naive = naive_y_step_seconds(D, M, X, n_cols)
    per_col = t_naive / n_cols
    L = D.shape[1]
    naive_iter = per_col * L  # Y step only, per iteration
    print(f"naive cvxpy Y step: {t_naive:.1f} s for {n_cols} columns = {per_col * 1e3:.2f} ms "
          f"a column -> {naive_iter:.0f} s a Y step over {L} columns, "
          f"{naive_iter * 20 / 3600:.1f} h for 20 iterations (Y steps only); speed-up of the "
          f"fast path (full iteration) {naive_iter / t_iter:.0f}x")
    ru = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    print(f"process peak RSS (ru_maxrss) {ru:.2f} GiB")


if __name__ == "__main__":
    main()
