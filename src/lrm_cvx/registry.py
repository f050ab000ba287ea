"""Registries: the one source of truth for every name a user can pick.

Each kind of choice is a :class:`Registry`: canonical name -> object, with aliases and a one-line
description; the CLI's ``choices``, the docs' tables and the contract tests read the same
registries. Names and aliases follow docs/planning.md, "Names and aliases".
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Hashable, Iterator
from dataclasses import dataclass, replace
from typing import Any

from .errors import LrmError, ModelError

__all__ = ["Registry", "Entry", "Choices", "PRIOR_REGISTRY", "prior_value"]


@dataclass(frozen=True)
class Entry:
    """One registered choice: canonical ``name``, the object, aliases and a one-line description."""

    name: str
    obj: Any
    description: str
    aliases: tuple[Any, ...] = ()


_DECORATE = object()


def lazy_attributes(module: str, table: dict[str, str]
                    ) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """``(__getattr__, __dir__)`` of the package ``module`` whose public names load on first use:
    ``table`` maps each name to the module defining it (absolute, or relative to ``module``), so
    importing the package costs none of those modules' imports (PEP 562)."""
    namespace = sys.modules[module].__dict__

    def get(name: str) -> Any:
        if name in table:
            value = namespace[name] = getattr(importlib.import_module(table[name], module), name)
            return value
        raise AttributeError(f"module {module!r} has no attribute {name!r}")

    def names() -> list[str]:
        return sorted(set(namespace) | set(table))

    return get, names


@dataclass(frozen=True)
class Deferred:
    """An object registered by its import path, ``"package.module:name"``: imported on first
    lookup, so that registering costs no import (a package's hooks registered when ``lrm_cvx``
    is imported, the heavy modules behind them loaded only when used)."""

    target: str

    def load(self) -> Any:
        """The object the path names."""
        module, _, name = self.target.partition(":")
        return getattr(importlib.import_module(module), name)


def _key(name: Any) -> Any:
    """Lookup key: strings compare case-insensitively and without surrounding blanks."""
    return name.strip().lower() if isinstance(name, str) else name


class Choices(tuple):
    """The canonical names of a registry (a plain tuple for ``==``, iteration and printing) whose
    ``in`` also accepts the registry's aliases and any letter case."""

    _registry: Registry

    def __new__(cls, names: tuple[str, ...], registry: Registry) -> Choices:
        self = super().__new__(cls, names)
        self._registry = registry
        return self

    def __contains__(self, name: object) -> bool:
        found = self._registry.resolve(name)
        return found is not None and tuple.__contains__(self, found)

    def __add__(self, other: Any) -> tuple:  # type: ignore[override]
        """``METHODS + GREEDY_VARIANTS`` stays alias-aware when both come from one registry."""
        joined = tuple(self) + tuple(other)
        if isinstance(other, Choices) and other._registry is self._registry:
            return Choices(joined, self._registry)
        return joined

    def __reduce__(self) -> tuple[Any, ...]:  # pickles as a plain tuple
        return (tuple, (tuple(self),))


class Registry:
    """Canonical name -> object, with aliases and one-line descriptions.

    ``kind`` names the choice in messages (``"criterion"``); ``error`` is the project error
    raised for an unknown name (``PlanningError`` for planning choices, ``ModelError`` for model
    choices). Entries keep registration order (the order of ``choices()`` and of docs tables).
    """

    def __init__(self, kind: str, error: type[LrmError] = ModelError) -> None:
        self.kind = kind
        self.error = error
        self._entries: dict[str, Entry] = {}
        self._lookup: dict[Any, str] = {}

    # ------------------------------------------------------------------ registration
    def register(self, name: str, obj: Any = _DECORATE, *, description: str,
                 aliases: tuple[Any, ...] = ()) -> Any:
        """Add ``name`` -> ``obj``; returns ``obj``. Without ``obj``, a decorator."""
        if obj is _DECORATE:
            def deco(o: Any) -> Any:
                self.register(name, o, description=description, aliases=aliases)
                return o
            return deco
        if not isinstance(name, str) or name != name.strip().lower() or not name:
            raise ValueError(f"a registered name must be a non-empty lower-case string: {name!r}")
        if "\n" in description or not description.strip():
            raise ValueError(f"{self.kind} {name!r} needs a one-line description")
        keys = [_key(name), *(_key(a) for a in aliases)]
        for k in keys:
            if k in self._lookup:
                raise ValueError(f"{self.kind} name {k!r} is already registered")
        self._entries[name] = Entry(name, obj, description.strip(), tuple(aliases))
        for k in keys:
            self._lookup[k] = name
        return obj

    # ------------------------------------------------------------------ lookup
    def resolve(self, name: Any) -> str | None:
        """The canonical name of ``name`` (a name or an alias, any case), or ``None``."""
        if not isinstance(name, Hashable):
            return None
        return self._lookup.get(_key(name))

    def canonical(self, name: Any, argument: str | None = None) -> str:
        """The canonical name of ``name``; raises the registry's error listing the choices."""
        found = self.resolve(name)
        if found is None:
            raise self.error(self.message(name, argument))
        return found

    def entry(self, name: Any, argument: str | None = None) -> Entry:
        """The :class:`Entry` of ``name`` (or an alias); raises the registry's error if unknown."""
        entry = self._entries[self.canonical(name, argument)]
        if isinstance(entry.obj, Deferred):  # registered by path: imported on first use
            entry = self._entries[entry.name] = replace(entry, obj=entry.obj.load())
        return entry

    def get(self, name: Any, argument: str | None = None) -> Any:
        """The object registered under ``name`` (or an alias); raises the registry's error
        (naming ``argument``, default the registry's kind, and the valid names) if unknown."""
        return self.entry(name, argument).obj

    def message(self, name: Any, argument: str | None = None) -> str:
        """The one-line error for an unknown ``name``."""
        alias = self.alias_map()
        extra = (" (aliases: " + ", ".join(f"{a!r} = {c!r}" for a, c in alias.items()) + ")"
                 if alias else "")
        return (f"{argument or self.kind} must be one of {list(self.choices())}{extra}, "
                f"got {name!r}")

    # ------------------------------------------------------------------ listings
    def choices(self) -> Choices:
        """Canonical names in registration order (``in`` accepts aliases)."""
        return Choices(tuple(self._entries), self)

    def entries(self) -> tuple[Entry, ...]:
        return tuple(self._entries.values())

    def alias_map(self) -> dict[Any, str]:
        """``{alias: canonical name}`` for every alias."""
        return {a: e.name for e in self._entries.values() for a in e.aliases}

    def markdown_table(self, header: tuple[str, str, str] = ("name", "aliases",
                                                            "description")) -> str:
        """The docs table of this registry (tests/test_docs_choices.py checks docs hold it)."""
        rows = [f"| {header[0]} | {header[1]} | {header[2]} |", "| --- | --- | --- |"]
        for e in self._entries.values():
            al = ", ".join(f"`{a}`" for a in e.aliases) or "-"
            rows.append(f"| `{e.name}` | {al} | {e.description} |")
        return "\n".join(rows)

    def __contains__(self, name: object) -> bool:
        return self.resolve(name) is not None

    def __iter__(self) -> Iterator[str]:
        return iter(self._entries)

    def __len__(self) -> int:
        return len(self._entries)

    def __repr__(self) -> str:
        return f"Registry({self.kind!r}, {list(self._entries)})"


# --------------------------------------------------------------------------- priors
PRIOR_REGISTRY = Registry("prior", ModelError)
"""Priors of the fold-in (``GLRM.complete(prior=...)``, ``planner_kwargs(prior=...)``).
The object is the value the functions take (``None`` or ``"empirical"``)."""
PRIOR_REGISTRY.register("none", None, description="no prior: the paper's least-squares "
                        "fold-in (pass `None`)", aliases=(None,))
PRIOR_REGISTRY.register("empirical", "empirical", description="Gaussian prior on the latent "
                        "vector: mean and covariance of the training columns of `X`")


def prior_value(name: Any) -> Any:
    """The value :mod:`lrm_cvx.glrm.predictive` takes for a prior name (``None`` for no prior)."""
    canon = PRIOR_REGISTRY.canonical(name)
    return None if canon == "none" else canon
