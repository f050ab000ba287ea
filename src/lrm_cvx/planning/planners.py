"""Planners as objects, held by the method registry.

Each planner is a small frozen object with one method, ``plan(Y, region, fleet, path, *, rng,
ridge, prior) -> Plan``; ``evaluate``, ``simulate_campaign`` and the CLI look a method's planner
up in :data:`METHOD_REGISTRY` by name. A new planner goes here, registered with one
``METHOD_REGISTRY.register(name, planner, description=...)`` line.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

from ..errors import ModelError
from ..information import CRITERION_REGISTRY
from ..recommended import RECOMMENDED, recommended_criterion
from ..registry import Choices, Registry
from .baselines import DIRECTIONS, random_walk, transect
from .greedy import plan_greedy
from .lines import CHECKS, lines_where_possible
from .plan import Plan
from .refine import refine_plan
from .refiners import RefineContext
from .request import Fleet, PathOptions
from .static import place_sensors
from .terms import prior_terms

__all__ = ["Planner", "GreedyPlanner", "StaticPlacement", "Transect", "RandomWalk", "Refined",
           "METHOD_REGISTRY", "METHODS", "GREEDY_VARIANTS", "check_method", "planner_for",
           "needs_spatial", "recommended_method"]


class Planner:
    """The interface of a planner: :meth:`plan`; :meth:`configure` fills the choices a planner
    leaves to the caller (``evaluate``'s ``criterion=`` / ``cost=``); :meth:`prior_of` is the
    belief it plans on given a fitted model (None: none); ``uses_rng``: whether its plan
    draws from ``rng`` (else the same inputs give the same plan)."""

    uses_rng = False

    def plan(self, Y: Any, region: Any, fleet: Fleet, path: PathOptions | None = None, *,
             rng: Any = None, ridge: float = 0.0, prior: Any = None) -> Plan:
        raise NotImplementedError

    def configure(self, *, criterion: str = "fisher", cost: str = "nearest-neighbor"
                  ) -> Planner:
        return self

    def prior_of(self, model: Any) -> Any:
        return None


@dataclass(frozen=True)
class GreedyPlanner(Planner):
    """The cost-benefit greedy (:func:`~lrm_cvx.planning.plan_greedy`) with ``criterion`` and
    route ``cost`` (None: the caller's, see :meth:`configure`); ``initial`` its forced cells;
    ``model_prior``: plan on the model's empirical latent prior (the ``greedy:<criterion>``
    methods of ``evaluate``, with the GP residual for ``"gp-variance"``); ``lines``: run the
    recommended check of the route against rivals (``plan_greedy(refine="rivals")``: the
    straight transects and the gentler greedy, kept when the criterion prefers one; where the
    path options allow it)."""

    criterion: str | None = None
    cost: str | None = None
    initial: str = "nearest"
    model_prior: bool = False
    lines: bool = False

    def configure(self, *, criterion: str = "fisher", cost: str = "nearest-neighbor"
                  ) -> GreedyPlanner:
        return replace(self, criterion=self.criterion or criterion, cost=self.cost or cost)

    def prior_of(self, model: Any) -> Any:
        if not self.model_prior:
            return None
        return model.latent_prior("empirical", spatial=self.criterion == "gp-variance")

    def plan(self, Y: Any, region: Any, fleet: Fleet, path: PathOptions | None = None, *,
             rng: Any = None, ridge: float = 0.0, prior: Any = None) -> Plan:
        return plan_greedy(Y, region, fleet, None, criterion=self.criterion or "fisher",
                           cost=self.cost or "nearest-neighbor", ridge=ridge, progress=False,
                           initial=self.initial, prior=prior, path=path,
                           refine=lines_where_possible(path) if self.lines else None,
                           stay=True)


@dataclass(frozen=True)
class StaticPlacement(Planner):
    """Fixed sensors, no travel (:func:`~lrm_cvx.planning.static.place_sensors`): the number of
    sensors is ``fleet.budgets[0]``; ``path.traversable`` (a mask) is where a sensor may
    stand. ``criterion`` ``"fisher"``, ``"a-optimal"``, ``"gp-variance"`` or ``"risk"`` (with
    ``training``), ``exchange`` the swap search."""

    criterion: str = "fisher"
    training: Any = None
    exchange: bool = False
    sweeps: int = 5

    def plan(self, Y: Any, region: Any, fleet: Fleet, path: PathOptions | None = None, *,
             rng: Any = None, ridge: float = 0.0, prior: Any = None) -> Plan:
        n = fleet.budgets[0] if fleet.budgets else None
        n = int(n) if n is not None and float(n) == int(n) else n
        return place_sensors(Y, region, n, criterion=self.criterion, ridge=ridge, prior=prior,
                             traversable=None if path is None else path.traversable,
                             training=self.training, exchange=self.exchange,
                             sweeps=self.sweeps)


@dataclass(frozen=True)
class Transect(Planner):
    """A straight transect (:func:`~lrm_cvx.planning.transect`) going ``direction``."""

    direction: str = "up"

    def plan(self, Y: Any, region: Any, fleet: Fleet, path: PathOptions | None = None, *,
             rng: Any = None, ridge: float = 0.0, prior: Any = None) -> Plan:
        return transect(region, fleet, None, self.direction, Y=Y, ridge=ridge, path=path)


@dataclass(frozen=True)
class RandomWalk(Planner):
    """The random walk on valid 8-neighbours (:func:`~lrm_cvx.planning.random_walk`), drawn
    from ``rng``."""

    uses_rng = True

    def plan(self, Y: Any, region: Any, fleet: Fleet, path: PathOptions | None = None, *,
             rng: Any = None, ridge: float = 0.0, prior: Any = None) -> Plan:
        return random_walk(region, fleet, None, rng, Y=Y, ridge=ridge, path=path)


@dataclass(frozen=True)
class Refined(Planner):
    """``planner``'s plan improved by the local search of
    :func:`~lrm_cvx.planning.refine.refine` (``options`` its keyword arguments): what
    ``plan_greedy(refine=options or True)`` returns for a greedy planner."""

    planner: Planner = field(default_factory=GreedyPlanner)
    options: dict[str, Any] = field(default_factory=dict)

    def configure(self, *, criterion: str = "fisher", cost: str = "nearest-neighbor"
                  ) -> Refined:
        return replace(self, planner=self.planner.configure(criterion=criterion, cost=cost))

    def prior_of(self, model: Any) -> Any:
        return self.planner.prior_of(model)

    @property
    def uses_rng(self) -> bool:  # type: ignore[override]
        return self.planner.uses_rng

    def plan(self, Y: Any, region: Any, fleet: Fleet, path: PathOptions | None = None, *,
             rng: Any = None, ridge: float = 0.0, prior: Any = None) -> Plan:
        plan = self.planner.plan(Y, region, fleet, path, rng=rng, ridge=ridge, prior=prior)
        terms = prior_terms(prior)
        terms.pop("targets")
        return refine_plan(plan, dict(self.options) or True, RefineContext(terms=terms))


# ------------------------------------------------------------------------------ the registry
METHOD_REGISTRY = Registry("method", ModelError)
"""Methods of :func:`~lrm_cvx.evaluation.evaluate` (name -> :class:`Planner`); ``METHODS`` are
the paper's (the default), ``GREEDY_VARIANTS`` the greedy with a criterion and the model's
predictive fold-in (docs/reconstruction.md). ``greedy:<alias>`` is accepted for every criterion
alias."""
METHOD_REGISTRY.register("greedy", GreedyPlanner(), description="the paper's cost-benefit "
                         "greedy (Fisher information, the paper's fold-in)")
for _d in DIRECTIONS:
    METHOD_REGISTRY.register(f"transect-{_d}", Transect(_d),
                             description=f"straight transect going {_d} (a lawnmower at the "
                                         "edge)")
METHOD_REGISTRY.register("random", RandomWalk(), description="random walk on valid "
                         "8-neighbours (`random_trials` walks per start)")
METHODS: tuple[str, ...] = METHOD_REGISTRY.choices()
for _c in CRITERION_REGISTRY.entries():
    METHOD_REGISTRY.register(
        f"greedy:{_c.name}", GreedyPlanner(_c.name, initial="start", model_prior=True,
                                           lines=RECOMMENDED["refine"] in CHECKS),
        aliases=tuple(f"greedy:{a}" for a in _c.aliases),
        description=f"greedy with the `{_c.name}` criterion and the model's predictive fold-in "
                    "(a straight transect or the gentler greedy's route instead where the "
                    "criterion prefers it)",
    )
GREEDY_VARIANTS: tuple[str, ...] = Choices(tuple(m for m in METHOD_REGISTRY.choices()
                                                 if m not in METHODS), METHOD_REGISTRY)


def check_method(m: str) -> str:
    """The canonical name of method ``m`` (aliases accepted); ModelError if unknown."""
    return METHOD_REGISTRY.canonical(m, "method")


def planner_for(method: str, *, criterion: str = "fisher", cost: str = "nearest-neighbor"
                ) -> Planner:
    """The planner of ``method`` (a name or alias) with the caller's ``criterion`` / ``cost``
    filled in where the method leaves them open (:meth:`Planner.configure`)."""
    return METHOD_REGISTRY.get(method, "method").configure(criterion=criterion, cost=cost)


def needs_spatial(method: str) -> bool:
    """Whether ``method`` plans on the model's GP residual (a ``gp-variance`` greedy)."""
    planner = planner_for(method)
    planner = getattr(planner, "planner", planner)  # a Refined planner's greedy
    return bool(getattr(planner, "model_prior", False)) and planner.criterion == "gp-variance"


def recommended_method(spatial: bool) -> str:
    """The recommended setting's method (``RECOMMENDED["method"]``, read now) for a model with
    (``spatial=True``) or without a GP residual: without, a method on the residual becomes the
    greedy on the model's empirical prior with :func:`~lrm_cvx.recommended.recommended_criterion`
    (a filter's forecast in a campaign)."""
    method = check_method(RECOMMENDED["method"])
    return f"greedy:{recommended_criterion(False)}" if not spatial and needs_spatial(method) \
        else method
