"""The CLI's defaults: the recommended setting unless ``--paper``.

No flag gives the same outputs as ``--recommended``; ``--paper`` gives the paper's outputs
(checked against the paper's Python calls); an explicit option beats either setting; ``--paper
--recommended`` is one line; a recommended default the input cannot take falls back with one
printed note (fit's ``temporal="auto"``, plan's / predict's spatial residual).
"""

from __future__ import annotations

import inspect

import numpy as np
import pandas as pd
import pytest
import xarray as xr

from lrm_cvx import cli_fit
from lrm_cvx.cli import main
from lrm_cvx.evaluation import METHODS, PlanningOptions, ScoringOptions, evaluate
from lrm_cvx.glrm import GLRM
from lrm_cvx.planning import plan_greedy
from lrm_cvx.recommended import RECOMMENDED

LAT = -30 + 2.0 * np.arange(6)
LON = -80 + 2.0 * np.arange(8)
START = (-24.0, -70.0)


def _field(T: int = 16, seed: int = 0) -> xr.DataArray:
    """A monthly rank-2 field with a smooth residual, 10% missing."""
    rng = np.random.default_rng(seed)
    k, ny, nx = 2, LAT.size, LON.size
    v = (rng.normal(size=(T, k)) @ rng.normal(size=(k, ny * nx))
         + 0.1 * rng.normal(size=(T, ny * nx))).reshape(T, ny, nx)
    v[rng.random(v.shape) < 0.1] = np.nan
    return xr.DataArray(v, dims=("time", "lat", "lon"), name="sst",
                        coords={"time": pd.date_range("2000-01-01", periods=T, freq="MS"),
                                "lat": LAT, "lon": LON}, attrs={"units": "K"})


def _run(*argv) -> int:
    return main(["-q", *map(str, argv)])


def _notes(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.startswith("note: ")]


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """The field, and the models ``fit`` writes with no flag, ``--recommended`` and
    ``--paper`` (rank 2, seed 0)."""
    root = tmp_path_factory.mktemp("defaults")
    da = _field()
    da.to_netcdf(root / "field.nc")
    snap = da.isel(time=-1).to_dataframe().dropna().reset_index()
    snap[["lat", "lon", "sst"]].iloc[::4].rename(columns={"sst": "value"}).to_csv(
        root / "obs.csv", index=False)
    for name, flags in (("default", []), ("recommended", ["--recommended"]),
                        ("paper", ["--paper"])):
        assert _run("fit", root / "field.nc", "--rank", 2, *flags, "-o",
                    root / f"{name}.nc") == 0
    return root, da


def _glrm_recommended() -> dict:
    own = set(inspect.signature(GLRM).parameters)
    return {k: v for k, v in RECOMMENDED.items() if k in own}


# ----------------------------------------------------------------------------- fit
def test_fit_default_is_the_recommended_fit(files):
    root, da = files
    default, rec = GLRM.load(root / "default.nc"), GLRM.load(root / "recommended.nc")
    ref = GLRM(rank=2, random_state=0, progress=False, **_glrm_recommended()).fit(da)
    assert default.offset and default.spatial == RECOMMENDED["spatial"]
    assert default.temporal == RECOMMENDED["temporal"] and default.selection_ is not None
    for model in (default, rec):
        np.testing.assert_allclose(model.Y_, ref.Y_, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(model.offset_, ref.offset_, rtol=1e-6, atol=1e-9)
        for key in ("sill", "range", "nugget"):
            assert getattr(model.spatial_cov_, key) == pytest.approx(
                getattr(ref.spatial_cov_, key), rel=1e-6)
        assert model.selection_.attrs["choice"] == ref.selection_.attrs["choice"]
        # the recommended fit calibrates its intervals, as GLRM(calibration=...) does
        assert model.calibration == RECOMMENDED["calibration"]
        np.testing.assert_equal(model.calibration_.to_attrs(), ref.calibration_.to_attrs())
    assert xr.load_dataset(root / "default.nc").equals(xr.load_dataset(root / "recommended.nc"))


def test_fit_paper_is_the_paper_fit(files):
    root, da = files
    paper = GLRM.load(root / "paper.nc")
    ref = GLRM(rank=2, random_state=0, progress=False).fit(da)
    np.testing.assert_allclose(paper.Y_, ref.Y_, rtol=1e-6, atol=1e-9)
    assert not paper.offset and paper.spatial is None and paper.temporal is None
    assert paper.spatial_cov_ is None and paper.dynamics_ is None and paper.selection_ is None


def test_explicit_model_options_beat_either_setting(files, tmp_path):
    root, _ = files
    assert _run("fit", root / "field.nc", "--rank", 2, "--paper", "--spatial", "matern32",
                "-o", tmp_path / "a.nc") == 0
    a = GLRM.load(tmp_path / "a.nc")
    assert a.spatial == "matern32" and not a.offset and a.temporal is None
    assert _run("fit", root / "field.nc", "--rank", 2, "--temporal", "none", "--spatial",
                "gaussian", "-o", tmp_path / "b.nc") == 0
    b = GLRM.load(tmp_path / "b.nc")
    assert b.spatial == "gaussian" and b.offset and b.temporal is None and b.selection_ is None


def test_a_glrm_key_added_to_recommended_reaches_the_fit(files, tmp_path, monkeypatch):
    root, _ = files
    monkeypatch.setitem(RECOMMENDED, "scale", True)
    assert _run("fit", root / "field.nc", "--rank", 2, "--temporal", "none", "-o",
                tmp_path / "s.nc") == 0
    assert GLRM.load(tmp_path / "s.nc").scale is True
    assert _run("fit", root / "field.nc", "--rank", 2, "--paper", "-o", tmp_path / "p.nc") == 0
    assert GLRM.load(tmp_path / "p.nc").scale is False
    assert "--scale" in cli_fit.recommended_fit()
    assert "--calibration" not in cli_fit.recommended_fit()  # no such option: said in words


def test_residual_scale_flag(files, tmp_path, capsys, monkeypatch):
    root, _ = files
    assert _run("fit", root / "field.nc", "--rank", 2, "--temporal", "none",
                "--residual-scale", "-o", tmp_path / "r.nc") == 0
    m = GLRM.load(tmp_path / "r.nc")
    assert m.scale == "residual" and m.scale_ is not None and m.offset
    assert "scale=residual" in capsys.readouterr().out
    assert _run("fit", root / "field.nc", "--rank", 2, "--scale", "--residual-scale", "-o",
                tmp_path / "x.nc") != 0
    assert "exclude each other" in capsys.readouterr().err
    monkeypatch.setitem(RECOMMENDED, "scale", "residual")
    assert "--residual-scale" in cli_fit.recommended_fit()


@pytest.mark.parametrize("kind, why", [
    ("five", "at least 8 snapshots"),
    ("irregular", "regularly spaced"),
    ("no-time", "time coordinate"),
])
def test_fit_falls_back_to_no_dynamics_with_one_note(files, tmp_path, capsys, kind, why):
    da = _field()
    data = {"five": da.isel(time=slice(0, 5)),
            "irregular": da.isel(time=[0, 1, 2, 4, 7, 11, 12, 13, 15]),
            "no-time": da.drop_vars("time")}[kind]
    path = tmp_path / f"{kind}.nc"
    data.to_netcdf(path)
    capsys.readouterr()
    assert _run("fit", path, "--rank", 2, "-o", tmp_path / "m.nc") == 0
    out = capsys.readouterr().out
    notes = _notes(out)
    auto = [n for n in notes if "temporal='auto'" in n]
    assert len(auto) == 1 and why in auto[0], out
    # the only other note a fallback may add: a record too short for the calibration's refits
    assert all("calibration" in n for n in notes if n not in auto), out
    model = GLRM.load(tmp_path / "m.nc")
    assert model.temporal is None and model.dynamics_ is None and model.selection_ is None
    assert (model.calibration_ is None) == (len(notes) == 2)
    assert model.offset and model.spatial == RECOMMENDED["spatial"]  # the rest stays
    # asked for explicitly, auto keeps its one-line error
    assert _run("fit", path, "--rank", 2, "--temporal", "auto", "-o", tmp_path / "x.nc") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("lrm-cvx fit: error:") and "auto" in err[0]
    assert not (tmp_path / "x.nc").exists()


@pytest.mark.parametrize("kind", ["good", "five", "irregular", "no-time", "unsorted"])
def test_auto_unavailable_agrees_with_the_fit(kind):
    """The pre-check fit's fallback relies on says no exactly when GLRM(temporal="auto")
    fails on the data."""
    from lrm_cvx.errors import LrmError
    from lrm_cvx.validation.selection import auto_unavailable

    da = _field()
    data = {"good": da, "five": da.isel(time=slice(0, 5)),
            "irregular": da.isel(time=[0, 1, 2, 4, 7, 11, 12, 13, 15]),
            "no-time": da.drop_vars("time"), "unsorted": da.isel(time=np.r_[1, 0, 2:16])}[kind]
    why = auto_unavailable(data)
    model = GLRM(rank=2, temporal="auto", random_state=0, progress=False)
    if why is None:
        assert model.fit(data).selection_ is not None
    else:
        assert "temporal='auto'" in why or "time" in why
        with pytest.raises(LrmError):
            model.fit(data)
    assert (why is None) == (kind == "good")


def test_fit_notes_the_fallback_after_hold_out(files, tmp_path, capsys):
    root, _ = files
    capsys.readouterr()
    assert _run("fit", root / "field.nc", "--rank", 2, "--hold-out", 10, "-o",
                tmp_path / "m.nc") == 0
    notes = _notes(capsys.readouterr().out)
    assert len([n for n in notes if "temporal='auto'" in n]) == 1
    assert GLRM.load(tmp_path / "m.nc").selection_ is None


def test_fit_notes_a_record_too_short_to_calibrate(files, tmp_path, capsys):
    """On 4 snapshots no refit of the recommended calibration can carry rank 2 with an offset:
    one note, the model is saved uncalibrated (its calibration parameter None). On 6 the
    blocks whose refit can are used (before, the first block's refit failed the
    whole calibration)."""
    root, _ = files
    capsys.readouterr()
    assert _run("fit", root / "field.nc", "--rank", 2, "--hold-out", 12, "-o",
                tmp_path / "s.nc") == 0
    notes = [n for n in _notes(capsys.readouterr().out) if "calibration" in n]
    assert len(notes) == 1 and "uncalibrated" in notes[0] and "cannot refit rank 2" in notes[0]
    short = GLRM.load(tmp_path / "s.nc")
    assert short.calibration_ is None and short.calibration is None
    assert _run("fit", root / "field.nc", "--rank", 2, "--hold-out", 10, "-o",
                tmp_path / "s6.nc") == 0
    assert not [n for n in _notes(capsys.readouterr().out) if "calibration" in n]
    assert GLRM.load(tmp_path / "s6.nc").calibration_ is not None


# -------------------------------------------------------------------- one-line refusal
@pytest.mark.parametrize("argv", [
    ["fit", "field.nc", "-o", "x.nc"],
    ["plan", "model.nc", "--start", "-24,-70", "--budget", "4"],
    ["bound", "model.nc", "--start", "-24,-70", "--budget", "4"],
    ["predict", "model.nc", "--observations", "obs.csv", "-o", "x.nc"],
    ["evaluate", "field.nc", "--out", "ev"],
    ["monitor", "plan", "state.nc", "--start", "-24,-70", "--budget", "4", "-o", "p.csv"],
])
def test_paper_and_recommended_together_is_one_line(argv, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)  # no input exists: the refusal comes before any file is read
    assert _run(*argv, "--paper", "--recommended") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--paper and --recommended exclude each other" in err[0]
    command = " ".join(argv[:2]) if argv[0] == "monitor" else argv[0]  # a monitor step too
    assert err[0].startswith(f"lrm-cvx {command}: error:")
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- plan
def _route(path) -> np.ndarray:
    return pd.read_csv(path)["cell"].to_numpy()


def test_plan_default_is_recommended_and_paper_is_the_paper(files, tmp_path, capsys):
    root, _ = files
    model_path = root / "default.nc"
    routes = {}
    for name, flags in (("default", []), ("recommended", ["--recommended"]),
                        ("paper", ["--paper"]),
                        ("old", ["--criterion", "fisher", "--prior", "none", "--initial",
                                 "nearest"])):
        routes[name] = tmp_path / f"{name}.csv"
        assert _run("plan", model_path, "--start", *START, "--budget", 6, *flags, "-o",
                    routes[name]) == 0
    assert _notes(capsys.readouterr().out) == []  # a spatial model takes every default
    model = GLRM.load(model_path)
    rec = plan_greedy(model.Y_, model.region_, START, 6, criterion="gp-variance",
                      initial="start", progress=False, refine=RECOMMENDED["refine"],
                      **model.planner_kwargs(prior="empirical", spatial=True))
    paper = plan_greedy(model.Y_, model.region_, START, 6, criterion="fisher",
                        initial="nearest", progress=False)
    np.testing.assert_array_equal(_route(routes["default"]), rec.route)
    np.testing.assert_array_equal(_route(routes["recommended"]), rec.route)
    np.testing.assert_array_equal(_route(routes["paper"]), paper.route)
    np.testing.assert_array_equal(_route(routes["old"]), paper.route)
    assert not np.array_equal(rec.route, paper.route)  # the two settings differ here


def test_plan_on_a_paper_model_falls_back_with_one_note(files, tmp_path, capsys):
    root, _ = files
    model_path = root / "paper.nc"
    capsys.readouterr()
    assert _run("plan", model_path, "--start", *START, "--budget", 6, "-o",
                tmp_path / "r.csv") == 0
    out = capsys.readouterr().out
    notes = _notes(out)
    assert len(notes) == 1 and "gp-variance" in notes[0] and "fisher" in notes[0], out
    model = GLRM.load(model_path)
    kw = model.planner_kwargs(prior="empirical")
    ref = plan_greedy(model.Y_, model.region_, START, 6, criterion="fisher", initial="start",
                      progress=False, **kw)
    np.testing.assert_array_equal(_route(tmp_path / "r.csv"), ref.route)
    # bound plans the same way
    assert _run("bound", model_path, "--start", *START, "--budget", 6) == 0
    assert len(_notes(capsys.readouterr().out)) == 1
    # asked for explicitly, gp-variance keeps its one-line error
    assert _run("plan", model_path, "--start", *START, "--budget", 6, "--criterion",
                "gp-variance") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "spatial covariance" in err[0]
    # with --paper nothing falls back: no note
    assert _run("plan", model_path, "--start", *START, "--budget", 6, "--paper") == 0
    assert _notes(capsys.readouterr().out) == []


# ----------------------------------------------------------------------------- predict
def test_predict_defaults(files, tmp_path, capsys):
    root, _ = files
    obs = pd.read_csv(root / "obs.csv")
    maps = {}
    for model_name, name, flags in (
            ("default", "default", []), ("default", "recommended", ["--recommended"]),
            ("default", "paper", ["--paper"]),
            ("default", "explicit", ["--paper", "--prior", "empirical", "--spatial"]),
            ("paper", "fallback", [])):
        out = tmp_path / f"{name}.nc"
        capsys.readouterr()
        assert _run("predict", root / f"{model_name}.nc", "--observations", root / "obs.csv",
                    *flags, "-o", out) == 0
        assert len(_notes(capsys.readouterr().out)) == (name == "fallback")
        maps[name] = xr.load_dataset(out)
    model, paper_model = GLRM.load(root / "default.nc"), GLRM.load(root / "paper.nc")
    cells = model.region_.cell_of(obs["lat"].to_numpy(), obs["lon"].to_numpy())
    values = obs["value"].to_numpy()
    refs = {"recommended": model.complete((cells, values), prior="empirical", spatial=True),
            "paper": model.complete((cells, values)),
            "fallback": paper_model.complete((cells, values), prior="empirical")}
    refs["default"] = refs["explicit"] = refs["recommended"]
    for name, ref in refs.items():
        for var in ("prediction", "std"):
            np.testing.assert_allclose(maps[name][var], ref[var], rtol=1e-6, atol=1e-9,
                                       err_msg=name)
    assert not np.allclose(refs["recommended"]["prediction"], refs["paper"]["prediction"])


# ----------------------------------------------------------------------------- evaluate
TINY = ["--rank", "2", "--n-test", "3", "--starts", "1", "--random-trials", "1",
        "--budgets", "4,8", "--min-observations", "1", "--certify", "off"]


def test_evaluate_default_is_recommended_and_paper_is_the_paper(files, tmp_path):
    root, da = files
    got = {}
    for name, flags in (("default", []), ("recommended", ["--recommended"]),
                        ("paper", ["--paper"])):
        assert _run("evaluate", root / "field.nc", *TINY, *flags, "--out",
                    tmp_path / name) == 0
        got[name] = xr.load_dataset(tmp_path / name / "results.nc")
    kw = dict(rank=2, n_test=3, n_starts=1, budgets=(4, 8), progress=False)
    planning = PlanningOptions(random_trials=1, certify=False, criterion="fisher")
    params = {k: v for k, v in _glrm_recommended().items() if k != "temporal"}
    rec = evaluate(da, methods=(RECOMMENDED["method"], *METHODS), planning=planning,
                   scoring=ScoringOptions(min_observations=1,
                                          model_params={**params, "noise": "global"},
                                          fold_in={"prior": RECOMMENDED["prior"], "spatial": True}),
                   **kw)
    paper = evaluate(da, methods=METHODS, paper=True, planning=planning,
                     scoring=ScoringOptions(min_observations=1, model_params={"noise": "global"}),
                     **kw)
    for name, ref in (("default", rec), ("recommended", rec), ("paper", paper)):
        assert list(got[name]["method"].values) == list(ref["method"].values), name
        np.testing.assert_allclose(got[name]["mse"], ref["mse"], rtol=1e-6, equal_nan=True,
                                   err_msg=name)
        np.testing.assert_array_equal(got[name]["greedy_route"], ref["greedy_route"])
    assert "'offset': True" in got["default"].attrs["model_params"]
    assert "offset" not in got["paper"].attrs["model_params"]


# ----------------------------------------------------------------------------- monitor
def _state(root, model, tmp_path, name):
    state = tmp_path / f"{name}.nc"
    assert _run("monitor", "init", root / f"{model}.nc", "--state", state, "--memoryless") == 0
    return state


def test_monitor_plan_defaults(files, tmp_path, capsys, monkeypatch):
    root, _ = files
    spatial = _state(root, "default", tmp_path, "spatial")
    plain = _state(root, "paper", tmp_path, "plain")
    plans = {}
    for state, name, flags in (
            (spatial, "default", []), (spatial, "recommended", ["--recommended"]),
            (spatial, "explicit-rec", ["--paper", "--criterion", "gp-variance", "--initial",
                                       "start"]),
            (spatial, "paper", ["--paper"]),
            (spatial, "explicit-paper", ["--criterion", "fisher", "--initial", "nearest"]),
            (plain, "fallback", []), (plain, "explicit-fallback", ["--criterion", "fisher"])):
        out = tmp_path / f"{name}.csv"
        capsys.readouterr()
        assert _run("monitor", "plan", state, "--start", *START, "--budget", 6, *flags,
                    "-o", out) == 0
        notes = _notes(capsys.readouterr().out)
        assert len(notes) == (name == "fallback"), (name, notes)
        plans[name] = _route(out)
    np.testing.assert_array_equal(plans["default"], plans["recommended"])
    # the explicit flags under --paper are the recommended planner without its route check
    monkeypatch.setitem(RECOMMENDED, "refine", None)
    unchecked = tmp_path / "unchecked.csv"
    assert _run("monitor", "plan", spatial, "--start", *START, "--budget", 6, "-o",
                unchecked) == 0
    np.testing.assert_array_equal(_route(unchecked), plans["explicit-rec"])
    np.testing.assert_array_equal(plans["paper"], plans["explicit-paper"])
    np.testing.assert_array_equal(plans["fallback"], plans["explicit-fallback"])
    assert not np.array_equal(plans["default"], plans["paper"])
