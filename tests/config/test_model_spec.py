"""Model descriptions: built-ins, strict model-file validation, and what the dynamics layer
derives from them (true system, references, GP columns)."""

from __future__ import annotations

import json

import pytest
import torch

from torch_gpmpc.config import Config
from torch_gpmpc.config.model_spec import double_integrator, load_model_file, parse_model, single_integrator
from torch_gpmpc.dynamics.systems import NominalModel, TrueSystem, VortexWind, make_system
from torch_gpmpc.errors import GpmpcError

F64 = torch.float64
GOOD = {"name": "quad", "dt": 0.1, "A": [[1, 0, 0.1, 0], [0, 1, 0, 0.1], [0, 0, 1, 0], [0, 0, 0, 1]],
        "B": [[0.005, 0], [0, 0.005], [0.1, 0], [0, 0.1]], "position": [0, 1], "residual": [2, 3],
        "gp_inputs": ["x2", "x3", "u0", "u1"], "input_bound": {"norm": 2.0}}


def test_double_integrator_matches_its_closed_form():
    spec = double_integrator(3, 0.2, 1.5)
    A, B = torch.tensor(spec.A), torch.tensor(spec.B)
    p, v, u = torch.tensor([1.0, 2, 3]), torch.tensor([0.5, -1, 2]), torch.tensor([1.0, 0, -1])
    nxt = A @ torch.cat([p, v]) + B @ u
    assert torch.allclose(nxt[:3], p + 0.2 * v + 0.5 * 0.04 * u)
    assert torch.allclose(nxt[3:], v + 0.2 * u)
    assert spec.position == (0, 1, 2) and spec.residual == (3, 4, 5) and spec.input_norm == 1.5


def test_a_model_file_round_trips_through_toml_and_json(tmp_path):
    toml = tmp_path / "m.toml"
    toml.write_text('name = "quad"\ndt = 0.1\nA = [[1, 0, 0.1, 0], [0, 1, 0, 0.1], [0, 0, 1, 0], [0, 0, 0, 1]]\n'
                    'B = [[0.005, 0], [0, 0.005], [0.1, 0], [0, 0.1]]\nposition = [0, 1]\nresidual = [2, 3]\n'
                    'gp_inputs = ["x2", "x3", "u0", "u1"]\n[input_bound]\nnorm = 2.0\n')
    js = tmp_path / "m.json"
    js.write_text(json.dumps(GOOD))
    assert load_model_file(toml) == load_model_file(js) == parse_model(GOOD, "m")


@pytest.mark.parametrize("change, message", [
    ({"Bx": 1}, "unknown key 'Bx' \\(did you mean 'B'\\?\\)"),
    ({"A": [[1, 0], [0, 1]]}, "A is 2 x 2 \\(n = 2 states\\) but B has 4 rows; give A and B one row per state"),
    ({"A": [[1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 0]]}, "A must be square"),
    ({"position": [0, 4]}, "position index 4 is not a state index in 0..3"),
    ({"residual": [2, 2]}, "lists an index twice"),
    ({"A": [[1, 0, float("nan"), 0], [0, 1, 0, 0.1], [0, 0, 1, 0], [0, 0, 0, 1]]}, "A\\[0\\]\\[2\\] must be finite"),
    ({"gp_inputs": ["x2", "v0"]}, "gp_inputs column 'v0' does not exist"),
    ({"gp_inputs": ["u2"]}, "inputs u0..u1"),
    ({"input_bound": {}}, "input_bound needs norm, box or both"),
    ({"state_box": {"indices": [2, 3], "lower": [-1, -1]}}, "state_box needs indices, lower and upper"),
    ({"state_box": {"indices": [2, 3], "lower": [-1], "upper": [1, 1]}}, "state_box.lower must list 2 numbers"),
    ({"state_box": {"indices": [2, 3], "lower": [1, -1], "upper": [1, 1]}}, "lower\\[0\\] = 1.0 must be <"),
    ({"state_box": {"indices": [2, 9], "lower": [-1, -1], "upper": [1, 1]}}, "state_box.indices index 9"),
    ({"state_box": {"indices": [2], "lower": [-1], "uper": [1]}}, "did you mean 'upper'"),
    ({"state_rows": {"G": [[1, 0, 0]], "h": [1]}}, "state_rows.G must have n = 4 columns"),
    ({"state_rows": {"G": [[1, 0, 0, 0]], "h": [1, 2]}}, "one number per row of G"),
    ({"state_rows": {"G": [[1, 0, 0, 0]]}}, "state_rows must be a table with G"),
    ({"input_bound": {"box": [1.0]}}, "must list m = 2 bounds"),
    ({"input_bound": {"nrm": 1.0}}, "did you mean 'norm'"),
    ({"state_bound": {"indices": [2, 3]}}, "state_bound needs indices and norm"),
    ({"dt": -0.1}, "dt must be > 0"),
])
def test_bad_model_files_get_one_clear_line(change, message):
    with pytest.raises(GpmpcError, match=message):
        parse_model({**GOOD, **change}, "model file 'm.toml'")


def test_missing_input_bound_and_missing_keys_are_named():
    data = dict(GOOD)
    del data["input_bound"]
    with pytest.raises(GpmpcError, match="missing \\[input_bound\\]"):
        parse_model(data)
    with pytest.raises(GpmpcError, match="missing key\\(s\\) residual"):
        parse_model({k: v for k, v in GOOD.items() if k != "residual"})


def test_config_model_key_accepts_builtins_and_files_and_refuses_the_rest(tmp_path):
    assert Config().model_spec() == single_integrator(2, 2.0)
    cfg = Config(model="double-integrator", dim=3, dt=0.05)
    assert (cfg.state_dim, cfg.input_dim, cfg.position_dim) == (6, 3, 3)
    assert cfg.uncertainty_mode == "propagated" and Config().uncertainty_mode == "pointwise"
    path = tmp_path / "m.json"
    path.write_text(json.dumps(GOOD))
    assert Config(model=str(path)).state_dim == 4
    with pytest.raises(GpmpcError, match="neither single-integrator nor double-integrator"):
        Config(model="quadrotor")
    with pytest.raises(GpmpcError, match="does not exist"):
        Config(model=str(tmp_path / "missing.toml"))


def test_double_integrator_wind_is_an_acceleration_scaled_by_dt():
    """At dt = 0.1 the velocity change per step equals the paper's displacement per step."""
    si = make_system(2, noise_std=0.0)
    di = make_system(double_integrator(2, 0.1, 2.0), noise_std=0.0)
    di_half = make_system(double_integrator(2, 0.05, 2.0), noise_std=0.0)
    p = torch.tensor([[0.3, -1.2]], dtype=F64)
    x = torch.cat([p, torch.zeros_like(p)], dim=1)
    zero_u = torch.zeros(1, 2, dtype=F64)
    wind_si = si.step(p, zero_u) - p
    assert torch.allclose(di.step(x, zero_u)[:, 2:], wind_si)
    assert torch.allclose(di_half.step(x, zero_u)[:, 2:], 0.5 * wind_si)
    assert torch.allclose(di.step(x, zero_u)[:, :2], p)  # the wind reaches the position a step later


def test_noise_acts_on_the_residual_rows_only():
    sys = TrueSystem(NominalModel(double_integrator(2, 0.1, 2.0)), VortexWind(0.0), noise_std=0.1)
    x = torch.zeros(1, 4, dtype=F64)
    nxt = sys.step(x, torch.zeros(1, 2, dtype=F64), noise=torch.ones(1, 2, dtype=F64))
    assert torch.allclose(nxt, torch.tensor([[0.0, 0.0, 0.1, 0.1]], dtype=F64))


def test_references_give_velocities_as_the_finite_difference_of_the_path():
    nominal = NominalModel(double_integrator(2, 0.1, 2.0))
    path = torch.tensor([[0.0, 0.0], [0.1, 0.0], [0.3, 0.1]], dtype=F64)
    ref = nominal.reference_states(path)
    assert torch.allclose(ref[:, :2], path)
    assert torch.allclose(ref[:, 2:], torch.tensor([[1.0, 0.0], [2.0, 1.0], [2.0, 1.0]], dtype=F64))


def test_gp_columns_select_states_and_inputs():
    nominal = NominalModel(parse_model(GOOD))
    x = torch.arange(4, dtype=F64)[None]
    u = torch.tensor([[10.0, 20.0]], dtype=F64)
    assert nominal.gp_input(x, u).tolist() == [[2.0, 3.0, 10.0, 20.0]]
    Sx, Su = nominal.gp_selectors()
    assert torch.equal(Sx @ x[0] + Su @ u[0], nominal.gp_input(x, u)[0])


def test_new_constraint_blocks_parse_round_trip_and_become_soft_rows():
    from torch_gpmpc.config.workspace import Workspace
    from torch_gpmpc.control.constraints import LocalConstraints

    table = {**GOOD, "input_bound": {"norm": 2.0, "box": [1.5, 1.0]},
             "state_box": {"indices": [2, 3], "lower": [-1.0, float("-inf")], "upper": [1.0, 0.5]},
             "state_rows": {"G": [[0, 0, 1, 1]], "h": [1.2]}}
    spec = parse_model(table, "m")
    assert spec.input_norm == 2.0 and spec.input_box == (1.5, 1.0)
    assert parse_model(spec.to_table(), "m") == spec
    c = LocalConstraints.of(spec, workspace=Workspace((-3.0, -2.0), (3.0, 2.0)))
    # box: v_x >= -1, -v_x >= -1, -v_y >= -0.5 (no lower row for -inf); row: -(v_x + v_y) >= -1.2; workspace 4
    assert c.num_rows == 3 + 1 + 4
    assert c.row_normals[2] == (0.0, 0.0, 0.0, -1.0) and c.row_bounds[2] == -0.5
    assert c.row_normals[3] == (0.0, 0.0, -1.0, -1.0) and c.row_bounds[3] == -1.2
    X = torch.zeros(1, 3, 4, dtype=F64)
    X[0, 1] = torch.tensor([3.5, 0.0, 0.0, 0.0], dtype=F64)  # 0.5 outside the workspace at tau = 1
    X[0, 2] = torch.tensor([0.0, 0.0, 1.0, 0.6], dtype=F64)  # v_y 0.1 over, row 0.4 over at tau = 2
    assert torch.allclose(c.state_violation(X), torch.tensor([[0.5, 0.4]], dtype=F64))
    U = torch.tensor([[[1.6, 0.0], [1.2, 1.0]]], dtype=F64)  # box 0.1 over; norm 1.56 < 2
    assert c.input_violation(U.numpy())[0] == pytest.approx(0.1)
    from torch_gpmpc.dynamics.systems import project_input

    tight = parse_model({**table, "input_bound": {"norm": 1.0, "box": [0.8, 0.5]}}, "m")
    applied = project_input(torch.tensor([[3.0, 3.0], [-3.0, 0.1]], dtype=F64), tight)
    assert (applied.abs() <= torch.tensor([0.8, 0.5], dtype=F64) + 1e-12).all()
    assert (applied.norm(dim=-1) <= 1.0 + 1e-12).all()


def test_workspace_is_validated_in_config_and_scenario_files(tmp_path):
    from torch_gpmpc.sim.scenarios import make_scenario, with_scenario_world

    cfg = Config(workspace={"min": [-5, -5], "max": [5, 5]})
    assert cfg.workspace.upper == (5.0, 5.0) and cfg.controller_settings().workspace == cfg.workspace
    assert Config.replace(cfg, seed=1).workspace == cfg.workspace  # survives to_dict / from_mapping
    for bad, message in (({"min": [-5], "max": [5]}, "has 1 coordinates but positions have 2"),
                         ({"min": [5, -5], "max": [5, 5]}, "min must be < max"),
                         ({"lo": [0, 0]}, "give the workspace as")):
        with pytest.raises(GpmpcError, match=message):
            Config(workspace=bad)
    path = tmp_path / "s.json"
    path.write_text(json.dumps({"starts": [[-3, 0], [3, 0]], "targets": [[3, 0], [-3, 0]],
                                "workspace": {"min": [-4, -1], "max": [4, 1]}}))
    scenario = make_scenario(Config(), path)
    assert scenario.workspace.lower == (-4.0, -1.0)
    assert with_scenario_world(Config(), scenario).workspace == scenario.workspace
    path.write_text(json.dumps({"starts": [[-3, 0]], "targets": [[3, 0]], "workspace": {"min": [-4], "max": [4]}}))
    with pytest.raises(GpmpcError, match="scenario file .*workspace has 1 coordinates"):
        make_scenario(Config(), path)


def test_states_at_names_the_position_size():
    nominal = NominalModel(double_integrator(2, 0.1, 2.0))
    x = nominal.states_at(torch.tensor([[1.0, -2.0]], dtype=torch.float64))
    assert x.tolist() == [[1.0, -2.0, 0.0, 0.0]]
    with pytest.raises(GpmpcError, match=r"shape \(\.\.\., 2\).*got \(2, 3\)"):
        nominal.states_at(torch.zeros(2, 3, dtype=torch.float64))
