"""The command line: bad or unusual inputs as a new user types them.

Every case asserts the outcome (exit status 2 and one line ``lrm-cvx <cmd>: error: ...`` naming
the problem, or the correct result) AND that no input file changed (``inputs_unchanged``,
tests/conftest.py: SHA-256 of every input before and after). Outputs that must not exist are
checked too. Data lie in the southern and western hemispheres so every coordinate is negative.
"""

from __future__ import annotations

import errno
import json
import os
import subprocess
import sys
from importlib import resources
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import xarray as xr

from lrm_cvx import cli, cli_fit
from lrm_cvx.cli import main
from lrm_cvx.evaluation import PlanningOptions, ScoringOptions
from lrm_cvx.glrm import GLRM

LAT = -30 + 2.0 * np.arange(6)  # -30 .. -20
LON = -80 + 2.0 * np.arange(8)  # -80 .. -66


# ---------------------------------------------------------------------------- fixtures
def _field(T: int = 14, seed: int = 0) -> xr.DataArray:
    rng = np.random.default_rng(seed)
    k, ny, nx = 2, LAT.size, LON.size
    v = (rng.normal(size=(T, k)) @ rng.normal(size=(k, ny * nx))
         + 0.05 * rng.normal(size=(T, ny * nx))).reshape(T, ny, nx)
    v[rng.random(v.shape) < 0.1] = np.nan
    return xr.DataArray(v.astype(np.float32), dims=("time", "lat", "lon"), name="sst",
                        coords={"time": pd.date_range("2000-01-01", periods=T, freq="MS"),
                                "lat": LAT, "lon": LON}, attrs={"units": "K"})


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """d/a.nc, d/b.nc (two halves in time), m/model.nc (offset + spatial), m/plain.nc (paper
    model), m/noregion.nc (fitted on an array), m/obs.csv, ev/results.nc (a data file named like
    evaluate's output)."""
    root = tmp_path_factory.mktemp("bad")
    d, m, ev = root / "d", root / "m", root / "ev"
    for p in (d, m, ev):
        p.mkdir()
    da = _field()
    da.isel(time=slice(0, 7)).to_netcdf(d / "a.nc")
    da.isel(time=slice(7, None)).to_netcdf(d / "b.nc")
    da.to_netcdf(ev / "results.nc")
    GLRM(2, offset=True, spatial="exponential", random_state=0, progress=False).fit(da).save(
        m / "model.nc")
    GLRM(2, random_state=0, progress=False).fit(da).save(m / "plain.nc")
    GLRM(2, random_state=0, progress=False).fit(np.nan_to_num(da.values.reshape(14, -1))).save(
        m / "noregion.nc")
    snap = da.isel(time=-1).to_dataframe().dropna().reset_index()
    snap[["lat", "lon", "sst"]].head(10).rename(columns={"sst": "value"}).to_csv(
        m / "obs.csv", index=False)
    return {"root": root, "d": d, "m": m, "ev": ev, "a": d / "a.nc", "b": d / "b.nc",
            "model": m / "model.nc", "plain": m / "plain.nc", "noregion": m / "noregion.nc",
            "obs": m / "obs.csv", "results": ev / "results.nc"}


@pytest.fixture
def run(files, inputs_unchanged, capsys, monkeypatch):
    """``run(argv)`` -> (status, stdout, stderr), with every fixture file watched; ``{key}`` in
    an argument is replaced by that fixture path."""
    inputs_unchanged.watch(files["d"], files["m"], files["ev"])
    monkeypatch.chdir(files["root"])

    def go(argv):
        argv = [a.format(**{k: str(v) for k, v in files.items()}) for a in argv]
        code = main(["-q", *argv])
        out, err = capsys.readouterr()
        return code, out, err

    return go


def one_line_error(err: str, cmd: str, *needles: str) -> None:
    """Exactly one error line (one-line warnings may precede it), naming every needle."""
    prefix = f"lrm-cvx {cmd}" if cmd else "lrm-cvx"
    lines = err.strip().splitlines()
    assert all(line.startswith(f"{prefix}: warning: ") for line in lines[:-1]), err
    assert lines[-1].startswith(f"{prefix}: error: "), err
    assert "Traceback" not in err
    for needle in needles:
        assert needle in lines[-1], (needle, lines[-1])


def leftovers(folder: Path) -> list[str]:
    """Temporary files an interrupted write would leave."""
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


# ------------------------------------------------------------------ never write onto an input
REFUSE_INPUT = [
    # the three data-loss cases
    (["fit", "{d}/*.nc", "--var", "sst", "--rank", "2", "-o", "{d}/a.nc"], "fit"),
    (["fit", "{d}", "--var", "sst", "--rank", "2", "-o", "{d}/b.nc"], "fit"),
    (["evaluate", "{ev}/results.nc", "--out", "{ev}"], "evaluate"),
    # the same with --overwrite: an input is never replaced
    (["fit", "{d}/*.nc", "--rank", "2", "-o", "{d}/a.nc", "--overwrite"], "fit"),
    (["fit", "{d}", "--rank", "2", "-o", "{d}/b.nc", "--overwrite"], "fit"),
    (["evaluate", "{ev}/results.nc", "--out", "{ev}", "--overwrite"], "evaluate"),
    # the literal path, a relative path, a detour through '..'
    (["fit", "{a}", "--rank", "2", "-o", "{a}", "--overwrite"], "fit"),
    (["fit", "d/a.nc", "--rank", "2", "-o", "d/a.nc"], "fit"),
    (["fit", "{a}", "--rank", "2", "-o", "{m}/../d/a.nc", "--overwrite"], "fit"),
    (["fit", "d/[ab].nc", "--rank", "2", "-o", "d/b.nc", "--overwrite"], "fit"),
    (["fit", "{a}", "{b}", "--rank", "2", "-o", "{b}", "--overwrite"], "fit"),
    # predict: the model and the observations are inputs
    (["predict", "{model}", "--observations", "{obs}", "-o", "{model}", "--overwrite"],
     "predict"),
    (["predict", "{model}", "--observations", "{obs}", "-o", "{obs}", "--overwrite"], "predict"),
]


@pytest.mark.parametrize("argv, cmd", REFUSE_INPUT)
def test_refuses_to_write_onto_an_input(run, argv, cmd):
    code, out, err = run(argv)
    assert code == 2
    one_line_error(err, cmd, "refusing to overwrite the input file")
    assert out == ""


def test_refuses_a_symlink_to_an_input(run, files, tmp_path):
    link = tmp_path / "link.nc"
    link.symlink_to(files["a"])
    code, _, err = run(["fit", "{a}", "--rank", "2", "-o", str(link), "--overwrite"])
    assert code == 2
    one_line_error(err, "fit", "input file")
    assert link.is_symlink()


def test_refuses_a_hard_link_to_an_input(run, files, tmp_path):
    link = tmp_path / "hard.nc"
    os.link(files["a"], link)
    code, _, err = run(["fit", "{a}", "--rank", "2", "-o", str(link), "--overwrite"])
    assert code == 2
    one_line_error(err, "fit", "input file")


def test_refuses_the_package_sample_file(run, monkeypatch):
    """``fit sample:sst -o <installed sst.nc>``: the guard must refuse before any work (the load
    is replaced by a tripwire, so a broken guard cannot damage the package)."""
    def tripwire(args):
        raise AssertionError("the guard let the command run")

    monkeypatch.setattr(cli_fit, "load_data", tripwire)
    target = resources.files("lrm_cvx") / "data" / "sst.nc"
    code, _, err = run(["fit", "sample:sst", "-o", str(target), "--overwrite"])
    assert code == 2
    one_line_error(err, "fit", "input file")


# ---------------------------------------------------------------------------- the overwrite rule
def test_existing_output_needs_overwrite(run, files, tmp_path):
    out = tmp_path / "model.nc"
    out.write_text("old")
    code, _, err = run(["fit", "{a}", "--rank", "2", "-o", str(out)])
    assert code == 2
    one_line_error(err, "fit", "already exists", "--overwrite")
    assert out.read_text() == "old"


def test_overwrite_replaces_an_output_that_is_not_an_input(run, tmp_path):
    out = tmp_path / "model.nc"
    out.write_text("old")
    code, stdout, err = run(["fit", "{d}/*.nc", "--rank", "2", "-o", str(out), "--overwrite"])
    assert code == 0, err
    assert GLRM.load(out).X_.sizes["time"] == 14
    assert leftovers(tmp_path) == []


def test_folder_input_writes_a_new_file_beside_its_data(run, files):
    out = files["root"] / "new-model.nc"
    code, _, err = run(["fit", "{d}", "--var", "sst", "--rank", "2", "-o", str(out)])
    assert code == 0, err
    assert GLRM.load(out).region_.n_cells == LAT.size * LON.size
    out.unlink()


@pytest.mark.parametrize("argv, cmd, needle", [
    (["fit", "{a}", "--rank", "2", "-o", "{m}"], "fit", "folder"),
    (["fit", "{a}", "--rank", "2", "-o", "{m}", "--overwrite"], "fit", "folder"),
    (["fit", "{a}", "--rank", "2", "-o", "{obs}/x.nc"], "fit", "not a folder"),
    (["predict", "{model}", "--observations", "{obs}", "-o", "{d}"], "predict", "folder"),
    (["plan", "{model}", "--start", "-25,-70", "--budget", "4", "-o", "{m}/r.txt"], "plan",
     ".csv, .geojson"),
    (["plan", "{model}", "--start", "-25,-70", "--budget", "4", "-o", "{obs}"], "plan",
     "already exists"),
    (["evaluate", "{a}", "--out", "{obs}"], "evaluate", "existing file"),
    (["fit", "{a}", "--rank", "2", "-o", "{d}/*.nc"], "fit", "glob pattern"),
    (["evaluate", "{a}", "--out", "{ev}"], "evaluate", "already exists"),
])
def test_bad_output_paths(run, argv, cmd, needle):
    code, _, err = run(argv)
    assert code == 2
    one_line_error(err, cmd, needle)


# ---------------------------------------------------------------------------- failing writes
def test_crash_while_writing_keeps_the_old_file(run, tmp_path, monkeypatch):
    out = tmp_path / "model.nc"
    out.write_text("old")

    def crash(self, *a, **k):
        Path(a[0]).write_text("half a file")
        raise RuntimeError("killed mid-write")

    monkeypatch.setattr(xr.Dataset, "to_netcdf", crash)
    code, _, err = run(["fit", "{a}", "--rank", "2", "-o", str(out), "--overwrite"])
    assert code == 2
    one_line_error(err, "fit", "unexpected RuntimeError", "killed mid-write", "--debug")
    assert out.read_text() == "old"
    assert leftovers(tmp_path) == []


def test_disk_full_keeps_the_old_file(run, tmp_path, monkeypatch):
    out = tmp_path / "model.nc"
    out.write_text("old")

    def full(src, dst):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(dst))

    monkeypatch.setattr(os, "replace", full)
    code, _, err = run(["fit", "{a}", "--rank", "2", "-o", str(out), "--overwrite"])
    assert code == 2
    one_line_error(err, "fit", "No space left on device", str(out))
    assert out.read_text() == "old"
    assert leftovers(tmp_path) == []


def test_unwritable_folder_fails_before_any_work(run, tmp_path, monkeypatch):
    import tempfile

    def denied(*a, **k):
        raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(tmp_path))

    def tripwire(args):
        raise AssertionError("loaded the data before checking the output folder")

    monkeypatch.setattr(tempfile, "mkstemp", denied)
    monkeypatch.setattr(cli_fit, "load_data", tripwire)
    code, _, err = run(["fit", "{a}", "--rank", "2", "-o", str(tmp_path / "m.nc")])
    assert code == 2
    one_line_error(err, "fit", "Permission denied")
    assert list(tmp_path.iterdir()) == []


EVAL = ["evaluate", "{a}", "{b}", "--rank", "2", "--n-test", "2", "--starts", "1",
        "--random-trials", "1", "--budgets", "3,6", "--min-observations", "1",
        "--certify", "off"]


def test_evaluate_failing_figure_writes_nothing(run, tmp_path, monkeypatch):
    import lrm_cvx.plots

    def broken(*a, **k):
        raise ValueError("cannot draw")

    monkeypatch.setattr(lrm_cvx.plots, "plot_predictions", broken)
    out = tmp_path / "ev"
    code, _, err = run([*EVAL, "--out", str(out)])
    assert code == 2
    one_line_error(err, "evaluate", "cannot draw")
    assert not out.exists()


def test_evaluate_failing_last_write_writes_nothing(run, tmp_path, monkeypatch):
    """The pdf of the last figure fails: results.nc and summary.csv must not appear either."""
    import matplotlib.figure

    real = matplotlib.figure.Figure.savefig

    def pdf_fails(self, fname, *a, format=None, **k):
        if format == "pdf":
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(fname))
        return real(self, fname, *a, format=format, **k)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", pdf_fails)
    out = tmp_path / "ev"
    out.mkdir()
    (out / "results.nc").write_text("previous run")
    code, _, err = run([*EVAL, "--out", str(out), "--overwrite"])
    assert code == 2
    one_line_error(err, "evaluate", "No space left on device")
    assert sorted(p.name for p in out.iterdir()) == ["results.nc"]
    assert (out / "results.nc").read_text() == "previous run"


def test_evaluate_writes_all_outputs(run, tmp_path):
    out = tmp_path / "ev"
    code, stdout, err = run([*EVAL, "--out", str(out)])
    assert code == 0, err
    assert sorted(p.name for p in out.iterdir()) == sorted(cli.EVALUATION_FILES)
    assert xr.load_dataset(out / "results.nc").attrs["n_test"] == 2


# ---------------------------------------------------------------------------- coordinates
@pytest.mark.parametrize("start", [["-25", "-70"], ["-25,-70"], ["-25,", "-70"],
                                   ["-2.5e1", "-70.0"]])
def test_negative_start_in_every_form(run, start, tmp_path):
    route = tmp_path / "r.csv"
    code, _, err = run(["plan", "{model}", "--start", *start, "--budget", "4",
                        "-o", str(route)])
    assert code == 0, err
    first = pd.read_csv(route).iloc[0]
    assert first["lat"] in (-26.0, -24.0) and first["lon"] == -70.0


def test_start_equals_form(run):
    code, out, err = run(["plan", "{model}", "--start=-25,-70", "--budget", "4"])
    assert code == 0, err
    assert "cells" in out


@pytest.mark.parametrize("bbox", [["-28,-78,-22,-70"], ["-28", "-78", "-22", "-70"]])
def test_negative_bbox(run, bbox, tmp_path):
    out = tmp_path / "m.nc"
    code, _, err = run(["fit", "{a}", "{b}", "--bbox", *bbox, "--rank", "2", "-o", str(out)])
    assert code == 0, err
    region = GLRM.load(out).region_
    assert region.lat.values.min() >= -28 and region.lon.values.max() <= -70


@pytest.mark.parametrize("argv, cmd, needle", [
    (["plan", "{model}", "--start", "-25", "--budget", "4"], "plan", "LAT,LON"),
    (["plan", "{model}", "--start", "-25,-70,3", "--budget", "4"], "plan", "LAT,LON"),
    (["plan", "{model}", "--start", "south,-70", "--budget", "4"], "plan", "numbers"),
    (["plan", "{model}", "--start", "-100,-70", "--budget", "4"], "plan", "[-90, 90]"),
    (["plan", "{model}", "--start", "-70,-100", "--budget", "4"], "plan", "outside"),
    (["plan", "{model}", "--start", "nan,-70", "--budget", "4"], "plan", "finite"),
    (["plan", "{model}", "--start", "10,10", "--budget", "4"], "plan", "outside"),
    (["fit", "{a}", "--bbox", "-20,-80,-30,-60", "-o", "x.nc"], "fit", "south (-20)"),
    (["fit", "{a}", "--bbox", "-20,-80,-30", "-o", "x.nc"], "fit", "S,W,N,E"),
    (["fit", "{a}", "--bbox", "10,10,20,20", "-o", "x.nc"], "fit", "bbox"),
])
def test_bad_coordinates(run, argv, cmd, needle, files):
    code, _, err = run(argv)
    assert code == 2
    one_line_error(err, cmd, needle)
    assert not (files["root"] / "x.nc").exists()


# ---------------------------------------------------------------------------- argparse
@pytest.mark.parametrize("argv, cmd, needle", [
    ([], "", "required"),
    (["frobnicate"], "", "invalid choice"),
    (["fit", "{a}"], "fit", "-o/--output"),
    (["fit", "{a}", "-o", "x.nc", "--frobnicate"], "", "unrecognized arguments"),
    (["fit", "{a}", "-o", "x.nc", "--rank", "0"], "fit", "integer >= 1"),
    (["fit", "{a}", "-o", "x.nc", "--rank", "two"], "fit", "integer >= 1"),
    (["fit", "{a}", "-o", "x.nc", "--loss", "l3"], "fit", "invalid choice"),
    (["fit", "{a}", "-o", "x.nc", "--spatial", "cubic"], "fit", "invalid choice"),
    (["fit", "{a}", "-o", "x.nc", "--tol", "inf"], "fit", "finite"),
    (["plan", "{model}", "--budget", "4"], "plan", "--start"),
    (["plan", "{model}", "--start", "-25,-70", "--budget", "four"], "plan", "number"),
    (["plan", "{model}", "--start", "-25,-70", "--budget", "4", "--criterion", "dopt"], "plan",
     "invalid choice"),
    (["plan", "{model}", "--start", "-25,-70", "--budget", "4", "--cost", "tsp"], "plan",
     "invalid choice"),
    (["plan", "{model}", "--start", "-25,-70", "--budget", "4", "--prior", "flat"], "plan",
     "invalid choice"),
    (["bound", "{model}", "--start", "-25,-70", "--budget", "4", "--certify", "off"], "bound",
     "invalid choice"),
    (["evaluate", "{a}", "--out", "x", "--starts", "0"], "evaluate", "integer >= 1"),
    (["evaluate", "{a}", "--out", "x", "--n-test", "-1"], "evaluate", "integer >= 1"),
    (["evaluate", "{a}", "--out", "x", "--certify", "maybe"], "evaluate", "invalid choice"),
])
def test_argparse_errors_are_one_line(run, argv, cmd, needle, files):
    code, out, err = run(argv)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "usage:" not in err, err
    assert lines[0].startswith(f"lrm-cvx {cmd}: error: " if cmd else "lrm-cvx"), err
    assert needle in lines[0]
    assert not (files["root"] / "x.nc").exists() and not (files["root"] / "x").exists()


def test_help_exits_0(run):
    code, out, _ = run(["fit", "--help"])
    assert code == 0 and "--recommended" in out and "--overwrite" in out


# ------------------------------------------------------------------ library errors, one line
@pytest.mark.parametrize("argv, cmd, needle", [
    (["plan", "{model}", "--start", "-25,-70", "--budget", "-1"], "plan", "budget"),
    (["plan", "{noregion}", "--start", "-25,-70", "--budget", "4"], "plan", "no region"),
    (["bound", "{noregion}", "--start", "-25,-70", "--budget", "4"], "bound", "no region"),
    (["predict", "{noregion}", "--observations", "{obs}", "-o", "p.nc"], "predict", "no region"),
    (["plan", "{a}", "--start", "-25,-70", "--budget", "4"], "plan", "not an lrm-cvx GLRM"),
    (["plan", "missing.nc", "--start", "-25,-70", "--budget", "4"], "plan", "does not exist"),
    (["plan", "{plain}", "--start", "-25,-70", "--budget", "4", "--criterion", "gp-variance"],
     "plan", "spatial covariance"),
    (["plan", "{plain}", "--start", "-25,-70", "--budget", "4", "--paper", "--criterion",
      "gp-variance"], "plan", "spatial covariance"),
    (["predict", "{plain}", "--observations", "{obs}", "--spatial", "-o", "p.nc"], "predict",
     "spatial covariance"),
    (["plan", "{model}", "--start", "-25,-70", "--budget", "4", "--initial", "far"], "plan",
     "initial"),
    (["plan", "{model}", "--start", "-25,-70", "--budget", "4", "--criterion", "gp-variance",
      "--prior", "none"], "plan", "--prior empirical"),
    (["fit", "missing/*.nc", "-o", "x.nc"], "fit", "no file matches"),
    (["fit", "missing.nc", "-o", "x.nc"], "fit", "not found"),
    (["fit", "{a}", "--var", "temp", "-o", "x.nc"], "fit", "no variable 'temp'"),
    (["fit", "{m}", "-o", "x.nc"], "fit", "cannot"),
    (["evaluate", "{a}", "--out", "x", "--methods", "greedy,zigzag"], "evaluate", "zigzag"),
    (["evaluate", "{a}", "--out", "x", "--paper", "--methods", "greedy:gp-variance"],
     "evaluate", "--spatial"),
    (["evaluate", "{a}", "--out", "x", "--paper", "--fold-spatial"], "evaluate", "--spatial"),
    (["evaluate", "{a}", "--out", "x", "--budgets", "5,x"], "evaluate", "--budgets"),
    (["evaluate", "{a}", "--out", "x", "--budgets", "-5"], "evaluate", "--budgets"),
    (["evaluate", "{a}", "--out", "x", "--n-test", "7"], "evaluate", "--n-test"),
    (["evaluate", "{a}", "{b}", "--out", "x", "--rank", "2", "--n-test", "2", "--starts", "500",
      "--certify", "off"], "evaluate", "exceeds"),
    (["plan", "{model}", "--start", "-25,-70", "--budget", "4", "--ridge", "-1"], "plan",
     "ridge"),
    (["predict", "{model}", "--observations", "{obs}", "--ridge", "-1", "-o", "p.nc"],
     "predict", "ridge"),
    (["fit", "{a}", "--tol", "-1", "-o", "x.nc"], "fit", "tol"),
    (["fit", "{a}", "--rank", "100", "-o", "x.nc"], "fit", "rank"),
    (["plan", "{plain}", "--start", "-25,-70", "--budget", "4", "--paper", "--criterion",
      "a-optimal"], "plan", "ridge > 0"),
])
def test_library_errors_are_one_line(run, argv, cmd, needle, files):
    code, _, err = run(argv)
    assert code == 2
    one_line_error(err, cmd, needle)
    for name in ("x.nc", "x", "p.nc"):
        assert not (files["root"] / name).exists()


@pytest.mark.parametrize("content, needle", [
    ("", "cannot read"),
    ("lat,lon\n-25,-70\n", "'value' column"),
    ("value,depth\n1.0,3\n", "'cell' column or 'lat'"),
    ("lat,lon,value\n-25,-70,warm\n", "'value' must hold numbers"),
    ("lat,lon,value\n", "no rows"),
    ("lat,lon,value\n10,10,1.0\n", "outside"),
    ("cell,value\n100000,1.0\n", "cell"),
    ("cell,value\n12.7,1.0\n30,2\n", "integer"),
    ("cell,value\n-1,1.0\n", "cell"),
    ("lat,lon,value\nnan,-70,1.0\n", "finite"),
    ("cell,value\n12,inf\n13,1\n", "finite"),
    ("cell,value\n12,\n30,2.0\n", "singular"),
])
def test_bad_observation_files(run, tmp_path, inputs_unchanged, content, needle, files):
    obs = tmp_path / "obs.csv"
    obs.write_text(content)
    inputs_unchanged.watch(obs)
    code, _, err = run(["predict", "{model}", "--observations", str(obs), "--paper", "-o",
                        str(tmp_path / "p.nc")])
    assert code == 2
    one_line_error(err, "predict", needle)
    assert not (tmp_path / "p.nc").exists()


def test_missing_observation_file(run, tmp_path):
    code, _, err = run(["predict", "{model}", "--observations", str(tmp_path / "none.csv"),
                        "-o", str(tmp_path / "p.nc")])
    assert code == 2
    one_line_error(err, "predict", "cannot read --observations")


def test_empty_data_file(run, tmp_path, inputs_unchanged):
    empty = tmp_path / "empty.nc"
    empty.write_bytes(b"")
    inputs_unchanged.watch(empty)
    code, _, err = run(["fit", str(empty), "-o", str(tmp_path / "m.nc")])
    assert code == 2
    one_line_error(err, "fit", "empty.nc")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty.nc"]


# ------------------------------------------------------------------ unexpected errors, --debug
def test_unexpected_error_is_one_line_and_debug_shows_traceback(run, monkeypatch, tmp_path):
    def bug(self, *a, **k):
        raise ZeroDivisionError("a bug")

    monkeypatch.setattr(GLRM, "fit", bug)
    argv = ["fit", "{a}", "--rank", "2", "-o", str(tmp_path / "m.nc")]
    code, _, err = run(argv)
    assert code == 2
    one_line_error(err, "fit", "unexpected ZeroDivisionError: a bug", "--debug")
    for with_debug in (["--debug", *argv], [*argv, "--debug"]):  # before or after the command
        code, _, err = run(with_debug)
        assert code == 2
        assert "Traceback" in err and "ZeroDivisionError" in err
        assert err.strip().splitlines()[-1].startswith("lrm-cvx fit: error: unexpected")
    assert list(tmp_path.iterdir()) == []


def test_warnings_are_one_line(run, files, tmp_path, inputs_unchanged):
    """Unsorted times: evaluate sorts them with a one-line warning and tests on the latest."""
    da = _field().isel(time=np.r_[13, 0:13])
    path = tmp_path / "shuffled.nc"
    da.to_netcdf(path)
    inputs_unchanged.watch(path)
    out = tmp_path / "ev"
    code, _, err = run([*EVAL[:1], str(path), *EVAL[3:], "--out", str(out)])
    assert code == 0, err
    warn = [line for line in err.splitlines() if "warning" in line]
    assert warn and all(line.startswith("lrm-cvx evaluate: warning: ") for line in warn)
    test_times = xr.load_dataset(out / "results.nc")["test_time"].values
    np.testing.assert_array_equal(test_times, np.sort(da["time"].values)[-2:])


# ---------------------------------------------------------------------------- as a process
def test_subprocess_one_line_error_and_negative_start(files, inputs_unchanged, tmp_path):
    inputs_unchanged.watch(files["d"], files["m"])
    exe = [sys.executable, "-m", "lrm_cvx.cli", "-q"]
    bad = subprocess.run([*exe, "fit", f"{files['d']}/*.nc", "-o", str(files["a"])],
                         capture_output=True, text=True, timeout=300)
    assert bad.returncode == 2
    one_line_error(bad.stderr, "fit", "input file")
    route = tmp_path / "route.geojson"
    ok = subprocess.run([*exe, "plan", str(files["model"]), "--start", "-25", "-70", "--budget",
                         "4", "-o", str(route)], capture_output=True, text=True, timeout=300)
    assert ok.returncode == 0, ok.stderr
    assert json.loads(route.read_text())["type"] == "FeatureCollection"


# ---------------------------------------------------------------------------- Python save functions
def _plan(model_path):
    from lrm_cvx.planning import plan_greedy

    model = GLRM.load(model_path)
    return plan_greedy(model.Y_, model.region_, (-25, -70), 4, progress=False)


def _save_figure(path):
    import matplotlib.pyplot as plt

    from lrm_cvx.plots import save_figure

    fig = plt.figure()
    try:
        save_figure(fig, path)
    finally:
        plt.close(fig)


def _failing_replace(src, dst):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(dst))


@pytest.mark.parametrize("name, write", [
    ("model.nc", lambda files, path: GLRM.load(files["model"]).save(path)),
    ("route.csv", lambda files, path: _plan(files["model"]).to_csv(path)),
    ("route.geojson", lambda files, path: _plan(files["model"]).to_geojson(path)),
    ("fig", lambda files, path: _save_figure(path)),
])
def test_python_save_functions_are_atomic(files, inputs_unchanged, tmp_path, monkeypatch, name,
                                          write):
    """A full disk at the final rename: the old file stays, no temporary file is left."""
    inputs_unchanged.watch(files["m"])
    target = tmp_path / name
    old = [target.with_suffix(s) for s in (".png", ".pdf")] if name == "fig" else [target]
    for path in old:
        path.write_text("old")
    monkeypatch.setattr(os, "replace", _failing_replace)
    with pytest.raises(OSError, match="No space"):
        write(files, target)
    assert all(p.read_text() == "old" for p in old)
    assert leftovers(tmp_path) == []
    monkeypatch.undo()
    write(files, target)
    assert all(p.read_bytes() != b"old" for p in old)


def test_save_results_is_atomic(files, inputs_unchanged, tmp_path, monkeypatch):
    from lrm_cvx.evaluation import evaluate, save_results

    inputs_unchanged.watch(files["d"])
    res = evaluate(_field(), rank=2, n_test=2, budgets=(3,), n_starts=1,
                   progress=False,
                   planning=PlanningOptions(random_trials=1, certify=False),
                   scoring=ScoringOptions(min_observations=1))
    (tmp_path / "results.nc").write_text("old")
    monkeypatch.setattr(os, "replace", _failing_replace)
    with pytest.raises(OSError):
        save_results(res, tmp_path)
    assert (tmp_path / "results.nc").read_text() == "old"
    assert leftovers(tmp_path) == []


def test_atomic_outputs_is_all_or_nothing(tmp_path):
    from lrm_cvx._validation import atomic_outputs

    a, b = tmp_path / "a.txt", tmp_path / "new" / "deeper" / "b.txt"
    a.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_outputs([a, b]) as (ta, tb):
            ta.write_text("new a")
            raise RuntimeError("second write failed")
    assert a.read_text() == "old" and not (tmp_path / "new").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]
    with atomic_outputs([a, b]) as (ta, tb):
        ta.write_text("new a")
        tb.write_text("b")
    assert a.read_text() == "new a" and b.read_text() == "b"
    mode = os.stat(b).st_mode & 0o777
    umask = os.umask(0)
    os.umask(umask)
    assert mode == 0o666 & ~umask  # a normal file's permissions, not mkstemp's 0600


def test_guard_outputs(tmp_path):
    from lrm_cvx._validation import guard_outputs

    src = tmp_path / "in.nc"
    src.write_text("data")
    with pytest.raises(FileExistsError, match="input file"):
        guard_outputs([tmp_path / "x" / ".." / "in.nc"], [src], overwrite=True)
    with pytest.raises(FileExistsError, match="--overwrite"):
        guard_outputs([src], [])
    with pytest.raises(IsADirectoryError, match="folder"):
        guard_outputs([tmp_path], [], overwrite=True)
    assert guard_outputs([src], [], overwrite=True) == [src]
    assert guard_outputs([tmp_path / "new.nc"], [src]) == [tmp_path / "new.nc"]
    assert src.read_text() == "data"


@pytest.mark.parametrize("argv, joined", [
    (["plan", "m", "--start", "-10", "150"], ["plan", "m", "--start=-10,150"]),
    (["plan", "m", "--start", "-10,150", "--budget", "5"],
     ["plan", "m", "--start=-10,150", "--budget", "5"]),
    (["--start", "-1e1", "-.5", "m"], ["--start=-1e1,-.5", "m"]),
    (["--bbox", "-20", "-80,10", "-60", "f.nc"], ["--bbox=-20,-80,10,-60", "f.nc"]),
    (["--start", "m.nc"], ["--start", "m.nc"]),
    (["--", "--start", "-1", "2"], ["--", "--start", "-1", "2"]),
])
def test_join_coordinates(argv, joined):
    assert cli._join_coordinates(argv) == joined


# ---------------------------------------------------------------------------- unusual data files
def _unusual(kind: str) -> xr.DataArray | str:
    da = _field()
    if kind == "all-nan":
        return da.where(False)
    if kind == "one-nan-snapshot":
        return da.where(da["time"] != da["time"][3])
    if kind == "duplicate-times":
        return da.assign_coords(time=np.r_[da["time"].values[:7], da["time"].values[:7]])
    if kind in ("nan-lat", "inf-lon"):
        dim = kind.split("-")[1]
        c = da[dim].values.copy()
        c[2] = np.nan if kind == "nan-lat" else np.inf
        return da.assign_coords({dim: c})
    if kind == "one-snapshot":
        return da.isel(time=[0])
    if kind == "inf-cell":  # one cell of fill values decoded as inf: named, not dropped
        v = da.copy()
        v[:, 1, 1] = np.inf
        return v
    if kind == "fill-value-1e20":
        v = da.copy()
        v[0, 0, 0] = 1e20
        return v
    if kind == "descending-lat":
        return da.isel(lat=slice(None, None, -1))
    return "not a NetCDF file"


@pytest.mark.parametrize("kind, code, needle", [
    ("all-nan", 2, "no finite value"),
    ("duplicate-times", 2, "more than once"),
    ("nan-lat", 2, "non-finite"),
    ("inf-lon", 2, "non-finite"),
    ("one-snapshot", 2, "rank"),
    ("text", 2, "cannot read"),
    ("one-nan-snapshot", 0, "all-NaN"),
    ("inf-cell", 2, "non-finite observed values (inf)"),
    ("fill-value-1e20", 0, "1e+20"),
    ("descending-lat", 0, ""),
])
def test_unusual_data_files(run, tmp_path, inputs_unchanged, kind, code, needle):
    path = tmp_path / f"{kind}.nc"
    data = _unusual(kind)
    if isinstance(data, str):
        path.write_text(data)
    else:
        data.to_netcdf(path)
    inputs_unchanged.watch(path)
    out = tmp_path / "model.nc"
    got, _, err = run(["fit", str(path), "--rank", "2", "--paper", "-o", str(out)])
    assert got == code, err
    if code:
        one_line_error(err, "fit", needle)
        assert not out.exists()
    else:
        assert all(line.startswith("lrm-cvx fit: warning: ") for line in err.splitlines())
        assert needle in err
        model = GLRM.load(out)
        region = model.region_
        cell = region.cell_of(-30.0, -78.0)  # a corner cell keeps its own coordinates
        assert (region.cell_lat[cell], region.cell_lon[cell]) == (-30.0, -78.0)


def _input_file(tmp_path: Path, da: xr.DataArray, name: str, guard) -> str:
    """``da`` written to ``tmp_path/in/name`` (a folder of its own, watched by ``guard``)."""
    path = tmp_path / "in" / name
    path.parent.mkdir()
    da.to_netcdf(path)
    guard.watch(path.parent)
    return str(path)


def test_fit_refuses_a_latitude_beyond_a_pole(run, inputs_unchanged, tmp_path):
    da = _field().assign_coords(lat=LAT + 120.0)  # 90 .. 100: colatitudes, or a typo
    path = _input_file(tmp_path, da, "polar.nc", inputs_unchanged)
    out = tmp_path / "m.nc"
    code, _, err = run(["fit", path, "--rank", "2", "-o", str(out)])
    assert code == 2
    one_line_error(err, "fit", "coordinate lat is 92", "[-90, 90]")
    assert not out.exists()


def test_hold_out_on_unsorted_times_holds_out_the_last_times(run, inputs_unchanged, tmp_path):
    da = _field()
    order = [0, 1, 2, 3, 12, 4, 5, 6, 13, 7, 8, 9, 10, 11]  # the two latest months mid-file
    path = _input_file(tmp_path, da.isel(time=order), "shuffled.nc", inputs_unchanged)
    out = tmp_path / "m.nc"
    code, stdout, err = run(["fit", path, "--hold-out", "2", "--rank", "2", "--paper", "-o",
                             str(out)])
    assert code == 0, err
    assert "time is not sorted; snapshots were sorted by time" in err
    assert ("held out the last 2 of 14 snapshots (2001-01-01T00:00:00 .. 2001-02-01T00:00:00)"
            in stdout)
    fitted = GLRM.load(out).X_["time"].values
    np.testing.assert_array_equal(fitted, da["time"].values[:12])


def test_hold_out_on_duplicate_times_is_refused(run, inputs_unchanged, tmp_path):
    da = _field()
    da = da.assign_coords(time=da["time"].values[[*range(13), 12]])
    path = _input_file(tmp_path, da, "twice.nc", inputs_unchanged)
    code, _, err = run(["fit", path, "--hold-out", "1", "--rank", "2", "-o",
                        str(tmp_path / "m.nc")])
    assert code == 2
    one_line_error(err, "fit", "2001-01-01", "more than once")
    assert not (tmp_path / "m.nc").exists()


def test_bbox_across_the_antimeridian_on_a_0_360_record(run, inputs_unchanged, tmp_path):
    rng = np.random.default_rng(3)
    lon = np.arange(0.0, 360.0, 5.0)
    T, ny = 12, LAT.size
    v = (rng.normal(size=(T, 2)) @ rng.normal(size=(2, ny * lon.size))
         + 0.05 * rng.normal(size=(T, ny * lon.size))).reshape(T, ny, lon.size)
    da = xr.DataArray(v.astype(np.float32), dims=("time", "lat", "lon"), name="sst",
                      coords={"time": pd.date_range("2000-01-01", periods=T, freq="MS"),
                              "lat": LAT, "lon": lon})
    path = _input_file(tmp_path, da, "global.nc", inputs_unchanged)
    out = tmp_path / "m.nc"
    code, _, err = run(["fit", path, "--bbox", "-30,170,-20,-170", "--rank", "2", "--paper",
                        "-o", str(out)])
    assert code == 0, err
    region = GLRM.load(out).region_
    np.testing.assert_array_equal(region.lon.values, np.arange(170.0, 191, 5))  # not 0 .. 360
    # a route across the antimeridian: a MultiLineString cut exactly on it (RFC 7946 3.1.9)
    route = tmp_path / "route.geojson"
    code, _, err = run(["plan", str(out), "--start", "-26,185", "--budget", "12", "--paper",
                        "-o", str(route)])
    assert code == 0, err
    geometry = json.loads(route.read_text())["features"][0]["geometry"]
    assert geometry["type"] == "MultiLineString"
    pieces = geometry["coordinates"]
    for piece in pieces:
        xs = np.array([x for x, _ in piece])
        assert len(piece) >= 2 and (np.all(xs >= 170) or np.all(xs <= -170))
        assert np.any(np.abs(xs) < 180)  # no part along the meridian
        assert all(p != q for p, q in zip(piece[:-1], piece[1:], strict=True))  # no repeats
    for a, b in zip(pieces[:-1], pieces[1:], strict=True):
        assert abs(a[-1][0]) == 180 and b[0] == [-a[-1][0], a[-1][1]]


def test_one_cell_bbox_is_a_clear_error(run, tmp_path):
    code, _, err = run(["fit", "{a}", "--bbox", "-30.5,-80.5,-29.5,-79.5", "--rank", "2", "-o",
                        str(tmp_path / "m.nc")])
    assert code == 2
    one_line_error(err, "fit", "rank")


def test_budget_zero_reports_the_forced_cells_honestly(run):
    code, out, err = run(["plan", "{plain}", "--start", "-24", "-70", "--budget", "0",
                          "--paper"])
    assert code == 0, err
    assert "> (forced initial cells) budget 0" in out and "<=" not in out
    assert err.startswith("lrm-cvx plan: warning: ") and "initial cells" in err


def test_huge_budget_covers_the_region(run, files, tmp_path):
    route = tmp_path / "r.csv"
    code, out, err = run(["plan", "{plain}", "--start", "-24", "-70", "--budget", "1e9", "-o",
                          str(route)])
    assert code == 0, err
    n_cells = GLRM.load(files["plain"]).region_.n_cells
    assert pd.read_csv(route)["cell"].nunique() == n_cells
    assert f"{n_cells} cells" in out and "<= budget 1e+09" in out


def test_ctrl_c_during_the_write_keeps_the_old_file(run, tmp_path, monkeypatch):
    out = tmp_path / "model.nc"
    out.write_text("old")

    def interrupted(self, *a, **k):
        Path(a[0]).write_text("half")
        raise KeyboardInterrupt

    monkeypatch.setattr(xr.Dataset, "to_netcdf", interrupted)
    code, _, err = run(["fit", "{a}", "--rank", "2", "-o", str(out), "--overwrite"])
    assert code == 130 and err.strip() == "lrm-cvx fit: interrupted"
    assert out.read_text() == "old" and leftovers(tmp_path) == []


# ------------------------------------------------------------- trust: files, locks, crashes
def _state(run, tmp_path, model="{model}"):
    state = tmp_path / "state.nc"
    code, _, err = run(["monitor", "init", model, "--state", str(state), "--temporal", "ar1"])
    assert code == 0, err
    return state


@pytest.mark.parametrize("step", ["map", "plan"])
def test_the_state_model_is_never_an_output(run, files, tmp_path, step):
    # the model a state points to is an input of every monitor step: --overwrite or not
    state = _state(run, tmp_path)
    argv = {"map": ["monitor", "map", str(state)],
            "plan": ["monitor", "plan", str(state), "--start", "-24,-70", "--budget", "3"]}
    out = files["model"].with_suffix(".png" if step == "map" else ".csv")
    out.symlink_to(files["model"])  # the model under a name the step accepts
    try:
        code, _, err = run([*argv[step], "-o", str(out), "--overwrite"])
    finally:
        out.unlink()
    assert code == 2
    one_line_error(err, f"monitor {step}", "input file", "model.nc")
    assert GLRM.load(files["model"]).rank == 2


def test_stale_temporary_files_are_removed_by_the_next_write(run, tmp_path):
    state = _state(run, tmp_path)
    legacy = tmp_path / ".state.nc.k2j3h4g5.tmp"  # killed before PIDs were recorded, 1 h ago
    dead = tmp_path / ".state.nc.999999999.ab12cd34.tmp"  # its writer is gone
    live = tmp_path / f".state.nc.{os.getpid()}.ef56gh78.tmp"  # a write still in progress
    for p in (legacy, dead, live):
        p.write_bytes(b"")
    os.utime(legacy, (os.path.getmtime(legacy) - 3600,) * 2)
    obs = tmp_path / "obs.csv"
    pd.DataFrame({"lat": [-24.0, -26.0], "lon": [-70.0, -74.0], "value": [0.1, 0.2]}).to_csv(
        obs, index=False)
    code, _, err = run(["monitor", "assimilate", str(state), str(obs), "--time", "2001-03-01"])
    assert code == 0, err
    assert not legacy.exists() and not dead.exists() and live.exists()
    live.unlink()


def test_fit_refuses_a_new_file_in_its_input_folder(run, files):
    code, _, err = run(["fit", "{d}", "--var", "sst", "--rank", "2", "-o", "{d}/new.nc"])
    assert code == 2
    one_line_error(err, "fit", "input folder")
    assert not (files["d"] / "new.nc").exists()


@pytest.mark.parametrize("kind", ["fifo", "device"])
def test_refuses_to_replace_a_file_that_is_not_regular(run, tmp_path, kind):
    import stat

    target = tmp_path / "model.nc"
    if kind == "fifo":
        os.mkfifo(target)
    else:  # a copy of /dev/full, as the user made it
        try:
            os.mknod(target, 0o666 | stat.S_IFCHR, os.stat("/dev/full").st_rdev)
        except (PermissionError, OSError):
            pytest.skip("mknod needs privileges here")
    code, _, err = run(["fit", "{a}", "--rank", "2", "-o", str(target), "--overwrite"])
    assert code == 2
    one_line_error(err, "fit", "not a regular file")
    mode = os.lstat(target).st_mode
    assert (stat.S_ISFIFO(mode) if kind == "fifo" else stat.S_ISCHR(mode))


def test_python_writes_refuse_a_target_that_is_not_regular(tmp_path):
    from lrm_cvx._validation import atomic_output

    target = tmp_path / "x.nc"
    os.mkfifo(target)
    with pytest.raises(FileExistsError, match="not a regular file"):
        with atomic_output(target) as tmp:
            tmp.write_text("x")
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_file_size_limit_is_reported_as_such(files, tmp_path):
    # 'ulimit -f': HDF5 reports "NetCDF: HDF error"; the message must name the real cause
    import resource

    out = tmp_path / "model.nc"
    out.write_text("old")
    limit = 16 * 1024

    def small_files():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    proc = subprocess.run([sys.executable, "-m", "lrm_cvx.cli", "-q", "fit", str(files["a"]),
                           "--rank", "2", "-o", str(out), "--overwrite"],
                          capture_output=True, text=True, preexec_fn=small_files, timeout=300)
    assert proc.returncode == 2, proc.stderr
    one_line_error(proc.stderr, "fit", "file too large", "intact")
    assert out.read_text() == "old" and leftovers(tmp_path) == []


@pytest.mark.parametrize("delay", [0.15, 0.4, 0.8])
def test_ctrl_c_while_the_package_imports_exits_130(tmp_path, delay):
    import signal
    import time

    script = "import sys, lrm_cvx_entry; sys.exit(lrm_cvx_entry.main())"  # the console script
    proc = subprocess.Popen([sys.executable, "-c", script, "fit", "sample:sst", "-o",
                             str(tmp_path / "m.nc")], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    time.sleep(delay)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    if proc.returncode == 0:  # finished before the signal: nothing to check
        pytest.skip("the command finished before Ctrl-C")
    assert proc.returncode == 130, err
    assert err.strip().splitlines()[-1].endswith(": interrupted") and "Traceback" not in err
    assert not (tmp_path / "m.nc").exists()


def test_observation_cell_and_coordinates_must_agree(run, files, tmp_path):
    model = GLRM.load(files["model"])
    region = model.region_
    obs = tmp_path / "both.csv"
    lat, lon = float(region.cell_lat[3]), float(region.cell_lon[3])
    pd.DataFrame({"cell": [3, 7], "lat": [lat, lat], "lon": [lon, lon],
                  "value": [0.1, 0.2]}).to_csv(obs, index=False)
    code, _, err = run(["predict", "{model}", "--observations", str(obs), "-o",
                        str(tmp_path / "p.nc")])
    assert code == 2
    one_line_error(err, "predict", "row 2", "cell 7", "cell 3")
    agree = tmp_path / "agree.csv"
    cells = [3, 10, 20]
    pd.DataFrame({"cell": cells, "lat": region.cell_lat[cells], "lon": region.cell_lon[cells],
                  "value": [0.1, 0.2, 0.3]}).to_csv(agree, index=False)
    code, _, err = run(["predict", "{model}", "--observations", str(agree), "-o",
                        str(tmp_path / "p.nc")])
    assert code == 0, err


def test_monitor_plan_budget_zero_is_an_error_naming_the_nearest_cell(run, tmp_path):
    state = _state(run, tmp_path)
    code, out, err = run(["monitor", "plan", str(state), "--start", "-24,-70", "--budget", "0",
                          "-o", str(tmp_path / "p.csv")])
    assert code == 2 and not (tmp_path / "p.csv").exists()
    one_line_error(err, "monitor plan", "cannot reach any cell beyond its start")
    assert "the nearest cell is" in err and "grid units away" in err
    # the paper's forced initial cells are a plan still (over the budget, said so)
    code, out, err = run(["monitor", "plan", str(state), "--start", "-24,-70", "--budget", "0",
                          "--paper", "-o", str(tmp_path / "p.csv")])
    assert code == 0, err
    assert "> (forced initial cells) budget 0" in out and "Fisher information" in out


def _assimilate_cmd(state, obs, time):
    return [sys.executable, "-m", "lrm_cvx.cli", "-q", "monitor", "assimilate", str(state),
            str(obs), "--time", time]


def test_concurrent_assimilate_never_loses_an_update(run, files, tmp_path):
    # two 'monitor assimilate' on one state at once, 20 times: every final state is the one of
    # the two updates in order, or one process failed with one line and the other's update alone
    # is there (the failed one can be retried); never an update silently gone
    import shutil

    from lrm_cvx.monitor import MonitorState

    state0 = _state(run, tmp_path, "{plain}")
    days = {"A": "2001-03-01", "B": "2001-04-01"}
    obs = {}
    for i, key in enumerate(days):
        obs[key] = tmp_path / f"{key}.csv"
        pd.DataFrame({"lat": [-24.0, -28.0], "lon": [-70.0, -76.0],
                      "value": [0.3 + i, -0.2 * i]}).to_csv(obs[key], index=False)

    def reference(*keys):
        path = tmp_path / f"ref{''.join(keys)}.nc"
        shutil.copy(state0, path)
        for key in keys:
            assert run(["monitor", "assimilate", str(path), str(obs[key]), "--time",
                        days[key]])[0] == 0
        return MonitorState.load(path)

    def same(a, b):
        return (a.n_assimilated == b.n_assimilated and a.time == b.time
                and np.allclose(a.posterior.mean, b.posterior.mean, rtol=1e-12, atol=0))

    both, only_b = reference("A", "B"), reference("B")
    outcomes = []
    for trial in range(20):
        state = tmp_path / f"trial{trial}.nc"
        shutil.copy(state0, state)
        order = ("A", "B") if trial % 2 else ("B", "A")
        procs = {key: subprocess.Popen(_assimilate_cmd(state, obs[key], days[key]),
                                       stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                 for key in order}
        done = {key: (p.wait(timeout=300), p.stderr.read()) for key, p in procs.items()}
        final = MonitorState.load(state)
        if done["A"][0] == 0 and done["B"][0] == 0:
            assert same(final, both), f"trial {trial}: an update was lost"
            outcomes.append("AB")
        else:  # B ran first: A (an earlier day) is refused with one line, B's update is kept
            assert done["B"][0] == 0 and done["A"][0] == 2, done
            one_line_error(done["A"][1], "monitor assimilate", "earlier")
            assert same(final, only_b), f"trial {trial}: B's update was lost"
            outcomes.append("B, A refused")
    assert len(outcomes) == 20


# ------------------------------------------------- dates datetime64[ns] cannot hold
OUT_OF_RANGE = [
    (["monitor", "plan", "{state}", "--start", "-24,-70", "--budget", "3", "--time",
      "2700-01-15", "-o", "{out}/p.csv"], "--time 2700-01-15"),
    (["monitor", "assimilate", "{state}", "{obs}", "--time", "2700-01-15"], "--time 2700-01-15"),
    (["monitor", "assimilate", "{state}", "{obs}", "--time", "2500-01-15"], "--time 2500-01-15"),
    (["monitor", "assimilate", "{state}", "{obs}", "--time", "1500-01-15", "--force"],
     "--time 1500-01-15"),
    (["monitor", "map", "{state}", "--forecast", "--time", "2700-01-15", "-o", "{out}/m.nc"],
     "--time 2700-01-15"),
    (["monitor", "replan", "{state}", "--done", "1", "--time", "2700-01-15"],
     "--time 2700-01-15"),
    (["monitor", "init", "{model}", "--state", "{out}/new.nc", "--temporal", "ar1", "--time",
      "2800-03-01"], "--time 2800-03-01"),
    (["fit", "{a}", "--rank", "2", "--until", "1600-01-01", "-o", "{out}/f.nc"],
     "--until 1600-01-01"),
]


@pytest.mark.parametrize("argv, needle", OUT_OF_RANGE)
def test_a_date_outside_datetime64_ns_is_refused_not_wrapped(run, files, tmp_path,
                                                              inputs_unchanged, argv, needle):
    # a datetime64[ns] record holds 1677-09-21 .. 2262-04-11: a date outside would wrap around
    # (2800-03-01 -> 2215-08-12); it is refused in one line naming the option
    state = _state(run, tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    code, _, err = run(["monitor", "plan", str(state), "--start", "-24,-70", "--budget", "3",
                        "-o", str(tmp_path / "day.csv")])  # a stored plan (for replan)
    assert code == 0, err
    inputs_unchanged.watch(state, out)
    argv = [a.replace("{state}", str(state)).replace("{out}", str(out)) for a in argv]
    code, _, err = run(argv)
    assert code == 2
    one_line_error(err, " ".join(argv[:2]) if argv[0] == "monitor" else argv[0], needle,
                   "1677-09-21 to 2262-04-11")


# ------------------------------------------- model and state files are untrusted input
def _restate(state: Path, out: Path, **attrs) -> Path:
    """A copy of the state file ``state`` at ``out`` with ``attrs`` changed."""
    with xr.open_dataset(state) as f:
        ds = f.load()
    ds.attrs.update(attrs)
    ds.to_netcdf(out)
    return out


def test_a_model_or_state_with_an_external_link_is_refused(run, files, tmp_path):
    import shutil

    h5py = pytest.importorskip("h5py")
    secret = tmp_path / "secret.h5"
    with h5py.File(secret, "w") as f:
        f["data"] = np.arange(4.0)
    model = tmp_path / "model.nc"
    shutil.copy(files["model"], model)
    with h5py.File(model, "a") as f:
        f["leak"] = h5py.ExternalLink(str(secret), "/data")
    code, out, err = run(["plan", str(model), "--start", "-24,-70", "--budget", "3", "-o",
                          str(tmp_path / "p.csv")])
    assert code == 2 and out == ""
    one_line_error(err, "plan", "model file", "model.nc", "external link 'leak'", "secret.h5")
    assert not (tmp_path / "p.csv").exists()
    state = _state(run, tmp_path)
    with h5py.File(state, "a") as f:
        f["leak"] = h5py.ExternalLink(str(secret), "/data")
    code, _, err = run(["monitor", "map", str(state), "-o", str(tmp_path / "m.png")])
    assert code == 2
    one_line_error(err, "monitor map", "state file", "state.nc", "external link 'leak'")


def test_a_state_whose_model_is_a_url_contacts_no_server(run, tmp_path):
    import socket

    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    server.settimeout(0.2)
    url = f"http://127.0.0.1:{server.getsockname()[1]}/model.nc"
    state = _restate(_state(run, tmp_path), tmp_path / "url.nc", model_path=url)
    try:
        code, _, err = run(["monitor", "map", str(state), "-o", str(tmp_path / "m.png")])
        with pytest.raises(TimeoutError):  # nobody knocked
            server.accept()
    finally:
        server.close()
    assert code == 2
    one_line_error(err, "monitor map", "url.nc", "records its model as the URL", url)


def test_a_state_relative_model_path_is_taken_from_the_state_folder(run, files, tmp_path):
    import shutil

    folder = tmp_path / "campaign"
    folder.mkdir()
    shutil.copy(files["model"], folder / "model.nc")
    state = _restate(_state(run, tmp_path), folder / "state.nc", model_path="model.nc")
    assert not (files["root"] / "model.nc").exists()  # run() works in another folder
    code, out, err = run(["monitor", "map", str(state), "-o", str(tmp_path / "m.png")])
    assert code == 0, err
    assert (tmp_path / "m.png").stat().st_size > 0


def test_a_fifo_as_the_state_model_or_the_observations_is_refused(run, tmp_path):
    fifo = tmp_path / "fifo.nc"
    os.mkfifo(fifo)  # opening it would wait for a writer forever
    state = _state(run, tmp_path)
    bad = _restate(state, tmp_path / "s.nc", model_path=str(fifo))
    code, _, err = run(["monitor", "map", str(bad), "-o", str(tmp_path / "m.png")])
    assert code == 2
    one_line_error(err, "monitor map", "fifo.nc", "not a regular file")
    fifo_csv = tmp_path / "obs.csv"
    os.mkfifo(fifo_csv)
    code, _, err = run(["monitor", "assimilate", str(state), str(fifo_csv), "--time",
                        "2001-03-01"])
    assert code == 2
    one_line_error(err, "monitor assimilate", "obs.csv", "not a regular file")


# ---------------------------------------------------------------------- symbolic links
def _obs_csv(path: Path, value: float) -> Path:
    pd.DataFrame({"lat": [-24.0, -28.0], "lon": [-70.0, -76.0],
                  "value": [value, -value]}).to_csv(path, index=False)
    return path


def test_assimilate_through_a_symlink_updates_the_real_state(run, tmp_path):
    from lrm_cvx.monitor import MonitorState

    real = _state(run, tmp_path, "{plain}")
    n0 = MonitorState.load(real).n_assimilated
    link = tmp_path / "link.nc"
    link.symlink_to(real)
    code, _, err = run(["monitor", "assimilate", str(link), str(_obs_csv(tmp_path / "a.csv",
                                                                         0.3)),
                        "--time", "2001-03-01"])
    assert code == 0, err
    assert link.is_symlink() and os.readlink(link) == str(real)
    assert MonitorState.load(real).n_assimilated == n0 + 2
    code, _, err = run(["monitor", "assimilate", str(real), str(_obs_csv(tmp_path / "b.csv",
                                                                         0.5)),
                        "--time", "2001-04-01"])
    assert code == 0, err
    assert MonitorState.load(link).n_assimilated == n0 + 4  # both updates, none lost
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_a_link_and_its_target_take_the_same_lock(tmp_path):
    from lrm_cvx._validation import file_lock

    real = tmp_path / "state.nc"
    real.write_text("x")
    link = tmp_path / "link.nc"
    link.symlink_to(real)
    with file_lock(real):
        with pytest.raises(TimeoutError, match="link.nc is being updated"):
            with file_lock(link, timeout=0.2):
                pass
    with file_lock(link):  # released: taken at once
        pass


def test_fit_onto_a_symlink_keeps_the_link(run, tmp_path):
    real = tmp_path / "models" / "m.nc"
    real.parent.mkdir()
    real.write_text("old")
    link = tmp_path / "current.nc"
    link.symlink_to(real)
    code, _, err = run(["fit", "{a}", "--rank", "2", "-o", str(link), "--overwrite"])
    assert code == 0, err
    assert link.is_symlink() and os.readlink(link) == str(real)
    assert GLRM.load(real).rank == 2
    assert leftovers(tmp_path) == [] and leftovers(real.parent) == []


@pytest.mark.parametrize("where", ["output", "data", "model"])
def test_a_symlink_loop_is_named(run, tmp_path, where):
    loop = tmp_path / "loop.nc"
    loop.symlink_to(loop)
    argv = {"output": ["fit", "{a}", "--rank", "2", "-o", str(loop)],
            "data": ["fit", str(loop), "--rank", "2", "-o", str(tmp_path / "m.nc")],
            "model": ["predict", str(loop), "--observations", "{obs}", "-o",
                      str(tmp_path / "p.nc")]}[where]
    code, _, err = run(argv)
    assert code == 2
    one_line_error(err, argv[0], "loop.nc is a symlink loop")


def test_place_onto_its_own_input_says_so(run, files):
    code, _, err = run(["place", "{model}", "--sensors", "3", "-o", "{model}", "--overwrite"])
    assert code == 2
    one_line_error(err, "place", "refusing to overwrite the input file", "model.nc")
