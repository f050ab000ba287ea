"""Validated choices: refit a model on part of its record, score the held-out part, choose.

``temporal="auto"`` (:mod:`.selection`), ``spatial="auto"`` (:mod:`.kernel_selection`), the
calibration (:mod:`.calibration`) and the dynamics blend (:mod:`.blending`) share the refits
(:mod:`.refits`), the sample designs a campaign flies (:mod:`.designs`) and the paired
bootstrap rule (:mod:`.paired`).
"""

from __future__ import annotations
