"""Old import location of the certificate (kept so existing code keeps working).

The relaxation and its dual bound moved to :mod:`lrm_cvx.planning.dopt`; the plan certificate
(``plan_bound``, ``PlanCertificate``, the distance limits) to :mod:`lrm_cvx.planning.certificate`.
Every name importable from here before the split still is (issue #15). New code imports from
the two modules.
"""

from __future__ import annotations

from .certificate import (  # noqa: F401
    _NUDGE,
    PlanCertificate,
    _cap_ladder,
    _check_plan_feasible,
    _check_plan_limits,
    _cover_squares,
    _gap,
    _midpoint_cover,
    _min_spacing_km,
    _online_bound,
    _path_aware,
    _plan_criterion,
    _refined,
    _square_distance,
    _square_limit,
    _start_limit,
    plan_bound,
)
from .dopt import (  # noqa: F401
    _CLARABEL_OPTS,
    _DIST_EPS,
    _FW_LIMITED,
    _SCS_OPTS,
    _SOLVERS,
    _TIGHT,
    Bound,
    _check_candidates,
    _check_n_ridge,
    _chol,
    _dual_from_M,
    _feasible,
    _frank_wolfe,
    _inv_lower,
    _leverages,
    _leverages_kernel,
    _line_search,
    _moment,
    _Polytope,
    _polytope_from_limits,
    _relaxation,
    _solve_restricted,
    _top_sum,
    _top_vertex,
    certify_weights,
    dopt_upper_bound,
    dual_value,
)

__all__ = [
    "Bound",
    "PlanCertificate",
    "dopt_upper_bound",
    "plan_bound",
    "dual_value",
    "certify_weights",
]
