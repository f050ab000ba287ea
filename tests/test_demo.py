"""The demo pipeline (``lrm_cvx.demo``): end to end on a reduced protocol, summary order."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import pytest  # noqa: E402

from lrm_cvx.demo import BASELINES, PAPER, RECOMMENDED, format_summary, run_demo  # noqa: E402
from lrm_cvx.errors import DataError  # noqa: E402

SMALL = {"budgets": (10.0, 20.0), "n_starts": 2, "random_trials": 2}


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    lines: list[str] = []
    return out, run_demo(out, progress=lines.append, settings=SMALL), lines


def test_demo_writes_every_output(demo):
    out, result, lines = demo
    names = {"results_recommended.nc", "results_paper.nc", "summary.csv", "summary.txt",
             "predictions.png", "predictions.pdf", "metrics.png", "metrics.pdf"}
    assert {p.name for p in result.paths} == names
    assert all((out / n).stat().st_size > 0 for n in names)
    assert lines and lines[0].startswith("sample 'sst'")
    assert (out / "summary.txt").read_text().strip() == result.text.strip()
    assert {"fit recommended", "evaluate recommended", "figures", "total"} <= set(result.timings)


def test_summary_lists_recommended_first_then_paper(demo):
    _, result, _ = demo
    settings = list(dict.fromkeys(result.table["setting"]))
    assert settings[:2] == [RECOMMENDED, PAPER]
    assert len(settings) == 2 + len(BASELINES)
    rows = [ln for ln in result.text.splitlines() if ln.startswith(("recommended", "paper"))]
    assert rows[0].startswith("recommended") and rows[1].startswith("paper")
    # one screen: at most 24 lines of at most 100 characters
    assert len(result.text.splitlines()) <= 24
    assert max(len(ln) for ln in result.text.splitlines()) <= 100
    # every (setting, budget) has an error from >= 1 prediction, and the csv is the same table
    assert (result.table["n"] > 0).all() and np.isfinite(result.table["mse_mean"]).all()
    csv = pd.read_csv(demo[0] / "summary.csv")
    assert list(csv["setting"]) == list(result.table["setting"])


def test_summary_names_the_setting_it_ran(demo):
    """The note describes the recommended setting as run (read from RECOMMENDED, with the
    kernel ``spatial="auto"`` chose), not a setting written into the text."""
    from lrm_cvx.recommended import RECOMMENDED as SETTING
    from lrm_cvx.spatial.covariance import MODELS

    _, result, _ = demo
    line = next(ln for ln in result.text.splitlines() if ln.startswith("recommended = GLRM"))
    assert f"spatial={SETTING['spatial']!r}" in line
    assert f"greedy {SETTING['criterion']!r}" in line
    if SETTING["spatial"] == "auto":
        chosen = line.split("spatial='auto': ")[1].split(" chosen")[0]
        assert chosen in MODELS


def test_summary_mse_matches_results(demo):
    """The table's means are the results' MSE averaged over starts x trials x test times."""
    import xarray as xr

    out, result, _ = demo
    res = xr.load_dataset(out / "results_recommended.nc")
    err = res["mse"].sel({"method": "greedy:gp-variance", "budget": 20.0}).values
    row = result.table[(result.table["setting"] == RECOMMENDED) & (result.table["budget"] == 20)]
    assert float(row["mse_mean"].iloc[0]) == pytest.approx(np.nanmean(err))


def test_format_summary_keeps_row_order_and_units():
    table = pd.DataFrame({"setting": ["b", "b", "a", "a"], "budget": [20.0, 10.0, 10.0, 20.0],
                          "mse_mean": [1.0, 2.0, 3.0, np.nan], "mse_se": [0.1] * 4})
    text = format_summary(table, units="K", notes=["note"])
    lines = text.splitlines()
    assert "(K)^2" in lines[0]
    assert lines[1].split()[1:] == ["budget", "10", "budget", "20"]
    assert lines[3].split()[0] == "b" and lines[4].split()[0] == "a"
    assert "2.0000 +- 0.1000" in lines[3] and "n/a" in lines[4]
    assert all("  " in ln[len("b"):] for ln in lines[3:5])  # columns never run together
    assert lines[-1] == "note"


def test_unknown_setting_is_a_data_error(tmp_path):
    with pytest.raises(DataError, match="n_start"):
        run_demo(tmp_path, settings={"n_start": 3}, progress=None)
