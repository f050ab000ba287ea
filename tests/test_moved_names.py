"""Layers: helpers re-exported where they were first defined are the same objects, the single
registries and settings are the ones every reader uses, and ``GLRM.X`` / ``Y`` are the arrays."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from lrm_cvx import GLRM
from lrm_cvx.errors import ModelError
from lrm_cvx.io.samples import synthetic_dynamic_field


@pytest.fixture(scope="module")
def model():
    field = synthetic_dynamic_field(24, (6, 7), 3, seed=2, noise=0.03)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return GLRM(3, progress=False, max_iter=20, random_state=0, temporal="ar1").fit(field)


def test_glrm_x_y_are_the_fitted_arrays(model):
    assert model.X.shape == model.X_.shape and model.Y.shape == model.Y_.shape
    assert model.X.dtype == np.float64 and model.Y.dtype == np.float64
    np.testing.assert_array_equal(model.Y, model.Y_.values)
    np.testing.assert_array_equal(model._Xv, model.X)
    with pytest.raises(AttributeError):
        model.Y = np.zeros((3, 4))
    with pytest.raises(ModelError):
        _ = GLRM(2).Y


def test_old_locations_of_moved_helpers_are_the_same_objects():
    import lrm_cvx.information as info
    import lrm_cvx.monitor as monitor
    import lrm_cvx.spatial as sp
    from lrm_cvx.belief import filter

    assert info.GridConv is sp.GridConv and info.gp_noise is sp.gp_noise
    assert info.gp_latent_cov is sp.gp_latent_cov and info.check_gp_inputs is sp.check_gp_inputs
    assert issubclass(monitor.MonitorState, filter.LatentFilter)


def test_moved_helpers_are_imported_from_their_module_only():
    """The calibration's and the filter's helpers have one import location each."""
    import lrm_cvx.monitor as monitor
    from lrm_cvx.glrm import calibrated
    from lrm_cvx.validation import blending, calibration

    assert monitor.__all__ == ["MonitorState"]
    assert not hasattr(monitor, "parse_time") and not hasattr(monitor, "memoryless_dynamics")
    for name in ("variance_scale", "noise_variance", "select_dynamics", "unblended_dynamics",
                 "sample_sets", "flown_sets"):
        assert not hasattr(calibration, name), name
    assert not {"Calibration", "clone_model", "training_values"} & set(calibration.__all__)
    assert calibrated.variance_scale and blending.select_dynamics


def test_one_temporal_registry():
    from lrm_cvx.cli import build_parser
    from lrm_cvx.glrm.dynamics import TEMPORAL, temporal_value

    assert TEMPORAL.choices() == ("none", "ar1", "seasonal", "auto")
    assert temporal_value(None) is None and temporal_value("none") is None
    assert temporal_value("AR1") == "ar1"
    with pytest.raises(ModelError, match="temporal must be one of"):
        temporal_value("ar2")
    sub = next(a for a in build_parser()._actions if hasattr(a, "_name_parser_map"))
    found = [a for p in sub.choices.values() for a in p._actions
             if "--temporal" in a.option_strings]
    assert found and all(list(a.choices) == list(TEMPORAL.choices()) for a in found)


def test_one_recommended_setting():
    from lrm_cvx import cli, demo
    from lrm_cvx.recommended import RECOMMENDED

    assert cli.RECOMMENDED is RECOMMENDED
    assert demo.SETTING is RECOMMENDED
