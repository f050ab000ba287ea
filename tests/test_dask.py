"""The dask (out-of-core) GLRM fit equals the in-memory fit; staging, errors, distributed."""

from __future__ import annotations

import os
import shutil
import warnings

import numpy as np
import pytest

dask = pytest.importorskip("dask")
da = pytest.importorskip("dask.array")

import xarray as xr  # noqa: E402
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from lrm_cvx.errors import DataError, ModelError  # noqa: E402
from lrm_cvx.evaluation import PlanningOptions, ScoringOptions  # noqa: E402
from lrm_cvx.glrm import GLRM, SolverOptions  # noqa: E402
from lrm_cvx.glrm.chunked import fit_chunked, is_dask_backed  # noqa: E402
from lrm_cvx.glrm.fit import SMALL_SVD  # noqa: E402
from lrm_cvx.io.samples import synthetic_field  # noqa: E402
from lrm_cvx.io.staging import _time_blocks, stage  # noqa: E402
from lrm_cvx.region import Region  # noqa: E402

SMALL_CHUNKS = {"chunk_mb": 0.05, "block_mb": 0.2}  # several column chunks and time blocks


@pytest.fixture(scope="module")
def field():
    return synthetic_field(48, (30, 60), rank=3, seed=4, noise=0.03)


def _pair(data, dask_data, options=SMALL_CHUNKS, **params):
    kw = dict(rank=3, max_iter=12, tol=0, random_state=7, progress=False)
    kw.update(params)
    ref = GLRM(**kw).fit(data)
    out = GLRM(**kw, dask=options).fit(dask_data)
    return ref, out


def _same_fit(ref, out, rtol=1e-5):
    np.testing.assert_allclose(out.objective_, ref.objective_, rtol=rtol)
    assert out.n_iter_ == ref.n_iter_ and out.converged_ == ref.converged_
    np.testing.assert_allclose(out.noise_std_, ref.noise_std_, rtol=rtol)
    X1, X2 = np.asarray(ref.X_), np.asarray(out.X_)
    Y1, Y2 = np.asarray(ref.Y_), np.asarray(out.Y_)
    np.testing.assert_allclose(X2.T @ Y2, X1.T @ Y1, atol=1e-5 * np.abs(X1.T @ Y1).max())
    np.testing.assert_array_equal(out.unobserved_cells_, ref.unobserved_cells_)
    assert out.n_observed_ == ref.n_observed_


@pytest.mark.parametrize("init", ["svd", "random"])
def test_same_answer_as_in_memory(field, init):
    ref, out = _pair(field, field.chunk({"time": 5}), solver=SolverOptions(init=init))
    assert is_dask_backed(field.chunk({"time": 5})) and not is_dask_backed(field)
    _same_fit(ref, out, rtol=1e-8)
    assert out.region_.equals(ref.region_)
    assert isinstance(out.Y_.data, np.ndarray)  # default: Y_ computed into memory
    np.testing.assert_array_equal(out.X_["time"].values, ref.X_["time"].values)


@pytest.mark.parametrize("loss,reg_x,reg_y", [
    ("huber", "ridge", None), ("absolute", None, "ridge"), ("quadratic", "l1", "nonneg")])
def test_same_answer_other_losses(field, loss, reg_x, reg_y):
    ref, out = _pair(field, field.chunk({"time": 16}), loss=loss, reg=(reg_x, reg_y),
                     max_iter=6)
    _same_fit(ref, out, rtol=1e-6)


def test_randomized_svd_regime_and_unobserved_cell():
    """Above SMALL_SVD entries the init is the randomized SVD with the same test matrix."""
    rng = np.random.default_rng(0)
    T, L, k = 40, SMALL_SVD // 40 + 500, 2
    D = (rng.standard_normal((T, k)) @ rng.standard_normal((k, L))).astype(np.float32)
    D += 0.01 * rng.standard_normal((T, L)).astype(np.float32)
    D[rng.random((T, L)) < 0.3] = np.nan
    D[:, 5] = np.nan  # a cell never observed
    ref, out = _pair(D, da.from_array(D, chunks=(8, -1)), {"chunk_mb": 4}, rank=k, max_iter=2,
                     solver=SolverOptions(init="svd"))
    _same_fit(ref, out, rtol=1e-6)
    assert out.unobserved_cells_.tolist() == [5]
    assert isinstance(out.Y_, np.ndarray)


def test_mask_input_and_tol_stopping(field):
    region = Region.from_dataarray(field)
    D = region.stack(field)
    M = ~np.isnan(D)
    Dz = np.where(M, D, 1e30).astype(np.float32)  # outside the mask never read
    kw = dict(rank=3, max_iter=50, tol=1e-3, random_state=1, progress=False)
    ref = GLRM(**kw).fit(Dz, mask=M)
    out = GLRM(**kw, dask=SMALL_CHUNKS).fit(da.from_array(Dz, chunks=(10, -1)),
                                                    mask=da.from_array(M, chunks=(10, -1)))
    assert ref.converged_ and ref.n_iter_ < 50
    _same_fit(ref, out, rtol=1e-8)


def test_stage_matches_region_stack(field, tmp_path):
    store, region, times, tdim = stage(field.chunk({"time": 3}), chunk_mb=0.03, block_mb=0.1,
                                       scratch_dir=str(tmp_path))
    ref_region = Region.from_dataarray(field)
    assert region.equals(ref_region) and tdim == "time" and times.size == field.sizes["time"]
    assert store.n_chunks > 3
    got = np.concatenate([np.load(f) for f in store.files], axis=1)
    np.testing.assert_array_equal(got, ref_region.stack(field))  # NaN positions equal too


def test_streaming_stage_irregular_time_chunks(field, tmp_path):
    """Blocks group whole time chunks and split chunks larger than a block; the staged files
    are exactly region.stack(data), and the array + mask path writes NaN where unobserved."""
    fd = field.chunk({"time": (1, 2, 9, 3, 20, 1, 12), "lat": 7, "lon": 25})
    row_mb = 4 * 30 * 60 / 2**20
    store, region, _, _ = stage(fd, chunk_mb=0.04, block_mb=5.5 * row_mb,
                                scratch_dir=str(tmp_path))
    ref = Region.from_dataarray(field).stack(field)
    got = np.concatenate([np.load(f) for f in store.files], axis=1)
    assert store.n_chunks > 3
    np.testing.assert_array_equal(got, ref)
    M = ~np.isnan(ref)
    Dz = np.where(M, ref, 7.0)
    st2, *_ = stage(da.from_array(Dz, chunks=(5, 40)), mask=da.from_array(M, chunks=(7, 50)),
                    chunk_mb=0.03, block_mb=0.01, scratch_dir=str(tmp_path))
    np.testing.assert_array_equal(np.concatenate([np.load(f) for f in st2.files], axis=1),
                                  ref.astype(np.float32))


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(1, 9), min_size=1, max_size=12), st.integers(1, 12))
def test_time_blocks_cover_and_respect_chunks(sizes, budget):
    arr = da.zeros((sum(sizes), 3), chunks=(tuple(sizes), 3), dtype=np.float32)
    blocks = _time_blocks(arr, 4, budget * 4 / 2**20)
    edges = set(np.cumsum((0, *sizes)).tolist())
    assert blocks[0][0] == 0 and blocks[-1][1] == sum(sizes)
    for (_, a1), (b0, _) in zip(blocks[:-1], blocks[1:], strict=True):
        assert a1 == b0
    for t0, t1 in blocks:
        assert t1 > t0
        inner = [e for e in edges if t0 < e < t1]
        if inner:  # a block spanning several chunks holds whole chunks within the budget
            assert t0 in edges and t1 in edges and t1 - t0 <= budget
        else:  # inside one chunk: at most the budget
            assert t1 - t0 <= max(budget, 1)


def test_keep_dask_save_load_complete(field, tmp_path):
    fd = field.chunk({"time": 8})
    m = GLRM(rank=3, max_iter=5, tol=0, random_state=0, progress=False,
             dask={**SMALL_CHUNKS, "keep_dask": True}).fit(fd)
    ref = GLRM(rank=3, max_iter=5, tol=0, random_state=0, progress=False).fit(field)
    assert is_dask_backed(m.Y_) and m.Y_.data.numblocks[1] > 1
    path = tmp_path / "m.nc"
    m.save(path)
    back = GLRM.load(path)
    np.testing.assert_allclose(back.Y_.values, ref.Y_.values, rtol=1e-6, atol=1e-9)
    snap = field.isel(time=3)
    np.testing.assert_allclose(m.complete(snap)["prediction"].values,
                               ref.complete(snap)["prediction"].values, rtol=1e-5, atol=1e-7)


def test_errors():
    rng = np.random.default_rng(1)
    D = rng.standard_normal((10, 30))
    with pytest.raises(ModelError, match="rank"):
        GLRM(rank=11, progress=False).fit(da.from_array(D))
    with pytest.raises(ModelError, match="fast path"):
        GLRM(rank=2, solver="cvxpy", progress=False).fit(da.from_array(D))
    Dinf = D.copy()
    Dinf[2, 3] = np.inf
    with pytest.raises(DataError, match="inf"):
        GLRM(rank=2, progress=False).fit(da.from_array(Dinf))
    Dt = D.copy()
    Dt[4] = np.nan
    with pytest.raises(DataError, match="times \\[4\\]"):
        GLRM(rank=2, progress=False).fit(da.from_array(Dt))
    with pytest.raises(DataError, match="mask"):
        GLRM(rank=2, progress=False).fit(da.from_array(D), mask=da.from_array(D > 0).astype(int))
    with pytest.raises(DataError):
        GLRM(rank=2, progress=False).fit(da.from_array(D)[None])
    with pytest.raises(ModelError, match="spatial= needs"):  # a (T, L) array has no region
        GLRM(rank=2, spatial="exponential", progress=False).fit(da.from_array(D))
    with pytest.raises(ModelError, match="noise"):
        GLRM(rank=2, noise="per-row", progress=False).fit(da.from_array(D))
    with pytest.raises(ModelError, match="degrees of freedom"):  # the offset's L parameters
        GLRM(rank=2, offset=True, progress=False).fit(da.from_array(D[:3]))
    with pytest.raises(DataError, match="all NaN"):
        fit_chunked(xr.DataArray(da.full((3, 4, 5), np.nan, chunks=1),
                                 dims=("time", "lat", "lon")), 1, *_defaults())


def _defaults():
    from lrm_cvx.glrm.losses import get_loss
    from lrm_cvx.glrm.regularizers import get_regularizer

    return get_loss("quadratic"), get_regularizer(None), get_regularizer(None)


def test_distributed_local_cluster(field, tmp_path):
    distributed = pytest.importorskip("distributed")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                           dashboard_address=None, memory_limit="1GiB")
    try:
        with distributed.Client(cluster) as client:
            assert len(client.scheduler_info()["workers"]) == 2
            ref, out = _pair(field, field.chunk({"time": 6}), {"chunk_mb": 0.1}, max_iter=5)
            _same_fit(ref, out, rtol=1e-8)
            m = GLRM(rank=3, max_iter=4, tol=0, random_state=7, progress=False,
                     dask={"chunk_mb": 0.1, "scratch_dir": str(tmp_path), "keep_dask": True}
                     ).fit(
                         field.chunk({"time": 6}))
            m.save(tmp_path / "d.nc")
            ref4 = GLRM(rank=3, max_iter=4, tol=0, random_state=7, progress=False).fit(field)
            np.testing.assert_allclose(GLRM.load(tmp_path / "d.nc").Y_.values,
                                       ref4.Y_.values, rtol=1e-6, atol=1e-9)
            assert not any(p.name.startswith("lrm-dask-") for p in tmp_path.iterdir())
            # every option runs unchanged on the cluster: the same model as in memory
            kw = dict(rank=3, max_iter=5, tol=0, random_state=7, progress=False, offset=True,
                      scale=True, noise="per-cell", spatial="exponential", temporal="ar1")
            ref5 = GLRM(**kw).fit(field)
            out5 = GLRM(**kw, dask={"chunk_mb": 0.05, "scratch_dir": str(tmp_path)}
                        ).fit(field.chunk({"time": 6}))
            _assert_model_equal(ref5, out5)
    finally:
        cluster.close()


def test_convergence_warning_points_at_the_callers_line(field):
    for data, options in ((field, None), (field.chunk({"time": 8}), SMALL_CHUNKS)):
        model = GLRM(rank=3, max_iter=1, tol=1e-12, progress=False, dask=options)
        with pytest.warns(Warning) as record:
            model.fit(data)
        hits = [w for w in record if "max_iter=1" in str(w.message)]
        assert len(hits) == 1 and hits[0].filename == __file__


# ----------------------------------------------------------------------------- every option
OPTIONS = [
    dict(offset=True),
    dict(scale=True),
    dict(offset=True, scale=True, noise="per-cell"),
    dict(offset=True, noise="per-cell", spatial="exponential", temporal="ar1"),
    dict(noise="per-cell", spatial="gaussian", reg="ridge"),
    dict(offset=True, scale="residual", spatial="exponential"),
]
CHUNKINGS = [  # (input time chunks, fit options): one chunk, several, ragged
    ({"time": -1}, {"chunk_mb": 64}),
    ({"time": 5}, SMALL_CHUNKS),
    ({"time": (7, 1, 20, 20), "lat": 11}, {"chunk_mb": 0.013, "block_mb": 0.05}),
]


def _assert_model_equal(ref, out, rtol=1e-7):
    """Objective history, factors and every fitted predictive statistic agree."""
    np.testing.assert_allclose(out.objective_, ref.objective_, rtol=rtol)
    for name in ("X_", "Y_"):
        a, b = np.asarray(getattr(ref, name)), np.asarray(getattr(out, name))
        np.testing.assert_allclose(b, a, rtol=0, atol=rtol * np.abs(a).max() * 10)
    np.testing.assert_allclose(out.noise_std_, ref.noise_std_, rtol=rtol)
    for name in ("offset_", "scale_", "noise_var_"):
        a, b = getattr(ref, name), getattr(out, name)
        assert (a is None) == (b is None), name
        if a is not None:
            np.testing.assert_allclose(b, a, rtol=rtol * 10, atol=1e-12, err_msg=name)
    if ref.spatial_cov_ is None:
        assert out.spatial_cov_ is None
    else:
        ra, oa = ref.spatial_cov_.to_attrs(), out.spatial_cov_.to_attrs()
        assert ra.keys() == oa.keys()
        for key, v in ra.items():
            if not isinstance(v, float):
                assert oa[key] == v
        # the covariance itself, in units of the total variance: a white residual (sill or
        # nugget ~1e-9 of the other) leaves its range and small term ill-determined
        dr, dc = np.meshgrid([0.0, 1.0, 2.0, 5.0], [0.0, 1.0, 3.0], indexing="ij")
        total = ref.spatial_cov_.total_variance
        np.testing.assert_allclose(out.spatial_cov_.lattice(dr, dc),
                                   ref.spatial_cov_.lattice(dr, dc), rtol=1e-4,
                                   atol=1e-6 * total)
        np.testing.assert_allclose(out.spatial_cov_.nugget, ref.spatial_cov_.nugget,
                                   rtol=1e-4, atol=1e-6 * total)
    if getattr(ref, "dynamics_", None) is not None:
        for name in ("A", "Q", "mean", "initial_mean", "initial_cov"):
            np.testing.assert_allclose(getattr(out.dynamics_, name),
                                       getattr(ref.dynamics_, name), rtol=1e-5, atol=1e-9,
                                       err_msg=name)
    assert out.is_plain_low_rank == ref.is_plain_low_rank


@pytest.mark.parametrize("chunking", range(len(CHUNKINGS)))
@pytest.mark.parametrize("options", OPTIONS, ids=lambda o: ",".join(f"{k}={v}"
                                                                     for k, v in o.items()))
def test_every_option_same_model_as_in_memory(field, options, chunking):
    chunks, fit_options = CHUNKINGS[chunking]
    kw = dict(rank=3, max_iter=8, tol=0, random_state=3, progress=False, **options)
    ref = GLRM(**kw).fit(field)
    out = GLRM(**kw, dask=fit_options).fit(field.chunk(chunks))
    _assert_model_equal(ref, out)


def test_scale_floor_is_that_of_all_cells_not_of_a_chunk(field):
    """``scale=True`` floors a nearly constant cell's std at SCALE_FLOOR x the median std of
    *all* cells: the chunked fit finds it before standardizing, so every column chunk gets
    the in-memory model's floor (a chunk's own median would give another)."""
    data = field.copy()
    data[:, :4, :10] = data[:, :4, :10] * 1e-3  # one corner of tiny but non-zero variance
    data[:, 20:, 40:] = data[:, 20:, 40:] * 10.0  # another of large variance
    kw = dict(rank=3, max_iter=6, tol=0, random_state=3, progress=False, offset=True,
              scale=True)
    ref = GLRM(**kw).fit(data)
    sd = np.nanstd(ref.region_.stack(data).astype(float), axis=0)
    from lrm_cvx.glrm.predictive import SCALE_FLOOR

    np.testing.assert_allclose(ref.scale_, np.maximum(sd, SCALE_FLOOR * np.median(sd)),
                               rtol=1e-6)
    assert np.sum(ref.scale_ > sd * (1 + 1e-6)) >= 20  # the corner is floored
    out = GLRM(**kw, dask=SMALL_CHUNKS).fit(data.chunk({"time": 5}))
    _assert_model_equal(ref, out)


def test_options_on_array_with_mask_and_randomized_init():
    """(T, L) dask array + mask, above SMALL_SVD (randomized init), offset + scale + per-cell
    noise, converging by tol: the same model."""
    rng = np.random.default_rng(5)
    T, L, k = 40, SMALL_SVD // 40 + 300, 2
    D = (rng.standard_normal((T, k)) @ rng.standard_normal((k, L)) + 3.0
         + rng.standard_normal(L)).astype(np.float32)
    D += 0.05 * rng.standard_normal((T, L)).astype(np.float32)
    M = rng.random((T, L)) > 0.4
    M[:, 7] = False  # a cell never observed
    Dz = np.where(M, D, np.float32(1e30))  # outside the mask never read
    kw = dict(rank=k, max_iter=30, tol=1e-6, random_state=2, progress=False, offset=True,
              scale=True, noise="per-cell")
    ref = GLRM(**kw).fit(Dz, mask=M)
    out = GLRM(**kw, dask={"chunk_mb": 3}).fit(
        da.from_array(Dz, chunks=(9, -1)), mask=da.from_array(M, chunks=(9, -1)))
    assert out.converged_ == ref.converged_ and out.n_iter_ == ref.n_iter_
    _assert_model_equal(ref, out, rtol=1e-6)
    assert out.unobserved_cells_.tolist() == [7]


def test_dask_fitted_model_downstream(field):
    """complete, the planner and evaluate accept a model fitted on dask (keep_dask Y_ too)."""
    from lrm_cvx.evaluation import evaluate
    from lrm_cvx.planning import plan_greedy

    kw = dict(rank=3, max_iter=6, tol=0, random_state=0, progress=False, offset=True,
              noise="per-cell", spatial="exponential")
    ref = GLRM(**kw).fit(field.isel(time=slice(0, 40)))
    out = GLRM(**kw, dask={**SMALL_CHUNKS, "keep_dask": True}).fit(
        field.isel(time=slice(0, 40)).chunk({"time": 8}))
    assert is_dask_backed(out.Y_)
    snap = field.isel(time=44)
    for prior, spatial in ((None, False), ("empirical", True)):
        a = ref.complete(snap, prior=prior, spatial=spatial)
        b = out.complete(snap, prior=prior, spatial=spatial)
        for var in ("prediction", "std"):
            np.testing.assert_allclose(b[var].values, a[var].values, rtol=1e-4, atol=1e-6)
    p1 = plan_greedy(ref.Y_, ref.region_, 0, 20.0, progress=False, ridge=1e-6,
                     **ref.planner_kwargs())
    p2 = plan_greedy(out.Y_, out.region_, 0, 20.0, progress=False, ridge=1e-6,
                     **out.planner_kwargs())
    assert list(p1.cells) == list(p2.cells)
    e1 = evaluate(field, model=ref, n_test=4, budgets=(10,), n_starts=2,
                  methods=("greedy", "random"), progress=False,
                  paper=True,
                  planning=PlanningOptions(random_trials=2, certify=False),
                  scoring=ScoringOptions(min_observations=1))
    e2 = evaluate(field, model=out, n_test=4, budgets=(10,), n_starts=2,
                  methods=("greedy", "random"), progress=False,
                  paper=True,
                  planning=PlanningOptions(random_trials=2, certify=False),
                  scoring=ScoringOptions(min_observations=1))
    for var in e1.data_vars:  # fold-ins from ~10 cells amplify the 1e-8 factor differences
        if np.issubdtype(e1[var].dtype, np.number):
            np.testing.assert_allclose(e2[var].values, e1[var].values, rtol=2e-3, atol=1e-8,
                                       err_msg=var)


def test_rounds_make_two_passes():
    """Pass counter (quadratic.PASSES): the in-memory quadratic fit reads the data once for
    the checks, once to pack the mask, four times for the randomized-SVD init and twice a
    round; the dask fit's kernels read the staged data twice a round plus once per init
    product (its staging and preparation reads are file reads, counted apart)."""
    from lrm_cvx.glrm import quadratic as Q

    rng = np.random.default_rng(0)
    T, L, k = 24, SMALL_SVD // 24 + 100, 2
    D = (rng.standard_normal((T, k)) @ rng.standard_normal((k, L))).astype(np.float32)
    D += 0.1 * rng.standard_normal((T, L)).astype(np.float32)
    M = rng.random((T, L)) > 0.5
    D[~M] = 0
    kw = dict(rank=k, max_iter=5, tol=0, random_state=0, progress=False)
    Q.PASSES.reset()
    GLRM(**kw).fit(D, mask=M)
    assert Q.PASSES.passes(D.shape) == 1 + 1 + 4 + 2 * 5
    Q.PASSES.reset()
    GLRM(**{**kw, "max_iter": 9}).fit(D, mask=M)
    assert Q.PASSES.passes(D.shape) == 1 + 1 + 4 + 2 * 9
    Dn = np.where(M, D, np.nan)
    Q.PASSES.reset()
    GLRM(**kw, dask={"chunk_mb": 1.5}).fit(da.from_array(Dn, chunks=(6, -1)))
    # prepare (scan) 1, range 1, power 2, projection 1, rounds 2 x 5; no final pass
    assert Q.PASSES.passes(D.shape) == pytest.approx(1 + 1 + 2 + 1 + 2 * 5)


# ----------------------------------------------------- file-level staging of CDR files
@pytest.fixture(scope="module")
def cdr_files(tmp_path_factory):
    """Small CDR files (AVHRR, with QA flags, fill, out-of-range values and a cell never
    observed), tiled 8 x 16, plus VIIRS days in another folder."""
    from lrm_cvx.io import write_ndvi_cdr

    f = synthetic_field(14, (20, 36), rank=3, seed=9, noise=0.03, land_fraction=0.8)
    rng = np.random.default_rng(3)
    qa = np.where(rng.random(f.shape) < 0.2, 2, 0).astype(np.int16)  # cloudy bit
    qa[rng.random(f.shape) < 0.05] = -32767  # QA fill
    qa[rng.random(f.shape) < 0.05] = 1 << 4  # sunglint
    qa[rng.random(f.shape) < 0.05] = 1 << 6  # dense dark vegetation: not masked by default
    vals = f.values.copy()
    vals[:, 3, 5] = np.nan
    vals[rng.random(f.shape) < 0.03] = -0.5  # below valid_range once scaled (-5000)
    f = f.copy(data=vals)
    d1 = tmp_path_factory.mktemp("avhrr")
    write_ndvi_cdr(d1, f, qa=qa, chunks=(8, 16))
    d2 = tmp_path_factory.mktemp("viirs")
    vqa = rng.choice(np.array([0, 1, 2, 8, -32768, 1 << 10, 3, 64], np.int16), size=f.shape)
    write_ndvi_cdr(d2, f.isel(time=slice(0, 6)), start_date="2030-01-01", product="VIIRS",
                   qa=vqa[:6], chunks=None)
    return d1, d2


def _staged(store):
    return np.concatenate([np.load(f) for f in store.files], axis=1)


@pytest.mark.parametrize("bbox", [None, (-30.0, -100.0, 30.0, 100.0)])
@pytest.mark.parametrize("chunk_mb", [0.002, 0.01, 1.0])
def test_cdr_file_staging_bit_identical(cdr_files, tmp_path, bbox, chunk_mb):
    """The file-level path stages exactly what the dask-graph path stages (same region, same
    bounds, same bytes, NaN included), for several column chunkings and a bbox window."""
    from lrm_cvx.io import open_ndvi_cdr
    from lrm_cvx.io.staging import cdr_source

    d1, d2 = cdr_files
    lazy = open_ndvi_cdr([d1, d2], bbox=bbox, chunks={"time": 1})
    assert cdr_source(lazy) is not None
    assert cdr_source(lazy * 1.0) is None and cdr_source(lazy.isel(time=slice(1, 5))) is None
    tm: dict = {}
    fast, r1, t1, _ = stage(lazy, chunk_mb=chunk_mb, scratch_dir=str(tmp_path), timings=tm)
    assert {"stage_read", "stage_inflate", "stage_decode", "stage_write"} <= set(tm)
    assert tm["stage_inflate"] > 0  # the AVHRR files (tiled, zlib) took the raw-chunk reader
    other = lazy.copy(data=lazy.data + 0.0)  # same values, a different graph: the old path
    assert cdr_source(other) is None
    slow, r2, t2, _ = stage(other, chunk_mb=chunk_mb, scratch_dir=str(tmp_path))
    mem = open_ndvi_cdr([d1, d2], bbox=bbox)
    assert r1.equals(r2) and r1.equals(Region.from_dataarray(mem))
    assert r1.n_cells < r1.shape[0] * r1.shape[1]  # the compaction ran
    np.testing.assert_array_equal(fast.bounds, slow.bounds)
    got = _staged(fast)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got.view(np.uint32), _staged(slow).view(np.uint32))
    np.testing.assert_array_equal(got, r1.stack(mem).astype(np.float32))
    np.testing.assert_array_equal(t1.values, t2.values)
    # with a region given: no compaction, the same bytes
    st3, r3, *_ = stage(lazy, region=r1, chunk_mb=chunk_mb, scratch_dir=str(tmp_path))
    assert r3 is r1
    np.testing.assert_array_equal(_staged(st3).view(np.uint32), got.view(np.uint32))


@pytest.mark.parametrize("chunks", [(8, 16), (5, 7), (20, 36)])
def test_cdr_raw_chunk_staging_equals_loader(tmp_path, chunks):
    """The raw-chunk reader (h5py chunks, zlib, compiled decode) stages bit for bit what
    ``open_ndvi_cdr`` loads, for tiles that do and do not divide the grid, a window crossing
    the antimeridian (columns as an index array, not a slice), with and without shuffle."""
    import h5py

    from lrm_cvx.io import open_ndvi_cdr, write_ndvi_cdr

    f = synthetic_field(7, (20, 36), rank=3, seed=4, noise=0.03, land_fraction=0.8)
    f = f.assign_coords(lon=np.arange(36) * 10.0 - 175.0)
    vals = f.values.copy()
    vals[:, :2] = np.nan  # 72 cells never observed: whole column files of them at 0.0005 MB
    f = f.copy(data=vals)
    qa = np.where(np.random.default_rng(1).random(f.shape) < 0.3, 2, 0).astype(np.int16)
    write_ndvi_cdr(tmp_path / "d", f, qa=qa, chunks=chunks)
    with h5py.File(sorted((tmp_path / "d").glob("*.nc"))[0]) as h:
        assert h["NDVI"].compression == "gzip" and h["NDVI"].chunks == (1, *chunks)
    for bbox in (None, (-30.0, 150.0, 30.0, -150.0), (-20.0, -60.0, 10.0, 40.0)):
        lazy = open_ndvi_cdr(tmp_path / "d", bbox=bbox, chunks={"time": 1})
        mem = open_ndvi_cdr(tmp_path / "d", bbox=bbox)
        for chunk_mb in (0.0005, 1.0):
            tm: dict = {}
            st, reg, *_ = stage(lazy, chunk_mb=chunk_mb, scratch_dir=str(tmp_path), timings=tm)
            assert tm["stage_inflate"] > 0
            assert reg.equals(Region.from_dataarray(mem))
            want = reg.stack(mem).astype(np.float32)
            np.testing.assert_array_equal(_staged(st).view(np.uint32), want.view(np.uint32))
            assert sorted(os.listdir(st.directory)) == [
                f"data_{c:05d}.npy" for c in range(st.n_chunks)]
            shutil.rmtree(st.directory)


@pytest.mark.parametrize("shuffled", [True, False])
def test_decode_tile_equals_decode_day(shuffled):
    """The compiled tile decoder on byte-shuffled or plain little-endian int16 bytes equals
    ``decode_day`` on every cell of a sub-window, and ORs exactly the finite cells."""
    from lrm_cvx.io import ndvi as N
    from lrm_cvx.io.staging import _decode_tile

    rng = np.random.default_rng(5)
    cr, cc = 6, 10
    nd = rng.integers(-12000, 12000, (cr, cc)).astype(np.int16)
    nd[0, :3] = -9999
    qa = rng.choice(np.array([0, 2, 4, 16, 64, -32767], np.int16), (cr, cc))
    tables = N.decode_tables("AVHRR", N.DEFAULT_MASK_FLAGS["AVHRR"], N.file_encoding({}, {}))
    want = N.decode_day(nd, qa, tables)

    def raw(a):
        b = a.astype("<i2").ravel().view(np.uint8)
        return b.reshape(-1, 2).T.ravel().copy() if shuffled else b.copy()

    out = np.full((4, 7), 7.0, dtype=np.float32)
    seen = np.zeros_like(out, dtype=bool)
    _decode_tile(raw(nd), raw(qa), shuffled, cc, cr * cc, 1, 5, 2, 9, *tables,
                 np.float32(np.nan), out, 0, 0, seen, True)
    np.testing.assert_array_equal(out.view(np.uint32), want[1:5, 2:9].view(np.uint32))
    np.testing.assert_array_equal(seen, np.isfinite(want[1:5, 2:9]))
    assert 0 < seen.sum() < seen.size


def test_cdr_staging_with_stdlib_zlib(cdr_files, tmp_path, monkeypatch):
    """Without the optional ISA-L inflater the standard library's zlib stages the same bytes."""
    import zlib

    from lrm_cvx.io import open_ndvi_cdr, staging

    d1, _ = cdr_files
    lazy = open_ndvi_cdr(d1, chunks={"time": 1})
    ref, *_ = stage(lazy, chunk_mb=0.004, scratch_dir=str(tmp_path))
    monkeypatch.setattr(staging, "_zlib", lambda: zlib)
    tm: dict = {}
    got, *_ = stage(lazy, chunk_mb=0.004, scratch_dir=str(tmp_path), timings=tm)
    assert tm["stage_inflate"] > 0
    np.testing.assert_array_equal(_staged(got).view(np.uint32), _staged(ref).view(np.uint32))


def _first_chunk(path):
    """Byte offset and size of the first NDVI chunk of a CDR file."""
    import h5py

    with h5py.File(path) as h:
        info = h["NDVI"].id.get_chunk_info(0)
    return info.byte_offset, info.size


def test_cdr_staging_corrupt_or_truncated_file_names_it(tmp_path):
    """A file whose compressed chunk is damaged, or which was cut short after it was opened,
    is a DataError naming that file; nothing is left in the scratch directory."""
    from lrm_cvx.io import open_ndvi_cdr, write_ndvi_cdr

    f = synthetic_field(4, (20, 36), rank=2, seed=0, noise=0.05)
    for case in ("corrupt", "truncated"):
        d = tmp_path / case
        write_ndvi_cdr(d, f, chunks=(8, 16))
        lazy = open_ndvi_cdr(d, chunks={"time": 1})
        victim = sorted(d.glob("*.nc"))[2]
        data = bytearray(victim.read_bytes())
        off, size = _first_chunk(victim)
        if case == "corrupt":
            data[off + 2: off + size] = bytes((b ^ 0x5A) for b in data[off + 2: off + size])
        else:
            data = data[: len(data) // 2]
        victim.write_bytes(bytes(data))
        scratch = tmp_path / f"scratch-{case}"
        scratch.mkdir()
        with pytest.raises(DataError, match=victim.name):
            stage(lazy, scratch_dir=str(scratch))
        assert list(scratch.iterdir()) == []


def test_decode_tables_match_loader_on_every_code():
    """Table decoding equals the loader's elementwise rules on all 65 536 x a sample of codes."""
    from lrm_cvx.io import ndvi as N

    enc = N.file_encoding({}, {})
    codes = np.arange(65536, dtype=np.uint32).astype(np.uint16).view(np.int16)
    rng = np.random.default_rng(0)
    for product in ("AVHRR", "VIIRS"):
        flags = N.DEFAULT_MASK_FLAGS[product]
        tables = N.decode_tables(product, flags, enc)
        qa = rng.permutation(codes)
        got = N.decode_day(codes, qa, tables)
        ok = ((codes != -9999) & (codes >= -1000) & (codes <= 10000) & (qa != -32767)
              & ~N.decode_qa(qa, product, flags))
        want = np.where(ok, codes.astype(np.float32) * np.float32(1e-4), np.float32(np.nan))
        np.testing.assert_array_equal(got.view(np.uint32),
                                      want.astype(np.float32).view(np.uint32))


def test_cdr_file_staging_fit_equals_in_memory(cdr_files):
    from lrm_cvx.io import open_ndvi_cdr

    d1, _ = cdr_files
    tm: dict = {}
    ref, out = _pair(open_ndvi_cdr(d1), open_ndvi_cdr(d1, chunks={"time": 1}),
                     {"chunk_mb": 0.004, "timings": tm}, max_iter=6)
    assert "stage_read" in tm  # GLRM.fit took the file-level path
    _same_fit(ref, out, rtol=1e-8)
    assert out.region_.equals(ref.region_)


def test_cdr_file_staging_errors(tmp_path):
    from lrm_cvx.io import open_ndvi_cdr, write_ndvi_cdr

    f = synthetic_field(3, (6, 8), rank=1, seed=0)
    write_ndvi_cdr(tmp_path / "a", f.copy(data=np.full(f.shape, np.nan, np.float32)))
    lazy = open_ndvi_cdr(tmp_path / "a", chunks={"time": 1})
    with pytest.raises(DataError, match="every cell is missing"):
        stage(lazy, scratch_dir=str(tmp_path))
    write_ndvi_cdr(tmp_path / "b", f)
    lazy = open_ndvi_cdr(tmp_path / "b", chunks={"time": 1})
    bad = Region.from_dataarray(f.isel(lat=slice(0, 3)))
    from lrm_cvx.errors import RegionError

    with pytest.raises(RegionError):
        stage(lazy, region=bad, scratch_dir=str(tmp_path))
    victim = sorted((tmp_path / "b").glob("*.nc"))[1]
    victim.write_bytes(b"not a netcdf file")
    with pytest.raises(DataError, match="cannot read NDVI file"):
        stage(lazy, scratch_dir=str(tmp_path))


def test_cdr_file_staging_on_local_cluster(cdr_files, tmp_path):
    """With a distributed Client the day groups run on the workers (processes): same bytes."""
    distributed = pytest.importorskip("distributed")
    from lrm_cvx.io import open_ndvi_cdr

    d1, _ = cdr_files
    lazy = open_ndvi_cdr(d1, chunks={"time": 1})
    ref, r0, *_ = stage(lazy, chunk_mb=0.004, scratch_dir=str(tmp_path))  # threads
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                           dashboard_address=None, memory_limit="1GiB")
    try:
        with distributed.Client(cluster):
            got, r1, *_ = stage(lazy, chunk_mb=0.004, scratch_dir=str(tmp_path))
    finally:
        cluster.close()
    assert r1.equals(r0) and got.n_chunks == ref.n_chunks > 3
    np.testing.assert_array_equal(_staged(got).view(np.uint32), _staged(ref).view(np.uint32))


def test_chunk_files_load_as_numpy_saved_them(tmp_path):
    """The thread-safe chunk reader (`chunked._load`: the header parsed under a lock, a CPython
    3.11.7 race in `ast.literal_eval` seen in CI) returns what `np.save` wrote, C or Fortran
    order, any dtype the fit stages, and names a truncated file."""
    from concurrent.futures import ThreadPoolExecutor

    from lrm_cvx.glrm.chunked import _load

    rng = np.random.default_rng(0)
    arrays = [rng.normal(size=(7, 5)).astype(np.float32),
              np.asfortranarray(rng.normal(size=(4, 9))),
              rng.integers(0, 255, size=(3, 11), dtype=np.uint8),
              np.arange(6, dtype=np.int64)]
    paths = []
    for i, a in enumerate(arrays):
        paths.append(str(tmp_path / f"a{i}.npy"))
        np.save(paths[i], a)
    with ThreadPoolExecutor(4) as pool:  # many loads at once, as dask's threads do
        loaded = list(pool.map(_load, paths * 25))
    for got, path in zip(loaded, paths * 25, strict=True):
        want = np.load(path)
        assert got.dtype == want.dtype and got.flags.writeable
        np.testing.assert_array_equal(got, want)
    with open(paths[0], "r+b") as f:
        f.truncate(f.seek(0, 2) - 8)
    with pytest.raises(OSError, match="truncated chunk file"):
        _load(paths[0])
