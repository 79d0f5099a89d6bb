"""Recording a closed-loop run: per-step records, TensorBoard scalars, the Rollout."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from torch_gpmpc.config.schema import Config
from torch_gpmpc.config.settings import agent_radii
from torch_gpmpc.control.obstacle_rows import obstacle_geometry
from torch_gpmpc.control.problem import FAILURE_KINDS
from torch_gpmpc.coordination.state import StepResult
from torch_gpmpc.sim.rollout import Rollout


@dataclass
class StepInfo:
    """What a closed-loop step reports to ``on_step`` callbacks.

    Attributes:
        iterations: ADMM iterations of the step.
        min_distance: smallest pair distance after the step (inf for one agent).
        converged: whether ADMM met its tolerance.
        primal: the last primal residual.
        violations_total: (step, pair) distances below r_safe so far.
        lost_agents: agents the distributed backend has lost (empty in-process).
        risk_spent: the pairs' collision-probability bounds and the obstacle rows' hit bounds
            summed over the steps so far (``metrics.json``'s ``risk_spent``; 0 without margins).
        min_obstacle_distance: smallest distance from an agent's centre to an obstacle after the
            step (NaN without obstacles).
        step_s: wall-clock seconds of the step's planning (NaN where not measured).
    """

    iterations: int
    min_distance: float
    converged: bool
    primal: float
    violations_total: int
    lost_agents: list[int] = field(default_factory=list)
    risk_spent: float = 0.0
    min_obstacle_distance: float = math.nan
    step_s: float = math.nan


def pair_min_distance(x: Tensor) -> float:
    """Smallest distance between two of the K positions ``x`` (K, D); inf for K < 2."""
    if x.shape[0] < 2:
        return math.inf
    dist = torch.cdist(x, x)
    dist.fill_diagonal_(math.inf)
    return float(dist.min())


def log_step(tb, t: int, info: StepInfo, res: StepResult) -> None:
    """Step t's ``admm/``, ``safety/`` and ``perf/`` scalars to a TensorBoard logger."""
    tb.scalar("admm/primal_residual", info.primal, t)
    tb.scalar("admm/dual_residual", res.dual_residuals[-1] if res.dual_residuals else math.nan, t)
    tb.scalar("admm/iterations", res.iterations, t)
    if res.unconverged_edges:  # the in-process backend counts them
        tb.scalar("admm/unconverged_edges", res.unconverged_edges[-1], t)
    tb.scalar("safety/min_distance", info.min_distance, t)
    tb.scalar("safety/violations", info.violations_total, t)
    tb.scalar("safety/chance_margin", res.max_margin, t)
    tb.scalar("safety/slack_max", res.slack_max, t)
    tb.scalar("safety/state_slack_max", res.state_slack_max, t)
    tb.scalar("safety/risk_spent", info.risk_spent, t)
    if not math.isnan(info.min_obstacle_distance):
        tb.scalar("safety/min_obstacle_distance", info.min_obstacle_distance, t)
    tb.scalar("perf/solve_ms", 1000.0 * res.solve_time_s / max(res.iterations, 1), t)
    tb.scalar("perf/step_ms", 1000.0 * info.step_s, t)  # NaN (not measured) is skipped


class StepRecorder:
    """Collects per-step arrays of a closed-loop run and builds its :class:`Rollout`.

    Args:
        cfg: run configuration.
        num_agents: K.
    """

    def __init__(self, cfg: Config, num_agents: int) -> None:
        self.cfg = cfg
        self.num_agents = num_agents
        self.rows: dict[str, list] = {k: [] for k in (
            "inputs", "plans", "adjacency", "admm_iterations", "converged", "primal", "dual",
            "slack_max", "state_slack_max", "infeasible_solves", "solve_time", "chance_margin", "messages",
            "failed_solves", "failed_by_kind", "fallback", "unsafe_plan", "pair_separation", "pair_required",
            "pair_risk", "obstacle_risk", "step_time")}
        self.pairs = torch.triu_indices(num_agents, num_agents, 1).unbind()
        radii = torch.tensor(agent_radii(cfg.radii, cfg.r_safe, num_agents), dtype=torch.float64)
        #: each pair's required centre distance (r_safe, or r_k + r_j), (pairs,)
        self.required = radii[self.pairs[0]] + radii[self.pairs[1]]
        self.position = list(cfg.model_spec().position)
        self.violations_total = 0
        self.risk_spent = 0.0
        self.predictions: dict[str, list] = {"error": [], "var": [], "frozen_error": [], "update_s": []}
        self.coverage_sum = 0.0

    def record_prediction(self, t: int, error: Tensor, var: Tensor, update_s: float, tb=None,
                          frozen_error: Tensor | None = None) -> None:
        """Step t's one-step GP prediction errors and predictive variances (K, R), the time of the
        GP updates and, with online GPs, the frozen fits' errors on the same transitions (K, R); to
        TensorBoard as ``gp/online_prediction_error`` (RMS over agents and rows),
        ``gp/frozen_prediction_error`` (the same for the frozen fits) and ``gp/online_coverage95``
        (the share of rows within 1.96 predictive standard deviations so far)."""
        p = self.predictions
        p["error"].append(error.numpy())
        p["var"].append(var.numpy())
        p["update_s"].append(update_s)
        if frozen_error is not None:
            p["frozen_error"].append(frozen_error.numpy())
            if tb is not None:
                tb.scalar("gp/frozen_prediction_error", float(frozen_error.square().mean().sqrt()), t)
        if tb is not None:
            inside = float((error.abs() <= 1.96 * var.sqrt()).double().mean())
            self.coverage_sum += inside  # every step has K x R rows: the mean of the steps' shares
            tb.scalar("gp/online_prediction_error", float(error.square().mean().sqrt()), t)
            tb.scalar("gp/online_coverage95", self.coverage_sum / len(p["error"]), t)
            tb.scalar("perf/gp_update_ms", 1000.0 * update_s, t)

    def record(self, t: int, res: StepResult, adjacency: Tensor, u: Tensor, x_next: Tensor,
               step_s: float) -> StepInfo:
        """Record step t: its ADMM result, graph (K, K), applied inputs (K, Du), next states (K, D)
        and the wall-clock seconds its planning took."""
        r = self.rows
        r["step_time"].append(step_s)
        r["inputs"].append(u.numpy())
        r["plans"].append(res.plans.numpy())
        r["adjacency"].append(adjacency.numpy())
        r["admm_iterations"].append(res.iterations)
        r["converged"].append(res.converged)
        r["primal"].append(res.primal_residuals)
        r["dual"].append(res.dual_residuals)
        r["slack_max"].append(res.slack_max)
        r["state_slack_max"].append(res.state_slack_max)
        r["infeasible_solves"].append(res.infeasible_solves)
        r["failed_solves"].append(res.failed_solves)
        r["failed_by_kind"].append([res.failed_by_kind[kind] for kind in FAILURE_KINDS])
        r["solve_time"].append(res.solve_time_s)
        r["chance_margin"].append(res.max_margin)
        r["messages"].append(res.messages.numpy())
        r["fallback"].append(res.fallback)
        r["unsafe_plan"].append(res.unsafe_plan)
        r["pair_separation"].append(self._per_pair(res.pair_separation))
        r["pair_required"].append(self._per_pair(res.pair_required))
        r["pair_risk"].append(self._per_pair(getattr(res, "pair_risk", None)))
        r["obstacle_risk"].append(self._per_agent(getattr(res, "obstacle_risk", None)))
        self.risk_spent += float(np.nansum(r["pair_risk"][-1])) + float(np.nansum(r["obstacle_risk"][-1]))
        pos = x_next[:, self.position]
        min_dist = pair_min_distance(pos)
        if self.num_agents > 1:
            dist = torch.cdist(pos, pos)
            self.violations_total += int((dist[self.pairs] < self.required).sum())
        return StepInfo(iterations=res.iterations, min_distance=min_dist, converged=res.converged,
                        primal=res.primal_residuals[-1] if res.primal_residuals else math.nan,
                        violations_total=self.violations_total, lost_agents=list(res.lost_agents),
                        risk_spent=self.risk_spent, min_obstacle_distance=self._obstacle_distance(pos),
                        step_s=step_s)

    def _obstacle_distance(self, positions: Tensor) -> float:
        """Smallest centre-to-obstacle distance of positions (K, P); NaN without obstacles."""
        if self.cfg.obstacles is None or not len(self.cfg.obstacles):
            return math.nan
        return float(obstacle_geometry(self.cfg.obstacles, positions)[0].min())

    def _per_agent(self, values: Tensor | None) -> np.ndarray:
        """(K,) per-agent values as an array (NaN when not reported)."""
        if values is None:
            return np.full(self.num_agents, np.nan)
        return values.detach().numpy()

    def _per_pair(self, matrix: Tensor | None) -> np.ndarray:
        """A (K, K) per-pair matrix as its P upper-triangle entries (NaN when not reported)."""
        if matrix is None:
            return np.full(self.pairs[0].numel(), np.nan)
        return matrix.detach()[self.pairs].numpy()

    def rollout(self, states: Tensor, targets: Tensor, wall: float, method: str,
                position: list[int] | None = None, input_memory: list[int] | None = None) -> Rollout:
        """The run's :class:`Rollout` from the states (S+1, K, D), targets (K, P), the
        position indices of the state (``None``: every state is a position) and the rows that hold
        the last input (:attr:`Rollout.input_memory`)."""
        r, cfg, k = self.rows, self.cfg, self.num_agents
        steps = len(r["inputs"])
        width = cfg.iteration_cap
        primal = np.full((steps, width), np.nan)
        dual = np.full((steps, width), np.nan)
        for i, (p, d) in enumerate(zip(r["primal"], r["dual"])):
            primal[i, : len(p)] = p
            dual[i, : len(d)] = d
        T, D, Du = cfg.horizon, cfg.state_dim, cfg.input_dim
        pred = self.predictions

        def stack(name, shape, dtype=float):
            return np.asarray(r[name], dtype=dtype) if steps else np.zeros(shape, dtype=dtype)

        return Rollout(
            states=states.numpy(),
            inputs=stack("inputs", (0, k, Du)),
            plans=stack("plans", (0, k, T + 1, D)),
            targets=targets.numpy(),
            adjacency=stack("adjacency", (0, k, k), bool),
            admm_iterations=stack("admm_iterations", (0,), int),
            converged=stack("converged", (0,), bool),
            primal_residuals=primal,
            dual_residuals=dual,
            slack_max=stack("slack_max", (0,)),
            state_slack_max=stack("state_slack_max", (0,)),
            infeasible_solves=stack("infeasible_solves", (0,), int),
            solve_time=stack("solve_time", (0,)),
            chance_margin=stack("chance_margin", (0,)),
            wall_time_s=wall,
            method=method,
            seed=cfg.seed,
            config=cfg.to_dict(),
            messages_per_iteration=stack("messages", (0, k), int),
            failed_solves=stack("failed_solves", (0,), int),
            failed_solves_by_kind=stack("failed_by_kind", (0, len(FAILURE_KINDS)), int),
            fallback=stack("fallback", (0,), bool),
            unsafe_plan=stack("unsafe_plan", (0,), bool),
            pair_separation=stack("pair_separation", (0, len(self.pairs[0]))),
            pair_required=stack("pair_required", (0, len(self.pairs[0]))),
            pair_risk=stack("pair_risk", (0, len(self.pairs[0]))),
            obstacle_risk=stack("obstacle_risk", (0, k)) if cfg.obstacles is not None and len(cfg.obstacles) else None,
            position=None if position is None or position == list(range(D)) else list(position),
            input_memory=list(input_memory) if input_memory else None,
            prediction_error=np.asarray(pred["error"]) if pred["error"] else None,
            prediction_var=np.asarray(pred["var"]) if pred["var"] else None,
            frozen_prediction_error=np.asarray(pred["frozen_error"])
            if pred["frozen_error"] and len(pred["frozen_error"]) == len(pred["error"]) else None,
            gp_update_time=np.asarray(pred["update_s"]) if pred["update_s"] else None,
            step_time=stack("step_time", (0,)),
        )
