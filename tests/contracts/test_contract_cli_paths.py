"""CLI parity for the path model (issue #15): every path option of the Python API has its flag,
with the library's choices, on every command that plans, and docs/cli.md names it."""

from __future__ import annotations

import argparse
import inspect
from pathlib import Path

from lrm_cvx.cli import build_parser
from lrm_cvx.evaluation import evaluate
from lrm_cvx.planning import plan_greedy, random_walk, transect
from lrm_cvx.planning.paths import METRICS

DOCS = Path(__file__).resolve().parents[2] / "docs"

#: Python keyword -> CLI flag, for the path options
FLAGS = {"metric": "--metric", "speed": "--speed", "stop_cost": "--stop-cost",
         "traversable": "--traversable", "closed": "--closed", "end": "--end",
         "sense_along": "--sense-along", "n_robots": "--robots"}
PLAN_OPTIONS = ("metric", "speed", "stop_cost", "traversable", "closed", "end", "sense_along")
EVALUATE_OPTIONS = ("metric", "speed", "stop_cost", "traversable", "closed", "n_robots")
BASELINE_OPTIONS = ("metric", "speed", "stop_cost", "traversable", "closed")


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def _flags(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    return {o: a for a in parser._actions for o in a.option_strings}


def test_the_python_api_takes_every_path_option():
    for fn, names in ((plan_greedy, PLAN_OPTIONS), (evaluate, EVALUATE_OPTIONS),
                      (transect, BASELINE_OPTIONS), (random_walk, BASELINE_OPTIONS)):
        params = inspect.signature(fn).parameters
        missing = [n for n in names if n not in params]
        assert not missing, f"{fn.__name__} lacks {missing}"
    # the baselines and evaluate default to the paper exactly as the planner does
    greedy = inspect.signature(plan_greedy).parameters
    for fn in (transect, random_walk, evaluate):
        params = inspect.signature(fn).parameters
        for n in BASELINE_OPTIONS:
            assert params[n].default == greedy[n].default, (fn.__name__, n)


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
