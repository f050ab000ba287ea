"""The pure parts of ``benchmarks/bench_peers.py`` on tiny data; the peers
(H2O, PySensors) are skipped when not installed."""

from __future__ import annotations

import importlib.util
import shutil
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture(scope="module")
def bp():
    sys.path.insert(0, str(BENCH))
    spec = importlib.util.spec_from_file_location("bench_peers", BENCH / "bench_peers.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["bench_peers"] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def planted(T=30, L=80, k=2, missing=0.3, noise=0.0, seed=0):
    rng = np.random.default_rng(seed)
    D = (rng.normal(size=(T, k)) @ rng.normal(size=(k, L))).astype(np.float32)
    D += noise * rng.normal(size=D.shape).astype(np.float32)
    D[rng.random(D.shape) < missing] = np.nan
    return D


def test_peer_missing(bp, monkeypatch):
    with pytest.raises(ValueError, match="unknown peer"):
        bp.peer_missing("sklearn")
    monkeypatch.setattr(bp.importlib.util, "find_spec", lambda name: None)
    assert "pip install h2o" in bp.peer_missing("h2o")
    assert "python-sensors" in bp.peer_missing("pysensors")
    monkeypatch.setattr(bp.importlib.util, "find_spec", lambda name: object())
    monkeypatch.setattr(bp.shutil, "which", lambda name: None)
    assert "Java" in bp.peer_missing("h2o")
    assert bp.peer_missing("pysensors") is None


def test_split_observed_is_a_partition(bp):
    D = planted(T=40, L=200)
    train, test = bp.split_observed(D, 0.1, seed=1)
    obs = np.isfinite(D)
    assert not (train & test).any()
    np.testing.assert_array_equal(train | test, obs)
    assert abs(test.sum() / obs.sum() - 0.1) < 0.02
    assert train.any(axis=1).all()


def test_heldout_rmse_matches_naive(bp):
    rng = np.random.default_rng(2)
    U, V = rng.normal(size=(7, 3)), rng.normal(size=(3, 11))
    D = rng.normal(size=(7, 11)).astype(np.float32)
    test = rng.random((7, 11)) < 0.4
    naive = np.sqrt(np.mean(((U @ V) - D)[test] ** 2))
    assert bp.heldout_rmse(U, V, D, test) == pytest.approx(naive, rel=1e-12)
    with pytest.raises(ValueError):
        bp.heldout_rmse(U, V, D, np.zeros_like(test))


def test_within(bp):
    assert bp.within(1.01, 1.0)
    assert bp.within(0.5, 1.0)
    assert not bp.within(1.0101, 1.0)


def test_h2o_csv_round_trip(bp, tmp_path):
    D = planted(T=5, L=9, missing=0.4, seed=3)
    train = np.isfinite(D) & (np.random.default_rng(0).random(D.shape) < 0.8)
    path = tmp_path / "m.csv"
    bp.write_h2o_csv(D, train, path)
    back = pd.read_csv(path)
    assert list(back.columns) == [f"t{j}" for j in range(5)]
    want = np.where(train, D, np.nan).T
    np.testing.assert_array_equal(np.isnan(back.values), np.isnan(want))
    np.testing.assert_allclose(back.values, want, rtol=1e-5, equal_nan=True)


def test_fit_lrm_recovers_a_planted_matrix(bp):
    D = planted(T=30, L=120, k=2, missing=0.3)
    train, test = bp.split_observed(D, 0.1, seed=0)
    model, sec = bp.fit_lrm(D, train, rank=2)
    assert sec > 0
    target = bp.heldout_rmse(model._Xv.T, model._Yv, D, test)
    assert target < 1e-3 * np.nanstd(D)
    # the fewest rounds to 1% of a looser target: found, and within it
    fast = bp.lrm_rounds_to_target(D, train, test, 0.01 * float(np.nanstd(D)), rank=2)
    assert fast is not None
    rounds, _, rmse = fast
    assert rounds >= 1 and rmse <= 1.01 * 0.01 * float(np.nanstd(D))


def test_qr_same_basis_is_pivoted_qr(bp):
    pytest.importorskip("pysensors")
    import scipy.linalg

    Y = np.random.default_rng(4).normal(size=(4, 50))
    cells = bp.qr_same_basis(Y, 10)
    assert cells.shape == (10,) and len(set(cells.tolist())) == 10
    # the first k pivots are those of QR with column pivoting of Y (after them, round-off)
    np.testing.assert_array_equal(cells[:4], scipy.linalg.qr(Y, pivoting=True)[2][:4])


def test_greedy_sets_on_a_small_sample(bp):
    import warnings

    import xarray as xr

    from lrm_cvx.glrm import GLRM

    rng = np.random.default_rng(5)
    n, T = 8, 20
    vals = (rng.normal(size=(T, 2)) @ rng.normal(size=(2, n * n))).reshape(T, n, n)
    vals += 0.1 * rng.normal(size=vals.shape)
    da = xr.DataArray(vals, dims=("time", "lat", "lon"),
                      coords={"time": np.arange(T), "lat": np.arange(n) * 1.0,
                              "lon": np.arange(n) * 1.0})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        paper = GLRM(2, random_state=0, progress=False).fit(da)
        model = GLRM(2, random_state=0, progress=False, offset=True,
                     spatial="exponential").fit(da)
    sets = bp.greedy_sets(paper, model, 6)
    assert set(sets) == {"fisher", "gp"}
    for cells in sets.values():
        assert cells.shape == (6,) and len(set(cells.tolist())) == 6
        assert cells.min() >= 0 and cells.max() < n * n
    # the Fisher greedy's first pick maximises log det(ridge I + y y^T): the longest column
    assert sets["fisher"][0] == int(np.argmax((paper._Yv ** 2).sum(axis=0)))


@pytest.mark.skipif(shutil.which("java") is None, reason="H2O needs Java")
def test_run_h2o_tiny(bp, tmp_path):
    pytest.importorskip("h2o")
    D = planted(T=12, L=60, k=2, missing=0.2, seed=6)
    train, test = bp.split_observed(D, 0.1, seed=0)
    model, _ = bp.fit_lrm(D, train, rank=2)
    target = bp.heldout_rmse(model._Xv.T, model._Yv, D, test)
    res = bp.run_h2o(D, train, test, max(target, 1e-3), rank=2, schedule=(200,),
                     max_mem="1G", nthreads=1, port=54391, tmpdir=str(tmp_path),
                     log=lambda *a: None)
    assert res.imported > 0 and len(res.runs) == 1
    run = res.runs[0]
    assert run.iterations >= 1 and np.isfinite(run.rmse)
    # an exact rank-2 matrix: H2O's fit is close on the held-out entries too
    assert run.rmse < 0.1 * float(np.nanstd(D))


def test_runs_cancelled(bp):
    class H2OJobCancelled(Exception):
        pass

    assert bp.runs_cancelled(KeyboardInterrupt())
    assert bp.runs_cancelled(H2OJobCancelled("job cancelled"))
    assert not bp.runs_cancelled(RuntimeError("JVM did not start"))
