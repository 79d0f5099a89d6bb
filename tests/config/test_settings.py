"""The controller settings, the model as a Config value, keys that another key overrides,
and model files that change while a session runs."""

from __future__ import annotations

import json
import warnings

import pytest

from torch_gpmpc import ControllerSettings, ModelSpec
from torch_gpmpc.config import Config, from_mapping
from torch_gpmpc.errors import GpmpcError


def test_controller_settings_are_the_configs_controller_keys():
    cfg = Config(horizon=7, eps=0.05, rho=3.0, admm_max_iter=9, solver="clarabel")
    s = cfg.controller_settings()
    assert isinstance(s, ControllerSettings)
    assert (s.horizon, s.eps, s.rho, s.admm_max_iter, s.solver) == (7, 0.05, 3.0, 9, "clarabel")
    assert ControllerSettings() == Config().controller_settings()  # the same defaults


def test_config_model_may_be_a_model_spec_or_a_table_and_round_trips():
    spec = ModelSpec.double_integrator(dim=3, dt=0.05, u_max=1.5)
    cfg = Config(model=spec, scenario="circle", num_agents=4)
    assert cfg.model_spec() is spec and cfg.state_dim == 6 and cfg.uncertainty_mode == "propagated"
    table = cfg.to_dict()["model"]
    json.dumps(cfg.to_dict())  # JSON-serializable
    assert ModelSpec.from_table(table) == spec
    assert cfg.replace(seed=3).model_spec() == spec
    assert from_mapping({"model": table}).model_spec() == spec
    with pytest.raises(GpmpcError, match="config key 'model'.*missing key"):
        Config(model={"A": [[1.0]]})


def test_keys_ignored_under_another_key_warn_naming_it(recwarn):
    spec = ModelSpec.double_integrator(dim=2)
    with pytest.warns(UserWarning, match="config key 'dim' is ignored under model=double-integrator"):
        Config(model=spec, dim=3)
    with pytest.warns(UserWarning, match="config key 'admm_rel_tol' is ignored under admm_stop=primal"):
        Config(admm_stop="primal", admm_rel_tol=1e-3)
    with pytest.warns(UserWarning, match="config key 'dt' is ignored under model=single-integrator"):
        Config(dt=0.05)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Config(model="double-integrator", dim=3, dt=0.05, u_max=1.0)  # they shape this model: no warning
        Config(model=spec)


def test_a_model_file_edited_while_the_session_runs_is_read_again(tmp_path):
    path = tmp_path / "m.json"
    table = ModelSpec.double_integrator(dim=2, u_max=2.0).to_table()
    path.write_text(json.dumps(table))
    cfg = Config(model=str(path))
    assert cfg.model_spec().input_norm == 2.0
    table["input_bound"] = {"norm": 3.5}
    path.write_text(json.dumps(table) + "\n")  # a different size: seen even within one mtime tick
    assert cfg.model_spec().input_norm == 3.5
    assert ModelSpec.load(path).input_norm == 3.5
