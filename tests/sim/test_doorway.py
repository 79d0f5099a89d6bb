"""Routes round walls, turn-taking at passages, and the ``doorway`` scenario.

Geometry is checked in closed form (route corners, lengths, passage extents); the turn-taking rule
on hand-made states; the closed loop on the doorway itself (noiseless, learned GPs)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torch_gpmpc import Config
from torch_gpmpc.config.obstacles import DOORWAY_GAP, ObstacleField
from torch_gpmpc.config.workspace import Workspace
from torch_gpmpc.sim.closed_loop import simulate
from torch_gpmpc.sim.metrics import compute_metrics
from torch_gpmpc.sim.path_following import PathFollower
from torch_gpmpc.sim.routes import (
    arc_lengths, box_footprints, passages, point_box_distance, route, segments_cross, walk,
)
from torch_gpmpc.sim.scenarios import make_scenario


def _wall_with_gap(half_gap: float = 0.45, half_wall: float = 0.2, height: float = 2.0):
    field = ObstacleField.parse([{"min": [-half_wall, half_gap], "max": [half_wall, height]},
                                 {"min": [-half_wall, -height], "max": [half_wall, -half_gap]}])
    return box_footprints(field)


def test_segments_cross_only_the_inside_of_a_box():
    lower, upper = np.array([[0.0, 0.0]]), np.array([[1.0, 1.0]])
    p = np.array([[-1.0, 0.5], [-1.0, 1.0], [-1.0, -1.0], [0.5, -1.0], [-1.0, 2.0], [2.0, 0.5]])
    q = np.array([[2.0, 0.5], [2.0, 1.0], [2.0, 2.0], [0.5, 0.5], [0.0, 1.0], [3.0, 0.5]])
    # through, along the top face, the diagonal, ending inside, touching a corner, beside it
    assert segments_cross(p, q, lower, upper)[:, 0].tolist() == [True, False, True, True, False, False]


def test_route_is_the_straight_line_when_nothing_is_in_the_way():
    lower, upper = _wall_with_gap()
    r = route(np.array([-3.0, 1.0]), np.array([-1.0, -1.0]), lower, upper, 0.35)
    assert r.tolist() == [[-3.0, 1.0], [-1.0, -1.0]]
    assert route(np.array([-3.0, 0.0]), np.array([3.0, 0.0]), lower[:0], upper[:0], 0.35).shape == (2, 2)


def test_route_through_a_doorway_hugs_the_grown_corners():
    """From (-3, 1) to (3, 1) through a gap |x2| < 0.45 in a wall |x1| < 0.2, clearance 0.35: the
    shortest route turns at the upper wall's grown lower corners (-0.55, 0.1) and (0.55, 0.1)."""
    lower, upper = _wall_with_gap()
    r = route(np.array([-3.0, 1.0]), np.array([3.0, 1.0]), lower, upper, 0.35)
    np.testing.assert_allclose(r, [[-3.0, 1.0], [-0.55, 0.1], [0.55, 0.1], [3.0, 1.0]], atol=1e-6)
    expected = 2 * math.hypot(2.45, 0.9) + 1.1
    assert arc_lengths(r)[-1] == pytest.approx(expected, abs=1e-6)
    # every point of the route keeps the clearance (to rounding)
    points = walk(r, np.linspace(0, arc_lengths(r)[-1], 400))
    assert point_box_distance(points, lower, upper).min() >= 0.35 - 1e-6


def test_route_round_a_single_box_and_in_3d():
    lower, upper = np.array([[-0.5, -1.0]]), np.array([[0.5, 1.0]])
    r = route(np.array([-2.0, 0.0, 1.0]), np.array([2.0, 0.0, 3.0]), lower, upper, 0.25)
    assert r.shape == (4, 3)
    # round the nearer (equal) side by the two grown corners; height rises with the arc length
    assert abs(r[1, 1]) == pytest.approx(1.25, abs=1e-6) and r[1, 1] == pytest.approx(r[2, 1])
    np.testing.assert_allclose(np.diff(r[:, 2]) / np.diff(arc_lengths(r)), 2.0 / arc_lengths(r)[-1], atol=1e-9)


def test_no_route_falls_back_to_the_straight_line():
    lower, upper = _wall_with_gap(half_gap=0.1)  # the grown walls close the gap
    r = route(np.array([-3.0, 0.0]), np.array([3.0, 0.0]), lower, upper, 0.35,
              Workspace((-4.0, -2.0), (4.0, 2.0)))
    assert r.tolist() == [[-3.0, 0.0], [3.0, 0.0]]


def test_passage_is_where_two_agents_do_not_fit_side_by_side():
    """Width 0.9 in the gap (< 2 r_safe + 0.2 = 1.2); just outside it the corners are
    sqrt(x^2 + 0.45^2) away on each side, so the passage ends where that sum reaches 1.2: at
    |x1| = 0.2 + sqrt(0.6^2 - 0.45^2) = 0.597 on the straight line x2 = 0."""
    lower, upper = _wall_with_gap()
    line = np.array([[-3.0, 0.0], [3.0, 0.0]])
    (a, b), = passages(line, lower, upper, 0.5)
    edge = 0.2 + math.sqrt(0.6 ** 2 - 0.45 ** 2)
    assert a == pytest.approx(3.0 - edge, abs=0.03) and b == pytest.approx(3.0 + edge, abs=0.03)
    assert passages(np.array([[-3.0, 1.5], [-1.0, 1.5]]), lower, upper, 0.5) == []  # beside one wall only


def _follower_through_a_gap():
    """Two agents bound through the same gap in opposite directions, one behind the other way."""
    field = ObstacleField.parse([{"min": [-0.2, 0.45], "max": [0.2, 2.0]}, {"min": [-0.2, -2.0], "max": [0.2, -0.45]}])
    starts = torch.tensor([[-3.0, 0.0], [3.0, 0.0]], dtype=torch.float64)
    return PathFollower.plan(field, None, starts, -starts, 0.5, 49)


def test_turns_the_lower_index_goes_first_and_a_going_agent_blocks_the_other_way():
    follower = _follower_through_a_gap()
    assert follower is not None and follower.followed.all()
    everyone = torch.ones(2, 2, dtype=torch.bool)
    wait_point = np.array([walk(follower.routes[k], np.array([follower.stretches[k][0][0] - follower.wait]))[0]
                           for k in range(2)])
    follower.update(torch.tensor(wait_point), everyone)  # both ready at once
    assert follower.going.tolist() == [True, False]
    window = follower.shape(torch.zeros(2, 14, 2, dtype=torch.float64))
    # agent 1 holds at its wait point (to the projection's sampling), agent 0's reference runs on
    np.testing.assert_allclose(window[1].numpy(), np.repeat(wait_point[1:], 14, axis=0), atol=2e-3)
    assert float(window[0, -1, 0]) > float(wait_point[0, 0]) + 1.0
    # agent 0 still in the gap: agent 1 keeps waiting; once 0 is through, 1 goes
    follower.update(torch.tensor(np.array([[0.0, 0.0], wait_point[1]])), everyone)
    assert follower.going.tolist() == [True, False]
    follower.update(torch.tensor(np.array([[1.5, 0.0], wait_point[1]])), everyone)
    assert follower.going.tolist() == [False, True] and follower.stage.tolist() == [1, 0]


def test_turns_only_count_agents_heard_and_going_the_other_way():
    follower = _follower_through_a_gap()
    wait_point = np.array([walk(follower.routes[k], np.array([follower.stretches[k][0][0] - follower.wait]))[0]
                           for k in range(2)])
    follower.update(torch.tensor(wait_point), torch.eye(2, dtype=torch.bool))  # they do not hear each other
    assert follower.going.tolist() == [True, True]


def test_progress_never_runs_backwards():
    follower = _follower_through_a_gap()
    everyone = torch.ones(2, 2, dtype=torch.bool)
    follower.update(torch.tensor([[-2.0, 0.0], [3.0, 0.0]]), everyone)
    assert follower.progress[0] == pytest.approx(1.0, abs=0.02)
    follower.update(torch.tensor([[-2.5, 0.0], [3.0, 0.0]]), everyone)  # pushed back
    assert follower.progress[0] == pytest.approx(1.0, abs=0.02)


def test_doorway_scenario_geometry():
    cfg = Config(scenario="doorway", num_agents=5)
    sc = make_scenario(cfg)
    assert sc.starts[:3, 0].tolist() == [-3.0] * 3 and sc.starts[3:, 0].tolist() == [3.0] * 2
    assert torch.equal(sc.targets[:, 0], -sc.starts[:, 0]) and torch.equal(sc.targets[:, 1], sc.starts[:, 1])
    walls = sc.obstacles.obstacles
    gap = walls[0].lower[1] - walls[1].upper[1]
    assert gap == pytest.approx(DOORWAY_GAP * cfg.r_safe) and gap < 2 * cfg.r_safe  # narrower than two agents
    assert sc.workspace.lower == (-4.0, -2.0) and sc.workspace.upper == (4.0, 2.0)
    assert cfg.scenario_extent == 4.0
    sc3 = make_scenario(Config(scenario="doorway", num_agents=4, dim=3))
    assert sc3.obstacles.obstacles[0].lower[2] == sc3.workspace.lower[2]


def _doorway_metrics(num_agents: int, seed: int = 0) -> dict:
    return compute_metrics(simulate(Config(scenario="doorway", num_agents=num_agents, noise_std=0.0, seed=seed)))


def _assert_swapped_safely(m: dict) -> None:
    assert m["reached"] and m["violations"] == 0 and m["obstacle_violations"] == 0
    assert m["min_obstacle_distance"] >= 0.25 - 1e-6 and m["min_pair_distance"] >= 0.5


def test_doorway_four_agents_swap_rooms_noiseless():
    """Two agents a side, learned GPs, the vortex: all swap rooms through the gap by taking turns
    (measured: t = 78, min distance 0.501, obstacle distance 0.252)."""
    _assert_swapped_safely(_doorway_metrics(4))


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_doorway_six_agents_swap_rooms_noiseless(seed):
    """The issue's doorway: 6 agents, noiseless (measured: t = 82 on seeds 0-2)."""
    _assert_swapped_safely(_doorway_metrics(6, seed))
