"""examples/python_api.py, the notebook-style use of the public API, runs as written and its
gradients (a plan cost to rho, the risk split and one GPyTorch lengthscale) match central
finite differences."""

from __future__ import annotations

import dataclasses
import importlib.util
import math
from pathlib import Path

import pytest

from torch_gpmpc.config import load_config

ROOT = Path(__file__).resolve().parents[1]


def _example():
    spec = importlib.util.spec_from_file_location("python_api_example", ROOT / "examples" / "python_api.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _check(result: dict) -> None:
    for name, grad in result["grads"].items():
        fd = result["fd"][name]
        assert abs(grad) > 1e-6, (name, grad)  # each parameter really moves the plans
        assert math.isclose(grad, fd, rel_tol=1e-4), (name, grad, fd)
    assert result["uncertainty"] == "propagated"


def test_python_api_example_short():
    """The same script, cut short: 3 agents, horizon 8, 18 steps, gradients at step 14 (crossing)."""
    result = _example().run(steps=18, gradient_step=14, agents=3, horizon=8, samples=40)
    _check(result)
    assert result["message_size"] == 2 * 9 * 6 + 8


@pytest.mark.slow
def test_python_api_example_as_written():
    """4 agents, horizon 13, 50 closed-loop steps: every agent near its target, no collision."""
    result = _example().run()
    _check(result)
    assert result["min_distance"] > 0.45 and result["final_error"] < 0.3


def test_rotorpy_forest_config_flies_the_swap_vehicles_in_the_same_wind():
    """examples/rotorpy/forest.toml differs from swap.toml only in the scenario (with its trunks) and the input-rate weight."""
    swap = load_config(ROOT / "examples" / "rotorpy" / "swap.toml")
    forest = load_config(ROOT / "examples" / "rotorpy" / "forest.toml")
    differ = {f.name for f in dataclasses.fields(swap) if getattr(swap, f.name) != getattr(forest, f.name)}
    assert differ == {"scenario", "num_obstacles", "input_rate_weight"}
    assert forest.scenario == "forest" and forest.input_rate_weight > swap.input_rate_weight


def test_example_configs_find_their_model_file_from_any_directory(tmp_path, monkeypatch):
    """A config's relative model file name is looked up beside the config when the working directory
    has no such file (the examples name ``crazyflie.toml`` beside them); a name that exists from the
    working directory keeps its value."""
    from torch_gpmpc.config.load import files_beside

    monkeypatch.chdir(tmp_path)
    cfg = load_config(ROOT / "examples" / "rotorpy" / "swap.toml")
    assert Path(cfg.model) == ROOT / "examples" / "rotorpy" / "crazyflie.toml"
    (tmp_path / "crazyflie.toml").write_text("")
    assert files_beside(ROOT / "examples" / "rotorpy" / "swap.toml", {"model": "crazyflie.toml"}) == \
        {"model": "crazyflie.toml"}
    assert files_beside(tmp_path / "c.toml", {"model": "nowhere.toml", "models": ["crazyflie.toml"]}) == \
        {"model": "nowhere.toml", "models": ["crazyflie.toml"]}
