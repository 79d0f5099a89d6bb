"""compute_metrics on hand-made rollouts against hand-computed values."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.sim.metrics import CONTRACT_KEYS, compute_metrics, pair_distances, pair_index, time_to_target
from torch_gpmpc.sim.rollout import Rollout


def make_rollout(states, targets, *, config=None, admm_iterations=None, converged=None,
                 solve_time=None, infeasible=None, horizon=2) -> Rollout:
    """A Rollout around given states (S+1, K, D) and targets (K, D); other arrays filled simply."""
    states = np.asarray(states, dtype=np.float64)
    targets = np.asarray(targets, dtype=np.float64)
    s, k = states.shape[0] - 1, states.shape[1]
    iters = 3
    plans = np.repeat(states[:-1, :, None, :], horizon + 1, axis=2)  # (S, K, T+1, D)
    primal = np.full((s, iters), np.nan)
    primal[:, 0], primal[:, 1] = 1.0, 0.1
    return Rollout(
        states=states,
        inputs=np.diff(states, axis=0) * 10.0,
        plans=plans,
        targets=targets,
        adjacency=np.ones((s, k, k), dtype=bool),
        admm_iterations=np.asarray(admm_iterations if admm_iterations is not None else [2] * s, dtype=int),
        converged=np.asarray(converged if converged is not None else [True] * s, dtype=bool),
        primal_residuals=primal,
        dual_residuals=primal * 2.0,
        slack_max=np.zeros(s),
        infeasible_solves=np.asarray(infeasible if infeasible is not None else [0] * s, dtype=int),
        solve_time=np.asarray(solve_time if solve_time is not None else [0.01] * s, dtype=np.float64),
        chance_margin=np.zeros(s),
        wall_time_s=1.5,
        method="gp-chance",
        seed=7,
        config=config if config is not None else {"r_safe": 4.0, "goal_tol": 0.1, "noise_std": 0.1,
                                                  "admm_tol": 1e-3, "admm_dual_tol": None},
    )


# Agent 0: (0,0) -> (3,0) -> (3,4) -> (6,8) -> (6,8); legs 3, 4, 5, 0; target (6,8), straight 10.
# Agent 1: (0,4) -> (0,1) -> (3,5) -> (0,9) -> (0,9); legs 3, 5, 5, 0; target (0,9), straight 5.
# Pair distances: 4, sqrt(10), 1, sqrt(37), sqrt(37). With r_safe = 4: violations at s=1, s=2
# (s=0 is exactly 4: not a violation). Both agents at their targets first at s=3.
HAND_STATES = [
    [[0, 0], [0, 4]],
    [[3, 0], [0, 1]],
    [[3, 4], [3, 5]],
    [[6, 8], [0, 9]],
    [[6, 8], [0, 9]],
]
HAND_TARGETS = [[6, 8], [0, 9]]


@pytest.fixture
def hand_rollout() -> Rollout:
    return make_rollout(HAND_STATES, HAND_TARGETS, admm_iterations=[3, 5, 2, 10],
                        converged=[True, True, False, True], solve_time=[0.1, 0.2, 0.3, 0.4],
                        infeasible=[0, 1, 0, 2])


def test_hand_computed_metrics(hand_rollout):
    m = compute_metrics(hand_rollout)
    assert set(CONTRACT_KEYS) <= set(m)
    assert m["method"] == "gp-chance" and m["seed"] == 7
    assert m["num_agents"] == 2 and m["steps"] == 4
    assert m["reached"] is True and m["time_to_target"] == 3
    assert m["min_pair_distance"] == pytest.approx(1.0)
    assert m["violations"] == 2
    assert m["path_length"] == pytest.approx([12.0, 13.0])
    assert m["straight_line_length"] == pytest.approx([10.0, 5.0])
    assert m["admm_iterations_mean"] == pytest.approx(5.0)
    assert m["admm_iterations_max"] == 10
    assert m["converged_fraction"] == pytest.approx(0.75)
    assert m["wall_time_s"] == pytest.approx(1.5)
    assert m["solve_time_s_per_step"] == pytest.approx(0.25)
    assert m["infeasible_local_solves"] == 3
    assert m["r_safe"] == 4.0 and m["goal_tol"] == 0.1 and m["noise_std"] == 0.1
    assert m["final_distance_to_target"] == pytest.approx([0.0, 0.0])
    assert m["at_target_final"] is True


def test_metrics_are_plain_json(hand_rollout):
    m = compute_metrics(hand_rollout)
    text = json.dumps(m, allow_nan=False)
    assert json.loads(text) == m
    for key in ("num_agents", "steps", "violations", "admm_iterations_max", "infeasible_local_solves"):
        assert type(m[key]) is int, key
    assert all(type(v) is float for v in m["path_length"])


def test_pair_distances_three_agents():
    # Agents at (0,0), (3,4), (0,8): pairs (0,1)=5, (0,2)=8, (1,2)=5.
    states = np.array([[[0.0, 0.0], [3.0, 4.0], [0.0, 8.0]]])
    assert pair_index(3) == [(0, 1), (0, 2), (1, 2)]
    np.testing.assert_allclose(pair_distances(states), [[5.0, 8.0, 5.0]])
    assert pair_distances(states[:, :1]).shape == (1, 0)


def test_never_reached_is_none():
    r = make_rollout(HAND_STATES, [[100, 100], [-100, 100]])
    m = compute_metrics(r)
    assert m["time_to_target"] is None and m["reached"] is False and m["at_target_final"] is False


def test_reached_at_step_zero():
    r = make_rollout(HAND_STATES, [[0, 0], [0, 4]])
    m = compute_metrics(r)
    assert m["time_to_target"] == 0 and m["reached"] is True
    assert m["straight_line_length"] == [0.0, 0.0]


def test_goal_tolerance_is_inclusive_and_all_agents_needed():
    # distances to the targets per step: agent 0: 1, 0.05, 0; agent 1: 0, 0.5, 0.05
    states = np.array([[[1.0, 0.0], [5.0, 0.0]], [[0.05, 0.0], [5.0, 0.5]], [[0.0, 0.0], [5.0, 0.05]]])
    targets = [[0.0, 0.0], [5.0, 0.0]]
    assert time_to_target(states, targets, 0.1) == 2
    assert time_to_target(states, targets, 0.5) == 1  # exactly 0.5 away counts
    assert time_to_target(states, targets, 1.0) == 0
    assert time_to_target(states, targets, 0.01) is None


def test_single_agent():
    states = [[[0.0, 0.0]], [[3.0, 4.0]], [[3.0, 4.0]]]
    m = compute_metrics(make_rollout(states, [[3.0, 4.0]]))
    assert m["num_agents"] == 1
    assert m["min_pair_distance"] is None and m["violations"] == 0
    assert m["path_length"] == pytest.approx([5.0]) and m["time_to_target"] == 1
    json.dumps(m, allow_nan=False)


def test_zero_steps_gives_null_means():
    m = compute_metrics(make_rollout([[[0.0, 0.0], [1.0, 0.0]]], [[0.0, 0.0], [1.0, 0.0]]))
    assert m["steps"] == 0 and m["time_to_target"] == 0
    assert m["admm_iterations_mean"] is None and m["admm_iterations_max"] is None
    assert m["solve_time_s_per_step"] is None and m["path_length"] == [0.0, 0.0]
    json.dumps(m, allow_nan=False)


def test_missing_config_uses_defaults():
    r = make_rollout(HAND_STATES, HAND_TARGETS, config={})
    m = compute_metrics(r)
    assert m["r_safe"] == 0.5 and m["goal_tol"] == 0.1
    assert m["violations"] == 0  # no distance below 0.5
    assert math.isclose(m["min_pair_distance"], 1.0)


def test_bad_shapes_raise():
    r = make_rollout(HAND_STATES, HAND_TARGETS)
    r.targets = np.zeros((3, 2))
    with pytest.raises(GpmpcError, match="targets"):
        compute_metrics(r)


def test_per_agent_arrival_differs_from_all_at_once():
    """Agent 1 is within 0.1 of its target at steps 0 and 2 but not 1; agent 0 first at 1.
    All at once: step 2; per agent: [1, 0], the last arrival 1."""
    states = np.array([[[1.0, 0.0], [5.0, 0.0]], [[0.05, 0.0], [5.0, 0.5]], [[0.0, 0.0], [5.0, 0.05]]])
    targets = [[0.0, 0.0], [5.0, 0.0]]
    r = make_rollout(states, targets)
    m = compute_metrics(r)
    assert m["time_to_target"] == 2
    assert m["arrival_steps"] == [1, 0] and m["arrival_step_max"] == 1
    never = compute_metrics(make_rollout(states, [[0.0, 0.0], [50.0, 0.0]]))
    assert never["arrival_steps"] == [1, None] and never["arrival_step_max"] is None


def test_fallback_and_unsafe_plan_steps_are_counted(hand_rollout):
    m = compute_metrics(hand_rollout)
    assert m["fallback_steps"] is None and m["unsafe_plan_steps"] is None  # not recorded: unknown
    hand_rollout.fallback = np.array([False, True, True, False])
    hand_rollout.unsafe_plan = np.array([False, False, True, False])
    m = compute_metrics(hand_rollout)
    assert m["fallback_steps"] == 2 and m["unsafe_plan_steps"] == 1


def test_risk_spent_sums_the_pair_bounds_and_survives_a_round_trip(hand_rollout, tmp_path):
    """``risk_spent`` is the sum of the recorded pair bounds (NaN = no contact); ``risk_budget``
    is reported under a mission budget only; files without the array give null."""
    assert compute_metrics(hand_rollout)["risk_spent"] is None
    hand_rollout.pair_risk = np.array([[0.01], [np.nan], [0.002], [0.0]])
    hand_rollout.config = {**hand_rollout.config, "risk_mode": "mission", "risk_budget": 0.05}
    path = tmp_path / "r.npz"
    hand_rollout.save(path)
    m = compute_metrics(Rollout.load(path))
    assert m["risk_spent"] == pytest.approx(0.012) and m["risk_mode"] == "mission" and m["risk_budget"] == 0.05


def test_risk_spent_shortfall_counts_only_pair_steps_whose_plans_fell_short_of_their_rows(hand_rollout, tmp_path):
    """Of the pair bounds 0.01, 0.002 and 0.3, only the last step's plan (0.6 apart where its rows
    asked 0.8) fell short by more than ``admm_tol``; the first is short by less than it."""
    assert compute_metrics(hand_rollout)["risk_spent_shortfall"] is None
    hand_rollout.pair_risk = np.array([[0.01], [np.nan], [0.002], [0.3]])
    hand_rollout.pair_separation = np.array([[0.7995], [np.nan], [0.9], [0.6]])
    hand_rollout.pair_required = np.array([[0.8], [np.nan], [0.8], [0.8]])
    path = tmp_path / "r.npz"
    hand_rollout.save(path)
    m = compute_metrics(Rollout.load(path))
    assert m["risk_spent"] == pytest.approx(0.312) and m["risk_spent_shortfall"] == pytest.approx(0.3)


def test_step_times_are_summarized_by_hand_and_survive_a_round_trip(hand_rollout, tmp_path):
    """Mean, median and worst of the recorded control-step times (4 steps, hand values);
    ``None`` where a run did not record them (files written before they were)."""
    assert compute_metrics(hand_rollout)["step_time_s_max"] is None
    hand_rollout.step_time = np.array([0.01, 0.04, 0.02, 0.03])
    path = tmp_path / "r.npz"
    hand_rollout.save(path)
    m = compute_metrics(Rollout.load(path))
    assert m["step_time_s_mean"] == pytest.approx(0.025)
    assert m["step_time_s_median"] == pytest.approx(0.025) and m["step_time_s_max"] == pytest.approx(0.04)


def test_prediction_metrics_around_a_change_by_hand_and_after_a_round_trip(hand_rollout, tmp_path):
    """4 steps, 1 agent, 1 row, the change at step 2: the online errors 0.1, 0.1, 0.4, 0.2 and the
    fit's on the same transitions 0.1, 0.1, 0.4, 0.6. A file with an array this version does not know
    (a later version's) still loads."""
    from torch_gpmpc.sim.metrics import prediction_metrics

    hand_rollout.prediction_error = np.array([0.1, 0.1, 0.4, 0.2])[:, None, None]
    hand_rollout.prediction_var = np.full((4, 1, 1), 0.04)
    hand_rollout.frozen_prediction_error = np.array([0.1, 0.1, 0.4, 0.6])[:, None, None]
    hand_rollout.gp_update_time = np.zeros(4)
    path = tmp_path / "r.npz"
    hand_rollout.save(path)
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    np.savez(path, **arrays, a_later_array=np.ones(3))
    m = prediction_metrics(Rollout.load(path), change_step=2)
    assert m["online_prediction_rmse_after_change"] == pytest.approx(np.sqrt((0.16 + 0.04) / 2))
    assert m["frozen_prediction_rmse_after_change"] == pytest.approx(np.sqrt((0.16 + 0.36) / 2))
    assert m["online_prediction_rmse_at_change"] == pytest.approx(0.4)
    assert m["frozen_prediction_rmse"] == pytest.approx(np.sqrt((0.01 + 0.01 + 0.16 + 0.36) / 4))
    hand_rollout.frozen_prediction_error = None
    m = prediction_metrics(hand_rollout, change_step=2)
    assert m["frozen_prediction_rmse"] is None and m["frozen_prediction_rmse_after_change"] is None


def test_obstacle_metrics_by_hand():
    import numpy as np

    from torch_gpmpc.sim.metrics import obstacle_metrics

    # one agent passing a unit disc at the origin: centre distances 2, 0.2 (closer than r_safe/2 = 0.25), 1
    positions = np.array([[[-3.0, 0.0]], [[0.0, 1.2]], [[2.0, 0.0]]])
    m = obstacle_metrics(positions, [{"center": [0.0, 0.0], "radius": 1.0}], r_safe=0.5)
    assert m == {"obstacle_violations": 1, "min_obstacle_distance": pytest.approx(0.2)}
    assert obstacle_metrics(positions, None, 0.5) == {"obstacle_violations": 0, "min_obstacle_distance": None}


def test_deadlock_steps_by_hand():
    import numpy as np

    from torch_gpmpc.sim.metrics import deadlock_steps

    # agent 0 walks to its target in 20 steps; agent 1 stops at x = 1 (target 3) from step 5 on
    s = np.arange(31, dtype=float)
    walker = np.stack([np.minimum(s / 20 * 3, 3), 0 * s], -1)
    stopper = np.stack([np.minimum(s / 5, 1.0), 0 * s + 1], -1)
    positions = np.stack([walker, stopper], 1)
    targets = np.array([[3.0, 0.0], [3.0, 1.0]])
    # stuck from s = 5 + 10 - ... : progress over [s-10, s] < 0.1 first at s = 15 (dist 2 at s-10 = 5), up to s = 30
    assert deadlock_steps(positions, targets, goal_tol=0.1, r_safe=0.5) == 16
    assert deadlock_steps(positions[:, :1], targets[:1], goal_tol=0.1, r_safe=0.5) == 0
    # hovering 0.3 from the target (within r_safe + goal_tol) is not a deadlock
    hover = positions.copy()
    hover[:, 1, 0] += 1.7  # the stopper stops 0.3 from its target
    assert deadlock_steps(hover, targets, goal_tol=0.1, r_safe=0.5) == 0


def test_pair_summary_in_chunks_equals_one_reduction(monkeypatch):
    """The chunked pair summary (bounded memory at K = 1000) gives the numbers of reducing every
    (step, pair) distance at once, with required distances per pair, and NaN states propagate."""
    from torch_gpmpc.sim import metrics

    rng = np.random.default_rng(3)
    states = rng.uniform(-2, 2, size=(7, 9, 2))  # S+1 = 7 steps, K = 9 agents, P = 36 pairs
    required = rng.uniform(0.3, 0.9, size=36)
    d = pair_distances(states)
    whole = metrics.pair_summary(states, required)
    monkeypatch.setattr(metrics, "PAIR_CHUNK", 50)  # 1 step of 36 pairs per block
    chunked = metrics.pair_summary(states, required)
    for got in (whole, chunked):
        np.testing.assert_array_equal(got["closest"], d.min(axis=1))
        assert got["violations"] == int(np.count_nonzero(d < required)) > 0
        assert got["min_clearance"] == float((d - required).min())
    states[4, 2] = np.nan
    assert metrics.pair_summary(states, required)["min_clearance"] is None
    single = metrics.pair_summary(states[:, :1], 0.5)
    assert single["violations"] == 0 and single["min_clearance"] is None and np.isinf(single["closest"]).all()


def test_prediction_metrics_split_at_the_wind_change_by_hand():
    """Errors 0.1 for 3 steps then 0.3 for 2 (change at step 3), standard deviation 0.1: before the
    change every row within 1.96 sd, after it none; RMSEs by hand."""
    from dataclasses import replace

    from torch_gpmpc.sim.metrics import prediction_metrics

    states = np.zeros((6, 2, 2))
    error = np.concatenate([np.full((3, 2, 2), 0.1), np.full((2, 2, 2), 0.3)])
    rollout = replace(make_rollout(states, states[-1]), prediction_error=error, prediction_var=np.full_like(error, 0.01),
                      gp_update_time=np.zeros(5))
    m = prediction_metrics(rollout, change_step=3)
    assert m["online_prediction_rmse_before_change"] == pytest.approx(0.1)
    assert m["online_prediction_rmse_after_change"] == pytest.approx(0.3)
    assert m["online_prediction_rmse_at_change"] == pytest.approx(0.3)
    assert (m["online_coverage95_before_change"], m["online_coverage95_after_change"]) == (1.0, 0.0)
    assert m["online_coverage95"] == pytest.approx(0.6) and m["frozen_prediction_rmse"] is None
