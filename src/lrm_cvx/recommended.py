"""The recommended setting of docs/reconstruction.md: one dict that the CLI and the demo read.

Fit ``GLRM(offset=True, spatial="exponential")``, plan with the gp-variance criterion from the
start cell alone (``method`` is its name in ``evaluate``), predict with the empirical prior and
the kriged GP residual (``fold_spatial``); a model for monitoring chooses its temporal model on
the training snapshots (``temporal="auto"``, glrm/selection.py). ``lrm-cvx ... --recommended``
switches it on; ``lrm_cvx.demo`` runs it beside the paper's setting. Plain data, so it sits at
the base of the layers.
"""

from __future__ import annotations

from typing import Any

__all__ = ["RECOMMENDED"]

RECOMMENDED: dict[str, Any] = {
    "offset": True, "spatial": "exponential", "criterion": "gp-variance",
    "method": "greedy:gp-variance", "initial": "start", "prior": "empirical",
    "fold_spatial": True, "temporal": "auto",
}
