"""Validated choices: candidates scored on held-out parts of a record, one rule, one table.

Every ``"auto"`` setting is a specification of the one search of :mod:`.search` (splitters,
rules, the selection table): ``rank=``/``temporal="auto"`` (:mod:`.selection`),
``spatial="auto"`` (:mod:`.kernel_selection`), the calibration (:mod:`.calibration`), the
dynamics blend (:mod:`.blending`) and :meth:`GLRM.select_rank
<lrm_cvx.glrm.model.GLRM.select_rank>`. They share the refits (:mod:`.refits`), the sample
designs a campaign flies (:mod:`.designs`) and the paired statistics (:mod:`.paired`);
:mod:`.choices` runs the ones ``GLRM.fit`` validates. Importing this package registers them in
:data:`~lrm_cvx.glrm.hooks.HOOKS` by import path (each module is loaded on first use).
"""

from __future__ import annotations

from ..glrm.hooks import HOOKS
from ..registry import Deferred

_HERE = "lrm_cvx.validation"
HOOKS.register("check-auto-data", Deferred(f"{_HERE}.selection:check_auto_data"),
               description="the early check of the data of temporal='auto' / rank='auto'")
HOOKS.register("choose-rank", Deferred(f"{_HERE}.choices:choose_rank"),
               description="rank='auto', before the fit")
HOOKS.register("validate-choices", Deferred(f"{_HERE}.choices:validate_choices"),
               description="temporal='auto' and calibration=, after the fit")
HOOKS.register("validation-window", Deferred(f"{_HERE}.choices:window_of"),
               description="the window of a large region the validations read")
HOOKS.register("clone-model", Deferred(f"{_HERE}.choices:clone"),
               description="an unfitted copy for a refit")
HOOKS.register("calibrate", Deferred(f"{_HERE}.calibration:calibrate"),
               description="calibration=: the keywords it accepts")
HOOKS.register("select-kernel", Deferred(f"{_HERE}.kernel_selection:select_kernel"),
               description="spatial='auto': the residual kernel validated on a sample")
HOOKS.register("select-rank", Deferred(f"{_HERE}.choices:select_rank"),
               description="GLRM.select_rank: held-out RMSE per rank")
