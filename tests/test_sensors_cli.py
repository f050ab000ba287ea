"""`lrm-cvx plan --sensor`: the same plan as the Python API, one-line errors for bad sensors."""

import numpy as np
import pandas as pd
import pytest

from lrm_cvx.cli import main
from lrm_cvx.glrm import GLRM
from lrm_cvx.planning import PathOptions, plan_greedy


@pytest.fixture(scope="module")
def sst_model(tmp_path_factory):
    path = tmp_path_factory.mktemp("sst_sensor") / "model.nc"
    assert main(["-q", "fit", "sample:sst", "--rank", "3", "--paper", "-o", str(path)]) == 0
    return path


@pytest.mark.parametrize("flag, sensor", [("disc:600km", "disc:600km"),
                                          ("leg-average", "leg-average")])
def test_plan_with_a_sensor_matches_plan_greedy(sst_model, tmp_path, capsys, flag, sensor):
    out = tmp_path / "route.csv"
    argv = ["plan", str(sst_model), "--start", "10", "-150", "--budget", "12", "--ridge",
            "1e-6", "--sensor", flag, "--paper", "-o", str(out)]
    assert main(argv) == 0
    line = capsys.readouterr().out.splitlines()[0]
    model = GLRM.load(sst_model)
    plan = plan_greedy(model.Y_, model.region_, (10, 210), 12.0, ridge=1e-6, progress=False,
                       path=PathOptions(sensor=sensor))
    np.testing.assert_array_equal(pd.read_csv(out)["cell"], plan.to_dataframe()["cell"])
    assert f"sensor {plan.sensor.describe()}" in line
    assert f"{plan.information:.4f}" in line


@pytest.mark.parametrize("flag, message", [("disc:-5km", "size_km"), ("blob", "sensor must be"),
                                           ("square", "width > 0")])
def test_bad_sensor_is_a_one_line_error(sst_model, capsys, flag, message):
    assert main(["-q", "plan", str(sst_model), "--start", "10", "-150", "--budget", "5",
                 "--sensor", flag]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
