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

    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert len(blocks) >= 2, "README has no persistent-monitoring block"
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(blocks[1], str(README), "exec"), namespace)  # noqa: S102 - our own README
    state = namespace["state"]
    assert state.time == namespace["test"].time.values[-1]
    back = MonitorState.load(tmp_path / "state.nc", namespace["model"])
    assert back.time == state.time
    assert float(namespace["today"]["std"].max()) > 0
