"""Excitation flights of RotorPy vehicles (``gpmpc collect --plant rotorpy``)."""

from __future__ import annotations

import pytest
import torch

pytest.importorskip("rotorpy")

from torch_gpmpc.cli import main  # noqa: E402
from torch_gpmpc.config.model_spec import ModelSpec  # noqa: E402
from torch_gpmpc.data import Transitions  # noqa: E402
from torch_gpmpc.data.flights import collect_flights, limit_speed  # noqa: E402
from torch_gpmpc.dynamics.rotorpy_plant import PlantSettings  # noqa: E402
from torch_gpmpc.dynamics.systems import NominalModel  # noqa: E402

MODEL = "examples/rotorpy/crazyflie.toml"


def test_speed_limit_scales_the_acceleration():
    v = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    a = limit_speed(v, torch.tensor([10.0, 0.0, 0.0], dtype=torch.float64), 0.1, 1.5)
    assert abs(float((v + 0.1 * a).norm()) - 1.5) < 1e-12
    assert torch.equal(limit_speed(v, -v, 0.1, 1.5), -v)


def test_an_agents_rows_do_not_depend_on_the_others():
    nominal = NominalModel(ModelSpec.load(MODEL))
    settings = PlantSettings(wind="constant", wind_speed=(1.0, 0.0, 0.0), seed=3)
    team = collect_flights(nominal, settings, num_agents=2, samples=12)
    alone = collect_flights(nominal, settings, samples=12, agents=range(1, 2))
    assert torch.equal(team.for_agent(1).x, alone.x) and torch.equal(team.for_agent(1).x_next, alone.x_next)
    spec = nominal.spec
    assert float(team.u.abs().max()) <= max(spec.input_box) + 1e-12
    assert float(team.x_next[:, 3:].norm(dim=1).max()) < spec.state_bound_norm + 0.3  # planned under the limit


def test_cli_collect_flights(tmp_path, capsys):
    out = tmp_path / "flights.npz"
    code = main(["collect", "--plant", "rotorpy", "--model", MODEL, "--agents", "1", "--samples", "10",
                 "--set", "plant_wind=sine", "--set", "plant_wind_speed=[1, 0, 0]", "--out", str(out)])
    assert code == 0 and "crazyflie flights" in capsys.readouterr().out
    data = Transitions.load(out)
    assert data.x.shape == (10, 6) and data.u.shape == (10, 3)


def test_cli_collect_refuses_set_without_the_rotorpy_plant(tmp_path, capsys):
    code = main(["collect", "--set", "plant_wind=sine", "--out", str(tmp_path / "t.npz")])
    assert code != 0 and "--plant rotorpy" in capsys.readouterr().err
    assert not (tmp_path / "t.npz").exists()
