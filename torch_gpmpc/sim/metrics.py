"""Metrics of one closed-loop run (the ``metrics.json`` contract).

Shapes use S = steps taken, K = agents, D = state dimension, P = K(K-1)/2 pairs.
Pairs are ordered as :func:`pair_index` returns them: (0,1), (0,2), ..., (K-2,K-1).
"""

from __future__ import annotations

import logging
import math
from typing import Any, Sequence

import numpy as np

from torch_gpmpc.config.schema import Config
from torch_gpmpc.config.settings import agent_radii
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.sim.rollout import Rollout

logger = logging.getLogger(__name__)

#: Keys every ``metrics.json`` has, in output order.
CONTRACT_KEYS = (
    "method", "seed", "num_agents", "steps", "reached", "time_to_target", "min_pair_distance",
    "violations", "path_length", "straight_line_length", "admm_iterations_mean",
    "admm_iterations_max", "converged_fraction", "wall_time_s", "solve_time_s_per_step",
    "infeasible_local_solves",
)

#: Steps over which an agent that has not closed ``goal_tol`` of its distance to target counts as stuck.
DEADLOCK_WINDOW = 10

#: An agent counts as hitting an obstacle when closer than ``r_safe / 2`` by more than this.
OBSTACLE_TOL = 1e-6

#: (step, pair) distances held at once by :func:`pair_summary`: all (S+1, P) of them at K = 1000
#: (P = 499 500) with their (S+1, P, D) differences took gigabytes per call.
PAIR_CHUNK = 1 << 21


def nearest_neighbour_distances(states: np.ndarray) -> np.ndarray:
    """Each agent's distance to its nearest other agent per step: (S+1, K, D) -> (S+1, K).
    One step's (K, K) distances at a time (16 MB at K = 1000)."""
    out = np.empty(states.shape[:2])
    for s, x in enumerate(states):
        d = np.linalg.norm(x[:, None, :] - x[None, :, :], axis=-1)
        np.fill_diagonal(d, np.inf)
        out[s] = d.min(axis=1)
    return out


def pair_index(num_agents: int) -> list[tuple[int, int]]:
    """All unordered agent pairs (i, j) with i < j, in row-major order.

    Args:
        num_agents: K.

    Returns:
        List of P = K(K-1)/2 tuples.
    """
    return [(i, j) for i in range(num_agents) for j in range(i + 1, num_agents)]


def pair_distances(states: Any) -> np.ndarray:
    """Euclidean distance of every agent pair at every step.

    Args:
        states: positions, array-like of shape (S+1, K, D).

    Returns:
        float64 array of shape (S+1, P), columns ordered as :func:`pair_index`
        (P = 0 for a single agent).
    """
    x = np.asarray(states, dtype=np.float64)
    if x.ndim != 3:
        raise ValueError(f"pair_distances: states must have shape (S+1, K, D), got {x.shape}")
    i, j = np.triu_indices(x.shape[1], k=1)  # the order of pair_index
    return np.linalg.norm(x[:, i, :] - x[:, j, :], axis=-1)


def pair_summary(states: Any, required: Any) -> dict[str, Any]:
    """The safety figures of every agent pair, computed a block of steps at a time.

    The same numbers as reducing ``d = pair_distances(states)`` at once: :func:`pair_distances`
    of blocks of steps, :data:`PAIR_CHUNK` (step, pair) entries at a time instead of (S+1) P.

    Args:
        states: positions, shape (S+1, K, D).
        required: each pair's required distance, shape (P,) (pairs as :func:`pair_index`) or scalar.

    Returns:
        ``closest`` (S+1,): the smallest pair distance per step (``inf`` for a single agent);
        ``violations``: (step, pair) entries with ``d < required``; ``min_clearance``: the
        smallest ``d - required`` (``None`` for a single agent).
    """
    x = np.asarray(states, dtype=np.float64)
    if x.ndim != 3:
        raise ValueError(f"pair_summary: states must have shape (S+1, K, D), got {x.shape}")
    num_pairs = x.shape[1] * (x.shape[1] - 1) // 2
    closest = np.full(x.shape[0], np.inf)
    if not num_pairs:
        return {"closest": closest, "violations": 0, "min_clearance": None}
    required = np.broadcast_to(np.asarray(required, dtype=np.float64), (num_pairs,))
    rows = max(1, PAIR_CHUNK // num_pairs)
    violations, clearance = 0, np.inf
    for s0 in range(0, x.shape[0], rows):
        d = pair_distances(x[s0:s0 + rows])  # (rows, P)
        closest[s0:s0 + rows] = d.min(axis=1)
        violations += int(np.count_nonzero(d < required))
        clearance = np.minimum(clearance, (d - required).min())  # NaN propagates, as in one reduction
    return {"closest": closest, "violations": violations, "min_clearance": _scalar(clearance)}


def target_distances(states: Any, targets: Any) -> np.ndarray:
    """Each agent's distance to its own target at every step: (S+1, K, D), (K, D) -> (S+1, K)."""
    x = np.asarray(states, dtype=np.float64)
    return np.linalg.norm(x - np.asarray(targets, dtype=np.float64)[None], axis=-1)


def time_to_target(states: Any, targets: Any, goal_tol: float) -> int | None:
    """First step s at which every agent is within ``goal_tol`` of its target.

    Args:
        states: positions, shape (S+1, K, D).
        targets: targets, shape (K, D).
        goal_tol: arrival tolerance (distance <= goal_tol counts as arrived).

    Returns:
        s in 0..S, or ``None`` if that never happens.
    """
    dist = target_distances(states, targets)
    hits = np.flatnonzero(np.all(dist <= goal_tol, axis=1))
    return int(hits[0]) if hits.size else None


def arrival_steps(states: Any, targets: Any, goal_tol: float) -> list[int | None]:
    """Per agent, the first step at which it is within ``goal_tol`` of its own target.

    Unlike :func:`time_to_target` (all agents at once, the paper's measure), this does not
    depend on every agent's noise being small at the same step.

    Args:
        states: positions, shape (S+1, K, D).
        targets: targets, shape (K, D).
        goal_tol: arrival tolerance.

    Returns:
        K entries, each a step in 0..S or ``None`` if that agent never arrives.
    """
    dist = target_distances(states, targets)
    out: list[int | None] = []
    for k in range(dist.shape[1]):
        hits = np.flatnonzero(dist[:, k] <= goal_tol)
        out.append(int(hits[0]) if hits.size else None)
    return out


def path_lengths(states: Any) -> np.ndarray:
    """Length of each agent's travelled polyline, sum_s ||x[s+1] - x[s]||.

    Args:
        states: positions, shape (S+1, K, D).

    Returns:
        float64 array of shape (K,).
    """
    x = np.asarray(states, dtype=np.float64)
    return np.linalg.norm(np.diff(x, axis=0), axis=-1).sum(axis=0)


def compute_metrics(rollout: Rollout | None = None, *, states: Any = None, targets: Any = None,
                    r_safe: float = 0.5, goal_tol: float = 0.1, position: Sequence[int] | None = None,
                    radii: Sequence[float] | None = None) -> dict[str, Any]:
    """The ``metrics.json`` dict of one run; every value is a plain Python type.

    From any loop: ``compute_metrics(states=..., targets=..., r_safe=..., goal_tol=...)`` with
    ``states`` (S+1, K, n) (give ``position``, the state indices of the position) or positions
    (S+1, K, P), and ``targets`` (K, P) (tensors or arrays) returns the keys that depend on the
    trajectories alone: :func:`trajectory_metrics`.

    Beyond the contract keys (:data:`CONTRACT_KEYS`) it adds ``noise_std``, ``r_safe``,
    ``goal_tol`` (from ``rollout.config``, defaults from :class:`Config` when absent),
    ``final_distance_to_target`` (per agent), ``at_target_final`` (all agents within
    ``goal_tol`` at the last state), ``max_slack``, ``failed_local_solves`` (local solves
    that failed and were replaced by the agent's previous plan; 0 when the rollout does
    not record them) and ``failed_local_solves_by_kind`` (``{"exception": n,
    "non-finite": n, "inaccurate": n}``).

    ``reached`` is ``time_to_target is not None``: with process noise an agent can
    drift out of the tolerance again after arriving (``at_target_final`` tells).
    ``min_pair_distance`` is ``None`` for a single agent; steps-based means are
    ``None`` for a run with zero steps.

    Safety and arrival beyond the paper: ``arrival_steps`` (per agent, :func:`arrival_steps`),
    ``arrival_step_max`` (the last agent's arrival; ``None`` if some agent never arrives),
    ``fallback_steps`` (steps at which the safety fallback re-planned an agent) and
    ``unsafe_plan_steps`` (steps at which some pair's applied plans were closer at tau = 1 than
    their collision rows require: the honest safety report of the planner; collision slack
    says nothing, because copies of neighbours' plans are free variables). With obstacles:
    ``obstacle_violations`` and ``min_obstacle_distance`` (:func:`obstacle_metrics`); and
    ``deadlock_steps`` (:func:`deadlock_steps`); the control steps' wall time
    (:func:`step_time_metrics`); ``plan_tracking_rmse`` (:func:`plan_tracking_rmse`);
    with GPs, their one-step prediction during the run (:func:`prediction_metrics`).

    Args:
        rollout: the run, with ``states`` (S+1, K, n) and ``targets`` (K, P).
        states, targets, r_safe, goal_tol, position, radii: the loop form above (without
            ``rollout``); ``radii`` (K,) the body radii.

    Returns:
        Dict of JSON-serializable values.

    Raises:
        GpmpcError: inconsistent array shapes in the rollout.
    """
    if rollout is None:
        if states is None or targets is None:
            raise GpmpcError("compute_metrics: give a Rollout, or states=(S+1, K, n) and targets=(K, P)")
        return trajectory_metrics(states, targets, r_safe, goal_tol, position, radii)
    if states is not None or targets is not None:
        raise GpmpcError("compute_metrics: give a Rollout or states= and targets=, not both")
    states, targets = _checked_states(rollout)
    cfg = rollout.config or {}
    r_safe, goal_tol, noise_std = (run_setting(cfg, key) for key in ("r_safe", "goal_tol", "noise_std"))

    radii = body_radii_of(cfg, states.shape[1], r_safe)  # (K,)
    i, j = np.triu_indices(states.shape[1], k=1)
    pairs = pair_summary(states, radii[i] + radii[j])  # required (P,): r_safe without radii
    ttt = time_to_target(states, targets, goal_tol)
    arrivals = arrival_steps(states, targets, goal_tol)
    final = np.linalg.norm(states[-1] - targets, axis=-1)  # (K,)
    iters = np.asarray(rollout.admm_iterations, dtype=np.float64)
    return {
        "method": str(rollout.method),
        "seed": int(rollout.seed),
        "num_agents": int(states.shape[1]),
        "steps": int(states.shape[0] - 1),
        "reached": ttt is not None,
        "time_to_target": ttt,
        "min_pair_distance": _scalar(pairs["closest"].min()) if i.size else None,
        "violations": pairs["violations"],
        "min_pair_clearance": pairs["min_clearance"],
        "path_length": [float(v) for v in path_lengths(states)],
        "straight_line_length": [float(v) for v in np.linalg.norm(targets - states[0], axis=-1)],
        "admm_iterations_mean": _mean(iters),
        "admm_iterations_max": int(iters.max()) if iters.size else None,
        "converged_fraction": _mean(np.asarray(rollout.converged, dtype=np.float64)),
        "wall_time_s": _scalar(rollout.wall_time_s),
        "solve_time_s_per_step": _mean(np.asarray(rollout.solve_time, dtype=np.float64)),
        **step_time_metrics(getattr(rollout, "step_time", None)),
        "infeasible_local_solves": int(np.sum(rollout.infeasible_solves)),
        "noise_std": noise_std,
        "r_safe": r_safe,
        "goal_tol": goal_tol,
        "final_distance_to_target": [float(v) for v in final],
        "at_target_final": bool(np.all(final <= goal_tol)),
        "max_slack": _max(np.asarray(rollout.slack_max, dtype=np.float64)),
        "state_slack_max": None if getattr(rollout, "state_slack_max", None) is None
        else _max(np.asarray(rollout.state_slack_max, dtype=np.float64)),
        "arrival_steps": arrivals,
        "arrival_step_max": None if any(a is None for a in arrivals) else max(arrivals, default=0),
        "fallback_steps": _count(getattr(rollout, "fallback", None)),
        "unsafe_plan_steps": _count(getattr(rollout, "unsafe_plan", None)),
        **_failures(rollout),
        **risk_metrics(rollout),
        **obstacle_metrics(states, cfg.get("obstacles"), r_safe, radii),
        "deadlock_steps": deadlock_steps(states, targets, goal_tol, r_safe),
        "plan_tracking_rmse": plan_tracking_rmse(rollout),
        **prediction_metrics(rollout, cfg.get("wind_change_step")),
    }


def trajectory_metrics(states: Any, targets: Any, r_safe: float = 0.5, goal_tol: float = 0.1,
                       position: Sequence[int] | None = None, radii: Sequence[float] | None = None) -> dict[str, Any]:
    """The metrics of trajectories from any closed loop, with the keys and meanings of ``metrics.json``:
    ``num_agents, steps, reached, time_to_target, min_pair_distance, violations, min_pair_clearance,
    path_length, straight_line_length, r_safe, goal_tol, final_distance_to_target, at_target_final,
    arrival_steps, arrival_step_max, deadlock_steps``.

    Args:
        states: (S+1, K, n) states (``position`` picks the position entries) or (S+1, K, P) positions.
        targets: (K, P) target positions.
        r_safe: the pair distance a violation falls below (with ``radii``: ``r_k + r_j`` per pair).
        goal_tol: an agent has arrived within this distance of its target.
        position: the position's state indices (``None``: ``states`` are positions).
        radii: per-agent body radii (K,), or ``None``: ``r_safe / 2`` each.

    Raises:
        GpmpcError: shapes that do not fit, or non-finite values, naming the argument.

    Examples:
        >>> import torch
        >>> s = torch.tensor([[[0.0, 0.0], [1.0, 0.0]], [[0.5, 0.0], [0.6, 0.0]]], dtype=torch.float64)
        >>> m = trajectory_metrics(s, targets=s[-1], r_safe=0.5, goal_tol=0.1)
        >>> m["violations"], m["time_to_target"], round(m["min_pair_distance"], 3)
        (1, 1, 0.1)
    """
    pos = np.asarray(states.detach().cpu() if hasattr(states, "detach") else states, dtype=np.float64)
    goal = np.asarray(targets.detach().cpu() if hasattr(targets, "detach") else targets, dtype=np.float64)
    if pos.ndim != 3 or pos.shape[0] < 1:
        raise GpmpcError(f"compute_metrics: states must have shape (S+1, K, n), got {pos.shape}")
    if position is not None:
        pos = pos[..., list(position)]
    if goal.shape != pos.shape[1:]:
        fix = "one row per agent" if goal.ndim == 2 and goal.shape[0] != pos.shape[1] else \
            "pass position=[state indices] when states hold more than the position"
        raise GpmpcError(f"compute_metrics: targets must have shape (K, P) = {pos.shape[1:]}, got {goal.shape}; {fix}")
    for name, arr in (("states", pos), ("targets", goal)):
        if not np.isfinite(arr).all():
            raise GpmpcError(f"compute_metrics: {name} hold NaN or inf")
    K = pos.shape[1]
    radii_k = np.asarray(agent_radii(radii, r_safe, K), dtype=np.float64)
    i, j = np.triu_indices(K, k=1)
    pairs = pair_summary(pos, radii_k[i] + radii_k[j])
    arrivals = arrival_steps(pos, goal, goal_tol)
    final = np.linalg.norm(pos[-1] - goal, axis=-1)
    return {
        "num_agents": int(K), "steps": int(pos.shape[0] - 1),
        "reached": time_to_target(pos, goal, goal_tol) is not None,
        "time_to_target": time_to_target(pos, goal, goal_tol),
        "min_pair_distance": _scalar(pairs["closest"].min()) if i.size else None,
        "violations": pairs["violations"], "min_pair_clearance": pairs["min_clearance"],
        "path_length": [float(v) for v in path_lengths(pos)],
        "straight_line_length": [float(v) for v in np.linalg.norm(goal - pos[0], axis=-1)],
        "r_safe": float(r_safe), "goal_tol": float(goal_tol),
        "final_distance_to_target": [float(v) for v in final], "at_target_final": bool(np.all(final <= goal_tol)),
        "arrival_steps": arrivals,
        "arrival_step_max": None if any(a is None for a in arrivals) else max(arrivals, default=0),
        "deadlock_steps": deadlock_steps(pos, goal, goal_tol, r_safe),
    }


def run_setting(cfg: dict, key: str) -> float:
    """A run's numeric setting ``key`` (``r_safe``, ``goal_tol``, ...) from its flat config dict (the
    :class:`Config` default when absent)."""
    return float(cfg.get(key, getattr(Config(), key)))


def body_radii_of(cfg: dict, num_agents: int, r_safe: float) -> np.ndarray:
    """The agents' body radii (K,) from a run's config: its ``radii``, else ``r_safe / 2`` each."""
    return np.asarray(agent_radii(cfg.get("radii"), r_safe, num_agents), dtype=np.float64)


def step_time_metrics(step_time: Any) -> dict[str, float | None]:
    """``step_time_s_mean``, ``step_time_s_median`` and ``step_time_s_max``: the wall-clock
    seconds of the run's control steps (:attr:`Rollout.step_time`, shape (S,)); ``None`` for
    files written before it was recorded and for runs without steps."""
    times = None if step_time is None else np.asarray(step_time, dtype=np.float64)
    if times is None or not times.size:
        return {"step_time_s_mean": None, "step_time_s_median": None, "step_time_s_max": None}
    return {"step_time_s_mean": float(times.mean()), "step_time_s_median": float(np.median(times)),
            "step_time_s_max": float(times.max())}


#: Steps after (and before) ``wind_change_step`` that the ``*_after_change`` (``*_before_change``)
#: prediction metrics cover.
CHANGE_WINDOW = 50


def prediction_metrics(rollout: Rollout, change_step: int | None) -> dict[str, Any]:
    """The GPs' one-step prediction during the run (frozen or ``gp_online``; empty without GPs):
    ``online_prediction_rmse`` over all steps, agents and residual rows; ``online_coverage95`` (share
    of rows within 1.96 predictive standard deviations); ``gp_update_s_per_step``; with
    ``wind_change_step`` c, the same two over steps [c, c + 50) (``*_after_change``) and
    [c - 50, c) (``*_before_change``), and ``online_prediction_rmse_at_change``, step c alone (the
    first transition in the changed world, which no model has seen), ``None`` where the run has no
    such steps. With ``gp_online`` (:attr:`Rollout.frozen_prediction_error`),
    ``frozen_prediction_rmse`` and ``frozen_prediction_rmse_after_change``: the GPs as fitted, with
    the offset estimates they would have made themselves, on the same transitions (``None``
    otherwise)."""
    error = getattr(rollout, "prediction_error", None)
    if error is None:
        return {}
    error, var = np.asarray(error), np.asarray(rollout.prediction_var)
    frozen = getattr(rollout, "frozen_prediction_error", None)
    frozen = None if frozen is None else np.asarray(frozen)

    def rmse(sl, err=error):
        if err is None:
            return None
        return float(np.sqrt(np.mean(err[sl] ** 2))) if err[sl].size else None

    def coverage(sl):
        return float(np.mean(np.abs(error[sl]) <= 1.96 * np.sqrt(var[sl]))) if error[sl].size else None

    out = {"online_prediction_rmse": rmse(slice(None)), "online_coverage95": coverage(slice(None)),
           "frozen_prediction_rmse": rmse(slice(None), frozen),
           "gp_update_s_per_step": _mean(np.asarray(rollout.gp_update_time, dtype=np.float64))}
    if change_step is not None:
        c = int(change_step)
        after, before = slice(c, c + CHANGE_WINDOW), slice(max(0, c - CHANGE_WINDOW), c)
        out.update({"online_prediction_rmse_after_change": rmse(after),
                    "online_coverage95_after_change": coverage(after),
                    "online_prediction_rmse_before_change": rmse(before),
                    "online_coverage95_before_change": coverage(before),
                    "online_prediction_rmse_at_change": rmse(slice(c, c + 1)),
                    "frozen_prediction_rmse_after_change": rmse(after, frozen)})
    return out


def plan_tracking_rmse(rollout: Rollout) -> float | None:
    """RMSE between every agent's planned next state (the plan at tau = 1) and the true state the plant
    reached, over steps, agents and state entries (``None`` for a run with zero steps): how well the
    planning model (nominal plus learned residual) predicts the plant one step ahead. The rows that
    hold the last input (:attr:`Rollout.input_memory`) are left out: a plan predicts them exactly."""
    plans, flown = np.asarray(rollout.plans), np.asarray(rollout.states)
    if plans.shape[0] == 0:
        return None
    memory = set(getattr(rollout, "input_memory", None) or ())
    rows = [i for i in range(plans.shape[-1]) if i not in memory]
    return float(np.sqrt(np.mean((plans[:, :, 1, rows] - flown[1:, :, rows]) ** 2)))


def deadlock_steps(positions: np.ndarray, targets: np.ndarray, goal_tol: float, r_safe: float,
                   window: int = DEADLOCK_WINDOW) -> int:
    """Steps s at which some agent is stuck: farther than ``r_safe + goal_tol`` from its target at
    s (nearer, noise keeps agents hovering), and its distance to the target has not shrunk by
    ``goal_tol`` over the last ``window`` steps.

    Args:
        positions: (S+1, K, P) true positions. targets: (K, P).
    """
    dist = target_distances(positions, targets)  # (S+1, K)
    if dist.shape[0] <= window:
        return 0
    stalled = (dist[window:] > r_safe + goal_tol) & (dist[:-window] - dist[window:] < goal_tol)
    return int(np.count_nonzero(stalled.any(axis=1)))


def obstacle_metrics(positions: np.ndarray, obstacles: Any, r_safe: float,
                     radii: np.ndarray | None = None) -> dict[str, Any]:
    """``min_obstacle_distance`` (the smallest distance from an agent's centre to an obstacle's
    surface over the run; negative inside; ``None`` without obstacles) and ``obstacle_violations``
    (the (step, agent, obstacle) entries closer than the agent's body radius by more than
    :data:`OBSTACLE_TOL`, the solvers' accuracy: a plan that holds its row exactly lands on it; 0 without).

    Args:
        positions: (S+1, K, P) true positions.
        obstacles: the run's ``obstacles`` (list of tables or an ``ObstacleField``), or ``None``.
        r_safe: the pair distance; the body radius is ``r_safe / 2`` unless ``radii`` (K,) gives one
            per agent.
    """
    import torch

    from torch_gpmpc.config.obstacles import ObstacleField
    from torch_gpmpc.control.obstacle_rows import obstacle_geometry

    if not obstacles:
        return {"obstacle_violations": 0, "min_obstacle_distance": None}
    dist, _ = obstacle_geometry(ObstacleField.parse(obstacles), torch.as_tensor(positions, dtype=torch.float64))
    dist = dist.numpy()  # (S+1, K, O)
    radius = r_safe / 2 if radii is None else np.asarray(radii, dtype=np.float64)[None, :, None]
    return {"obstacle_violations": int(np.count_nonzero(dist < radius - OBSTACLE_TOL)),
            "min_obstacle_distance": _scalar(dist.min())}


def risk_metrics(rollout: Rollout) -> dict[str, Any]:
    """``risk_spent`` (the sum over applied steps of the bounds on each pair's collision
    probability and each agent's obstacle hits at the next sample: by Boole's inequality a bound on
    the probability of any collision or hit in the run, under the chance constraints' assumptions;
    ``None`` without margins or in older files), ``risk_mode`` and ``risk_budget`` (``None`` under
    ``pair_step``).
    """
    cfg = rollout.config or {}
    mode = str(cfg.get("risk_mode", "pair_step"))
    parts = [np.asarray(r, dtype=np.float64).ravel() for r in (getattr(rollout, "pair_risk", None),
                                                               getattr(rollout, "obstacle_risk", None)) if r is not None]
    risks = np.concatenate(parts) if parts else None
    spent = None if risks is None or not np.isfinite(risks).any() else float(np.nansum(risks))
    return {"risk_spent": spent, "risk_spent_shortfall": shortfall_risk(rollout, run_setting(cfg, "admm_tol")),
            "risk_mode": mode,
            "risk_budget": float(cfg.get("risk_budget", Config().risk_budget)) if mode == "mission" else None}


def shortfall_risk(rollout: Rollout, tol: float) -> float | None:
    """The part of ``risk_spent``'s pair risk spent at pair-steps whose applied plans were closer at
    tau = 1 than their rows require (by more than ``tol``, the consensus tolerance): slack or an
    unconverged stop, risk the controller took beyond what its rows promise. The rest is the rows'
    own per-step risk, which grows with the number of pair-steps at the bound. ``None`` without
    pair risks."""
    risk, sep, req = (getattr(rollout, k, None) for k in ("pair_risk", "pair_separation", "pair_required"))
    if risk is None or sep is None or req is None or not np.isfinite(risk).any():
        return None
    short = np.nan_to_num(sep, nan=np.inf) < np.nan_to_num(req, nan=-np.inf) - tol
    return float(np.nansum(np.where(short, risk, 0.0)))


def _count(flags: Any) -> int | None:
    """Number of true flags; ``None`` when the rollout does not record them."""
    return None if flags is None else int(np.count_nonzero(flags))


def _failures(rollout: Rollout) -> dict[str, Any]:
    """``failed_local_solves`` and its split by kind (zeros when the rollout lacks them)."""
    from torch_gpmpc.control.problem import FAILURE_KINDS

    by_kind = getattr(rollout, "failed_solves_by_kind", None)
    total = getattr(rollout, "failed_solves", None)
    counts = (np.asarray(by_kind, dtype=np.int64).reshape(-1, len(FAILURE_KINDS)).sum(axis=0)
              if by_kind is not None else np.zeros(len(FAILURE_KINDS), dtype=np.int64))
    return {
        "failed_local_solves": int(np.sum(total)) if total is not None else int(counts.sum()),
        "failed_local_solves_by_kind": {kind: int(n) for kind, n in zip(FAILURE_KINDS, counts)},
    }


def _checked_states(rollout: Rollout) -> tuple[np.ndarray, np.ndarray]:
    """Positions (S+1, K, P) of the states and ``targets`` (K, P) as float64, shapes checked."""
    states = np.asarray(rollout.positions, dtype=np.float64)
    targets = np.asarray(rollout.targets, dtype=np.float64)
    if states.ndim != 3 or states.shape[0] < 1:
        raise GpmpcError(f"rollout 'states' must have shape (S+1, K, D), got {states.shape}")
    if targets.shape != states.shape[1:]:
        raise GpmpcError(f"rollout 'targets' must have shape (K, D) = {states.shape[1:]}, got {targets.shape}")
    return states, targets


def _scalar(value: Any) -> float | None:
    """Python float, or ``None`` when not finite."""
    v = float(value)
    return v if math.isfinite(v) else None


def _mean(values: np.ndarray) -> float | None:
    """Mean as a Python float; ``None`` for an empty array or a non-finite mean."""
    return _scalar(values.mean()) if values.size else None


def _max(values: np.ndarray) -> float | None:
    """Largest finite value; ``None`` if there is none."""
    finite = values[np.isfinite(values)]
    return float(finite.max()) if finite.size else None
