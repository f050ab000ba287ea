"""The path request: PathOptions and Fleet validated once, plan.path a read-only
mapping, planners as objects equal to the keyword functions, EvaluationProtocol equal to
evaluate, and the 15-parameter rule of the public API."""

from __future__ import annotations

import importlib
import inspect
import json
import pkgutil
import re
import warnings

import numpy as np
import pytest
import xarray as xr

import lrm_cvx
from lrm_cvx import Region
from lrm_cvx.errors import PlanningError, RegionError
from lrm_cvx.evaluation import PlanningOptions
from lrm_cvx.planning import (
    METHOD_REGISTRY,
    Fleet,
    GreedyPlanner,
    PathOptions,
    PlanPath,
    RandomWalk,
    Refined,
    StaticPlacement,
    Transect,
    place_sensors,
    plan_greedy,
    random_walk,
    transect,
)
from lrm_cvx.planning.plan import PAPER_PATH


@pytest.fixture(scope="module")
def small():
    """A small real region (the bundled SST sample, a corner of it) and a rank-3 factor."""
    da = lrm_cvx.load_sample("sst").isel(lat=slice(0, 9), lon=slice(0, 10))
    region = Region.from_dataarray(da)
    Y = np.random.default_rng(7).standard_normal((3, region.n_cells))
    return region, Y


# ------------------------------------------------------------------ PathOptions
@pytest.mark.parametrize("kw, name", [
    (dict(metric="miles"), "metric"),
    (dict(speed=2.0), "speed"),
    (dict(metric="km", speed=0.0), "speed"),
    (dict(metric="km", speed="fast"), "speed"),
    (dict(stop_cost=-1.0), "stop_cost"),
    (dict(stop_cost="1"), "stop_cost"),
    (dict(closed="yes"), "closed"),
    (dict(closed=True, end=3), "closed"),
    (dict(sense_along=1), "sense_along"),
    (dict(traversable="land"), "traversable"),
    (dict(traversable=[[True]]), "traversable"),
])
def test_path_options_refuse_bad_values_naming_the_argument(kw, name):
    with pytest.raises(PlanningError) as info:
        PathOptions(**kw)
    assert name in str(info.value) and "\n" not in str(info.value)


def test_path_options_normalise_and_describe_themselves():
    p = PathOptions(metric="KM", speed=3, stop_cost=1, traversable=" Valid ")
    assert (p.metric, p.speed, p.stop_cost, p.traversable) == ("km", 3.0, 1.0, "valid")
    assert p.unit == "h" and p.traversable_kind == "valid" and not p.is_paper
    assert p.changed() == {"metric": "km", "speed": 3.0, "stop_cost": 1.0,
                           "traversable": "valid"}
    assert PathOptions().is_paper and PathOptions().unit == "grid units"
    assert PathOptions(metric="km").unit == "km"
    assert PathOptions(metric="km", stop_cost=1) == PathOptions(metric="km", stop_cost=1.0)
    assert PathOptions(closed=True) != PathOptions()
    mask = np.ones((2, 2), bool)
    assert PathOptions(traversable=mask) == PathOptions(traversable=mask.copy())
    with pytest.raises(AttributeError):
        p.metric = "grid"  # frozen


def test_from_kwargs_updates_a_request_and_refuses_unknown_names():
    base = PathOptions(metric="km")
    assert PathOptions.from_kwargs(base, closed=True) == PathOptions(metric="km", closed=True)
    assert PathOptions.from_kwargs(None) == PathOptions()
    with pytest.raises(TypeError, match="plan_greedy.*'metrc'"):
        PathOptions.from_kwargs(None, where="plan_greedy", metrc="km")
    with pytest.raises(TypeError, match="transect.*'end'"):
        PathOptions.from_kwargs(None, where="transect", allowed=("metric",), end=3)
    with pytest.raises(PlanningError, match="sense_along"):
        PathOptions.from_kwargs(PathOptions(sense_along=True), where="transect",
                                allowed=("metric",))
    with pytest.raises(PlanningError, match="PathOptions"):
        PathOptions.from_kwargs({"metric": "km"})


# ------------------------------------------------------------------ Fleet
def test_fleet_resolves_one_robot_a_fleet_and_lat_lon(small):
    region, _ = small
    one = Fleet.resolve(region, 5, 3)
    assert one == Fleet((5,), (3.0,)) and not one.is_fleet and one.n_robots == 1
    two = Fleet.resolve(region, [5, 9], [3, 4.5], "km")
    assert two.starts == (5, 9) and two.budgets == (3.0, 4.5) and two.is_fleet
    assert two.unit == "km"
    lat, lon = float(region.cell_lat[7]), float(region.cell_lon[7])
    assert Fleet.resolve(region, (lat, lon), 1).starts == (7,)
    assert Fleet.resolve(region, [lat, lon], 1).starts == (7,)  # one [lat, lon]
    assert Fleet.resolve(region, np.array([3, 4]), 1).budgets == (1.0, 1.0)
    assert Fleet.resolve(region, two, None, "km") is two


@pytest.mark.parametrize("start, budget, error, text", [
    (0, -1.0, PlanningError, "budget (km)"),
    (0, "3", PlanningError, "budget (km)"),
    (0, True, PlanningError, "budget (km)"),
    (0, np.nan, PlanningError, "budget (km)"),
    (0, None, PlanningError, "budget"),
    (0, [3.0], PlanningError, "budget"),
    ([0, 1], [3.0, 2.0, 1.0], PlanningError, "budget has 3 values"),
    (None, 3.0, PlanningError, "start"),
    ([], 3.0, PlanningError, "start"),
    (10**6, 3.0, RegionError, "start"),
])
def test_fleet_refuses_bad_requests_naming_the_argument(small, start, budget, error, text):
    region, _ = small
    with pytest.raises(error) as info:
        Fleet.resolve(region, start, budget, "km")
    assert text in str(info.value)


def test_a_fleet_checks_its_budgets_in_one_place():
    with pytest.raises(PlanningError, match=r"budget \(h\)"):
        Fleet((1,), (-2.0,), unit="h")
    with pytest.raises(PlanningError, match="budget has 2 values"):
        Fleet((1,), (2.0, 3.0))


# ------------------------------------------------------------------ plan.path
def test_plan_path_is_a_read_only_mapping_with_the_old_items(small):
    region, Y = small
    plan = plan_greedy(Y, region, 5, 6.0, ridge=1e-3, progress=False,
                       path=PathOptions(closed=True, stop_cost=0.5))
    path = plan.path
    assert isinstance(path, PlanPath)
    assert list(path) == [*PAPER_PATH, "starts", "budgets", "n_robots"]
    assert path["closed"] is True and path.get("unit") == "grid units"
    assert dict(path) == dict(PAPER_PATH, closed=True, stop_cost=0.5, starts=[5],
                              budgets=[6.0], n_robots=1)
    assert path == dict(path) and path.options == PathOptions(closed=True, stop_cost=0.5)
    assert path.fleet == Fleet((5,), (6.0,)) and path.kind == "path"
    with pytest.raises(TypeError):
        path["closed"] = False  # read-only
    doc = plan.to_geojson()
    assert json.loads(json.dumps(doc))["properties"]["path"] == dict(path)
    default = plan_greedy(Y, region, 5, 6.0, ridge=1e-3, progress=False)
    assert default.path.is_paper and not path.is_paper


# ------------------------------------------------------------------ planners as objects
def test_greedy_planner_is_plan_greedy(small):
    region, Y = small
    fleet = Fleet.resolve(region, 5, 8.0)
    for planner, kw in ((GreedyPlanner(), {}),
                        (GreedyPlanner("a-optimal", "insertion"),
                         dict(criterion="a-optimal", cost="insertion")),
                        (GreedyPlanner(initial="start"), dict(initial="start"))):
        a = planner.plan(Y, region, fleet, PathOptions(closed=True), ridge=1e-2)
        b = plan_greedy(Y, region, 5, 8.0, ridge=1e-2, progress=False,
                        path=PathOptions(closed=True), **kw)
        assert a == b and a.information == b.information and a.cost == b.cost
    fleet2 = Fleet.resolve(region, [5, 40], 6.0)
    a = GreedyPlanner().plan(Y, region, fleet2, None, ridge=1e-2)
    b = plan_greedy(Y, region, [5, 40], 6.0, ridge=1e-2, progress=False)
    assert a == b and a.n_robots == 2


def test_baseline_planners_are_the_baselines(small):
    region, Y = small
    fleet = Fleet.resolve(region, 5, 7.0)
    for d in ("up", "down", "left", "right"):
        a = Transect(d).plan(Y, region, fleet, PathOptions(metric="km"))
        b = transect(region, 5, 7.0, d, Y=Y, path=PathOptions(metric="km"))
        assert a == b
    a = RandomWalk().plan(Y, region, fleet, None, rng=np.random.default_rng(3), ridge=0.1)
    b = random_walk(region, 5, 7.0, np.random.default_rng(3), Y=Y, ridge=0.1)
    assert a == b and np.array_equal(a.cells, b.cells)


def test_static_placement_is_place_sensors(small):
    region, Y = small
    a = StaticPlacement().plan(Y, region, Fleet((), (6,), unit="sensors"), None, ridge=1e-3)
    b = place_sensors(Y, region, 6, ridge=1e-3)
    assert a == b and a.path["kind"] == "static"
    with pytest.raises(PlanningError, match="place_sensors"):
        plan_greedy(Y, region, None, 6, path="static", ridge=1e-3, progress=False)


def test_refined_is_plan_greedy_refine(small):
    region, Y = small
    opts = {"time_limit": 30.0, "kicks": 2, "shapes": 20}
    a = Refined(GreedyPlanner(), opts).plan(Y, region, Fleet.resolve(region, 5, 6.0), None)
    b = plan_greedy(Y, region, 5, 6.0, progress=False, refine=opts)
    assert a == b and a.refinement["moves"] == b.refinement["moves"]


def test_the_method_registry_holds_the_planners():
    assert isinstance(METHOD_REGISTRY.get("greedy"), GreedyPlanner)
    assert METHOD_REGISTRY.get("transect-up") == Transect("up")
    assert METHOD_REGISTRY.get("random") == RandomWalk()
    variant = METHOD_REGISTRY.get("Greedy:GP-Variance")  # any letter case
    assert variant == GreedyPlanner("gp-variance", initial="start", model_prior=True, lines=True)
    assert METHOD_REGISTRY.get("greedy").configure(criterion="a-optimal", cost="insertion") \
        == GreedyPlanner("a-optimal", "insertion")


# ------------------------------------------------------------------ the protocol object
def test_evaluation_protocol_run_is_evaluate():
    from lrm_cvx.evaluation import EvaluationProtocol, evaluate

    da = lrm_cvx.load_sample("sst").isel(lat=slice(0, 12), lon=slice(0, 12))
    kw = dict(rank=2, n_test=2, budgets=(3, 6), n_starts=2,
              progress=False, methods=("greedy", "transect-up", "random"), seed=4,
              planning=PlanningOptions(random_trials=2, certify=False))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        a = EvaluationProtocol(da, path=PathOptions(stop_cost=0.5), **kw).run()
        b = evaluate(da, path=PathOptions(stop_cost=0.5), **kw)
    xr.testing.assert_identical(a, b)
    assert a.attrs["stop_cost"] == 0.5
    with pytest.raises(PlanningError, match="temporal campaigns only"):
        evaluate(da, path=PathOptions(sense_along=True), **kw)  # sensing along needs a campaign
    with pytest.raises(PlanningError, match="n_robots"):
        EvaluationProtocol(da, n_robots=0, **kw)  # checked when built, before any fit


# ------------------------------------------------------------------ at most 15 parameters
KNOWN_LONG: set[str] = set()  # to stay empty
RECORDS = {"Plan", "PlanCertificate", "Calibration"}
"""Results the library builds and returns: their generated ``__init__`` lists outputs, not
settings a user chooses."""
RECORD_BUILDERS = {"Plan.build"}
"""The planners' constructor of a result record: its arguments are the plan's fields (cells,
route, costs, information, ...), which the planner computed, not settings a user chooses."""
PENDING: dict[str, int] = {}
"""Entry points still over 15 settings, with their counts today: each may only shrink (and
leave this table at 15 or fewer)."""
_OPTION_KEYS = re.compile(r"^(\s*)([A-Za-z_][\w, ]*?) : \(``\*\*(\w+)``\)", re.M)


def _public_modules() -> list[str]:
    """Every module of the package with an ``__all__`` (the experimental package aside)."""
    names = ["lrm_cvx"]
    for info in pkgutil.walk_packages(lrm_cvx.__path__, "lrm_cvx."):
        if ".experimental" in info.name or info.name.rsplit(".", 1)[-1].startswith("_"):
            continue
        names.append(info.name)
    return names


def _documented_keys(fn, var_kw: str) -> set[str]:
    """The keys of ``**var_kw`` documented in ``fn``'s numpydoc Parameters section, written
    ``a, b : (``**var_kw``) ...``."""
    doc = inspect.getdoc(fn) or ""
    return {key.strip() for m in _OPTION_KEYS.finditer(doc) if m.group(3) == var_kw
            for key in m.group(2).split(",") if key.strip()}


def _count(fn) -> int:
    """The settings of ``fn``: its named parameters (``self`` aside), ``*args`` one, and
    ``**options`` as many as the keys its docstring documents (one if it documents none)."""
    n = 0
    for i, p in enumerate(inspect.signature(fn).parameters.values()):
        if i == 0 and p.name in ("self", "cls"):
            continue
        if p.kind is p.VAR_KEYWORD:
            n += max(1, len(_documented_keys(fn, p.name)))
        else:
            n += 1
    return n


def _callables(obj):
    """``obj`` itself (a function) or a class's ``__init__`` (a record's aside) and public
    methods defined on it."""
    if inspect.isfunction(obj):
        yield obj.__name__, obj
    elif inspect.isclass(obj):
        for key, member in vars(obj).items():
            if key == "__init__" and obj.__name__ in RECORDS:
                continue
            if f"{obj.__name__}.{key}" in RECORD_BUILDERS:
                continue
            if key == "__init__" or not key.startswith("_"):
                member = getattr(member, "__func__", member)
                if inspect.isfunction(member):
                    yield f"{obj.__name__}.{key}", member


def test_the_settings_counter_counts_documented_option_keys():
    def f(a, b, *, c=1, **options):
        """Doc.

        Parameters
        ----------
        a : one
        x, y, z : (``**options``) three keys
        w : (``**other``) not these options
        """
    assert _count(f) == 6
    assert _count(lambda a, **kw: None) == 2
    assert _count(plan_greedy) > len(inspect.signature(plan_greedy).parameters) - 1 or not \
        _documented_keys(plan_greedy, "options")


def test_no_public_function_takes_more_than_15_parameters():
    too_many = {}
    for name in _public_modules():
        module = importlib.import_module(name)
        for attr in getattr(module, "__all__", ()):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", DeprecationWarning)
                obj = getattr(module, attr, None)
            for label, fn in _callables(obj):
                if label not in KNOWN_LONG and _count(fn) > 15:
                    too_many[label] = _count(fn)
    pending = {label: n for label, n in too_many.items() if n <= PENDING.get(label, 15)}
    assert not set(too_many) - set(pending), sorted(too_many.items())
    assert set(pending) == set(PENDING), f"narrowed: drop {set(PENDING) - set(pending)}"
    for fn in (plan_greedy, lrm_cvx.plan_bound, place_sensors, transect, random_walk,
               lrm_cvx.refine, lrm_cvx.simulate_campaign):
        assert _count(fn) <= 15, (fn.__name__, _count(fn))


# ------------------------------------------------------------------ one object per idea
def test_every_refine_mode_is_an_entry_of_refiners(small, monkeypatch):
    from lrm_cvx.planning.refiners import REFINERS

    region, Y = small
    assert {"local", "lines", "rivals"} <= set(REFINERS)
    monkeypatch.setattr(REFINERS, "_entries", dict(REFINERS._entries))
    monkeypatch.setattr(REFINERS, "_lookup", dict(REFINERS._lookup))
    seen = {}

    def keep(plan, options, context):
        seen.update(options=options, context=context)
        return plan

    REFINERS.register("keep", keep, description="the plan as it is")
    kw = dict(ridge=1e-3, progress=False)
    plain = plan_greedy(Y, region, 5, 6.0, **kw)
    assert plan_greedy(Y, region, 5, 6.0, refine="keep", **kw) == plain
    context = seen["context"]
    assert seen["options"] == {} and context.criterion == "fisher" and context.ridge == 1e-3
    gentle = plan_greedy(Y, region, 5, 6.0, cost_exponent=0.5, **kw)
    assert context.rival(0.5) == gentle  # the greedy rerun, as "rivals" uses it
    with pytest.raises(PlanningError, match="refine must be"):
        plan_greedy(Y, region, 5, 6.0, refine="nope", **kw)


def test_the_prior_and_the_path_are_one_argument_each(small):
    from lrm_cvx.planning import PriorTerms

    region, Y = small
    k, L = Y.shape
    terms = PriorTerms(prior_precision=np.eye(k), noise_var=np.linspace(0.5, 1.5, L))
    plan = plan_greedy(Y, region, 5, 6.0, criterion="a-optimal", initial="start",
                       progress=False, prior=terms)
    assert plan.posterior and plan.cells[0] == 5
    assert terms.same(PriorTerms(np.eye(k), np.linspace(0.5, 1.5, L)))
    assert not terms.same(PriorTerms(noise_var=1.0))
    for bad in (dict(noise_var=1.0), dict(closed=True), dict(static=True)):
        with pytest.raises(TypeError, match=next(iter(bad))):
            plan_greedy(Y, region, 5, 6.0, progress=False, **bad)
    with pytest.raises(PlanningError, match="PriorTerms"):
        plan_greedy(Y, region, 5, 6.0, progress=False, prior={"noise_var": 1.0})
    for fn in (transect, random_walk):
        with pytest.raises(TypeError, match="metric"):
            fn(region, 5, 6.0, *(("up",) if fn is transect else ()), metric="km")


def test_the_recommended_criterion_and_its_fallback_read_recommended(monkeypatch):
    from lrm_cvx.recommended import RECOMMENDED, recommended_criterion

    assert recommended_criterion(True) == RECOMMENDED["criterion"] == "gp-variance"
    assert recommended_criterion(False) == "fisher"  # gp-variance needs the residual
    monkeypatch.setitem(RECOMMENDED, "criterion", "a-optimal")
    assert recommended_criterion(False) == recommended_criterion(True) == "a-optimal"
