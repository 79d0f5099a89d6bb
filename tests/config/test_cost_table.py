"""The run configuration's ``[cost]`` table and ``terminal_cost``: parsed, checked against the model,
carried into the local problems, and refused with the key named when malformed."""

from __future__ import annotations

import json

import pytest
import torch

from torch_gpmpc.cli import main
from torch_gpmpc.config import Config, load_config
from torch_gpmpc.coordination.agent_step import LocalStep
from torch_gpmpc.errors import GpmpcError
from tests.helpers import lag_model

COST_FILE = """
method = "nominal"
model = "double-integrator"
[cost]
Q = [1.0, 1.0, 0.2, 0.2]
R = 0.01
P = [[10, 0, 0, 0], [0, 10, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
u_ref = [0.0, 0.1]
"""


def test_a_cost_table_reaches_the_local_problems(tmp_path):
    path = tmp_path / "cost.toml"
    path.write_text(COST_FILE)
    cfg = load_config(path)
    Q, R, P, u_ref = LocalStep(cfg, cfg.model_spec()).cost_weights
    torch.testing.assert_close(Q[0], torch.diag(torch.tensor([1.0, 1.0, 0.2, 0.2], dtype=torch.float64)))
    assert float(R[0, 1, 1]) == 0.01 and float(P[0, 0, 0]) == 10.0 and u_ref[0].tolist() == [0.0, 0.1]
    assert Config.replace(cfg, seed=1).cost == cfg.cost  # round-trips through to_dict
    out = tmp_path / "run"
    assert main(["run", "--config", str(path), "--no-figures", "--set", "max_steps=2", "--out", str(out)]) == 0
    saved = json.loads((out / "metrics.json").read_text())
    assert saved["steps"] == 2


def test_without_a_table_the_terminal_weight_follows_terminal_cost():
    cfg = Config(method="nominal", model="double-integrator")
    Q, R, P, _ = LocalStep(cfg, cfg.model_spec()).cost_weights
    assert float(P[0, 0, 0]) > 5.0 and float(R[0, 0, 0]) == cfg.alpha  # the LQR cost-to-go of the position
    stage = cfg.replace(terminal_cost="stage")
    assert LocalStep(stage, stage.model_spec()).cost_weights is None  # the paper's cost, as it always ran
    table = stage.replace(cost={"Q": 2.0, "R": 0.1})
    _, _, P, _ = LocalStep(table, table.model_spec()).cost_weights
    torch.testing.assert_close(P[0], 2.0 * torch.eye(4, dtype=torch.float64))  # P = Q


@pytest.mark.parametrize("table, match", [
    ({"Q": 1.0}, "missing entry R"),
    ({"Q": 1.0, "R": 1.0, "Qf": 1.0}, "unknown entry 'Qf' \\(did you mean 'Q'\\?\\)"),
    (5.0, "with Q and R"),
    ({"Q": "big", "R": 1.0}, r"'cost', entry Q: give a finite number"),
    ({"Q": [[1, 0], [0]], "R": 1.0}, r"'cost', entry Q"),
    ({"Q": 1.0, "R": 1.0, "u_ref": [[0.0]]}, r"'cost', entry u_ref"),
])
def test_malformed_tables_name_the_key(table, match):
    with pytest.raises(GpmpcError, match=match):
        Config(cost=table)


def test_a_table_of_the_wrong_size_names_the_key_and_the_model():
    cfg = Config(method="nominal", cost={"Q": [1.0, 1.0, 1.0], "R": 1.0})
    with pytest.raises(GpmpcError, match=r"config key 'cost', entry Q: a diagonal of 2 entries"):
        LocalStep(cfg, cfg.model_spec())
    with pytest.raises(GpmpcError, match="terminal_cost"):
        Config(terminal_cost="none")


@pytest.mark.parametrize("terminal", ["lqr", "stage"])
def test_the_default_cost_leaves_the_last_command_rows_to_the_input_cost(terminal):
    """A row that holds the last input (w' = u) gets no state weight by default: Q = diag(1, 1, 1, 1, 0, 0), the
    same weights as stating that cost (and P = Q under terminal_cost = stage)."""
    cfg = Config(method="nominal", model=lag_model(), terminal_cost=terminal)
    Q, R, P, _ = LocalStep(cfg, cfg.model_spec()).cost_weights
    weights = [1.0, 1.0, 1.0, 1.0, 0.0, 0.0]
    torch.testing.assert_close(Q[0], torch.diag(torch.tensor(weights, dtype=torch.float64)))
    stated = cfg.replace(cost={"Q": weights, "R": cfg.alpha})
    Qs, Rs, Ps, _ = LocalStep(stated, stated.model_spec()).cost_weights
    assert torch.equal(Q, Qs) and torch.equal(R, Rs) and torch.equal(P, Ps)
    if terminal == "stage":
        assert torch.equal(P, Q)
