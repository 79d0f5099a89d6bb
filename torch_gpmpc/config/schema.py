"""Run configuration: one frozen dataclass with flat keys, strict loading.

Keys work the same in a TOML/YAML/JSON file and as ``--set NAME=VALUE``. Unknown
keys and wrong types raise :class:`~torch_gpmpc.errors.GpmpcError` naming the
nearest valid key; out-of-range values raise naming the allowed range
(:mod:`~torch_gpmpc.config.fields` checks every settings class the same way).
"""

from __future__ import annotations

import dataclasses
import warnings
import typing
from dataclasses import dataclass
from typing import Any, Mapping

from torch_gpmpc.config.fields import Rules, build, check_keys, coerce_lists, validate
from torch_gpmpc.config.model_spec import ModelSpec, check_model_name, parse_model, resolve_model
from torch_gpmpc.config.obstacles import FOREST_GAP_EXTRA, ObstacleField, doorway_extent, forest_extent
from torch_gpmpc.config.cost_table import CostTable
from torch_gpmpc.config.workspace import Workspace
from torch_gpmpc.config.plant import PLANTS, VEHICLES, WINDS
from torch_gpmpc.config.team import TeamSpec, team_spec
from torch_gpmpc.config.settings import (
    CONTROLLER_CHOICES, CONTROLLER_RANGES, METHOD_NAMES, ControllerSettings, GPFitSettings, check_coupling,
    check_risk_mode, controller_keys, parse_world, resolve_uncertainty,
)
from torch_gpmpc.errors import GpmpcError

METHODS = METHOD_NAMES
REFERENCES = ("line", "target")
SCENARIOS = ("paper", "circle", "random", "forest", "doorway")


@dataclass(frozen=True)
class Config:
    """All tunable settings of a run. Defaults are the paper scenario.

    Attributes:
        horizon: MPC horizon T (plans have T+1 states, T inputs).
        rho: ADMM penalty rho > 0.
        r_safe: minimum allowed distance between two agents.
        eps: total collision risk per pair, in (0, 1); split between the two agents.
        risk_split: share of ``eps`` taken by the lower-indexed agent of each pair, in (0, 1).
        u_max: bound on the Euclidean norm of each input.
        alpha: control-effort weight in the cost (R = alpha I when no ``cost`` is given).
        cost: a stated tracking cost, a ``[cost]`` table ``{Q, R, P, u_ref}`` (each weight a number times
            I, a diagonal list or a list of rows; :class:`~torch_gpmpc.control.cost.QuadraticCost`):
            stage cost ``(x - r)^T Q (x - r) + (u - u_ref)^T R (u - u_ref)``, terminal ``(x_T - r_T)^T P
            (x_T - r_T)``; null: Q = I, R = alpha I.
        terminal_cost: the terminal weight P when the cost gives none: ``lqr`` (the model's LQR
            cost-to-go, the default) or ``stage`` (P = Q, the paper's cost; ``gpmpc reproduce`` uses it).
        input_rate_weight: weight beta of the input changes ``beta sum_t ||U_t - U_{t-1}||^2`` in
            the cost (``U_{-1}``: the input applied at the previous step); smooth plans for
            vehicles whose acceleration cannot jump (quadrotors: tilt and motor lag). 0: off.
        noise_std: standard deviation s of the process noise w ~ N(0, s^2 I).
        admm_tol: absolute tolerance of the per-edge primal residual ||y - z||.
        admm_dual_tol: absolute tolerance of the per-edge dual residual rho ||z - z_prev||
            (``null``: 10 ``admm_tol``; the paper's ``primal`` rule tests it only when set).
        admm_rel_tol: relative tolerance (Boyd et al. 2011 §3.3.1) of the ``primal-dual`` rule:
            adds ``admm_rel_tol * max(||y||, ||z||)`` to the primal and ``admm_rel_tol * ||lam||``
            to the dual tolerance of each edge (:mod:`torch_gpmpc.coordination.penalty`).
        admm_stop: ``primal-dual`` (both residuals, Boyd et al. 2011 §3.3.1) or ``primal`` (the
            paper's rule: a consensus that is feasible, not necessarily optimal).
        rho_update: ``adaptive`` (residual balancing per edge, Boyd et al. 2011 §3.4.1: rho_e
            doubles when its primal residual ratio (residual over tolerance) exceeds 10x its
            dual one, halves in the opposite case; ``rho`` is the start, carried over by warm
            starts) or ``fixed``.
        admm_max_iter: ADMM iteration cap per time step.
        admm_acceleration: ``off`` or ``anderson`` (type-II Anderson acceleration of each step's
            consensus and duals, :mod:`torch_gpmpc.coordination.acceleration`).
        admm_anderson_memory: how many past iterates the Anderson mix uses.
        admm_coupling: what neighbours agree on: ``copies`` (the paper's copies of the pair's
            trajectories) or ``planes`` (a separating-plane offset per edge and horizon step;
            :mod:`torch_gpmpc.coordination.planes`).
        comm_radius: agents closer than this communicate; ``None`` = all pairs.
        goal_tol: an agent has arrived when within this distance of its target.
        max_steps: closed-loop step cap.
        uncertainty: ``auto`` (default: ``pointwise`` for models whose residual rows are their
            positions, as the paper's; ``propagated`` otherwise, e.g. the double integrator, whose
            velocity residual reaches the position only through the dynamics),
            ``pointwise`` (paper: GP variance at the linearization point),
            ``propagated`` (covariance pushed open loop through the linearized dynamics) or
            ``feedback`` (pushed through them under the LQR feedback of the nominal model, as
            tube MPC does: bounded instead of growing like sqrt(tau)).
        margin_variance: ``predictive`` (latent GP variance plus the learned noise variance: what
            moves an agent off its plan) or ``latent`` (the paper's GP variance alone).
        pair_margin: how a pair's chance margin is built: ``sum`` (both agents' margins
            ``m_k + m_j``, sound by the union bound), ``joint`` (``Phi^-1(1 - eps) sqrt(s_k + s_j)``,
            the tightest sound choice for independent Gaussian agents, no risk split) or
            ``own`` (the paper's eq. 24: each agent only its own margin; not sound).
        scenario: ``paper``, ``circle``, ``random``, ``forest`` or ``doorway`` (obstacles and
            walls: :mod:`~torch_gpmpc.sim.scenarios`).
        num_agents: K (the paper scenario has 3).
        seed: seed for data, noise and scenario generation.
        solver: ``fast`` (structure-exploiting interior point compiled with numba, :mod:`~torch_gpmpc.control.solvers.interior_point`),
            ``clarabel`` (cvxpylayers + diffcp with Clarabel) or ``reference`` (cvxpylayers' default).
        solver_warm: with ``fast``, solve each ADMM iteration's problems first by the exact
            active-set method from the previous iteration's solutions (falling back to the cold
            interior point per problem); ``false``: every solve cold. Gradient tuning always solves cold.
        admm_compiled: with ``fast`` and a frozen linearization (``relinearize = false``), a control
            step's ADMM iterations after its second run as compiled calls (the same plans, a third of
            the time per iteration); ``false``: every iteration through the torch path (the reference).
        method: one of :data:`METHODS`.
        dim: position dimension (2 or 3) of the built-in models; the single integrator's state
            and input have this dimension, the double integrator's state has twice it.
        model: the agent model: ``single-integrator`` (the paper), ``double-integrator`` (state
            ``[p, v]``, input acceleration), a model file path (TOML/JSON, see
            :mod:`~torch_gpmpc.config.model_spec`), a :class:`ModelSpec`, or a model table
            (a mapping with the model file's keys). ``dim``, ``dt`` and ``u_max`` shape the
            built-in models only: with a model file, table or ModelSpec they are ignored, and
            setting them warns.
        dt: sampling time of the double integrator (s).
        reference: ``line`` (straight line over ``ref_points`` steps, then hold) or ``target``.
        ref_points: number of points of the straight-line reference.
        circle_radius: radius of the start circle of ``paper``/``circle`` scenarios (and the
            half-width of ``random`` ones).
        gp_box: half-width of the box the GP training states are drawn from (the paper's data
            recipe); ``null``: :attr:`scenario_extent` (``circle_radius``, or the forest's
            half-length), so the data cover the scenario.
        min_separation: minimum start (and target) separation of ``random`` scenarios.
        gp_samples: training transitions per agent (paper: 100).
        gp_inputs: ``state`` (paper) or ``state_input``.
        gp_optimizer: ``lbfgs`` (paper) or ``adam``.
        gp_iters: optimizer iterations for GP fitting.
        slack_penalty: exact-penalty weight on collision slacks.
        relinearize: re-set linearization points from each ADMM iterate (Algorithm 1, step 9);
            false (default): linearize once per control step around the warm start, so ADMM
            converges on one convex problem (the paper's per-iterate rule keeps it moving).
        wind_scale: amplitude of the vortex wind g (paper: 0.1).
        workspace: a soft box on the positions, ``{"min": [...], "max": [...]}`` (P numbers each),
            or null (none); a scenario file's ``workspace`` sets it for its run.
        risk_mode: ``pair_step`` (default: every pair's collision rows hold with probability
            ``1 - eps`` at every step) or ``mission`` (the probability of any collision over the
            whole run is at most ``risk_budget``: each agent starts with ``risk_budget / K`` and
            spends it on its pairs' steps; :mod:`~torch_gpmpc.coordination.mission_risk`).
        risk_budget: the mission's collision probability delta (``risk_mode = mission``).
        risk_pacing: under ``mission``, a control step spends at most ``1 / risk_pacing`` of an
            agent's remaining budget (so it never runs out, however long the run).
        obstacles: static obstacles, a list of ``{"center": [...], "radius": r}`` (disc/sphere),
            ``{"center": [x, y], "radius": r, "z": [zmin, zmax]}`` (vertical cylinder, 3D) and
            ``{"min": [...], "max": [...]}`` (box) tables, or null; a scenario's obstacles set it.
            An agent's centre keeps ``r_safe / 2`` from every obstacle.
        obstacle_eps: the risk of one obstacle row per step (chance methods: the row's margin is
            ``Phi^{-1}(1 - obstacle_eps)`` times the agent's own standard deviation along it;
            default 1e-6, as an agent rides a row for many steps of a run).
        obstacle_rows: obstacle rows per agent and horizon step (its nearest obstacles).
        radii: each agent's body radius, a list of K numbers (a pair keeps ``r_k + r_j`` between
            centres, an agent ``r_k`` from every obstacle), or null: ``r_safe / 2`` each; a
            scenario file's ``radii`` set it for its run.
        models: a mixed team: one model per agent (built-in names or model files, K of them), or
            null (every agent has ``model``); overrides ``model``. Models of different sizes are
            lifted to the largest (:mod:`~torch_gpmpc.config.team`); they must share ``dt``, the
            position indices and the number of residual rows. A scenario file's ``models`` set it.
        pair_buffer: extra distance the collision rows ask beyond ``r_safe`` (or ``r_k + r_j``),
            for example ``admm_tol``, so that plans whose copies agree only to the consensus
            tolerance still keep ``r_safe``; metrics and risk bounds judge ``r_safe`` itself.
        safety_fallback: the re-plan after an unconverged ADMM stop: ``cells`` (agents that can
            stop at once, among neighbours that can too, re-plan inside buffered Voronoi cells;
            agents with momentum against their neighbours' plans as fixed obstacles) or
            ``obstacles`` (every agent of a pair unsafe at tau = 1 against its neighbours' plans).
        num_obstacles: the cylinders (discs in 2D) of ``scenario = forest``.
        forest_gap: the free gap ``scenario = forest`` keeps between two trees beyond ``r_safe``
            (room for an agent's chance margins on both sides; a wider gap also lengthens the band,
            whose trees keep the same share of it, and widens the lanes by half of it).
        deadlock_detour: an agent stuck behind a neighbour (no progress for 10 steps) detours
            round it on a fixed side (:class:`~torch_gpmpc.sim.detours.DeadlockBreaker`).
        plant: what the closed loop steps: ``model`` (the model's true system, the paper's world)
            or ``rotorpy`` (simulated multirotors tracking the plans,
            :mod:`~torch_gpmpc.dynamics.rotorpy_plant`; needs a 3D double-integrator model).
        plant_vehicle: RotorPy's ``crazyflie`` or ``hummingbird`` parameters.
        plant_wind: ``none``, ``constant``, ``sine`` or ``dryden``; ``plant_wind_speed`` is its
            velocity [wx, wy, wz] in m/s (the amplitude of ``sine``, the mean of ``dryden``).
        plant_rate_hz: the rate of RotorPy's tracking controller and simulator.
        plant_sensor_noise: standard deviation of the measured position (m) and velocity (m/s).
        wind_change_step: the control step from which the plant's wind (RotorPy's, or the model
            plant's vortex) is turned 90 degrees about the vertical axis (null: never).
        gp_online: each agent adds its own observed transitions to its GP during the run
            (:mod:`~torch_gpmpc.gp.online`); ``gp_online_budget`` points per agent (the oldest
            leave first), hyperparameters re-fitted every ``gp_online_refit_every`` steps (0: never);
            with ``gp_online_max_input_change`` only transitions whose input changed by at most that
            (norm, input units) since the agent's previous step are added (null: all).

    Example:
        >>> from torch_gpmpc import Config
        >>> cfg = Config(model="double-integrator", dim=3, scenario="circle", num_agents=6)
        >>> cfg.state_dim, cfg.input_dim, cfg.uncertainty_mode
        (6, 3, 'propagated')
        >>> cfg.controller_settings().horizon
        13
    """

    horizon: int = 13
    rho: float = 20.0
    r_safe: float = 0.5
    eps: float = 0.1
    risk_split: float = 0.5
    u_max: float = 2.0
    alpha: float = 1e-3
    cost: CostTable | None = None
    terminal_cost: str = "lqr"
    input_rate_weight: float = 0.0
    noise_std: float = 0.1
    admm_tol: float = 1e-3
    admm_dual_tol: float | None = None
    admm_rel_tol: float = 1e-4
    admm_max_iter: int = 100
    admm_acceleration: str = "off"
    admm_anderson_memory: int = 5
    admm_coupling: str = "copies"
    admm_stop: str = "primal-dual"
    rho_update: str = "adaptive"
    comm_radius: float | None = None
    goal_tol: float = 0.1
    max_steps: int = 150
    uncertainty: str = "auto"
    margin_variance: str = "predictive"
    pair_margin: str = "sum"
    scenario: str = "paper"
    num_agents: int = 3
    seed: int = 0
    solver: str = "fast"
    solver_warm: bool = True
    admm_compiled: bool = True
    method: str = "gp-chance"
    dim: int = 2
    model: str | ModelSpec = "single-integrator"
    dt: float = 0.1
    reference: str = "line"
    ref_points: int = 50
    circle_radius: float = 4.0
    gp_box: float | None = None
    min_separation: float = 1.0
    gp_samples: int = 100
    gp_inputs: str = "state"
    gp_optimizer: str = "lbfgs"
    gp_iters: int = 50
    slack_penalty: float = 1e4
    relinearize: bool = False
    wind_scale: float = 0.1
    workspace: Workspace | None = None
    risk_mode: str = "pair_step"
    risk_budget: float = 0.05
    risk_pacing: int = 10
    obstacles: ObstacleField | None = None
    obstacle_eps: float = 1e-6
    obstacle_rows: int = 4
    radii: tuple[float, ...] | None = None
    models: tuple[str, ...] | None = None
    pair_buffer: float = 0.0
    safety_fallback: str = "cells"
    num_obstacles: int = 20
    forest_gap: float = FOREST_GAP_EXTRA
    deadlock_detour: bool = True
    plant: str = "model"
    plant_vehicle: str = "crazyflie"
    plant_wind: str = "none"
    plant_wind_speed: tuple[float, ...] = (0.0, 0.0, 0.0)
    plant_rate_hz: float = 100.0
    plant_sensor_noise: float = 0.0
    wind_change_step: int | None = None
    gp_online: bool = False
    gp_online_budget: int = 200
    gp_online_refit_every: int = 0
    gp_online_max_input_change: float | None = None

    def __new__(cls, *args: Any, **kwargs: Any) -> "Config":
        """Refuse a misspelt keyword with the nearest valid key, as config files and ``--set`` do (the
        dataclass's ``__init__`` would raise a bare ``TypeError``)."""
        check_keys(kwargs, [f.name for f in dataclasses.fields(cls)], "config key")
        return super().__new__(cls)

    def __post_init__(self) -> None:
        if isinstance(self.model, dict):  # an inline model table (a config file's [model])
            object.__setattr__(self, "model", parse_model(self.model, "config key 'model'"))
        parse_world(self, "config key")
        coerce_lists(self)  # plant_wind_speed = [1, 0, 0], radii = [0.2, 0.3] from Python, TOML or --set
        validate(self, RULES)
        check_risk_mode(self.risk_mode, self.method, self.pair_margin, "config key")
        check_coupling(self.admm_coupling, self.admm_acceleration, self.relinearize, "config key")
        if isinstance(self.model, str):
            check_model_name(self.model)
        if self.models is not None:
            for name in self.models:
                check_model_name(name, "models")
            self.team()  # refuses models that cannot plan together
        if self.workspace is not None:
            self.workspace.check_dim(self.position_dim, "config key 'workspace'")
        if self.obstacles is not None:
            self.obstacles.check_dim(self.position_dim, "config key 'obstacles'")
        if self.scenario == "paper" and self.num_agents != 3:
            raise GpmpcError(
                f"config key 'num_agents': the paper scenario has 3 agents, got {self.num_agents}; "
                "use scenario=circle or scenario=random for other team sizes"
            )
        warn_ignored_keys(self)

    def model_spec(self) -> ModelSpec:
        """The agent model of this run (built-in, read from the model file, or given); with
        ``models``, agent 0's model lifted to the team's sizes (every agent's state and input
        then have its sizes, position and number of residual rows)."""
        if self.models is not None:
            return self.team().agent_spec(0)
        if isinstance(self.model, ModelSpec):
            return self.model
        return resolve_model(self.model, self.dim, self.dt, self.u_max)

    def team(self) -> TeamSpec | None:
        """The team's models lifted to common sizes (:func:`~torch_gpmpc.config.team.team_spec`), or
        ``None`` without ``models``."""
        if self.models is None:
            return None
        return team_spec([resolve_model(name, self.dim, self.dt, self.u_max) for name in self.models])

    def controller_settings(self) -> ControllerSettings:
        """The controller's settings (the keys of :class:`ControllerSettings`)."""
        return ControllerSettings(**{key: getattr(self, key) for key in controller_keys()})

    def gp_fit_settings(self) -> GPFitSettings:
        """How the agents' GPs are fitted (``gp_samples``, ``gp_iters``, ``gp_optimizer``, the
        data box ``gp_box`` (default :attr:`scenario_extent`), ``seed``)."""
        box = self.scenario_extent if self.gp_box is None else self.gp_box
        return GPFitSettings(self.gp_samples, self.gp_iters, self.gp_optimizer, box, self.seed)

    @property
    def scenario_extent(self) -> float:
        """Half-width of the region the built-in scenario spans: ``circle_radius``, the
        ``forest``'s half-length (:func:`~torch_gpmpc.config.obstacles.forest_extent`), the
        ``doorway``'s larger half-side, or for a ``random`` scenario in a workspace the largest
        coordinate of the workspace."""
        if self.scenario == "random" and self.workspace is not None:
            return max(abs(v) for v in self.workspace.lower + self.workspace.upper)
        if self.scenario == "doorway":
            return max(doorway_extent(self.num_agents, self.circle_radius, self.min_separation, self.r_safe))
        if self.scenario != "forest":
            return self.circle_radius
        return forest_extent(self.num_agents, self.num_obstacles, self.circle_radius, self.min_separation,
                             self.r_safe, self.forest_gap)[0]

    @property
    def uncertainty_mode(self) -> str:
        """The covariance model in use: ``uncertainty`` with ``auto`` resolved (see above)."""
        return resolve_uncertainty(self.uncertainty, self.model_spec())

    @property
    def state_dim(self) -> int:
        """n, the model's state dimension (``dim`` for the single integrator)."""
        return self.model_spec().state_dim

    @property
    def input_dim(self) -> int:
        """m, the model's input dimension."""
        return self.model_spec().input_dim

    @property
    def position_dim(self) -> int:
        """P, the dimension of positions (scenarios, collision rows, arrival)."""
        return self.model_spec().position_dim

    def replace(self, **changes: Any) -> "Config":
        """Return a copy with ``changes`` applied (same checks as loading)."""
        return from_mapping({**self.to_dict(), **changes})

    def to_dict(self) -> dict[str, Any]:
        """Plain dict of all keys (JSON-serializable; a :class:`ModelSpec` becomes its model table)."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        if isinstance(self.model, ModelSpec):
            out["model"] = self.model.to_table()
        if self.workspace is not None:
            out["workspace"] = self.workspace.to_table()
        if self.obstacles is not None:
            out["obstacles"] = self.obstacles.to_table()
        if self.cost is not None:
            out["cost"] = self.cost.to_table()
        return out


#: Keys that shape only the built-in models, and their defaults.
_BUILTIN_MODEL_KEYS = ("dim", "dt", "u_max")


def warn_ignored_keys(cfg: Config) -> None:
    """Warn, naming the key that overrides it, about every key set to a non-default value that
    the current choices ignore."""
    defaults = {f.name: f.default for f in dataclasses.fields(Config)}
    ignored = []
    if cfg.models is not None:  # dim, dt and u_max shape the built-ins it names
        if cfg.model != defaults["model"]:
            ignored.append(("model", "models", "every agent has its own model"))
    elif not (isinstance(cfg.model, str) and cfg.model in ("single-integrator", "double-integrator")):
        ignored += [(key, "model", "the model defines its own state, sampling time and input bound")
                    for key in _BUILTIN_MODEL_KEYS if getattr(cfg, key) != defaults[key]]
    elif cfg.model == "single-integrator" and cfg.dt != defaults["dt"]:
        ignored.append(("dt", "model", "the single integrator has the paper's B = 0.1 I"))
    if cfg.plant == "model":
        ignored += [(key, "plant", "it configures the RotorPy plant") for key in
                    ("plant_vehicle", "plant_wind", "plant_wind_speed", "plant_rate_hz", "plant_sensor_noise")
                    if getattr(cfg, key) != defaults[key]]
    if cfg.admm_stop == "primal" and cfg.admm_rel_tol != defaults["admm_rel_tol"]:
        ignored.append(("admm_rel_tol", "admm_stop", "the paper's primal rule has absolute tolerances only"))
    for key, by, why in ignored:
        warnings.warn(f"config key '{key}' is ignored under {by}={_show(getattr(cfg, by))}: {why}",
                      UserWarning, stacklevel=4)


def _show(value: Any) -> str:
    return value.name if isinstance(value, ModelSpec) else str(value)


_CHOICES = {
    **CONTROLLER_CHOICES,
    "scenario": SCENARIOS,
    "reference": REFERENCES,
    "gp_inputs": ("state", "state_input"),
    "gp_optimizer": ("lbfgs", "adam"),
    "plant": PLANTS,
    "plant_vehicle": VEHICLES,
    "plant_wind": WINDS,
}

# (predicate, description of the allowed range); checked in __post_init__.
_RANGES: dict[str, tuple[typing.Callable[[Any], bool], str]] = {
    **CONTROLLER_RANGES,
    "u_max": (lambda v: v > 0, "a number > 0"),
    "noise_std": (lambda v: v >= 0, "a number >= 0"),
    "goal_tol": (lambda v: v > 0, "a number > 0"),
    "max_steps": (lambda v: 1 <= v <= 1_000_000, "an integer in [1, 1000000]"),
    "num_agents": (lambda v: 1 <= v <= 1000, "an integer in [1, 1000]"),
    "num_obstacles": (lambda v: 0 <= v <= 10_000, "an integer in [0, 10000]"),
    "forest_gap": (lambda v: 0 <= v <= 100, "a number in [0, 100] (metres)"),
    "seed": (lambda v: v >= 0, "an integer >= 0"),
    "dim": (lambda v: v in (2, 3), "2 or 3"),
    "ref_points": (lambda v: v >= 2, "an integer >= 2"),
    # the same bound as scenario-file coordinates (scenarios.MAX_COORDINATE)
    "circle_radius": (lambda v: 0 < v <= 1e4, "a number in (0, 10000]"),
    "gp_box": (lambda v: v is None or 0 < v <= 1e4, "a number in (0, 10000] or null (circle_radius)"),
    "min_separation": (lambda v: v >= 0, "a number >= 0"),
    # an exact GP costs O(N^3) time and O(N^2) memory per agent
    "gp_samples": (lambda v: 2 <= v <= 5000, "an integer in [2, 5000]"),
    "gp_iters": (lambda v: v >= 1, "an integer >= 1"),
    "wind_scale": (lambda v: v >= 0, "a number >= 0"),
    "dt": (lambda v: 0 < v <= 10, "a number in (0, 10]"),
    "plant_wind_speed": (lambda v: len(v) == 3 and all(abs(w) <= 50 for w in v), "3 numbers [wx, wy, wz] in m/s, each within 50"),
    "plant_rate_hz": (lambda v: 1 <= v <= 10_000, "a number in [1, 10000]"),
    "plant_sensor_noise": (lambda v: v >= 0, "a number >= 0"),
    "models": (lambda v: v is None or len(v) >= 1, "a list of model names or files, one per agent, or null"),
    "wind_change_step": (lambda v: v is None or v >= 0, "an integer >= 0 or null (never)"),
    "gp_online_budget": (lambda v: 2 <= v <= 5000, "an integer in [2, 5000]"),
    "gp_online_refit_every": (lambda v: v >= 0, "an integer >= 0 (0: never re-fit)"),
    "gp_online_max_input_change": (lambda v: v is None or v > 0, "a number > 0 or null (add every transition)"),
}


RULES = Rules("config key", "", _CHOICES, _RANGES)


def from_mapping(data: Mapping[str, Any]) -> Config:
    """Build a :class:`Config` from a flat mapping; unknown keys raise.

    Raises:
        GpmpcError: unknown key (with the nearest valid key), wrong type or range.
    """
    return build(Config, _retire_deprecated(data), RULES)


def _retire_deprecated(data: Mapping[str, Any]) -> dict[str, Any]:
    """Map retired keys onto their replacements (with a warning naming the new key)."""
    data = dict(data)
    if "gp_noise_in_margin" in data:
        old = data.pop("gp_noise_in_margin")
        if not isinstance(old, bool):
            raise GpmpcError(f"config key 'gp_noise_in_margin': expected bool, got {old!r}; "
                             "better, use margin_variance=predictive|latent")
        new = "predictive" if old else "latent"
        # FutureWarning, not DeprecationWarning: Python shows it by default, and the reader is the user
        warnings.warn(f"config key 'gp_noise_in_margin' is deprecated; it means margin_variance={new}",
                      FutureWarning, stacklevel=3)
        data.setdefault("margin_variance", new)
    return data
