"""Per-agent body radii: a pair keeps r_k + r_j, an agent r_k from obstacles; without radii the
runs are unchanged to the bit."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from torch_gpmpc import Config
from torch_gpmpc.config.settings import ControllerSettings
from torch_gpmpc.coordination.bodies import body_radii, edge_distances, slot_distances
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.sim.closed_loop import simulate
from torch_gpmpc.sim.metrics import compute_metrics, obstacle_metrics
from torch_gpmpc.config.obstacles import ObstacleField
from torch_gpmpc.sim.scenarios import Scenario, make_scenario, with_scenario_world
from tests.sim.test_metrics import make_rollout


def test_required_distances_in_closed_form():
    plain = ControllerSettings()
    assert slot_distances(plain, torch.tensor([0]), torch.tensor([[1]])) == 0.5 and body_radii(plain, torch.tensor([0])) == 0.25
    s = ControllerSettings(radii=[0.1, 0.2, 0.4])
    d = slot_distances(s, torch.tensor([0, 2]), torch.tensor([[1, 2], [0, 1]]))
    assert d.shape == (2, 2, 1)
    np.testing.assert_allclose(d[..., 0].numpy(), [[0.3, 0.5], [0.5, 0.6]])
    assert edge_distances(s, torch.tensor([[0, 1], [1, 2]])).tolist() == pytest.approx([0.3, 0.6])
    assert body_radii(s, torch.tensor([2, 0])).tolist() == [0.4, 0.1]


def test_radii_are_checked_with_the_field_and_the_fix():
    with pytest.raises(GpmpcError, match="'radii'.*out of range"):
        Config(scenario="circle", num_agents=2, radii=[0.2, 0.0])
    with pytest.raises(GpmpcError, match="'radii': expected a list of float or null"):
        Config(radii=0.3)
    cfg = Config(scenario="circle", num_agents=3, radii=[0.2, 0.2])
    with pytest.raises(GpmpcError, match="'radii': 2 radii for 3 agents; give one body radius per agent"):
        with_scenario_world(cfg, make_scenario(cfg))


def test_scenario_file_radii(tmp_path):
    path = tmp_path / "two.json"
    path.write_text(json.dumps({"starts": [[0.0, 0.0], [0.7, 0.0]], "targets": [[3.0, 0.0], [-3.0, 0.0]],
                                "radii": [0.3, 0.3]}))
    cfg = Config(scenario="circle", num_agents=2)
    sc = make_scenario(cfg, path)
    assert sc.radii == (0.3, 0.3) and with_scenario_world(cfg, sc).radii == (0.3, 0.3)
    assert sc.to_dict()["radii"] == [0.3, 0.3]
    path.write_text(json.dumps({"starts": [[0.0, 0.0], [0.5, 0.0]], "targets": [[3.0, 0.0], [-3.0, 0.0]],
                                "radii": [0.3, 0.3]}))
    with pytest.raises(GpmpcError, match=r"0.5 apart, closer than r_safe = 0.6"):  # equal radii: one distance
        make_scenario(cfg, path)
    path.write_text(json.dumps({"starts": [[0.0, 0.0], [0.55, 0.0]], "targets": [[3.0, 0.0], [-3.0, 0.0]],
                                "radii": [0.2, 0.4]}))
    with pytest.raises(GpmpcError, match=r"0.55 apart, closer than the sum of their radii = 0.6"):
        make_scenario(cfg, path)
    path.write_text(json.dumps({"starts": [[0.0, 0.0], [1.0, 0.0]], "targets": [[3.0, 0.0], [-3.0, 0.0]],
                                "radii": [0.2]}))
    with pytest.raises(GpmpcError, match="'radii' must be a list of 2 body radii"):
        make_scenario(cfg, path)


def test_metrics_count_each_pair_against_its_own_distance():
    # three agents held still: pair (0, 1) at 0.55, pair (0, 2) at 0.65, pair (1, 2) at 1.2
    states = np.array([[[0.0, 0.0], [0.55, 0.0], [-0.65, 0.0]]] * 3)
    run = make_rollout(states, states[-1], config={"r_safe": 0.5, "radii": [0.3, 0.3, 0.3]})
    m = compute_metrics(run)  # every pair needs 0.6: (0, 1) breaks it at every step
    assert m["violations"] == 3 and m["min_pair_clearance"] == pytest.approx(-0.05)
    run = make_rollout(states, states[-1], config={"r_safe": 0.5})
    assert compute_metrics(run)["violations"] == 0  # r_safe 0.5: none
    positions = np.array([[[0.0, 1.2], [0.0, -1.35]]])  # 0.2 and 0.35 from a unit disc
    disc = [{"center": [0.0, 0.0], "radius": 1.0}]
    assert obstacle_metrics(positions, disc, 0.5)["obstacle_violations"] == 1
    assert obstacle_metrics(positions, disc, 0.5, np.array([0.1, 0.4]))["obstacle_violations"] == 1  # agent 1 only
    assert obstacle_metrics(positions, disc, 0.5, np.array([0.1, 0.3]))["obstacle_violations"] == 0


def _two_agents(**changes) -> Config:
    return Config(scenario="circle", num_agents=2, method="nominal", noise_std=0.0, wind_scale=0.0, **changes)


def test_equal_radii_of_half_r_safe_change_nothing():
    plain = simulate(_two_agents(max_steps=25))
    same = simulate(_two_agents(max_steps=25, radii=[0.25, 0.25]))
    assert np.array_equal(plain.states, same.states)


def test_a_small_and_a_large_agent_keep_the_sum_of_their_radii_head_on():
    """No wind, no noise: the nominal model is exact, so the pair keeps 0.15 + 0.45 = 0.6 (to ADMM's
    tolerance) where two default agents would keep 0.5."""
    cfg = _two_agents(radii=[0.15, 0.45])
    m = compute_metrics(simulate(cfg))
    assert m["reached"] and m["min_pair_distance"] >= 0.6 - cfg.admm_tol
    assert m["min_pair_distance"] < 0.6 + 0.05  # they really met


def test_a_large_agent_keeps_its_own_radius_from_an_obstacle():
    """One agent of radius 0.6 past a disc its reference rounds at 0.5 (r_safe beyond the radius):
    its obstacle rows, not the reference, keep it 0.6 away."""
    cfg = Config(scenario="circle", num_agents=2, method="nominal", noise_std=0.0, wind_scale=0.0, max_steps=80,
                 radii=[0.6])
    scenario = Scenario(torch.tensor([[-3.0, 0.0]]), torch.tensor([[3.0, 0.0]]),
                        obstacles=ObstacleField.parse([{"center": [0.0, 0.05], "radius": 0.5}]))
    m = compute_metrics(simulate(cfg, scenario))
    assert m["reached"] and m["obstacle_violations"] == 0
    assert 0.6 - 1e-6 <= m["min_obstacle_distance"] < 0.62


def test_pair_buffer_is_asked_by_the_rows_and_keeps_r_safe_strictly():
    s = ControllerSettings(radii=[0.1, 0.2], pair_buffer=0.01)
    np.testing.assert_allclose(slot_distances(s, torch.tensor([0]), torch.tensor([[1]]))[..., 0].numpy(), [[0.31]])
    assert slot_distances(ControllerSettings(pair_buffer=0.01), torch.tensor([0]), torch.tensor([[1]])) == 0.51
    assert edge_distances(s, torch.tensor([[0, 1]])).tolist() == pytest.approx([0.3])  # risk judges the distance
    # exact model, head on: without a buffer the pair sits on r_safe to rounding (strict count > 0)
    m = compute_metrics(simulate(_two_agents(pair_buffer=1e-3)))
    assert m["reached"] and m["violations"] == 0 and m["min_pair_distance"] >= 0.5
