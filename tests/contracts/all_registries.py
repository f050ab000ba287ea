"""Every registry of the package by kind, for the contract tests (moved from ``lrm_cvx.registry``).

``lrm_cvx.registry`` sits at the base of the layers, so it cannot import the modules that own the
registries; the tests can.
"""

from __future__ import annotations

from lrm_cvx.registry import PRIOR_REGISTRY, Registry


def registries() -> dict[str, Registry]:
    """Every registry of the package by kind (imports the modules that own them)."""
    from lrm_cvx.evaluation import METHOD_REGISTRY
    from lrm_cvx.glrm.dynamics import TEMPORAL
    from lrm_cvx.glrm.losses import LOSS_REGISTRY
    from lrm_cvx.glrm.regularizers import REGULARIZER_REGISTRY
    from lrm_cvx.information import CRITERION_REGISTRY
    from lrm_cvx.planning.routecost import COST_REGISTRY
    from lrm_cvx.planning.sensors import SENSOR_REGISTRY
    from lrm_cvx.spatial import KERNEL_REGISTRY

    return {
        "criterion": CRITERION_REGISTRY,
        "cost": COST_REGISTRY,
        "loss": LOSS_REGISTRY,
        "regularizer": REGULARIZER_REGISTRY,
        "prior": PRIOR_REGISTRY,
        "kernel": KERNEL_REGISTRY,
        "method": METHOD_REGISTRY,
        "temporal": TEMPORAL,
        "sensor": SENSOR_REGISTRY,
    }
