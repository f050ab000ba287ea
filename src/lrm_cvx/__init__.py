"""lrm-cvx: persistent environmental monitoring with low-rank models.

Load gridded snapshots, fit a generalized low rank model, plan where a robot should sample under a
path budget, certify the plan's optimality gap, and predict the whole map from a few observations.

The main entry points are importable from the top level (loaded on first use)::

    from lrm_cvx import GLRM, load_sample, plan_greedy, evaluate
"""

from __future__ import annotations

from . import accessor as _accessor  # noqa: F401  (registers the .lrm accessor)
from . import belief as _belief  # noqa: F401  (registers the model's fold-in hooks)
from . import errors
from . import validation as _validation  # noqa: F401  (registers its validated choices)
from .region import Region
from .registry import lazy_attributes

__version__ = "0.1.0"

_LAZY = {
    "GLRM": "lrm_cvx.glrm",
    "SolverOptions": "lrm_cvx.glrm",
    "SpatialOptions": "lrm_cvx.glrm",
    "load_sample": "lrm_cvx.datasets",
    "list_samples": "lrm_cvx.datasets",
    "open_data": "lrm_cvx.io.generic",
    "open_ndvi_cdr": "lrm_cvx.io.ndvi",
    "open_image_stack": "lrm_cvx.io.imagery",
    "synthetic_field": "lrm_cvx.io.samples",
    "fisher_information": "lrm_cvx.information",
    "nearest_neighbor_tour": "lrm_cvx.planning.routecost",
    "Plan": "lrm_cvx.planning",
    "plan_greedy": "lrm_cvx.planning",
    "place_sensors": "lrm_cvx.planning",
    "transect": "lrm_cvx.planning",
    "random_walk": "lrm_cvx.planning",
    "refine": "lrm_cvx.planning",
    "PathOptions": "lrm_cvx.planning",
    "PriorTerms": "lrm_cvx.planning",
    "Fleet": "lrm_cvx.planning",
    "plan_bound": "lrm_cvx.planning.certificate",
    "dopt_upper_bound": "lrm_cvx.planning.dopt",
    "evaluate": "lrm_cvx.evaluation",
    "backtest": "lrm_cvx.evaluation",
    "summary": "lrm_cvx.evaluation",
    "EvaluationProtocol": "lrm_cvx.evaluation",
    "PlanningOptions": "lrm_cvx.evaluation",
    "ScoringOptions": "lrm_cvx.evaluation",
    "MonitorState": "lrm_cvx.monitor",
    "simulate_campaign": "lrm_cvx.campaign",
    "Dynamics": "lrm_cvx.glrm.dynamics",
    "calibrate": "lrm_cvx.validation.calibration",
    "select_dynamics": "lrm_cvx.validation.blending",
    "synthetic_dynamic_field": "lrm_cvx.io.samples",
}

__all__ = ["Region", "errors", "__version__", *_LAZY]


__getattr__, __dir__ = lazy_attributes(__name__, _LAZY)
