"""Module boundaries: no module imports another module's private (``_name``) helpers.

A helper two modules need gets a public name in the module that owns it (docs/architecture.md).
The pairs below are the debt left when this test was written; a new pair fails here. Shrink the
list when a pair is cleaned up, never grow it.
"""

import ast
from pathlib import Path

import lrm_cvx

SRC = Path(lrm_cvx.__file__).parent

# (importer, owner): private names the importer may still take from the owner
KNOWN_DEBT = {
    ("lrm_cvx.glrm.quadratic", "lrm_cvx.glrm.kernels"),
    ("lrm_cvx.planning.bound", "lrm_cvx.planning.certificate"),  # the old import location
    ("lrm_cvx.planning.bound", "lrm_cvx.planning.dopt"),  # re-exports every name
    ("lrm_cvx.planning.certificate", "lrm_cvx.planning.dopt"),
    ("lrm_cvx.planning.relaxation", "lrm_cvx.planning.certificate"),
    ("lrm_cvx.planning.relaxation", "lrm_cvx.planning.dopt"),
}


def private_imports() -> set[tuple[str, str, str]]:
    """``(importer, owner, name)`` of every ``from <lrm_cvx module> import _name``."""
    found = set()
    for path in sorted(SRC.rglob("*.py")):
        parts = list(path.relative_to(SRC.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
            package = parts
        else:
            package = parts[:-1]
        importer = ".".join(parts)
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if not isinstance(node, ast.ImportFrom):
                continue
            if node.level:
                base = package[:len(package) - (node.level - 1)]
                owner = ".".join(base + ([node.module] if node.module else []))
            else:
                owner = node.module or ""
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
