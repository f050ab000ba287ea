"""The registries: one rule for names and aliases, the old constants equal their choices, and
every docs table listing choices names exactly the registered entries."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from all_registries import registries

from lrm_cvx.errors import ModelError, PlanningError
from lrm_cvx.registry import PRIOR_REGISTRY, Choices, Registry, prior_value

DOCS = Path(__file__).resolve().parents[2] / "docs"


# ---------------------------------------------------------------- the Registry itself
def test_registry_get_aliases_case_and_errors():
    reg = Registry("colour", PlanningError)
    reg.register("red", 1, description="warm", aliases=("r", "rouge"))

    @reg.register("blue", description="cold")
    class Blue:
        pass

    assert reg.get("red") == 1 and reg.get("R") == 1 and reg.get(" Rouge ") == 1
    assert reg.get("blue") is Blue and reg.canonical("BLUE") == "blue"
    assert reg.choices() == ("red", "blue") and list(reg) == ["red", "blue"] and len(reg) == 2
    assert "rouge" in reg.choices() and "green" not in reg.choices() and [] not in reg.choices()
    with pytest.raises(PlanningError, match=r"colour must be one of \['red', 'blue'\] "
                                            r"\(aliases: 'r' = 'red', 'rouge' = 'red'\), got 'x'"):
        reg.get("x")
    with pytest.raises(PlanningError, match="paint must be one of"):
        reg.get(3, "paint")
    with pytest.raises(PlanningError):
        reg.get(["red"])  # unhashable: still the project error
    with pytest.raises(ValueError, match="already registered"):
        reg.register("r", 2, description="clash")
    with pytest.raises(ValueError, match="lower-case"):
        reg.register("Green", 2, description="x")
    with pytest.raises(ValueError, match="one-line"):
        reg.register("green", 2, description="two\nlines")
    assert "| `red` | `r`, `rouge` | warm |" in reg.markdown_table()


def test_choices_is_a_tuple_that_accepts_aliases():
    reg = Registry("x")
    reg.register("a", 1, description="a", aliases=("aa",))
    reg.register("b", 2, description="b")
    c = reg.choices()
    assert isinstance(c, Choices) and isinstance(c, tuple) and c == ("a", "b")
    assert "AA" in c and c.index("b") == 1 and sorted(c) == ["a", "b"]
    head = Choices(("a",), reg)
    assert "b" not in head and "aa" in head  # a snapshot: only its own names
    assert "b" in head + Choices(("b",), reg)
    import pickle

    assert pickle.loads(pickle.dumps(c)) == ("a", "b")


# ---------------------------------------------------------------- constants = choices
def test_constants_are_the_registries_choices():
    from lrm_cvx.evaluation import GREEDY_VARIANTS, METHODS
    from lrm_cvx.glrm.losses import LOSSES
    from lrm_cvx.glrm.predictive import PRIORS
    from lrm_cvx.glrm.regularizers import REGULARIZERS
    from lrm_cvx.information import CRITERIA
    from lrm_cvx.planning.routecost import COSTS
    from lrm_cvx.spatial import MODELS

    regs = registries()
    assert CRITERIA == regs["criterion"].choices()
    assert COSTS == regs["cost"].choices()
    assert LOSSES == regs["loss"].choices()
    assert REGULARIZERS == regs["regularizer"].choices()
    assert MODELS == regs["kernel"].choices()
    assert METHODS + GREEDY_VARIANTS == regs["method"].choices()
    assert GREEDY_VARIANTS == tuple(f"greedy:{c}" for c in CRITERIA)
    # predictive.PRIORS holds the values the functions take: None for "none"
    assert tuple(prior_value(p) for p in PRIOR_REGISTRY.choices()) == PRIORS
    for kind, reg in regs.items():
        assert len(reg) > 0 and all(e.description for e in reg.entries()), kind


def test_errors_are_the_steps_errors():
    regs = registries()
    for kind in ("criterion", "cost"):
        with pytest.raises(PlanningError, match="must be one of"):
            regs[kind].get("nope")
    for kind in ("loss", "regularizer", "prior", "kernel", "method"):
        with pytest.raises(ModelError, match="must be one of"):
            regs[kind].get("nope")


# ---------------------------------------------------------------- aliases everywhere
def test_aliases_are_accepted_by_the_public_functions_and_normalised():
    import xarray as xr

    from lrm_cvx import Region
    from lrm_cvx.evaluation import check_method
    from lrm_cvx.glrm.losses import Absolute, get_loss
    from lrm_cvx.glrm.regularizers import L1, NonNegative, ZeroReg, get_regularizer
    from lrm_cvx.information import AOptimalOracle, make_oracle
    from lrm_cvx.planning import plan_greedy
    from lrm_cvx.planning.routecost import make_cost

    rng = np.random.default_rng(0)
    lat, lon = np.linspace(4, 0, 5), np.linspace(0, 4, 5)
    region = Region(lat=xr.DataArray(lat, dims="lat", coords={"lat": lat}),
                    lon=xr.DataArray(lon, dims="lon", coords={"lon": lon}),
                    mask=np.ones((5, 5), bool))
    Y = rng.standard_normal((2, 25))
    a = plan_greedy(Y, region, 12, 5, criterion="aopt", cost="nn", ridge=1e-3, progress=False)
    b = plan_greedy(Y, region, 12, 5, criterion="a-optimal", cost="nearest-neighbor",
                    ridge=1e-3, progress=False)
    assert a == b and a.criterion == "a-optimal" and a.cost_function == "nearest-neighbor"
    assert plan_greedy(Y, region, 12, 5, criterion="A_Optimal", ridge=1e-3,
                       progress=False) == b
    assert isinstance(make_oracle("aopt", Y, 1e-3, [0, 1]), AOptimalOracle)
    assert make_cost("NN", region.grid_index, [12], np.arange(25)).name == "nearest-neighbor"
    assert isinstance(get_loss("l1"), Absolute) and isinstance(get_loss("L1"), Absolute)
    assert isinstance(get_regularizer("lasso"), L1)
    assert isinstance(get_regularizer("nonnegative"), NonNegative)
    assert isinstance(get_regularizer(None), ZeroReg)
    assert check_method("greedy:aopt") == "greedy:a-optimal"
    assert check_method("Transect-Up") == "transect-up"
    assert prior_value(None) is None and prior_value("none") is None
    assert prior_value("Empirical") == "empirical"


# ---------------------------------------------------------------- docs tables
_MARK = re.compile(r"<!-- choices: (\w+)(?:, column (\d+))? -->")
_TOKEN = re.compile(r"`([^`]+)`")


def _doc_tables():
    for path in sorted(DOCS.glob("*.md")):
        lines = path.read_text().splitlines()
        for i, line in enumerate(lines):
            m = _MARK.search(line)
            if not m:
                continue
            rows = []
            for row in lines[i + 1:]:
                if not row.startswith("|"):
                    break
                rows.append(row)
            yield path.name, m.group(1), int(m.group(2) or 1), rows


def _cells(row: str) -> list[str]:
    """The cells of a markdown table row (pipes inside backticks do not split)."""
    cells, cur, code = [], "", False
    for ch in row.strip()[1:]:
        if ch == "`":
            code = not code
        if ch == "|" and not code:
            cells.append(cur.strip())
            cur = ""
        else:
            cur += ch
    return cells


def _names(cell: str) -> list:
    out = []
    for tok in _TOKEN.findall(cell):
        tok = tok.strip().strip('"')
        out.append(None if tok == "None" else tok)
    return out


def test_every_registry_has_a_docs_table():
    kinds = {kind for _, kind, _, _ in _doc_tables()}
    assert kinds == set(registries()), "a registry without a docs table (or an unknown marker)"


@pytest.mark.parametrize("doc,kind,column,rows",
                         [pytest.param(*t, id=f"{t[0]}:{t[1]}") for t in _doc_tables()])
def test_docs_table_names_exactly_the_registered_entries(doc, kind, column, rows):
    reg = registries()[kind]
    names, aliases = [], {}
    header = _cells(rows[0])
    alias_col = header.index("aliases") if "aliases" in header else None
    for row in rows[2:]:
        cells = _cells(row)
        found = _names(cells[column - 1])
        if alias_col is not None:  # a separate aliases column
            found += _names(cells[alias_col])
        if not found:
            continue  # e.g. "any callable" (not a named choice)
        names.append(found[0])
        aliases[found[0]] = set(found[1:])
    assert names == list(reg.choices()), f"{doc}: the {kind} table"
    for e in reg.entries():
        assert aliases[e.name] == set(e.aliases), f"{doc}: aliases of {e.name}"


def test_cli_docs_list_the_registered_choices():
    """docs/cli.md: every ``--option a|b|c`` list of a registry's option is exactly its
    choices, and every registered criterion, cost, loss and kernel is named."""
    opt_kind = {"criterion": "criterion", "cost": "cost", "loss": "loss", "spatial": "kernel",
                "prior": "prior"}
    text = (DOCS / "cli.md").read_text()
    for opt, values in re.findall(r"--(\w+) ([\w:-]+(?:\|[\w:-]+)+)", text):
        if opt in opt_kind:
            assert values.split("|") == list(registries()[opt_kind[opt]].choices()), opt
    words = set(re.findall(r"[\w:-]+", text))
    for kind in ("criterion", "cost", "loss", "kernel"):
        missing = set(registries()[kind].choices()) - words
        assert not missing, f"docs/cli.md does not name the {kind} {sorted(missing)}"


def test_cli_choices_are_the_registries():
    from lrm_cvx.cli import build_parser

    opt_kind = {"--criterion": "criterion", "--cost": "cost", "--loss": "loss",
                "--spatial": "kernel", "--prior": "prior"}
    sub = next(a for a in build_parser()._actions if a.choices and hasattr(a, "_name_parser_map"))
    checked = 0
    for parser in sub.choices.values():
        for action in parser._actions:
            kind = next((opt_kind[o] for o in action.option_strings if o in opt_kind), None)
            if kind and action.choices is not None:
                extra = {"auto"} if kind == "kernel" else set()  # spatial="auto" chooses one
                assert set(action.choices) == set(registries()[kind].choices()) | extra, action
                checked += 1
    assert checked >= 5
