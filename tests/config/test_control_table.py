"""A model file's [control] table: defaults of the config keys it names, for runs with that model."""

from __future__ import annotations

import warnings

import pytest

from torch_gpmpc import Config, ModelSpec
from torch_gpmpc.config.model_spec import CONTROL_KEYS
from torch_gpmpc.errors import GpmpcError

CRAZYFLIE = "examples/rotorpy/crazyflie.toml"
TABLE = {"A": [[1.0, 0.1], [0.0, 1.0]], "B": [[0.005], [0.1]], "position": [0], "residual": [1],
         "input_bound": {"box": [2.0]}}


def _model_file(tmp_path, name, control=None):
    lines = ['A = [[1.0, 0.1], [0.0, 1.0]]', 'B = [[0.005], [0.1]]', 'position = [0]', 'residual = [1]',
             '[input_bound]', 'box = [2.0]']
    if control:
        lines += ["[control]"] + [f"{k} = {v}" for k, v in control.items()]
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def test_the_crazyflie_file_states_what_its_vehicle_needs_and_a_set_value_wins():
    cfg = Config(model=CRAZYFLIE)
    assert (cfg.input_rate_weight, cfg.disturbance_drift, cfg.gp_online_max_input_change) == (2.0, 0.01, 0.1)
    assert Config(model=CRAZYFLIE, input_rate_weight=0, disturbance_drift=0.0).input_rate_weight == 0
    assert Config(model=CRAZYFLIE).to_dict()["input_rate_weight"] == 2.0   # metrics.json records what ran


def test_built_in_models_keep_the_package_defaults():
    cfg = Config()
    assert {k: getattr(cfg, k) for k in CONTROL_KEYS} == CONTROL_KEYS
    assert cfg.gp_samples == 100 and Config(plant="rotorpy", model=CRAZYFLIE).gp_samples == 400


def test_replace_fills_again_from_the_new_model_but_keeps_a_value_the_user_set():
    cfg = Config(model=CRAZYFLIE)
    assert cfg.replace(model="double-integrator", dim=3).input_rate_weight == 0.0
    assert cfg.replace(horizon=9).disturbance_drift == 0.01
    own = Config(model=CRAZYFLIE, input_rate_weight=5.0)
    assert own.replace(horizon=9).input_rate_weight == 5.0


def test_a_config_written_by_to_dict_loads_without_warnings():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Config(**Config(model=CRAZYFLIE, method="nominal").to_dict())   # filled keys count as defaults
        Config(**Config(method="nominal").to_dict())


def test_a_team_whose_files_disagree_must_set_the_key(tmp_path):
    smooth = _model_file(tmp_path, "smooth.toml", {"input_rate_weight": 2.0})
    plain = _model_file(tmp_path, "plain.toml")
    with pytest.raises(GpmpcError, match="input_rate_weight.*different values.*set input_rate_weight"):
        Config(models=(smooth, plain), num_agents=2, scenario="circle")
    cfg = Config(models=(smooth, plain), num_agents=2, scenario="circle", input_rate_weight=1.0)
    assert cfg.input_rate_weight == 1.0


def test_the_table_is_checked_and_round_trips():
    spec = ModelSpec.from_table({**TABLE, "control": {"disturbance_drift": 0.02}})
    assert spec.control == (("disturbance_drift", 0.02),)
    assert ModelSpec.from_table(spec.to_table()) == spec
    with pytest.raises(GpmpcError, match="unknown key 'input_rate'.*did you mean 'input_rate_weight'"):
        ModelSpec.from_table({**TABLE, "control": {"input_rate": 2.0}})
    with pytest.raises(GpmpcError, match="control.gp_online_max_input_change must be > 0"):
        ModelSpec.from_table({**TABLE, "control": {"gp_online_max_input_change": 0.0}})
    with pytest.raises(GpmpcError, match="control.input_rate_weight must be >= 0"):
        ModelSpec.from_table({**TABLE, "control": {"input_rate_weight": -1.0}})


@pytest.mark.parametrize("plant, samples", [("model", 100), ("rotorpy", 400)])
def test_collect_defaults_to_the_plants_samples(tmp_path, plant, samples):
    from torch_gpmpc.cli.collect import _validate
    from torch_gpmpc.cli.parser import build_parser

    args = build_parser().parse_args(["collect", "--plant", plant, "--out", str(tmp_path / "d.npz")])
    _validate(args)
    assert args.samples == samples


def test_a_stated_config_fills_again_from_another_model_as_a_benchmark_task_does(tmp_path):
    stated = Config(model=CRAZYFLIE).stated_dict()
    assert stated["input_rate_weight"] is None and stated["gp_samples"] is None
    smooth = _model_file(tmp_path, "smooth.toml", {"input_rate_weight": 3.0})
    team = Config(**{**Config().stated_dict(), "models": (smooth, smooth), "num_agents": 2, "scenario": "circle"})
    assert team.input_rate_weight == 3.0
    assert Config(**{**stated, "model": "double-integrator", "dim": 3}).input_rate_weight == 0.0


@pytest.mark.parametrize("key, value", [("model", 3), ("models", 3), ("plant", [1])])
def test_a_wrong_type_is_named_before_any_model_is_read(key, value):
    with pytest.raises(GpmpcError, match=f"config key '{key}'"):
        Config(**{key: value})
