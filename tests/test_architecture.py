"""Module boundaries: imports run down the layers, never in a circle, never into private names.

The import graph is drawn from the code's own imports, module level and function level (every
``import`` / ``from ... import`` anywhere in a file, and every ``importlib.import_module`` /
``__import__`` of a literal module name). ``from lrm_cvx.pkg import name`` where
``pkg/__init__.py`` re-exports ``name`` counts as an import of the module that defines ``name``;
a package ``__init__`` importing its own children is fine. The layer order below is the one
``docs/architecture.md`` draws; an import may go to its own layer or any layer below.

A helper two modules need gets a public name in the module that owns it (docs/architecture.md).
``KNOWN_DEBT`` (private names) is the debt left: a new entry fails here. Shrink it when a pair is
cleaned up, never grow it. No import runs up a layer or closes a cycle (``KNOWN_VIOLATIONS`` stays
empty).
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

import lrm_cvx

SRC = Path(lrm_cvx.__file__).parent

# ------------------------------------------------------------------------------ the layer order
# lowest first; a module belongs to the layer of its longest matching prefix (a package name
# covers its submodules). An import may go sideways (same layer) or down, never up.
LAYERS: tuple[tuple[str, ...], ...] = (
    # base: errors, shared checks, BLAS threads, the Registry class, the recommended setting
    # and the map helpers, which take plain arrays: the interactive (folium) map builder, the
    # coastlines of the static maps (plots and Plan.plot draw them)
    ("lrm_cvx.errors", "lrm_cvx._validation", "lrm_cvx._blas", "lrm_cvx.registry",
     "lrm_cvx.recommended", "lrm_cvx.interactive", "lrm_cvx.coastlines"),
    # grid geometry (the readers crop and order by it, so it sits below io)
    ("lrm_cvx.region",),
    # loaders and writers; the bundled samples (io.generic's `sample:NAME`)
    ("lrm_cvx.io", "lrm_cvx.datasets"),
    # the GP residual model (covariance, kriging): the fold-in's spatial noise uses it
    ("lrm_cvx.spatial",),
    # the low-rank model and its fit (with the temporal model of its factors and the variance
    # factors it carries); it reaches the packages above through glrm.hooks.HOOKS
    ("lrm_cvx.glrm",),
    # the belief: the posterior of a new snapshot, observation rows, fold-in, the filter
    ("lrm_cvx.belief",),
    # validated choices: refits, designs, the paired rule, temporal / spatial / rank "auto",
    # the calibration and the dynamics blend
    ("lrm_cvx.validation",),
    # what a planner maximises and what a route costs
    ("lrm_cvx.information", "lrm_cvx.gp_structured", "lrm_cvx.oracles"),
    # planners, plans and certificates
    ("lrm_cvx.planning",),
    # research tools used by tests and benchmarks (the convex floor); nothing imports them
    ("lrm_cvx.experimental",),
    # persistent monitoring: the filter state and the day-after-day simulation
    # and scoring: a plan's scores on held-out snapshots (evaluation and campaigns)
    ("lrm_cvx.monitor", "lrm_cvx.campaign", "lrm_cvx.replanning", "lrm_cvx.scoring"),
    # the paper's protocol and its result tables
    ("lrm_cvx.evaluation", "lrm_cvx.evaluation_tables"),
    # the edges: commands, the demo, figures, the xarray accessor
    ("lrm_cvx.cli", "lrm_cvx.cli_common", "lrm_cvx.cli_fit", "lrm_cvx.cli_plan",
     "lrm_cvx.cli_evaluate", "lrm_cvx.cli_monitor", "lrm_cvx.demo", "lrm_cvx.plots",
     "lrm_cvx.accessor"),
)

# (importer, imported): an import the layer / cycle checks would accept, with the reason. Empty:
# keep it so.
KNOWN_VIOLATIONS: dict[tuple[str, str], str] = {}


# ------------------------------------------------------------------------------ the checker
@dataclass(frozen=True)
class Edge:
    """One import: ``importer`` imports ``target`` at ``path:line``."""

    importer: str
    target: str
    path: Path
    line: int

    def where(self) -> str:
        return f"{self.path}:{self.line}: {self.importer} imports {self.target}"


def module_map(src: Path) -> dict[str, tuple[Path, list[str]]]:
    """``module name -> (file, package parts)`` of every ``.py`` under the package ``src``."""
    mods = {}
    for path in sorted(src.rglob("*.py")):
        parts = list(path.relative_to(src.parent).with_suffix("").parts)
        package = parts[:-1]
        if parts[-1] == "__init__":
            parts = parts[:-1]
            package = parts
        mods[".".join(parts)] = (path, package)
    return mods


def _owner(node: ast.ImportFrom, package: list[str]) -> str:
    """The absolute module name of a ``from X import ...`` (relative imports resolved)."""
    if node.level:
        base = package[:len(package) - (node.level - 1)]
        return ".".join(base + ([node.module] if node.module else []))
    return node.module or ""


def reexports(mods: dict) -> dict[tuple[str, str], str]:
    """``(package, name) -> module``: names a package ``__init__`` takes from a child."""
    out = {}
    for mod, (path, package) in mods.items():
        if path.name != "__init__.py":
            continue
        body = ast.parse(path.read_text(encoding="utf-8")).body
        for block in body:  # names loaded on first use are declared under TYPE_CHECKING
            if isinstance(block, ast.If) and getattr(block.test, "id", "") == "TYPE_CHECKING":
                body = body + block.body
        for node in body:
            if isinstance(node, ast.ImportFrom):
                owner = _owner(node, package)
                for alias in node.names:
                    child = f"{owner}.{alias.name}"
                    out[(mod, alias.asname or alias.name)] = child if child in mods else owner
    return out


def _resolve(target: str, mods: dict, again: dict) -> str | None:
    """The module ``target`` names: itself, the nearest enclosing module, or a re-export's."""
    seen = set()
    while target not in mods and "." in target:
        pkg, name = target.rsplit(".", 1)
        if (pkg, name) in again and target not in seen:
            seen.add(target)
            target = again[(pkg, name)]
        else:
            target = pkg
    return target if target in mods else None


def _dynamic_import(node: ast.AST, package: list[str]) -> str | None:
    """The module an ``importlib.import_module("...")`` / ``import_module(".x", __package__)`` /
    ``__import__("...")`` call names with a literal string (relative names resolved against
    ``package``), else None."""
    if not isinstance(node, ast.Call) or not node.args:
        return None
    func = node.func
    name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)
    arg = node.args[0]
    if name not in ("import_module", "__import__") or not (
            isinstance(arg, ast.Constant) and isinstance(arg.value, str)):
        return None
    text = arg.value
    if not text.startswith("."):
        return text
    level = len(text) - len(text.lstrip("."))
    base = package[:len(package) - (level - 1)]
    return ".".join(base + ([text[level:]] if text[level:] else []))


def import_edges(src: Path) -> list[Edge]:
    """Every import between modules of ``src`` (module and function level)."""
    mods = module_map(src)
    again = reexports(mods)
    root = src.name
    edges = []
    for mod, (path, package) in mods.items():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom):
                owner = _owner(node, package)
                names = [f"{owner}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif (name := _dynamic_import(node, package)) is not None:
                names = [name]
            else:
                continue
            for name in names:
                if name.split(".")[0] != root:
                    continue
                target = _resolve(name, mods, again)
                if target is None or target == mod:
                    continue
                if path.name == "__init__.py" and target.startswith(mod + "."):
                    continue  # a package importing its own children
                edges.append(Edge(mod, target, path, node.lineno))
    return sorted(set(edges), key=lambda e: (e.importer, e.line, e.target))


def layer_of(module: str, layers) -> int:
    """The index of ``module``'s layer (its longest matching prefix); -1 for the root package."""
    best, where = -1, -1
    for i, layer in enumerate(layers):
        for prefix in layer:
            if (module == prefix or module.startswith(prefix + ".")) and len(prefix) > best:
                best, where = len(prefix), i
    return where


def cycles(edges: list[Edge]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    graph: dict[str, set[str]] = {}
    for e in edges:
        graph.setdefault(e.importer, set()).add(e.target)
        graph.setdefault(e.target, set())
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def layer_problems(src: Path, layers, allowed) -> list[str]:
    """Every upward import and every import inside a cycle, as ``file:line: ...`` lines."""
    edges = [e for e in import_edges(src) if (e.importer, e.target) not in allowed]
    problems = []
    for e in edges:
        a, b = layer_of(e.importer, layers), layer_of(e.target, layers)
        if a == -1 and e.importer != src.name:
            problems.append(f"{e.where()} ({e.importer} is in no layer: add it to LAYERS)")
        elif b > a >= 0:
            problems.append(f"{e.where()} (runs up from layer {a} to layer {b})")
    for comp in cycles(edges):
        members = set(comp)
        first: dict[tuple[str, str], Edge] = {}
        for e in edges:
            if e.importer in members and e.target in members:
                first.setdefault((e.importer, e.target), e)
        inside = [e.where() for e in first.values()]
        problems.append("cycle between " + ", ".join(comp) + ":\n    " + "\n    ".join(inside))
    return problems


# ------------------------------------------------------------------------------ the package
def test_imports_run_down_the_layers_without_cycles():
    problems = layer_problems(SRC, LAYERS, KNOWN_VIOLATIONS)
    assert not problems, ("imports that run up the layers or close a cycle (docs/architecture.md, "
                          "'Layers'):\n" + "\n".join(problems))


def test_every_module_has_a_layer():
    missing = [m for m in module_map(SRC) if m != "lrm_cvx" and layer_of(m, LAYERS) < 0]
    assert not missing, f"add these modules to LAYERS: {missing}"


def test_known_violations_are_still_there():
    # an allow-list entry whose import is gone is removed, so the list only shrinks
    present = {(e.importer, e.target) for e in import_edges(SRC)}
    stale = sorted(f"{a} -> {b}" for a, b in KNOWN_VIOLATIONS if (a, b) not in present)
    assert not stale, "remove these entries from KNOWN_VIOLATIONS:\n" + "\n".join(stale)


def test_graph_sees_function_level_and_reexported_imports():
    edges = {(e.importer, e.target) for e in import_edges(SRC)}
    # `from .glrm import GLRM` in cli_common resolves to the module that defines GLRM
    assert ("lrm_cvx.cli_common", "lrm_cvx.glrm.model") in edges
    # a package __init__ importing its children is not an edge
    assert not any(a == "lrm_cvx.glrm" and b.startswith("lrm_cvx.glrm.") for a, b in edges)


def test_the_model_reaches_the_packages_above_through_registered_hooks():
    # glrm imports neither the belief nor the validation: GLRM looks their steps up in HOOKS,
    # which `import lrm_cvx` fills (a step used but never registered fails here)
    import re

    from lrm_cvx.glrm.hooks import HOOKS

    used = {name for path in sorted((SRC / "glrm").glob("*.py"))
            for name in re.findall(r'HOOKS\.get\("([a-z-]+)"\)', path.read_text(encoding="utf-8"))}
    assert {"model-prior", "choose-rank", "validate-choices"} <= used
    assert used <= set(HOOKS.choices()), sorted(used - set(HOOKS.choices()))
    assert not [e.where() for e in import_edges(SRC) if e.importer.startswith("lrm_cvx.glrm")
                and e.target.startswith(("lrm_cvx.belief", "lrm_cvx.validation"))]


# ------------------------------------------------------------------------------ the checker itself
FAKE_LAYERS = (("fake.low",), ("fake.mid",), ("fake.high",))


def _fake(tmp_path: Path, files: dict[str, str]) -> Path:
    src = tmp_path / "fake"
    for name, text in {"__init__.py": "", **files}.items():
        (src / name).parent.mkdir(parents=True, exist_ok=True)
        (src / name).write_text(text, encoding="utf-8")
    return src


def test_checker_catches_an_upward_import_at_function_level(tmp_path):
    src = _fake(tmp_path, {
        "low.py": "import os\n\n\ndef f():\n    from .high import g\n    return g\n",
        "mid.py": "from .low import f\n",
        "high.py": "from fake import mid\n\n\ndef g():\n    pass\n",
    })
    problems = layer_problems(src, FAKE_LAYERS, {})
    assert len(problems) == 2  # the upward import, and the cycle it closes
    assert problems[0].startswith(f"{src / 'low.py'}:5: fake.low imports fake.high")
    assert "runs up from layer 0 to layer 2" in problems[0]
    assert problems[1].startswith("cycle between fake.high, fake.low, fake.mid")
    # an allowed entry is accepted, and then nothing is left
    allowed = {("fake.low", "fake.high"): "test"}
    assert layer_problems(src, FAKE_LAYERS, allowed) == []


def test_checker_sees_importlib_imports(tmp_path):
    src = _fake(tmp_path, {
        "low.py": ("import importlib\n\n\ndef f():\n"
                   "    return importlib.import_module('fake.high')\n"),
        "mid.py": "from importlib import import_module\n\nm = import_module('.low', __package__)\n",
        "high.py": "",
    })
    edges = {(e.importer, e.target, e.line) for e in import_edges(src)}
    assert ("fake.low", "fake.high", 5) in edges and ("fake.mid", "fake.low", 3) in edges
    problems = layer_problems(src, FAKE_LAYERS, {})
    assert len(problems) == 1 and "runs up from layer 0 to layer 2" in problems[0]


def test_checker_catches_a_cycle_inside_a_layer_through_a_reexport(tmp_path):
    src = _fake(tmp_path, {
        "low.py": "",
        "mid/__init__.py": "from .a import f\nfrom .b import g\n",
        "mid/a.py": "def f():\n    from fake.mid import g\n    return g\n",
        "mid/b.py": "from . import a\n\n\ndef g():\n    pass\n",
    })
    problems = layer_problems(src, FAKE_LAYERS, {})
    assert len(problems) == 1
    assert problems[0].startswith("cycle between fake.mid.a, fake.mid.b")
    assert f"{src / 'mid' / 'a.py'}:2: fake.mid.a imports fake.mid.b" in problems[0]


def test_checker_allows_a_package_importing_its_children(tmp_path):
    src = _fake(tmp_path, {
        "low.py": "",
        "mid/__init__.py": "from .a import f\n",
        "mid/a.py": "from ..low import *\n\n\ndef f():\n    from fake.mid import f\n",
    })
    assert layer_problems(src, FAKE_LAYERS, {}) == []


def test_nothing_outside_glrm_reads_the_models_private_arrays():
    # GLRM.X / GLRM.Y are the public (k, T) / (k, L) arrays
    inside = {"glrm", "validation"}  # validation.selection still reads model._Xv
    found = [f"{path}:{i}" for path in sorted(SRC.rglob("*.py")) if not inside & set(path.parts)
             for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
             if "._Xv" in line or "._Yv" in line]
    assert not found, "use model.X / model.Y:\n" + "\n".join(found)


# ------------------------------------------------------------------------------ private names
# (importer, owner): private names the importer may still take from the owner
KNOWN_DEBT = {
    ("lrm_cvx.planning.certificate", "lrm_cvx.planning.dopt"),
    ("lrm_cvx.planning.relaxation", "lrm_cvx.planning.certificate"),
    ("lrm_cvx.planning.relaxation", "lrm_cvx.planning.dopt"),
}


def private_imports() -> set[tuple[str, str, str]]:
    """``(importer, owner, name)`` of every ``from <lrm_cvx module> import _name``."""
    found = set()
    for importer, (path, package) in module_map(SRC).items():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if not isinstance(node, ast.ImportFrom):
                continue
            owner = _owner(node, package)
            if owner.split(".")[0] != "lrm_cvx" or owner == importer:
                continue
            for alias in node.names:
                if alias.name.startswith("_") and not alias.name.startswith("__"):
                    found.add((importer, owner, alias.name))
    return found


def test_scanner_sees_relative_and_absolute_imports():
    # the scanner itself: it resolves relative imports and finds a known debt pair
    found = private_imports()
    assert ("lrm_cvx.planning.relaxation", "lrm_cvx.planning.dopt", "_Polytope") in found
    assert all(owner.startswith("lrm_cvx") for _, owner, _ in found)


def test_no_new_private_imports_across_modules():
    new = sorted(f"{imp} imports {name} from {owner}" for imp, owner, name in private_imports()
                 if (imp, owner) not in KNOWN_DEBT)
    assert not new, ("give these helpers a public name in the module that owns them:\n"
                     + "\n".join(new))


if __name__ == "__main__":  # print the graph's problems and cycles (a development aid)
    for line in layer_problems(SRC, LAYERS, {}):
        print(line)


def test_importing_the_package_loads_neither_cvxpy_nor_numba():
    # the public names load on first use (registry.lazy_attributes): a CLI start stays light
    import subprocess
    import sys

    code = ("import sys, lrm_cvx, lrm_cvx.glrm, lrm_cvx.belief; "
            "print(sorted(m for m in ('cvxpy', 'numba') if m in sys.modules)); "
            "from lrm_cvx.glrm import GLRM; from lrm_cvx.glrm.model import GLRM as G; "
            "print(GLRM is G)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.split("\n")
    assert out[0] == "[]" and out[1] == "True"


def test_no_module_is_over_900_lines():
    """Small modules with one job each: a module that grows past 900 lines is split at its seams
    (its docstrings left whole), not trimmed."""
    long = {str(p.relative_to(SRC)): n for p in SRC.rglob("*.py")
            if (n := len(p.read_text(encoding="utf-8").splitlines())) > 900}
    assert not long, long
