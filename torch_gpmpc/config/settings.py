"""The controller's settings: what a consensus-ADMM GP-MPC controller reads, and nothing else.

:class:`ControllerSettings` is the small frozen object the controller layers take
(:class:`~torch_gpmpc.coordination.controller.Controller`, the ADMM, the per-agent step, the
distributed agent, tuning); :meth:`~torch_gpmpc.config.schema.Config.controller_settings`
builds it from the flat run configuration, whose keys have the same names. Anything that
depends on the agent model (state size, input bound, the ``auto`` uncertainty mode) comes
from the model, never from here: see :func:`resolve_uncertainty`.

The choice lists of the settings (methods, uncertainty modes, ...) live here too, so the
configuration layer never imports a later layer.
"""

from __future__ import annotations

import typing
import warnings
from dataclasses import dataclass

from torch_gpmpc.config.cost_table import TERMINAL_COSTS, CostTable
from torch_gpmpc.config.fields import Applies, Rules, build, check_keys, coerce_lists, validate, warn_ignored
from torch_gpmpc.config.model_spec import ModelSpec
from torch_gpmpc.config.obstacles import ObstacleField
from torch_gpmpc.config.workspace import Workspace
from torch_gpmpc.errors import GpmpcError

#: The controller methods of the paper's Table 1 (``--method``), in its order;
#: :class:`~torch_gpmpc.dynamics.methods.Method` is the typed form.
METHOD_NAMES: tuple[str, ...] = ("nominal", "nominal-chance", "nonlinear", "nonlinear-chance", "gp", "gp-chance")
UNCERTAINTY_MODES = ("pointwise", "propagated", "feedback")
MARGIN_VARIANCES = ("latent", "predictive")
PAIR_MARGINS = ("own", "sum", "joint")
RHO_UPDATES = ("fixed", "adaptive")
ADMM_STOPS = ("primal", "primal-dual")
RISK_MODES = ("pair_step", "mission")
SOLVERS = ("fast", "clarabel", "reference")
SAFETY_FALLBACKS = ("cells", "obstacles")
ADMM_COUPLINGS = ("copies", "planes")
#: Each coupling's iteration budget per control step where ``admm_max_iter`` is null: the planes'
#: iterates are safe, so a step warm-started from the last one needs few (5 meets the small teams'
#: arrivals and the crowd's safety; the docs' Coordination page); the copies are safe only once they
#: agree, so they run towards convergence.
DEFAULT_ITERATIONS = {"planes": 5, "copies": 100}

CONTROLLER_CHOICES: dict[str, tuple] = {
    "uncertainty": ("auto", *UNCERTAINTY_MODES),
    "margin_variance": MARGIN_VARIANCES,
    "pair_margin": PAIR_MARGINS,
    "rho_update": RHO_UPDATES,
    "admm_stop": ADMM_STOPS,
    "solver": SOLVERS,
    "method": METHOD_NAMES,
    "risk_mode": RISK_MODES,
    "safety_fallback": SAFETY_FALLBACKS,
    "admm_coupling": ADMM_COUPLINGS,
    "terminal_cost": TERMINAL_COSTS,
}

CONTROLLER_RANGES: dict[str, tuple[typing.Callable[[typing.Any], bool], str]] = {
    "horizon": (lambda v: 1 <= v <= 1000, "an integer in [1, 1000]"),
    "rho": (lambda v: v > 0, "a number > 0"),
    "r_safe": (lambda v: v >= 0, "a number >= 0"),
    "eps": (lambda v: 0 < v < 1, "a number in (0, 1)"),
    "risk_split": (lambda v: 0 < v < 1, "a number in (0, 1)"),
    "alpha": (lambda v: v >= 0, "a number >= 0"),
    "input_rate_weight": (lambda v: v >= 0, "a number >= 0 (0: no input-rate term)"),
    "admm_tol": (lambda v: v > 0, "a number > 0"),
    "admm_dual_tol": (lambda v: v is None or v > 0, "a number > 0 or null"),
    "admm_rel_tol": (lambda v: 0 <= v < 1, "a number in [0, 1)"),
    "admm_max_iter": (lambda v: v is None or 1 <= v <= 100_000,
                      "an integer in [1, 100000], or null (the coupling's default budget)"),
    "admm_time_budget_ms": (lambda v: v is None or v > 0, "a number of milliseconds > 0, or null"),
    "comm_radius": (lambda v: v is None or v > 0, "a number > 0 or null (all pairs)"),
    "slack_penalty": (lambda v: v > 0, "a number > 0"),
    "risk_budget": (lambda v: 0 < v < 1, "a number in (0, 1)"),
    "risk_pacing": (lambda v: 1 <= v <= 1_000_000, "an integer in [1, 1000000]"),
    "obstacle_eps": (lambda v: 0 < v < 1, "a number in (0, 1)"),
    "obstacle_rows": (lambda v: 1 <= v <= 256, "an integer in [1, 256]"),
    "pair_buffer": (lambda v: 0 <= v <= 1e3, "a number in [0, 1000] (0: none)"),
    "radii": (lambda v: v is None or (len(v) >= 1 and all(0 < r <= 1e3 for r in v)),
              "a list of body radii in (0, 1000], one per agent, or null (r_safe / 2 each)"),
}


@dataclass(frozen=True)
class ControllerSettings:
    """Settings of the cooperative controller (defaults: the paper scenario, sound margins).

    The run configuration (:class:`~torch_gpmpc.config.schema.Config`) extends these keys with
    the run's (scenario, model, noise, GP data, plant), under the same flat names; each key is
    documented once, here or there. The model-dependent parts (input bound, state size,
    ``uncertainty = auto``, the LQR terminal weight) are resolved from the agent model.

    Attributes:
        method: one of :data:`METHODS`.
        horizon: MPC horizon T (plans have T+1 states, T inputs).
        alpha: control-effort weight in the cost (R = alpha I when no ``cost`` is given).
        cost: a stated tracking cost, a ``[cost]`` table ``{Q, R, P, u_ref}`` (each weight a number times
            I, a diagonal list or a list of rows; :class:`~torch_gpmpc.control.cost.QuadraticCost`):
            stage cost ``(x - r)^T Q (x - r) + (u - u_ref)^T R (u - u_ref)``, terminal ``(x_T - r_T)^T P
            (x_T - r_T)``; null: Q = I (0 on the rows that hold the last input,
            :attr:`~torch_gpmpc.config.model_spec.ModelSpec.input_memory`), R = alpha I.
        terminal_cost: the terminal weight P when the cost gives none: ``lqr`` (the model's LQR
            cost-to-go, the default) or ``stage`` (P = Q, the paper's cost; ``gpmpc reproduce`` uses it).
        input_rate_weight: weight beta of the input changes ``beta sum_t ||U_t - U_{t-1}||^2`` in
            the cost (``U_{-1}``: the input applied at the previous step); smooth plans for
            vehicles whose acceleration cannot jump (quadrotors: tilt and motor lag). 0: off.
        slack_penalty: exact-penalty weight on collision slacks.
        solver: ``fast`` (structure-exploiting interior point compiled with numba, :mod:`~torch_gpmpc.control.solvers.interior_point`),
            ``clarabel`` (cvxpylayers + diffcp with Clarabel) or ``reference`` (cvxpylayers' default).
        solver_warm: with ``fast``, solve each ADMM iteration's problems first by the exact
            active-set method from the previous iteration's solutions (falling back to the cold
            interior point per problem); ``false``: every solve cold. Gradient tuning always solves cold.
        admm_compiled: with ``fast`` and a frozen linearization (``relinearize = false``), a control
            step's ADMM iterations after its second run as compiled calls (the same plans, a third of
            the time per iteration); ``false``: every iteration through the torch path (the reference).
        r_safe: minimum allowed distance between two agents.
        eps: total collision risk per pair, in (0, 1); split between the two agents.
        risk_split: share of ``eps`` taken by the lower-indexed agent of each pair, in (0, 1).
        pair_margin: how a pair's chance margin is built: ``sum`` (both agents' margins
            ``m_k + m_j``, sound by the union bound), ``joint`` (``Phi^-1(1 - eps) sqrt(s_k + s_j)``,
            the tightest sound choice for independent Gaussian agents, no risk split) or
            ``own`` (the paper's eq. 24: each agent only its own margin; not sound).
        margin_variance: ``predictive`` (latent GP variance plus the learned noise variance: what
            moves an agent off its plan) or ``latent`` (the paper's GP variance alone).
        uncertainty: ``auto`` (default: ``pointwise`` for models whose residual rows are their
            positions, as the paper's; ``propagated`` otherwise, e.g. the double integrator, whose
            velocity residual reaches the position only through the dynamics),
            ``pointwise`` (paper: GP variance at the linearization point),
            ``propagated`` (covariance pushed open loop through the linearized dynamics) or
            ``feedback`` (pushed through them under the LQR feedback of the nominal model, as
            tube MPC does: bounded instead of growing like sqrt(tau)).
        rho: ADMM penalty rho > 0; with ``admm_coupling = planes`` the inverse of a plane's first
            step (``c`` moves by ``(mu_lo - mu_hi) / (2 rho)``).
        rho_update: ``adaptive`` (residual balancing per edge, Boyd et al. 2011 §3.4.1: rho_e
            doubles when its primal residual ratio (residual over tolerance) exceeds 10x its
            dual one, halves in the opposite case; ``rho`` is the start, carried over by warm
            starts) or ``fixed``.
        admm_tol: absolute tolerance of the per-edge primal residual ||y - z||.
        admm_dual_tol: absolute tolerance of the per-edge dual residual rho ||z - z_prev||
            (``null``: 10 ``admm_tol``; the paper's ``primal`` rule tests it only when set).
        admm_rel_tol: relative tolerance (Boyd et al. 2011 §3.3.1) of the ``primal-dual`` rule:
            adds ``admm_rel_tol * max(||y||, ||z||)`` to the primal and ``admm_rel_tol * ||lam||``
            to the dual tolerance of each edge (:mod:`torch_gpmpc.coordination.penalty`).
        admm_stop: ``primal-dual`` (both residuals, Boyd et al. 2011 §3.3.1) or ``primal`` (the
            paper's rule: a consensus that is feasible, not necessarily optimal).
        admm_max_iter: ADMM iteration cap per time step (``null``: 5 with planes, 100 with
            copies; :attr:`iteration_cap` resolves it).
        admm_time_budget_ms: also stop a step's iterations once they have taken this many
            milliseconds of wall time (``null``: no time limit): the iteration that starts after
            the budget is spent is the last, so a step runs at least two. Meant for
            ``admm_coupling = planes``, whose iterates are safe (with copies an early stop falls
            back); a run with a time budget depends on the machine's speed, so it is not
            reproducible.
        admm_coupling: what neighbours agree on: ``copies`` (the paper's copies of the pair's
            trajectories; a step is safe once they agree) or ``planes`` (the default: a separating
            plane per edge and horizon step, each agent keeping its own half: an iteration whose
            halves held has jointly safe plans, so a step may stop early and apply its last such
            iterate; see the docs' Plane coupling).
        relinearize: re-set linearization points from each ADMM iterate (Algorithm 1, step 9);
            false (default): linearize once per control step around the warm start, so ADMM
            converges on one convex problem (the paper's per-iterate rule keeps it moving).
        comm_radius: agents closer than this communicate; ``None`` = all pairs.
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
        pair_buffer: extra distance the collision rows ask beyond ``r_safe`` (or ``r_k + r_j``),
            for example ``admm_tol``, so that plans whose copies agree only to the consensus
            tolerance still keep ``r_safe``; metrics and risk bounds judge ``r_safe`` itself.
        safety_fallback: the re-plan after a stop on plans not known to be jointly safe:
            ``cells`` (in pairs of agents that can both stop at once, an agent with its row short
            at tau = 1 and the agents whose plans leave their buffered Voronoi cells towards it
            re-plan inside their cells, and the agents of an unsafe pair with momentum re-plan
            too; a re-plan treats neighbours with momentum as fixed obstacles) or ``obstacles``
            (every agent of a pair unsafe at tau = 1 against its neighbours' plans).
    Examples:
        >>> from torch_gpmpc import ControllerSettings
        >>> s = ControllerSettings(horizon=10, eps=0.05)
        >>> s.horizon, s.pair_margin, s.solver
        (10, 'sum', 'fast')
        >>> s.replace(rho=5.0).rho
        5.0
    """

    method: str = "gp-chance"
    horizon: int = 13
    alpha: float = 1e-3
    cost: CostTable | None = None
    terminal_cost: str = "lqr"
    input_rate_weight: float = 0.0
    slack_penalty: float = 1e4
    solver: str = "fast"
    solver_warm: bool = True
    admm_compiled: bool = True
    r_safe: float = 0.5
    eps: float = 0.1
    risk_split: float = 0.5
    pair_margin: str = "sum"
    margin_variance: str = "predictive"
    uncertainty: str = "auto"
    rho: float = 20.0
    rho_update: str = "adaptive"
    admm_tol: float = 1e-3
    admm_dual_tol: float | None = None
    admm_rel_tol: float = 1e-4
    admm_stop: str = "primal-dual"
    admm_max_iter: int | None = None
    admm_time_budget_ms: float | None = None
    admm_coupling: str = "planes"
    relinearize: bool = False
    comm_radius: float | None = None
    workspace: Workspace | None = None
    risk_mode: str = "pair_step"
    risk_budget: float = 0.05
    risk_pacing: int = 10
    obstacles: ObstacleField | None = None
    obstacle_eps: float = 1e-6
    obstacle_rows: int = 4
    radii: tuple[float, ...] | None = None
    pair_buffer: float = 0.0
    safety_fallback: str = "cells"

    def __new__(cls, *args: typing.Any, **kwargs: typing.Any) -> "ControllerSettings":
        """Refuse a misspelt keyword with the nearest valid key (the dataclass's ``__init__`` would raise a
        bare ``TypeError``)."""
        check_keys(kwargs, list(cls.__dataclass_fields__), "controller setting")
        return super().__new__(cls)

    def __post_init__(self) -> None:
        parse_world(self, "controller setting")
        coerce_lists(self)  # radii = [0.2, 0.3] from Python
        validate(self, RULES)
        check_risk_mode(self.risk_mode, self.method, self.pair_margin, "controller setting")
        check_coupling(self.admm_coupling, self.relinearize, "controller setting")
        warn_ignored(self, CONTROLLER_CONDITIONS, "controller setting")

    def replace(self, **changes: typing.Any) -> "ControllerSettings":
        """A copy with ``changes`` applied (same checks; unknown keys name the nearest one); of the keys a
        change leaves ignored, only the changed ones warn."""
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            out = build(ControllerSettings, {**self.__dict__, **changes}, RULES)
        warn_ignored(out, {k: v for k, v in CONTROLLER_CONDITIONS.items() if k in changes}, "controller setting")
        return out

    @property
    def iteration_cap(self) -> int:
        """The ADMM iteration budget per control step: ``admm_max_iter``, or the coupling's default
        (:data:`DEFAULT_ITERATIONS`) where it is null."""
        return DEFAULT_ITERATIONS[self.admm_coupling] if self.admm_max_iter is None else self.admm_max_iter

    def check_team(self, num_agents: int, where: str = "controller setting") -> None:
        """Refuse ``radii`` whose length is not the team size K."""
        if self.radii is not None and len(self.radii) != num_agents:
            raise GpmpcError(f"{where} 'radii': {len(self.radii)} radii for {num_agents} agents; "
                             f"give one body radius per agent, or null for r_safe / 2 each")

    def uncertainty_for(self, spec: ModelSpec) -> str:
        """The covariance model used for agents of model ``spec`` (``auto`` resolved)."""
        return resolve_uncertainty(self.uncertainty, spec)


RULES = Rules("controller setting", "", CONTROLLER_CHOICES, CONTROLLER_RANGES)


def _chance(s) -> bool:
    return s.method in CHANCE_METHODS


#: When each controller key applies (the rest always do); a key set while it does not warns, naming the
#: key that decides (:func:`~torch_gpmpc.config.fields.warn_ignored`).
CONTROLLER_CONDITIONS: dict[str, tuple[Applies, ...]] = {
    "eps": (Applies("method", _chance, "only the chance methods have pair margins"),
            Applies("risk_mode", lambda s: s.risk_mode == "pair_step", "the mission budget sets every risk")),
    "risk_split": (Applies("method", _chance, "only the chance methods have pair margins"),
                   Applies("risk_mode", lambda s: s.risk_mode == "pair_step", "the mission budget sets every risk"),
                   Applies("pair_margin", lambda s: s.pair_margin != "joint", "the joint margin has no split")),
    "pair_margin": (Applies("method", _chance, "only the chance methods have pair margins"),),
    "obstacle_eps": (Applies("method", _chance, "only the chance methods have obstacle margins"),
                     Applies("risk_mode", lambda s: s.risk_mode == "pair_step", "the mission budget sets every risk")),
    "risk_budget": (Applies("risk_mode", lambda s: s.risk_mode == "mission", "it is the mission's budget"),),
    "risk_pacing": (Applies("risk_mode", lambda s: s.risk_mode == "mission", "it paces the mission's budget"),),
    "admm_rel_tol": (Applies("admm_stop", lambda s: s.admm_stop == "primal-dual",
                             "the paper's primal rule has absolute tolerances only"),
                     Applies("admm_coupling", lambda s: s.admm_coupling == "copies",
                             "the planes' residual is absolute (how far a plane moves)")),
    "rho_update": (Applies("admm_coupling", lambda s: s.admm_coupling == "copies",
                           "the planes adapt each offset's step themselves"),),
    "admm_stop": (Applies("admm_coupling", lambda s: s.admm_coupling == "copies",
                          "the planes stop when no plane moves and the iterate is safe"),),
    "admm_dual_tol": (Applies("admm_coupling", lambda s: s.admm_coupling == "copies",
                              "the planes have no dual residual"),),
    "solver_warm": (Applies("solver", lambda s: s.solver == "fast", "only the compiled solver keeps warm points"),),
    "admm_compiled": (Applies("solver", lambda s: s.solver == "fast", "only the compiled solver has them"),),
    "alpha": (Applies("cost", lambda s: s.cost is None or s.uncertainty == "feedback",
                      "the cost's R replaces alpha I"),),
    "terminal_cost": (Applies("cost", lambda s: s.cost is None or s.cost.P is None, "the cost gives its own P"),),
}



def agent_radii(radii: typing.Sequence[float] | None, r_safe: float, num_agents: int) -> tuple[float, ...]:
    """Every agent's body radius (K numbers): ``radii`` when it gives one per agent, else
    ``r_safe / 2`` each (a length mismatch is refused where a run starts, by
    :meth:`ControllerSettings.check_team`)."""
    if radii is None or len(radii) != num_agents:
        return (r_safe / 2,) * num_agents
    return tuple(float(r) for r in radii)


def parse_world(obj, what: str) -> None:
    """Turn the tables of a frozen dataclass's ``workspace``, ``obstacles`` and ``cost`` fields (from a
    file or ``--set``) into :class:`Workspace`, :class:`ObstacleField` and :class:`CostTable`, naming
    ``<what> '<field>'`` on error."""
    for name, kind in (("workspace", Workspace), ("obstacles", ObstacleField), ("cost", CostTable)):
        value = getattr(obj, name)
        if value is not None and not isinstance(value, kind):
            object.__setattr__(obj, name, kind.parse(value, f"{what} '{name}'"))

#: The methods with chance margins (the ones a mission budget can be spent on).
CHANCE_METHODS = tuple(name for name in METHOD_NAMES if name.endswith("-chance"))


def check_risk_mode(risk_mode: str, method: str, pair_margin: str, what: str) -> None:
    """A mission budget needs chance margins and a sound pair margin (its bound adds the two
    agents' risks of a pair).

    Raises:
        GpmpcError: ``risk_mode = mission`` with a method without margins or ``pair_margin = own``.
    """
    if risk_mode != "mission":
        return
    if method not in CHANCE_METHODS:
        raise GpmpcError(f"{what} 'risk_mode': mission needs chance margins, but method {method!r} has none; "
                         f"use one of {', '.join(CHANCE_METHODS)} or risk_mode=pair_step")
    if pair_margin == "own":
        raise GpmpcError(f"{what} 'risk_mode': mission needs a sound pair margin (the pair's risk is the sum "
                         "of its agents' shares), but pair_margin=own is the paper's unsound one; "
                         "use pair_margin=sum or joint")


def check_coupling(coupling: str, relinearize: bool, what: str) -> None:
    """Plane coupling keeps its planes in the frame of one linearization per step.

    Raises:
        GpmpcError: ``admm_coupling = planes`` with ``relinearize``.
    """
    if coupling == "planes" and relinearize:
        raise GpmpcError(f"{what} 'admm_coupling': planes keeps one linearization per step; "
                         "use relinearize=false, or admm_coupling=copies")


def resolve_uncertainty(uncertainty: str, spec: ModelSpec) -> str:
    """``uncertainty`` with ``auto`` resolved for a model: ``pointwise`` when the residual rows
    cover the position (the paper's single integrator: the GP variance is the position's),
    ``propagated`` otherwise (e.g. a double integrator, whose velocity residual reaches the
    position only through the dynamics)."""
    if uncertainty != "auto":
        return uncertainty
    return "pointwise" if set(spec.position) <= set(spec.residual) else "propagated"


@dataclass(frozen=True)
class GPFitSettings:
    """How each agent's residual GP is fitted by the paper's data recipe
    (:func:`~torch_gpmpc.gp.fit.fit_agent_gps`); built by ``Config.gp_fit_settings()``.

    Attributes:
        samples: training transitions per agent (``gp_samples``).
        iters: optimizer iterations (``gp_iters``). optimizer: ``lbfgs`` or ``adam`` (``gp_optimizer``).
        box: half-width of the box the training positions are drawn from (``gp_box``, by default
            the scenario's ``circle_radius``).
        seed: the run seed (data stream ``2 seed + 1``, fit of agent k ``seed + k``).

    Examples:
        >>> from torch_gpmpc.config import Config
        >>> Config(circle_radius=6.0).gp_fit_settings().box
        6.0
    """

    samples: int = 100
    iters: int = 50
    optimizer: str = "lbfgs"
    box: float = 4.0
    seed: int = 0

    def __post_init__(self) -> None:
        validate(self, GP_FIT_RULES)


GP_FIT_RULES = Rules("GP fit setting", "", {"optimizer": ("lbfgs", "adam")}, {
    "samples": (lambda v: 2 <= v <= 5000, "an integer in [2, 5000]"),
    "iters": (lambda v: v >= 1, "an integer >= 1"),
    "box": (lambda v: v > 0, "a number > 0"),
    "seed": (lambda v: v >= 0, "an integer >= 0"),
})


def controller_keys() -> tuple[str, ...]:
    """The names of the controller settings (also keys of the run configuration)."""
    return tuple(ControllerSettings.__dataclass_fields__)
