"""CLI parity for the path model: every path option of the Python API has its flag,
with the library's choices, on every command that plans, and docs/cli.md names it."""

from __future__ import annotations

import argparse
import dataclasses
import inspect
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from lrm_cvx import Region
from lrm_cvx.cli import build_parser
from lrm_cvx.errors import PlanningError
from lrm_cvx.evaluation import evaluate
from lrm_cvx.planning import plan_greedy, random_walk, transect
from lrm_cvx.planning.paths import METRICS
from lrm_cvx.planning.request import PathOptions

DOCS = Path(__file__).resolve().parents[2] / "docs"

#: Python keyword -> CLI flag, for the path options
FLAGS = {"metric": "--metric", "speed": "--speed", "stop_cost": "--stop-cost",
         "traversable": "--traversable", "closed": "--closed", "end": "--end",
         "sense_along": "--sense-along", "n_robots": "--robots", "sensor": "--sensor"}
PLAN_OPTIONS = ("metric", "speed", "stop_cost", "traversable", "closed", "end", "sense_along",
                "sensor")
EVALUATE_OPTIONS = ("metric", "speed", "stop_cost", "traversable", "closed", "n_robots")
BASELINE_OPTIONS = ("metric", "speed", "stop_cost", "traversable", "closed")


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def _flags(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    return {o: a for a in parser._actions for o in a.option_strings}


def test_the_python_api_takes_every_path_option():
    # a path option is a field of the one request object (PathOptions), taken as
    # `path=PathOptions(...)` only, with the request's defaults
    fields = {f.name: f.default for f in dataclasses.fields(PathOptions)}
    for fn, names in ((plan_greedy, PLAN_OPTIONS), (evaluate, EVALUATE_OPTIONS),
                      (transect, BASELINE_OPTIONS), (random_walk, BASELINE_OPTIONS)):
        params = inspect.signature(fn).parameters
        assert "path" in params and not set(names) & set(fields) & set(params), fn.__name__
        missing = [n for n in names if n not in fields and n not in params]
        assert not missing, f"{fn.__name__} lacks {missing}"
    # the baselines, evaluate and the planner share the paper's defaults: the request's
    assert {n: fields[n] for n in BASELINE_OPTIONS} == {
        "metric": "grid", "speed": None, "stop_cost": 0.0, "traversable": None, "closed": False}
    region = Region.from_dataarray(xr.DataArray(np.zeros((1, 3, 3)), dims=("time", "lat", "lon"),
                                                coords={"lat": [0.0, 1, 2], "lon": [0.0, 1, 2]}))
    for call in (lambda **k: plan_greedy(np.eye(1, 9), region, 0, 2.0, progress=False, **k),
                 lambda **k: transect(region, 0, 2.0, "up", **k),
                 lambda **k: random_walk(region, 0, 2.0, 0, **k)):
        with pytest.raises(PlanningError, match="metric"):
            call(path=PathOptions(metric="miles"))
        with pytest.raises(TypeError, match="nonsense"):
            call(nonsense=1)
        with pytest.raises(TypeError, match="metric"):  # the path is one object
            call(metric="km")


def test_every_path_option_has_its_flag_on_every_planning_command():
    parsers = _subparsers()
    for command, names in (("plan", PLAN_OPTIONS), ("bound", PLAN_OPTIONS),
                           ("evaluate", EVALUATE_OPTIONS)):
        flags = _flags(parsers[command])
        missing = [FLAGS[n] for n in names if FLAGS[n] not in flags]
        assert not missing, f"lrm-cvx {command} lacks {missing}"
        metric = flags["--metric"]
        assert tuple(metric.choices) == tuple(METRICS) and metric.default == "grid"
        assert flags["--closed"].default is False and flags["--stop-cost"].default == 0.0
        assert flags["--speed"].default is None and flags["--traversable"].default is None
    plan = _flags(parsers["plan"])
    assert plan["--start"].__class__.__name__ == "_AppendAction"  # a fleet: repeated --start
    assert plan["--budget"].__class__.__name__ == "_AppendAction"


def test_cli_docs_name_every_path_flag_and_metric():
    text = (DOCS / "cli.md").read_text()
    for flag in FLAGS.values():
        assert f"`{flag}" in text, flag
    assert f"--metric {'|'.join(METRICS)}" in text
