"""Footprint readings through the daily loop: ``monitor assimilate`` folds in one average per
footprint (the stored plan's sensor by default), the state file keeps today's averaged rows, and
the stored plan keeps its sensor."""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import pytest

from lrm_cvx import GLRM, load_sample
from lrm_cvx.cli import main
from lrm_cvx.monitor import MonitorState
from lrm_cvx.planning.sensors import Sensor, footprint_matrix

SENSOR = "disc:1500km"  # covers a cell's neighbours on the 5-degree sst grid


@pytest.fixture(scope="module")
def loop(tmp_path_factory):
    """A spatial model on all but the last sst winter, a state, and a footprint plan."""
    d = tmp_path_factory.mktemp("footprint_loop")
    model, state = d / "model.nc", d / "state.nc"
    assert main(["-q", "fit", "sample:sst", "--rank", "3", "--paper", "--spatial", "exponential",
                 "--hold-out", "1", "-o", str(model)]) == 0
    assert main(["-q", "monitor", "init", str(model), "--state", str(state),
                 "--memoryless"]) == 0
    assert main(["-q", "monitor", "plan", str(state), "--start", "0", "200", "--budget", "8",
                 "--sensor", SENSOR, "-o", str(d / "plan.csv")]) == 0
    return d, model, state


def _readings(state_path, day):
    """The last winter averaged over the stored plan's footprints: a CSV of centres."""
    state = MonitorState.load(state_path)
    region = state.model.region_
    truth = region.stack(load_sample("sst").isel(time=-1)).astype(np.float64)
    cells = np.asarray(state.current_plan.cells, dtype=np.int64)
    rows = footprint_matrix(region, Sensor.parse(SENSOR), cells)
    covered = rows.multiply(np.isfinite(truth)[None, :]).tocsr()
    values = (covered @ np.nan_to_num(truth)) / np.asarray(covered.sum(axis=1)).ravel()
    path = day / "readings.csv"
    pd.DataFrame({"cell": cells, "value": values}).to_csv(path, index=False)
    return state, cells, values, path


def test_the_stored_plan_keeps_its_sensor(loop):
    _, _, state_path = loop
    assert MonitorState.load(state_path).current_plan.sensor == Sensor.parse(SENSOR)


def test_assimilate_folds_in_footprint_averages(loop, tmp_path, capsys):
    d, _, state_path = loop
    work = tmp_path / "state.nc"
    work.write_bytes(state_path.read_bytes())
    before, cells, values, csv = _readings(work, tmp_path)
    t = str(load_sample("sst").time.values[-1])[:10]
    assert main(["monitor", "assimilate", str(work), str(csv), "--time", t]) == 0
    assert "disc 1500 km footprint averages" in capsys.readouterr().out
    after = MonitorState.load(work)
    expected = before.assimilate_rows(footprint_matrix(before.model.region_, SENSOR, cells),
                                      values, t)
    np.testing.assert_allclose(after.posterior.precision, expected.posterior.precision,
                               rtol=1e-10)
    np.testing.assert_allclose(after.posterior.shift, expected.posterior.shift, rtol=1e-10)
    # --sensor point reads the same file as point values: a different belief
    point = tmp_path / "point.nc"
    point.write_bytes(state_path.read_bytes())
    assert main(["-q", "monitor", "assimilate", str(point), str(csv), "--time", t,
                 "--sensor", "point"]) == 0
    assert not np.allclose(MonitorState.load(point).posterior.shift,
                           after.posterior.shift)


def test_the_state_file_keeps_todays_averaged_rows(tmp_path):
    """A same-day update after save/load equals the update without the round trip (the GLS
    with the spatial residual is re-solved over the day's points *and* averaged rows)."""
    sst = load_sample("sst")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(3, offset=True, spatial="exponential", random_state=0,
                     progress=False).fit(sst.isel(time=slice(None, -1)))
    region = model.region_
    truth = region.stack(sst.isel(time=-1)).astype(np.float64)
    ok = np.flatnonzero(np.isfinite(truth))
    t = sst.time.values[-1]
    state = MonitorState.from_model(model, memoryless=True)
    rows = footprint_matrix(region, SENSOR, ok[[5, 60, 200]])
    state.assimilate_rows(rows, [0.1, -0.2, 0.3], t)
    state.save(tmp_path / "s.nc")
    loaded = MonitorState.load(tmp_path / "s.nc", model=model)
    assert (loaded.posterior.rows != state.posterior.rows).nnz == 0
    cells = ok[[10, 90]]
    a = state.assimilate((cells, truth[cells]), t, force=True).posterior
    b = loaded.assimilate((cells, truth[cells]), t, force=True).posterior
    np.testing.assert_allclose(b.precision, a.precision, rtol=1e-12)
    np.testing.assert_allclose(b.shift, a.shift, rtol=1e-12)


def test_a_towed_sensor_is_refused_by_assimilate(loop, tmp_path, capsys):
    _, _, state_path = loop
    work = tmp_path / "state.nc"
    work.write_bytes(state_path.read_bytes())
    csv = tmp_path / "r.csv"
    pd.DataFrame({"cell": [0], "value": [0.1]}).to_csv(csv, index=False)
    assert main(["-q", "monitor", "assimilate", str(work), str(csv), "--time", "2013-01-01",
                 "--sensor", "towed"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "towed" in err[0]


@pytest.mark.parametrize("text", ["point", "towed", "disc:5km", "square:0.3km,errors=shared",
                                  "square:1km,altitude=0.1,fov=90"])
def test_a_sensor_spec_reads_back(text):
    sensor = Sensor.parse(text)
    assert Sensor.parse(sensor.spec()) == sensor
