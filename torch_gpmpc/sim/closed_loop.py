"""The one closed loop: plan, apply the first input, step the true system, repeat.

At step t: build the communication graph from the current states, take the reference
window ``x_ref^{t..t+T}``, ask the planner for every agent's plan, apply ``u^t`` of each
plan to the true system ``x' = A x + B u + g(x) + w``. Stop when every agent is within
``goal_tol`` of its target or after ``max_steps``.

The planner is the in-process consensus ADMM (:class:`ADMMPlanner`, warm-started from
the previous step's iterate shifted by one step) or the distributed backend's world,
which asks the agent processes (:mod:`~torch_gpmpc.sim.distributed`); both go through
:func:`run_closed_loop`.

Seeds: run seed s fixes the GP training data (stream ``2 s + 1``) and the noise
sequence (stream ``2 s``), so every method sees the same data and the same noise.
"""

from __future__ import annotations

import time
from typing import Callable, Protocol

import torch
from torch import Tensor

from torch_gpmpc.config.schema import Config
from torch_gpmpc.config.settings import agent_radii
from torch_gpmpc.control.risk import chance_quantile
from torch_gpmpc.coordination.admm import ADMM
from torch_gpmpc.coordination.controller import Controller
from torch_gpmpc.coordination.graph import Graph, communication_graph
from torch_gpmpc.coordination.state import ADMMState, StepResult
from torch_gpmpc.dynamics.methods import Method
from torch_gpmpc.config.model_spec import ModelSpec
from torch_gpmpc.control.solvers.ipm_threads import planning_threads
from torch_gpmpc.dynamics.plants import Plant, plant_from_config
from torch_gpmpc.dynamics.systems import TrueSystem
from torch_gpmpc.dynamics.team import TeamSystem, team_system_from_config
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.gp.online import OnlineLearning, run_models
from torch_gpmpc.sim.detours import DeadlockBreaker, detour_clearance, detour_reference
from torch_gpmpc.sim.path_following import PathFollower
from torch_gpmpc.sim.recorder import StepInfo, StepRecorder, log_step
from torch_gpmpc.sim.rollout import Rollout
from torch_gpmpc.sim.scenarios import Scenario, make_scenario, with_scenario_world

StepCallback = Callable[[int, StepInfo], None]


class Planner(Protocol):
    """What the closed loop asks at every step."""

    def plan(self, t: int, x: Tensor, xref: Tensor, graph: Graph) -> StepResult | None:
        """Plans for step t from states ``x`` (K, D) and references ``xref`` (K, T+1, D);
        ``None`` ends the run (no agent left to plan)."""


class ADMMPlanner:
    """The in-process planner: a :class:`~torch_gpmpc.coordination.controller.Controller` (consensus
    ADMM over all agents, warm-started step to step) stepped by the closed loop.

    Args:
        controller: the run's controller (:meth:`Controller.for_run
            <torch_gpmpc.coordination.controller.Controller.for_run>`).
    """

    def __init__(self, controller: Controller) -> None:
        self.controller = controller

    @property
    def admm(self) -> ADMM:
        """The controller's consensus ADMM."""
        return self.controller.admm

    def plan(self, t: int, x: Tensor, xref: Tensor, graph: Graph) -> StepResult:
        """One controller step (it keeps the iterate as the next step's warm start).

        The step runs under ``torch.inference_mode`` (nothing in a closed loop is differentiated):
        the same arithmetic as under ``no_grad``, with less of torch's per-operation bookkeeping
        (10-20 % of a small team's ADMM iteration)."""
        with torch.inference_mode():
            return self.controller.step(x, xref, graph)


def needs_gp(method: str | Method) -> bool:
    """Whether ``method`` uses a residual GP (for its dynamics or its chance margins)."""
    return Method.parse(method).needs_gp


def noise_sequence(cfg: Config, num_agents: int) -> Tensor:
    """Standard-normal process noise for the whole run, shape (max_steps, K, R) (R: the model's
    residual rows, where the noise acts), float64."""
    gen = torch.Generator().manual_seed(2 * cfg.seed)
    return torch.randn(cfg.max_steps, num_agents, len(cfg.model_spec().residual), generator=gen,
                       dtype=torch.float64)


def check_gps(gps: list, num_agents: int, spec: ModelSpec | list[ModelSpec]) -> list:
    """One GP per agent (a single GP is shared), each with its model's GP inputs and residual rows
    (``spec``: the team's model, or one per agent).

    Raises:
        GpmpcError: wrong count or dimension.
    """
    if len(gps) == 1 and num_agents > 1:
        gps = gps * num_agents
    if len(gps) != num_agents:
        raise GpmpcError(f"got {len(gps)} GP models for {num_agents} agents; give one, or one per agent")
    specs = spec if isinstance(spec, list) else [spec] * num_agents
    for gp, spec in zip(gps, specs):
        din, dout = len(spec.gp_inputs), len(spec.residual)
        if gp.input_dim != din or gp.output_dim != dout:
            raise GpmpcError(
                f"GP model has input/output dimension {gp.input_dim}/{gp.output_dim} but the model "
                f"{spec.name!r} has {din} GP inputs and {dout} residual rows; fit it with "
                "gpmpc fit-gp --model on transitions of that model"
            )
    return gps


def agent_specs(cfg: Config, num_agents: int) -> list[ModelSpec]:
    """Every agent's model (lifted to the team's sizes with ``models``, whose length
    :func:`~torch_gpmpc.sim.scenarios.with_scenario_world` has checked against the team size)."""
    team = cfg.team()
    return [cfg.model_spec()] * num_agents if team is None else [team.agent_spec(k) for k in range(num_agents)]


def simulate(
    cfg: Config,
    scenario: Scenario | None = None,
    method: str | None = None,
    gps: list | None = None,
    on_step: StepCallback | None = None,
    tb=None,
) -> Rollout:
    """Run one closed-loop scenario in this process.

    Args:
        cfg: run configuration.
        scenario: starts/targets/reference (default: ``make_scenario(cfg)``).
        method: controller method (default ``cfg.method``).
        gps: residual GPs, one per agent or one shared; trained from the seed's data if
            ``None`` and the method needs them.
        on_step: called after every step with ``(t, StepInfo)``.
        tb: a :class:`~torch_gpmpc.report.tensorboard.TBLogger` (or ``None``).

    Returns:
        The :class:`Rollout` (S steps, K agents, horizon T).
    """
    from torch_gpmpc.gp.fit import fit_agent_gps

    cfg = cfg.replace(method=method or cfg.method)
    scenario = scenario or make_scenario(cfg)
    cfg = with_scenario_world(cfg, scenario)
    num_agents = scenario.num_agents
    system = team_system_from_config(cfg)
    if needs_gp(cfg.method):
        gps = check_gps(gps, num_agents, agent_specs(cfg, num_agents)) if gps is not None \
            else fit_agent_gps(cfg, system, num_agents)
    learning = None
    if gps is not None:
        gps = run_models(gps, cfg)
        learning = OnlineLearning(gps, system.nominal, cfg.gp_online, cfg.gp_online_max_input_change)
    planner = ADMMPlanner(Controller.for_run(cfg, system, gps))
    return run_closed_loop(cfg, scenario, system, planner, on_step, tb, learning)


def reference_window(cfg: Config, scenario: Scenario, t: int, follower: PathFollower | None = None) -> Tensor:
    """The position references of step ``t`` (K, T+1, P): routed agents' along their routes from
    where they are (``follower``), then bent round the run's discs and cylinders
    (:mod:`~torch_gpmpc.sim.detours`; clearance :func:`reference_clearance` beyond each obstacle's
    radius)."""
    window = scenario.reference_window(t, cfg.horizon)
    if follower is not None:
        window = follower.shape(window)
    if cfg.obstacles is None or not len(cfg.obstacles):
        return window
    return detour_reference(cfg.obstacles, window, scenario.starts, scenario.targets,
                            reference_clearance(cfg, scenario.num_agents))


def reference_clearance(cfg: Config, num_agents: int) -> Tensor:
    """(K,) how far beyond an obstacle's radius the references bend: each agent's body radius
    plus one obstacle row's chance margin at the model plant's noise, ``Phi^{-1}(1 - obstacle_eps)
    noise_std`` (chance methods; 0 for other plants, whose disturbance is not a noise level), and
    at least ``r_safe`` (:func:`~torch_gpmpc.sim.detours.detour_clearance`)."""
    noisy = Method.parse(cfg.method).chance and cfg.plant == "model"
    margin = float(chance_quantile(cfg.obstacle_eps)) * cfg.noise_std if noisy else 0.0
    radii = torch.tensor(agent_radii(cfg.radii, cfg.r_safe, num_agents), dtype=torch.float64)
    return detour_clearance(cfg.r_safe, radii, margin)


def deadlock_breaker(cfg: Config, scenario: Scenario) -> DeadlockBreaker | None:
    """The run's :class:`~torch_gpmpc.sim.detours.DeadlockBreaker` (``None`` with
    ``deadlock_detour = false``); its detours advance at the scenario line's speed."""
    if not cfg.deadlock_detour:
        return None
    speed = float(torch.linalg.vector_norm(scenario.targets - scenario.starts, dim=-1).max()) / (scenario.ref_points - 1)
    return DeadlockBreaker(scenario.starts, scenario.targets, cfg.r_safe, cfg.goal_tol, speed)


def path_follower(cfg: Config, scenario: Scenario) -> PathFollower | None:
    """The run's :class:`~torch_gpmpc.sim.path_following.PathFollower`: routes round the boxes
    (``None`` without boxes, with ``reference = target``, or when no route bends or narrows)."""
    if scenario.reference_kind != "line":
        return None
    return PathFollower.plan(cfg.obstacles, cfg.workspace, scenario.starts, scenario.targets, cfg.r_safe,
                             scenario.ref_points - 1, cfg.radii)


def run_closed_loop(cfg: Config, scenario: Scenario, system: TrueSystem | Plant, planner: Planner,
                    on_step: StepCallback | None = None, tb=None, learning: OnlineLearning | None = None) -> Rollout:
    """The closed loop of ``scenario`` with any :class:`Planner` on a
    :class:`~torch_gpmpc.dynamics.plants.Plant` (a :class:`TrueSystem` is stepped as
    ``plant_from_config(cfg, system)``).

    The planner sees the plant's measured states; the rollout records its true states (what
    arrival, collisions and metrics are judged on). With ``learning``, every agent's GP predicts
    each transition it makes (and with ``gp_online`` learns from it) before the next step's plan.
    The loop runs under :func:`~torch_gpmpc.control.solvers.ipm_threads.planning_threads`: the
    compiled solver splits its batches over the caller's thread count (``gpmpc --threads``) while
    torch's own operations run on one thread (the same states; faster, see that module).

    Returns:
        The :class:`Rollout`.
    """
    plant = plant_from_config(cfg, system) if isinstance(system, (TrueSystem, TeamSystem)) else system
    num_agents = scenario.num_agents
    noise = noise_sequence(cfg, num_agents)
    recorder = StepRecorder(cfg, num_agents)
    breaker = deadlock_breaker(cfg, scenario)
    follower = path_follower(cfg, scenario)
    start_time = time.perf_counter()
    nominal = plant.nominal
    x = plant.reset(scenario.starts)
    states = [plant.true_states]
    with torch.no_grad(), planning_threads():
        for t in range(cfg.max_steps):
            if bool(((nominal.positions(states[-1]) - scenario.targets).norm(dim=1) < cfg.goal_tol).all()):
                break
            step_start = time.perf_counter()
            positions = nominal.positions(x)
            graph = communication_graph(positions, cfg.comm_radius)
            if follower is not None:
                follower.update(positions, graph.adjacency())
            window = reference_window(cfg, scenario, t, follower)
            if breaker is not None:
                waiting = None if follower is None else torch.as_tensor(follower.queued)
                rejoin = None if follower is None else follower.rejoin_points(positions)
                breaker.update(t, positions, waiting)
                window = breaker.shape(t, window, positions, rejoin)
            xref = nominal.reference_states(window)
            res = planner.plan(t, x, xref, graph)
            if res is None:
                break
            step_s = time.perf_counter() - step_start
            u = nominal.project(res.inputs[:, 0])
            x_prev, x = x, plant.step(t, x, u, noise=noise[t])
            states.append(plant.true_states)
            if learning is not None:
                error, var = learning.observe(x_prev, u, x)
                recorder.record_prediction(t, error, var, learning.update_seconds[-1], tb, learning.frozen_error)
                if tb is not None and learning.adopted_share:
                    tb.scalar("gp/online_adopted", learning.adopted_share[-1], t)
            info = recorder.record(t, res, graph.adjacency(), u, states[-1], step_s)
            if tb is not None:
                log_step(tb, t, info, res)
            if on_step is not None:
                on_step(t, info)
    wall = time.perf_counter() - start_time
    return recorder.rollout(torch.stack(states), scenario.targets, wall, cfg.method, nominal.position,
                            nominal.input_memory_rows)
