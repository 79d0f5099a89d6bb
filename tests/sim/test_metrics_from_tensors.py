"""compute_metrics from any loop's tensors equals the Rollout path's keys, and checks its arguments."""

import numpy as np
import pytest
import torch

from torch_gpmpc import GpmpcError, compute_metrics
from torch_gpmpc.sim.metrics import trajectory_metrics


def _two_agents():
    """Two agents passing 0.3 apart at step 2 (closed form: 1 violation at r_safe 0.5), both home at 4."""
    a = np.array([[-2.0, 0.15], [-1.0, 0.15], [0.0, 0.15], [1.0, 0.15], [2.0, 0.15]])
    b = a * np.array([-1.0, -1.0])
    return np.stack([a, b], axis=1), np.array([[2.0, 0.15], [-2.0, -0.15]])


def test_positions_from_tensors_give_the_contract_values():
    states, targets = _two_agents()
    m = compute_metrics(states=torch.tensor(states), targets=torch.tensor(targets), r_safe=0.5, goal_tol=0.1)
    assert m["violations"] == 1 and m["min_pair_distance"] == pytest.approx(0.3)
    assert m["arrival_steps"] == [4, 4] and m["arrival_step_max"] == 4 and m["time_to_target"] == 4
    assert m["path_length"] == pytest.approx([4.0, 4.0]) and m["reached"]


def test_full_states_with_a_position_index_equal_the_positions():
    states, targets = _two_agents()
    full = np.concatenate([states, np.zeros_like(states)], axis=-1)  # [p, v]
    assert compute_metrics(states=full, targets=targets, position=[0, 1]) == trajectory_metrics(states, targets)


@pytest.mark.parametrize("kwargs, match", [
    (dict(states=np.zeros((3, 2, 4)), targets=np.zeros((2, 2))), "position="),
    (dict(states=np.zeros((3, 2)), targets=np.zeros((2, 2))), r"states must have shape"),
    (dict(states=np.full((3, 2, 2), np.nan), targets=np.zeros((2, 2))), "NaN"),
    (dict(targets=np.zeros((2, 2))), "give a Rollout"),
])
def test_bad_arguments_are_named(kwargs, match):
    with pytest.raises(GpmpcError, match=match):
        compute_metrics(**kwargs)
