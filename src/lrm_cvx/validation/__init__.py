"""Validated choices: refit a model on part of its record, score the held-out part, choose.

``rank=``/``temporal="auto"`` (:mod:`.selection`), ``spatial="auto"``
(:mod:`.kernel_selection`), the calibration (:mod:`.calibration`) and the dynamics blend
(:mod:`.blending`) share the refits (:mod:`.refits`), the sample designs a campaign flies
(:mod:`.designs`) and the paired bootstrap rule (:mod:`.paired`); :mod:`.choices` runs the
ones ``GLRM.fit`` validates. Importing this package registers them in
:data:`~lrm_cvx.glrm.hooks.HOOKS`.
"""

from __future__ import annotations

from ..glrm.hooks import HOOKS
from .calibration import calibrate
from .choices import choose_rank, clone, validate_choices, window_of
from .kernel_selection import select_kernel
from .selection import check_auto_data

HOOKS.register("check-auto-data", check_auto_data,
               description="the early check of the data of temporal='auto' / rank='auto'")
HOOKS.register("choose-rank", choose_rank, description="rank='auto', before the fit")
HOOKS.register("validate-choices", validate_choices,
               description="temporal='auto' and calibration=, after the fit")
HOOKS.register("validation-window", window_of,
               description="the window of a large region the validations read")
HOOKS.register("clone-model", clone, description="an unfitted copy for a refit")
HOOKS.register("calibrate", calibrate, description="calibration=: the keywords it accepts")
HOOKS.register("select-kernel", select_kernel,
               description="spatial='auto': the residual kernel validated on a sample")
