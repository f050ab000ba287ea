"""rank="auto": the rank chosen with the temporal model by rolling-origin validation
(validation/selection.py, ``select_temporal(ranks=)``)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import xarray as xr

from lrm_cvx import GLRM
from lrm_cvx.cli import main
from lrm_cvx.errors import DataError, ModelError
from lrm_cvx.evaluation import PlanningOptions
from lrm_cvx.io.samples import synthetic_dynamic_field
from lrm_cvx.validation.refits import clone_model
from lrm_cvx.validation.selection import REFERENCE_RANK, format_selection, select_temporal


def _auto(data, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return GLRM(rank="auto", random_state=0, progress=False, **kw).fit(data)


@pytest.fixture(scope="module")
def rank8_field():
    """Eight persistent latent modes (A = 0.98), little noise: a forecast carries all eight.
    A grid large enough for the 50-cell designs, where eight modes pay (on a 10 x 12 grid only
    5 and 15 cells are scored, and ranks 5 and 8 tie within 2 %)."""
    return synthetic_dynamic_field(150, (14, 16), 8, seed=4, A=0.98 * np.eye(8),
                                   Q=(1 - 0.98 ** 2) * np.eye(8), freq="D", missing=0.1,
                                   noise=0.05)


@pytest.fixture(scope="module")
def rank2_field():
    return synthetic_dynamic_field(100, (10, 12), 2, seed=4, A=0.9 * np.eye(2),
                                   Q=0.1 * (1 - 0.81) * np.eye(2), freq="D", missing=0.1,
                                   noise=0.1)


def _best_per_rank(sel) -> dict[int, float]:
    """The lowest worst-size MSE ratio of each rank's candidates."""
    worst = sel["ratio"].max("size")
    return {int(r): float(worst.where(sel["rank"] == r).min())
            for r in np.unique(sel["rank"].values)}


def test_a_persistent_rank8_field_chooses_rank8(rank8_field):
    model = _auto(rank8_field, temporal="auto")
    sel = model.selection_
    assert model.rank_ == 8 == sel.attrs["choice_rank"]
    assert model.Y_.shape[0] == 8 and model.dynamics_.rank == 8
    assert sel.attrs["choice"].startswith("rank 8 ")
    # the reference is memoryless at rank 5; every rank was tried with every temporal kind
    assert sel["candidate"].values[0] == f"rank {REFERENCE_RANK} none"
    assert set(np.unique(sel["rank"].values)) == {3, 5, 8, 12}
    best = _best_per_rank(sel)
    assert best[8] == min(best.values()) and best[8] < best[3]
    # the final model is the chosen candidate fitted on all snapshots
    assert model.dynamics_.kind == sel.attrs["choice_kind"]
    assert model.residual_inflation_ == sel.attrs["choice_inflation"]


def test_a_rank2_field_memoryless_chooses_below_the_reference(rank2_field):
    model = _auto(rank2_field)
    sel = model.selection_
    assert model.dynamics_ is None and model.residual_inflation_ == 1.0
    assert set(sel["kind"].values) == {"none"}  # temporal=None: the rank alone
    assert model.rank_ < REFERENCE_RANK
    # the choice is the lowest worst ratio among the admissible candidates
    adm = sel["admissible"].values
    worst = sel["ratio"].max("size").values
    assert worst[list(sel["candidate"].values).index(sel.attrs["choice"])] == \
        worst[adm].min()


def test_refits_see_only_the_snapshots_before_their_window(rank8_field, refits):
    """Every validation refit (each rank, each window) is fitted on the snapshots before the
    window it is scored on, nothing after; the scored windows end at the last snapshot."""
    data = rank8_field.isel(time=slice(0, 100))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = GLRM(rank=5, random_state=0, progress=False).fit(data)
    sel = select_temporal(ref, data, ranks=(3, 5, 8), kinds=(), inflations=(1.0,), n_val=10)
    assert sorted((o.get("rank"), n) for o, n in refits) == sorted(
        (r, lo) for r in (3, 5, 8) for lo in (80, 90))
    assert sel.attrs["n_days"] == 20


def test_rank_auto_is_deterministic_and_paired(rank2_field):
    """Two fits give the same table; the ranks are scored on the same cells (paired): the
    reference rank's memoryless errors equal those of a selection offering it alone."""
    a, b = _auto(rank2_field).selection_, _auto(rank2_field).selection_
    xr.testing.assert_identical(a, b)
    assert a["candidate"].values[0] == f"rank {REFERENCE_RANK} none"
    assert float(a["ratio"].values[0].max()) == 1.0


def test_rank_auto_is_saved_cloned_and_printed(rank2_field, tmp_path):
    model = _auto(rank2_field)
    model.save(tmp_path / "m.nc")
    back = GLRM.load(tmp_path / "m.nc")
    assert back.rank == "auto" and back.rank_ == model.rank_
    xr.testing.assert_identical(back.selection_, model.selection_)
    assert clone_model(back).rank == model.rank_  # refits (calibration, placement) keep it
    text = format_selection(back.selection_)
    assert f"rank {model.rank_} none" in text and "chose" in text
    assert f"{back.selection_.attrs['choice']} " in text and text.count(" *") == 1


def test_the_printed_table_keeps_the_reference_the_choice_and_each_ranks_best(rank8_field):
    sel = _auto(rank8_field.isel(time=slice(0, 80)), temporal="auto").selection_
    lines = format_selection(sel).splitlines()
    rows = [ln.split("  ")[0].strip() for ln in lines[2:] if ln.startswith("rank ")]
    worst = sel["ratio"].max("size")
    best = {int(r): str(worst.where(sel["rank"] == r, drop=True).idxmin().item())
            for r in np.unique(sel["rank"].values)}
    assert rows[0] == f"rank {REFERENCE_RANK} none"
    assert set(rows) == {rows[0], sel.attrs["choice"], *best.values()}
    assert sel.sizes["candidate"] > len(rows)
    assert any("all in model.selection_" in ln for ln in lines)
    chosen = [ln for ln in lines if ln.endswith(" *")]
    assert len(chosen) == 1 and chosen[0].startswith(sel.attrs["choice"] + " ")


def test_rank_auto_bad_input(rank2_field):
    with pytest.raises(ModelError, match="rank must be an integer or 'auto'"):
        GLRM(rank="best", progress=False).fit(rank2_field)
    with pytest.raises(ModelError, match="temporal='auto' or None"):
        _auto(rank2_field, temporal="ar1")
    with pytest.raises(ModelError, match="rank='auto'"):
        GLRM(rank="auto", progress=False).fit(
            np.nan_to_num(rank2_field.values.reshape(100, -1)),
            mask=np.ones((100, 120), bool))
    with pytest.raises((ModelError, DataError), match="at least 8 snapshots"):
        _auto(rank2_field.isel(time=slice(0, 5)))
    # a short record: the ranks its earliest window cannot carry are skipped and named
    sel = _auto(rank2_field.isel(time=slice(0, 20))).selection_
    assert "rank 8" in sel.attrs["skipped"] and "rank 12" in sel.attrs["skipped"]
    with pytest.raises(ModelError, match="none of the ranks"):
        select_temporal(_auto(rank2_field.isel(time=slice(0, 20))),
                        rank2_field.isel(time=slice(0, 20)), ranks=(40,), kinds=())
    with pytest.raises(ModelError, match="positive integers"):
        select_temporal(_auto(rank2_field.isel(time=slice(0, 20))),
                        rank2_field.isel(time=slice(0, 20)), ranks=(0, 3), kinds=())


def test_cli_fit_rank_auto(rank2_field, tmp_path, capsys):
    path = tmp_path / "d.nc"
    rank2_field.rename("v").to_netcdf(path)
    assert main(["fit", str(path), "--rank", "auto", "--paper", "-o",
                 str(tmp_path / "m.nc")]) == 0
    out = capsys.readouterr().out
    model = GLRM.load(tmp_path / "m.nc")
    assert f"fitted rank-{model.rank_} GLRM" in out
    assert main(["fit", str(path), "--rank", "many", "-o", str(tmp_path / "x.nc")]) != 0
    assert "--rank: must be an integer >= 1 or 'auto'" in capsys.readouterr().err
    assert not (tmp_path / "x.nc").exists()



def test_evaluate_with_rank_auto():
    """evaluate's own fit (memoryless protocol) validates the rank on the training snapshots
    only; the result records the rank fitted. (A field whose 44 training snapshots favour
    rank 3 over 5 by 5 %; the module's rank-2 field ties the two there.)"""
    from lrm_cvx import evaluate

    rank2_field = synthetic_dynamic_field(100, (10, 12), 2, seed=6, A=0.9 * np.eye(2),
                                          Q=0.1 * (1 - 0.81) * np.eye(2), freq="D",
                                          missing=0.1, noise=0.1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = evaluate(rank2_field.isel(time=slice(0, 48)), rank="auto", n_test=4,
                       budgets=(4,), n_starts=1, methods=("greedy",),
                       progress=False, paper=True,
                       planning=PlanningOptions(certify=False))
        ref = _auto(rank2_field.isel(time=slice(0, 44)))
    assert res.attrs["rank"] == ref.rank_ < REFERENCE_RANK
