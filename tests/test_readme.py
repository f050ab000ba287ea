"""The README's quick start runs as written (its two set-up commands are CI's own)."""

import re
from pathlib import Path

README = Path(__file__).parents[1] / "README.md"


def test_quick_start_runs(tmp_path, monkeypatch):
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert blocks, "README has no python quick start"
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    namespace: dict = {}
    exec(compile(blocks[0], str(README), "exec"), namespace)  # noqa: S102 - our own README
    assert (tmp_path / "route.geojson").exists() and (tmp_path / "model.nc").exists()
    assert namespace["plan"].cost <= 20 + 1e-9
    assert namespace["result"]["prediction"].dims == ("lat", "lon")


def test_setup_commands_are_the_documented_two():
    text = README.read_text()
    block = re.search(r"## Set up\n\n```bash\n(.*?)```", text, flags=re.S).group(1)
    assert block.strip().splitlines() == ['pip install -e ".[dev]" && lrm-cvx demo', "pytest"]


def test_persistent_monitoring_block_runs(tmp_path, monkeypatch):
    """The README's monitoring loop runs as written and its state loads back with the model."""
    from lrm_cvx.monitor import MonitorState

    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(_block("MonitorState.from_model(model)"), str(README), "exec"), namespace)  # noqa: S102
    state = namespace["state"]
    assert state.time == namespace["test"].time.values[-1]
    back = MonitorState.load(tmp_path / "state.nc", namespace["model"])
    assert back.time == state.time
    assert float(namespace["today"]["std"].max()) > 0


def _block(marker: str) -> str:
    """The README's python block that contains ``marker``."""
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    found = [b for b in blocks if marker in b]
    assert found, f"README has no python block with {marker!r}"
    return found[0]


def test_robots_block_runs(tmp_path, monkeypatch, capsys):
    """Two closed gliders in km: each within 8000 km, each route ends at its start, the printed
    table has the documented columns, the certificate bounds the plan."""
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(_block('metric="km"'), str(README), "exec"), namespace)  # noqa: S102
    plan = namespace["plan"]
    assert len(plan.robot_costs) == 2 and max(plan.robot_costs) <= 8000 + 1e-6
    df = plan.to_dataframe()
    for _, rows in df.groupby("robot"):
        assert rows["cell"].iloc[-1] == rows["cell"].iloc[0]
    assert "waypoint" in capsys.readouterr().out
    cert = plan.certify()
    assert cert.bound >= plan.information


def test_own_record_block_runs(tmp_path, monkeypatch):
    """The README's 'own record' block: open_data on a NetCDF file, the last 8 held out."""
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(_block("open_data("), str(README), "exec"), namespace)  # noqa: S102
    da, model = namespace["da"], namespace["model"]
    assert da.dims == ("time", "lat", "lon")
    assert model.X_.sizes[model.X_.dims[1]] == da.sizes["time"] - 8


def test_defaults_block_runs(tmp_path, monkeypatch, capsys):
    """The README's 'Defaults' block: plan_greedy on a model is the recommended planner (the
    same plan as spelled out), paper=True the paper's on the bare factor matrix."""
    import numpy as np

    from lrm_cvx import plan_greedy
    from lrm_cvx.recommended import RECOMMENDED

    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(_block("paper=True"), str(README), "exec"), namespace)  # noqa: S102
    model, plan, paper = namespace["model"], namespace["plan"], namespace["paper"]
    want = plan_greedy(model.Y_, model.region_, (10.0, 200.0), 20, progress=False,
                       criterion=RECOMMENDED["criterion"], initial=RECOMMENDED["initial"],
                       refine=RECOMMENDED["refine"],
                       prior=model.latent_prior(RECOMMENDED["prior"], spatial=True))
    np.testing.assert_array_equal(plan.route, want.route)
    bare = plan_greedy(model.Y_, model.region_, (10.0, 200.0), 20, progress=False)
    np.testing.assert_array_equal(paper.route, bare.route)
    assert plan.criterion == "gp-variance" and paper.criterion == "fisher"
    assert "gp-variance" in capsys.readouterr().out
