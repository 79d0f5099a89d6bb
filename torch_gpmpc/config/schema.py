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

from torch_gpmpc.config.fields import Rules, build, validate
from torch_gpmpc.dynamics.methods import METHOD_NAMES
from torch_gpmpc.config.model_spec import ModelSpec, check_model_name, resolve_model
from torch_gpmpc.errors import GpmpcError

METHODS = METHOD_NAMES
UNCERTAINTY_MODES = ("pointwise", "propagated", "feedback")
MARGIN_VARIANCES = ("latent", "predictive")
PAIR_MARGINS = ("own", "sum", "joint")
RHO_UPDATES = ("fixed", "adaptive")
ADMM_STOPS = ("primal", "primal-dual")
SOLVERS = ("fast", "clarabel", "reference")
REFERENCES = ("line", "target")
SCENARIOS = ("paper", "circle", "random")


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
        alpha: control-effort weight in the cost.
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
        scenario: ``paper``, ``circle`` or ``random``.
        num_agents: K (the paper scenario has 3).
        seed: seed for data, noise and scenario generation.
        solver: ``fast`` (structure-exploiting interior point compiled with numba, :mod:`~torch_gpmpc.control.solvers.interior_point`),
            ``clarabel`` (cvxpylayers + diffcp with Clarabel) or ``reference`` (cvxpylayers' default).
        method: one of :data:`METHODS`.
        dim: position dimension (2 or 3) of the built-in models; the single integrator's state
            and input have this dimension, the double integrator's state has twice it.
        model: the agent model: ``single-integrator`` (the paper), ``double-integrator`` (state
            ``[p, v]``, input acceleration) or a model file path (TOML/JSON, see
            :mod:`~torch_gpmpc.config.model_spec`).
        dt: sampling time of the double integrator (s).
        reference: ``line`` (straight line over ``ref_points`` steps, then hold) or ``target``.
        ref_points: number of points of the straight-line reference.
        circle_radius: radius of the start circle of ``paper``/``circle`` scenarios.
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
    """

    horizon: int = 13
    rho: float = 20.0
    r_safe: float = 0.5
    eps: float = 0.1
    risk_split: float = 0.5
    u_max: float = 2.0
    alpha: float = 1e-3
    noise_std: float = 0.1
    admm_tol: float = 1e-3
    admm_dual_tol: float | None = None
    admm_rel_tol: float = 1e-4
    admm_max_iter: int = 100
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
    method: str = "gp-chance"
    dim: int = 2
    model: str = "single-integrator"
    dt: float = 0.1
    reference: str = "line"
    ref_points: int = 50
    circle_radius: float = 4.0
    min_separation: float = 1.0
    gp_samples: int = 100
    gp_inputs: str = "state"
    gp_optimizer: str = "lbfgs"
    gp_iters: int = 50
    slack_penalty: float = 1e4
    relinearize: bool = False
    wind_scale: float = 0.1

    def __post_init__(self) -> None:
        validate(self, RULES)
        check_model_name(self.model)
        if self.scenario == "paper" and self.num_agents != 3:
            raise GpmpcError(
                f"config key 'num_agents': the paper scenario has 3 agents, got {self.num_agents}; "
                "use scenario=circle or scenario=random for other team sizes"
            )

    def model_spec(self) -> ModelSpec:
        """The agent model of this run (built-in or read from the model file)."""
        return resolve_model(self.model, self.dim, self.dt, self.u_max)

    @property
    def uncertainty_mode(self) -> str:
        """The covariance model in use: ``uncertainty`` with ``auto`` resolved (see above)."""
        if self.uncertainty != "auto":
            return self.uncertainty
        spec = self.model_spec()
        return "pointwise" if set(spec.position) <= set(spec.residual) else "propagated"

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
        """Plain dict of all keys (JSON-serializable)."""
        return dataclasses.asdict(self)


_CHOICES = {
    "uncertainty": ("auto", *UNCERTAINTY_MODES),
    "margin_variance": MARGIN_VARIANCES,
    "pair_margin": PAIR_MARGINS,
    "rho_update": RHO_UPDATES,
    "admm_stop": ADMM_STOPS,
    "scenario": SCENARIOS,
    "solver": SOLVERS,
    "method": METHODS,
    "reference": REFERENCES,
    "gp_inputs": ("state", "state_input"),
    "gp_optimizer": ("lbfgs", "adam"),
}

# (predicate, description of the allowed range); checked in __post_init__.
_RANGES: dict[str, tuple[typing.Callable[[Any], bool], str]] = {
    "horizon": (lambda v: 1 <= v <= 1000, "an integer in [1, 1000]"),
    "rho": (lambda v: v > 0, "a number > 0"),
    "r_safe": (lambda v: v >= 0, "a number >= 0"),
    "eps": (lambda v: 0 < v < 1, "a number in (0, 1)"),
    "risk_split": (lambda v: 0 < v < 1, "a number in (0, 1)"),
    "u_max": (lambda v: v > 0, "a number > 0"),
    "alpha": (lambda v: v >= 0, "a number >= 0"),
    "noise_std": (lambda v: v >= 0, "a number >= 0"),
    "admm_tol": (lambda v: v > 0, "a number > 0"),
    "admm_dual_tol": (lambda v: v is None or v > 0, "a number > 0 or null"),
    "admm_rel_tol": (lambda v: 0 <= v < 1, "a number in [0, 1)"),
    "admm_max_iter": (lambda v: 1 <= v <= 100_000, "an integer in [1, 100000]"),
    "comm_radius": (lambda v: v is None or v > 0, "a number > 0 or null (all pairs)"),
    "goal_tol": (lambda v: v > 0, "a number > 0"),
    "max_steps": (lambda v: 1 <= v <= 1_000_000, "an integer in [1, 1000000]"),
    "num_agents": (lambda v: 1 <= v <= 1000, "an integer in [1, 1000]"),
    "seed": (lambda v: v >= 0, "an integer >= 0"),
    "dim": (lambda v: v in (2, 3), "2 or 3"),
    "ref_points": (lambda v: v >= 2, "an integer >= 2"),
    # the same bound as scenario-file coordinates (scenarios.MAX_COORDINATE)
    "circle_radius": (lambda v: 0 < v <= 1e4, "a number in (0, 10000]"),
    "min_separation": (lambda v: v >= 0, "a number >= 0"),
    # an exact GP costs O(N^3) time and O(N^2) memory per agent
    "gp_samples": (lambda v: 2 <= v <= 5000, "an integer in [2, 5000]"),
    "gp_iters": (lambda v: v >= 1, "an integer >= 1"),
    "slack_penalty": (lambda v: v > 0, "a number > 0"),
    "wind_scale": (lambda v: v >= 0, "a number >= 0"),
    "dt": (lambda v: 0 < v <= 10, "a number in (0, 10]"),
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
        warnings.warn(f"config key 'gp_noise_in_margin' is deprecated; it means margin_variance={new}",
                      DeprecationWarning, stacklevel=3)
        data.setdefault("margin_variance", new)
    return data
