"""The closed loop: plan with ADMM, apply the first input, step the true system, repeat.

At step t: build the communication graph from the current states, take the
reference window ``x_ref^{t..t+T}``, warm-start ADMM from the previous step's
iterate shifted by one step, apply ``u^t`` of each agent's plan to the true system
``x' = A x + B u + g(x) + w``. Stop when every agent is within ``goal_tol`` of its
target or after ``max_steps``.

Seeds: run seed s fixes the GP training data (stream ``2 s + 1``) and the noise
sequence (stream ``2 s``), so every method sees the same data and the same noise.
"""

from __future__ import annotations

import logging
import math
import time
from typing import Callable

import numpy as np
import torch
from torch import Tensor

from torch_gpmpc.coordination.admm import ADMM, StepResult
from torch_gpmpc.config.schema import Config
from torch_gpmpc.dynamics.methods import Method
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.coordination.graph import communication_graph
from torch_gpmpc.control.problem import FAILURE_KINDS
from torch_gpmpc.sim.rollout import Rollout
from torch_gpmpc.sim.scenarios import Scenario, make_scenario
from torch_gpmpc.dynamics.systems import TrueSystem, make_system

log = logging.getLogger(__name__)

StepCallback = Callable[[int, dict], None]


def needs_gp(method: str | Method) -> bool:
    """Whether ``method`` uses a residual GP (for its dynamics or its chance margins)."""
    return Method.parse(method).needs_gp


def noise_sequence(cfg: Config, num_agents: int) -> Tensor:
    """Standard-normal process noise for the whole run, shape (max_steps, K, D)."""
    gen = torch.Generator().manual_seed(2 * cfg.seed)
    return torch.randn(cfg.max_steps, num_agents, cfg.dim, generator=gen)


def check_gp_inputs(cfg: Config) -> None:
    """The controller linearizes GPs of the state alone (paper eq. 12).

    Raises:
        GpmpcError: ``gp_inputs`` is not ``state``.
    """
    if cfg.gp_inputs != "state":
        raise GpmpcError("config key 'gp_inputs': the controller needs state-input GPs; use gp_inputs=state")


def train_agent_gps(cfg: Config, system: TrueSystem, num_agents: int) -> list:
    """Fit one residual GP per agent from the paper's data recipe (design.md §3).

    Each agent gets its own ``cfg.gp_samples`` transitions of the true system,
    drawn with the run's seed (stream ``2 seed + 1``).

    Returns:
        K fitted :class:`~torch_gpmpc.gp.model.ResidualGP` models.
    """
    from torch_gpmpc.data.transitions import collect_transitions
    from torch_gpmpc.gp.model import fit_residual_gp

    check_gp_inputs(cfg)
    data = collect_transitions(system, num_agents=num_agents, samples=cfg.gp_samples,
                               seed=2 * cfg.seed + 1, u_max=cfg.u_max, box=cfg.circle_radius)
    gps = []
    for k in range(num_agents):
        inputs, y = data.for_agent(k).residuals(system.nominal)
        gps.append(fit_residual_gp(inputs, y, optimizer=cfg.gp_optimizer, iters=cfg.gp_iters, seed=cfg.seed + k))
    return gps


def _check_gps(gps: list, num_agents: int, dim: int) -> list:
    if len(gps) == 1 and num_agents > 1:
        gps = gps * num_agents
    if len(gps) != num_agents:
        raise GpmpcError(f"got {len(gps)} GP models for {num_agents} agents; give one, or one per agent")
    for gp in gps:
        if gp.input_dim != dim or gp.output_dim != dim:
            raise GpmpcError(
                f"GP model has input/output dimension {gp.input_dim}/{gp.output_dim} but the run has "
                f"dim={dim}; fit it on {dim}-D state transitions (gp_inputs=state)"
            )
    return gps


def _pair_min_distance(x: Tensor) -> float:
    if x.shape[0] < 2:
        return math.inf
    dist = torch.cdist(x, x)
    dist.fill_diagonal_(math.inf)
    return float(dist.min())


def simulate(
    cfg: Config,
    scenario: Scenario | None = None,
    method: str | None = None,
    gps: list | None = None,
    on_step: StepCallback | None = None,
    tb=None,
) -> Rollout:
    """Run one closed-loop scenario.

    Args:
        cfg: run configuration.
        scenario: starts/targets/reference (default: ``make_scenario(cfg)``).
        method: controller method (default ``cfg.method``).
        gps: residual GPs, one per agent or one shared; trained from the seed's data if
            ``None`` and the method needs them.
        on_step: called after every step with ``(t, info)``; info has ``iterations``,
            ``min_distance``, ``converged``, ``primal``.
        tb: a :class:`~torch_gpmpc.report.tensorboard.TBLogger` (or ``None``).

    Returns:
        The :class:`Rollout` (S steps, K agents, horizon T).
    """
    method = method or cfg.method
    cfg = cfg.replace(method=method)
    scenario = scenario or make_scenario(cfg)
    num_agents = scenario.starts.shape[0]
    system = make_system(cfg.dim, cfg.noise_std, cfg.wind_scale)
    if needs_gp(method):
        gps = _check_gps(gps, num_agents, cfg.dim) if gps is not None else train_agent_gps(cfg, system, num_agents)
    else:
        gps = None
    wind = system.wind if Method.parse(method).needs_wind else None
    admm = ADMM(cfg, method, system.nominal, wind, gps)
    noise = noise_sequence(cfg, num_agents)
    targets = scenario.targets
    recorder = _Recorder(cfg, num_agents)

    start_time = time.perf_counter()
    x = scenario.starts.clone()
    states = [x]
    warm = None
    with torch.no_grad():
        for t in range(cfg.max_steps):
            if bool(((x - targets).norm(dim=1) < cfg.goal_tol).all()):
                break
            graph = communication_graph(x, cfg.comm_radius)
            xref = scenario.reference_window(t, cfg.horizon)
            res = admm.solve_step(x, xref, graph, warm=warm)
            u = _clip_norm(res.inputs[:, 0], cfg.u_max)
            x = system.step(x, u, noise=noise[t])
            states.append(x)
            warm = res.state.shifted()
            info = recorder.record(t, res, graph.adjacency(), u, x)
            if tb is not None:
                _log_step(tb, t, info, res)
            if on_step is not None:
                on_step(t, info)
    wall = time.perf_counter() - start_time
    return recorder.rollout(torch.stack(states), targets, wall, method)


def _clip_norm(u: Tensor, u_max: float) -> Tensor:
    """Project inputs onto the ball ||u|| <= u_max (guards solver tolerance and fallbacks)."""
    norm = u.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    return u * torch.clamp(u_max / norm, max=1.0)


def _log_step(tb, t: int, info: dict, res: StepResult) -> None:
    tb.scalar("admm/primal_residual", res.primal_residuals[-1], t)
    tb.scalar("admm/dual_residual", res.dual_residuals[-1], t)
    tb.scalar("admm/iterations", res.iterations, t)
    tb.scalar("safety/min_distance", info["min_distance"], t)
    tb.scalar("safety/violations", info["violations_total"], t)
    tb.scalar("safety/chance_margin", res.max_margin, t)
    tb.scalar("safety/slack_max", res.slack_max, t)
    tb.scalar("perf/solve_ms", 1000.0 * res.solve_time_s / max(res.iterations, 1), t)


class _Recorder:
    """Collects per-step arrays and builds the :class:`Rollout`."""

    def __init__(self, cfg: Config, num_agents: int) -> None:
        self.cfg = cfg
        self.num_agents = num_agents
        self.rows: dict[str, list] = {k: [] for k in (
            "inputs", "plans", "adjacency", "admm_iterations", "converged", "primal", "dual",
            "slack_max", "infeasible_solves", "solve_time", "chance_margin", "messages",
            "failed_solves", "failed_by_kind")}
        self.violations_total = 0

    def record(self, t: int, res: StepResult, adjacency: Tensor, u: Tensor, x_next: Tensor) -> dict:
        r = self.rows
        r["inputs"].append(u.numpy())
        r["plans"].append(res.plans.numpy())
        r["adjacency"].append(adjacency.numpy())
        r["admm_iterations"].append(res.iterations)
        r["converged"].append(res.converged)
        r["primal"].append(res.primal_residuals)
        r["dual"].append(res.dual_residuals)
        r["slack_max"].append(res.slack_max)
        r["infeasible_solves"].append(res.infeasible_solves)
        r["failed_solves"].append(res.failed_solves)
        r["failed_by_kind"].append([res.failed_by_kind[kind] for kind in FAILURE_KINDS])
        r["solve_time"].append(res.solve_time_s)
        r["chance_margin"].append(res.max_margin)
        r["messages"].append(res.messages.numpy())
        min_dist = _pair_min_distance(x_next)
        if self.num_agents > 1:
            dist = torch.cdist(x_next, x_next)
            self.violations_total += int((dist[torch.triu_indices(self.num_agents, self.num_agents, 1).unbind()] < self.cfg.r_safe).sum())
        return {"iterations": res.iterations, "min_distance": min_dist, "converged": res.converged,
                "primal": res.primal_residuals[-1], "violations_total": self.violations_total}

    def rollout(self, states: Tensor, targets: Tensor, wall: float, method: str) -> Rollout:
        r, cfg, k = self.rows, self.cfg, self.num_agents
        steps = len(r["inputs"])
        width = cfg.admm_max_iter
        primal = np.full((steps, width), np.nan)
        dual = np.full((steps, width), np.nan)
        for i, (p, d) in enumerate(zip(r["primal"], r["dual"])):
            primal[i, : len(p)] = p
            dual[i, : len(d)] = d
        T, D = cfg.horizon, cfg.dim

        def stack(name, shape, dtype=float):
            return np.asarray(r[name], dtype=dtype) if steps else np.zeros(shape, dtype=dtype)

        return Rollout(
            states=states.numpy(),
            inputs=stack("inputs", (0, k, D)),
            plans=stack("plans", (0, k, T + 1, D)),
            targets=targets.numpy(),
            adjacency=stack("adjacency", (0, k, k), bool),
            admm_iterations=stack("admm_iterations", (0,), int),
            converged=stack("converged", (0,), bool),
            primal_residuals=primal,
            dual_residuals=dual,
            slack_max=stack("slack_max", (0,)),
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
        )
