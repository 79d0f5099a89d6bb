r"""Gradient tuning of the ADMM penalty rho and the per-pair risk split (``gpmpc tune``).

Parameters (:class:`TuningParameters`):

* ``log_rho`` (scalar): ``rho = exp(log_rho)``, one global penalty;
* ``theta`` (K, K): for each edge ``(lo, hi)``, ``lo < hi``, the split
  ``s_lo,hi = sigmoid(theta[lo, hi])``, so that ``eps_lo = eps s`` and
  ``eps_hi = eps (1 - s)`` (paper eq. 21: the pair's total ``eps`` stays fixed).
  Entries below the diagonal are unused. The split is handed to
  :meth:`ADMM.solve_step <torch_gpmpc.coordination.admm.ADMM.solve_step>` as the (K, K) tensor
  ``sigmoid(theta)`` (entry ``[lo, hi]``).

Objective (:class:`TuningObjective`), averaged over a batch of training instances
(:class:`TuneInstance`: a start state, a reference, a fixed noise sequence) and over
``mpc_steps`` closed-loop MPC steps per instance. At every step ADMM runs a **fixed**
number ``admm_iters`` of iterations (no early stop, so the objective is one smooth
function of the parameters) with gradients through every local solve (cvxpylayers)::

    L = w_primal   * r_p                                 (final primal residual)
      + w_dual     * r_d                                 (final dual residual)
      + w_cost     * mean_k J_k                          (planned cost)
      + w_distance * sum_{tau,k<j} beta softplus((r_safe - d_kj^tau) / beta) / #pairs

with, at the last iteration (``E`` edges, ``a`` the two ends of an edge),

* ``r_p = sqrt(mean_{e,a} ||y_{e,a} - z_e||^2)`` (root mean square of the per-edge primal
  residuals of the paper's stopping rule; smooth, unlike their max);
* ``r_d = rho sqrt(mean_e ||z_e - z_e^prev||^2)`` (the dual residual; the primal
  residual alone rewards ever larger rho, the dual one penalizes it);
* ``J_k = ||X_k - Xref_k||_F^2 + alpha ||U_k||_F^2`` of agent k's final local plan;
* ``d_kj^tau = ||X_k^tau - X_j^tau||`` for ``tau = 1..T`` between the agents' *own*
  plans (not the copies): a consensus that is not reached shows up here.

Between MPC steps the true system is stepped with the plans' first inputs and the
instance's fixed noise; the next ADMM is warm-started from the shifted iterate (as in
:func:`~torch_gpmpc.sim.closed_loop.simulate`), and gradients flow through the closed loop.
Optionally ``warmup_iters`` gradient-free iterations run first at the current
parameters (truncated back-propagation: a near-converged start, then the unrolled
iterations), which makes the planned cost that of a (nearly) converged consensus.

Implementation note: the unroll calls the public ``ADMM.solve_step`` once per
iteration (``max_iter=1``, ``tol=0``) warm-started from the previous iterate, which is
exactly one iteration of the multi-iteration loop (for ``relinearize=False`` the
linearization points are held at the start plans, as ``solve_step`` does). The
tensor residuals need each end's copy of each edge, taken with the ADMM helper
``ADMM._edge_copies`` (``solve_step`` reports residuals only as floats).

Seeds: instance seed ``s`` draws the start perturbation and the closed-loop noise from
``torch.Generator().manual_seed(s)``; nothing else is random, so an objective value is
reproducible and tuning resumes exactly.
"""

from __future__ import annotations

import json
import logging
import math
import warnings
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import torch
from torch import Tensor, nn

from torch_gpmpc.coordination.admm import ADMM, ADMMState, StepResult, adapt_state, initial_state
from torch_gpmpc.config.schema import Config
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.coordination.graph import Graph, communication_graph
from torch_gpmpc.sim.scenarios import Scenario, make_scenario
from torch_gpmpc.dynamics.systems import TrueSystem, make_system

log = logging.getLogger(__name__)

#: Added under square roots of residuals (keeps gradients finite at an exact consensus).
_SQRT_FLOOR = 1e-24

#: Names of the objective's parts, in logging order (TensorBoard ``tune/<name>``).
PARTS = ("primal", "dual", "cost", "distance_penalty")


# --------------------------------------------------------------------------- settings
@dataclass(frozen=True)
class TuneSettings:
    """Settings of a tuning run (flat keys; on the command line ``--set tune.NAME=VALUE``).

    Attributes:
        seeds: training instance seeds.
        heldout_seeds: seeds of held-out instances (evaluated before and after tuning).
        admm_iters: ADMM iterations unrolled per MPC step (fixed, no early stop).
        mpc_steps: closed-loop MPC steps per instance (noise fixed by the seed).
        warmup_iters: gradient-free ADMM iterations before the unrolled ones (0 = none).
        warm_start: start each instance from the previous step's converged ADMM iterate
            (as the closed loop does; :func:`with_warm_starts`) instead of a cold start.
        warm_rho: rho of the warm-start solve (the converged point does not depend on it).
        warm_tol: primal and dual tolerance of the warm-start solve.
        warm_max_iter: iteration cap of the warm-start solve.
        crossing_distance: instances start where the reference is this far from the
            point where the straight paths cross (``paper``: the centre).
        perturb_std: standard deviation of the seeded perturbation of the start state.
        w_primal: weight of the final primal residual.
        w_dual: weight of the final dual residual.
        w_cost: weight of the mean planned cost per agent.
        w_distance: weight of the softplus penalty on planned distances below r_safe.
        distance_width: softplus width beta of that penalty.
        optimizer: ``adam`` or ``lbfgs``.
        lr: learning rate (Adam) or step length (L-BFGS).
        lr_decay: Adam's learning rate is multiplied by this every iteration.
        tune_rho: optimize log rho.
        tune_split: optimize the per-edge split logits.
        grid_points: after tuning, also evaluate a grid of this many rho values
            log-spaced in ``[grid_min, grid_max]`` (split from the config) as a
            baseline (0 = no grid search).
        grid_min: smallest grid rho.
        grid_max: largest grid rho.
    """

    seeds: tuple[int, ...] = (0, 1)
    heldout_seeds: tuple[int, ...] = (100, 101)
    admm_iters: int = 6
    mpc_steps: int = 1
    warmup_iters: int = 0
    warm_start: bool = True
    warm_rho: float = 2.0
    warm_tol: float = 1e-3
    warm_max_iter: int = 300
    crossing_distance: float = 1.0
    perturb_std: float = 0.2
    w_primal: float = 1.0
    w_dual: float = 1.0
    w_cost: float = 0.01
    w_distance: float = 10.0
    distance_width: float = 0.05
    optimizer: str = "adam"
    lr: float = 0.2
    lr_decay: float = 0.95
    tune_rho: bool = True
    tune_split: bool = True
    grid_points: int = 0
    grid_min: float = 1.0
    grid_max: float = 200.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "seeds", tuple(int(s) for s in _as_list(self.seeds, "seeds")))
        object.__setattr__(self, "heldout_seeds",
                           tuple(int(s) for s in _as_list(self.heldout_seeds, "heldout_seeds")))
        checks = {
            "seeds": (len(self.seeds) >= 1 and min(self.seeds) >= 0, "a non-empty list of integers >= 0"),
            "heldout_seeds": (all(s >= 0 for s in self.heldout_seeds), "a list of integers >= 0"),
            "admm_iters": (isinstance(self.admm_iters, int) and self.admm_iters >= 1, "an integer >= 1"),
            "mpc_steps": (isinstance(self.mpc_steps, int) and self.mpc_steps >= 1, "an integer >= 1"),
            "warmup_iters": (isinstance(self.warmup_iters, int) and self.warmup_iters >= 0, "an integer >= 0"),
            "warm_start": (isinstance(self.warm_start, bool), "true or false"),
            "warm_rho": (self.warm_rho > 0, "a number > 0"),
            "warm_tol": (self.warm_tol > 0, "a number > 0"),
            "warm_max_iter": (isinstance(self.warm_max_iter, int) and self.warm_max_iter >= 1, "an integer >= 1"),
            "crossing_distance": (self.crossing_distance >= 0, "a number >= 0"),
            "perturb_std": (self.perturb_std >= 0, "a number >= 0"),
            "w_primal": (self.w_primal >= 0, "a number >= 0"),
            "w_dual": (self.w_dual >= 0, "a number >= 0"),
            "w_cost": (self.w_cost >= 0, "a number >= 0"),
            "w_distance": (self.w_distance >= 0, "a number >= 0"),
            "distance_width": (self.distance_width > 0, "a number > 0"),
            "optimizer": (self.optimizer in ("adam", "lbfgs"), "adam or lbfgs"),
            "lr": (self.lr > 0, "a number > 0"),
            "lr_decay": (0 < self.lr_decay <= 1, "a number in (0, 1]"),
            "tune_rho": (isinstance(self.tune_rho, bool), "true or false"),
            "tune_split": (isinstance(self.tune_split, bool), "true or false"),
            "grid_points": (isinstance(self.grid_points, int) and self.grid_points >= 0, "an integer >= 0"),
            "grid_min": (self.grid_min > 0, "a number > 0"),
            "grid_max": (self.grid_max >= self.grid_min, "a number >= grid_min"),
        }
        for name, (ok, allowed) in checks.items():
            if not ok:
                raise GpmpcError(f"tune setting '{name}': {getattr(self, name)!r} is invalid; use {allowed}")

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any]) -> "TuneSettings":
        """Build from a flat mapping; unknown keys raise naming the nearest valid key."""
        import difflib

        names = [f.name for f in fields(cls)]
        for key in data:
            if key not in names:
                near = difflib.get_close_matches(key, names, n=1, cutoff=0.0)
                raise GpmpcError(f"unknown tune setting '{key}'; did you mean 'tune.{near[0]}'?")
        try:
            return cls(**dict(data))
        except TypeError as exc:  # wrong value types in comparisons
            raise GpmpcError(f"tune settings: {exc}") from exc

    def weights(self) -> "ObjectiveWeights":
        """The objective's weights."""
        return ObjectiveWeights(self.w_primal, self.w_dual, self.w_cost, self.w_distance, self.distance_width)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-serializable dict."""
        out = asdict(self)
        out["seeds"], out["heldout_seeds"] = list(self.seeds), list(self.heldout_seeds)
        return out


def _as_list(value: Any, name: str) -> list:
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return [value]
    if isinstance(value, (list, tuple)) and all(isinstance(v, int) and not isinstance(v, bool) for v in value):
        return list(value)
    raise GpmpcError(f"tune setting '{name}': expected a list of integers, got {value!r}")


@dataclass(frozen=True)
class ObjectiveWeights:
    """Weights of the tuning objective (see the module docstring).

    Attributes:
        primal: weight of the final primal residual ``r_p``.
        dual: weight of the final dual residual ``r_d``.
        cost: weight of the mean planned cost per agent.
        distance: weight of the softplus penalty on planned distances below r_safe.
        distance_width: the softplus width beta (> 0).
    """

    primal: float = 1.0
    dual: float = 1.0
    cost: float = 0.01
    distance: float = 10.0
    distance_width: float = 0.05


# --------------------------------------------------------------------------- parameters
class TuningParameters(nn.Module):
    """The tuned quantities: ``log_rho`` () and per-edge split logits ``theta`` (K, K).

    Args:
        num_agents: K.
        rho: initial penalty (> 0).
        split: initial split of every edge, in (0, 1), or a (K, K) tensor (entry
            ``[lo, hi]`` per edge).
    """

    def __init__(self, num_agents: int, rho: float = 20.0, split: float | Tensor = 0.5) -> None:
        super().__init__()
        if rho <= 0:
            raise GpmpcError(f"rho must be > 0, got {rho}")
        split_t = torch.as_tensor(split, dtype=torch.float64).expand(num_agents, num_agents).clone()
        if not bool(((split_t > 0) & (split_t < 1)).all()):
            raise GpmpcError("risk split must be in (0, 1)")
        self.num_agents = int(num_agents)
        self.log_rho = nn.Parameter(torch.tensor(math.log(rho), dtype=torch.float64))
        self.theta = nn.Parameter(torch.logit(split_t))

    def rho(self) -> Tensor:
        """``exp(log_rho)``, a 0-d tensor."""
        return self.log_rho.exp()

    def split(self) -> Tensor:
        """``sigmoid(theta)``, shape (K, K): the lower-indexed agent's share per edge."""
        return torch.sigmoid(self.theta)

    def split_per_edge(self, edges: Sequence[Sequence[int]] | None = None) -> dict[str, float]:
        """``{"lo_hi": s}`` for the given edges (default: all pairs ``lo < hi``)."""
        split = self.split().detach()
        if edges is None:
            edges = [(i, j) for i in range(self.num_agents) for j in range(i + 1, self.num_agents)]
        return {f"{lo}_{hi}": float(split[lo, hi]) for lo, hi in edges}

    def mean_split(self, edges: Sequence[Sequence[int]] | None = None) -> float:
        """Mean split over the given edges (default all pairs); 0.5 for K < 2."""
        values = list(self.split_per_edge(edges).values())
        return float(sum(values) / len(values)) if values else 0.5


# --------------------------------------------------------------------------- instances
@dataclass(frozen=True, eq=False)
class TuneInstance:
    """One training situation: a start, a reference and fixed closed-loop noise.

    Attributes:
        x0: start states, shape (K, D).
        scenario: gives the reference windows.
        t0: reference time index of the start.
        noise: standard-normal process noise of the closed-loop steps, shape (S, K, D)
            (scaled by the system's ``noise_std`` when stepping).
        name: a label.
        warm: ADMM warm start of the first MPC step (``None``: cold start); see
            :func:`with_warm_starts`.
    """

    x0: Tensor
    scenario: Scenario
    t0: int
    noise: Tensor
    name: str = "instance"
    warm: ADMMState | None = None


def crossing_index(scenario: Scenario, distance: float) -> int:
    """Reference index at which the agents are ``distance`` from the crossing point.

    For a ``line`` reference agent k is at ``start_k + (target_k - start_k) i / (R-1)``;
    half of its path is ``h_k = ||target_k - start_k|| / 2`` and it is ``distance`` from
    its path's midpoint at ``i = (R-1)/2 (1 - distance / h_k)``. Returns the rounded mean
    over agents, clipped to ``[0, R-1]`` (0 for a ``target`` reference).
    """
    if scenario.reference_kind != "line":
        return 0
    half = (scenario.targets - scenario.starts).norm(dim=1) / 2
    frac = (1 - distance / half.clamp_min(1e-12)).clamp(min=0.0)
    index = (scenario.ref_points - 1) / 2 * float(frac.mean())
    return int(min(max(round(index), 0), scenario.ref_points - 1))


def make_instances(
    cfg: Config, seeds: Sequence[int], settings: TuneSettings | None = None, scenario: Scenario | None = None
) -> list[TuneInstance]:
    """Training instances near the crossing of the config's scenario.

    Instance ``s``: the reference position at :func:`crossing_index` plus a seeded
    Gaussian perturbation (std ``perturb_std``), and ``mpc_steps`` steps of
    standard-normal noise, all from ``torch.Generator().manual_seed(s)``. Starts closer
    than ``r_safe`` are pushed apart along their difference (so the local problems
    start feasible).

    Args:
        cfg: run configuration (scenario, horizon, r_safe, ...).
        seeds: one instance per seed.
        settings: tuning settings (default :class:`TuneSettings`).
        scenario: the scenario (default ``make_scenario(cfg)``).

    Returns:
        One :class:`TuneInstance` per seed.
    """
    settings = settings or TuneSettings()
    scenario = scenario or make_scenario(cfg)
    t0 = crossing_index(scenario, settings.crossing_distance)
    base = scenario.reference_window(t0, 0)[:, 0]  # (K, D)
    out = []
    for seed in seeds:
        gen = torch.Generator().manual_seed(int(seed))
        x0 = base + settings.perturb_std * torch.randn(base.shape, generator=gen, dtype=torch.float64)
        x0 = _separate(x0, cfg.r_safe)
        noise = torch.randn(settings.mpc_steps, *base.shape, generator=gen, dtype=torch.float64)
        out.append(TuneInstance(x0=x0, scenario=scenario, t0=t0, noise=noise, name=f"{scenario.name}@t{t0}/s{seed}"))
    return out


def with_warm_starts(admm: ADMM, instances: Sequence[TuneInstance], rho: float = 2.0, tol: float = 1e-3,
                     max_iter: int = 300) -> list[TuneInstance]:
    """Give each instance the warm start a well-converged closed loop would give it.

    In the closed loop, ADMM at step ``t0`` starts from step ``t0 - 1``'s final iterate
    shifted by one step (:func:`~torch_gpmpc.sim.closed_loop.simulate`). Here step ``t0 - 1`` is
    solved from ``x_prev = x0 - (ref(t0) - ref(t0 - 1))`` (no gradients) until both the
    primal and the dual residual are below ``tol`` (or ``max_iter``), and its final
    state is shifted (for ``t0 = 0``: the converged iterate at ``t0``, unshifted). A
    converged ``(z, lam)`` does not depend on rho, so a fast ``rho`` is used and the warm
    start does not depend on the tuned parameters.

    Why not a cold start: from "every plan holds x0" with rho = 20 the primal residual
    drops below 1e-3 within 2 iterations at plans that barely move (the consensus is
    pinned, the dual residual stays ~4): primal-feasible, far from optimal. A cold start
    is still available (``TuneSettings.warm_start = false``).

    Args:
        admm: the ADMM (config, method, models).
        instances: instances to warm-start.
        rho: penalty used for the warm-start solve.
        tol: primal and dual tolerance of the warm-start solve.
        max_iter: iteration cap of the warm-start solve.

    Returns:
        New instances with ``warm`` set.
    """
    cfg = admm.cfg.replace(admm_tol=tol, admm_dual_tol=tol, admm_max_iter=max_iter)
    solver = ADMM(cfg, admm.method, admm.nominal, admm.wind, admm.gps)
    out = []
    with torch.no_grad():
        for inst in instances:
            t_prev = max(inst.t0 - 1, 0)
            step = inst.scenario.reference_window(inst.t0, 0)[:, 0] - inst.scenario.reference_window(t_prev, 0)[:, 0]
            x_prev = inst.x0 - step
            graph = communication_graph(x_prev, cfg.comm_radius)
            res = solver.solve_step(x_prev, inst.scenario.reference_window(t_prev, cfg.horizon), graph,
                                    rho=float(rho))
            if not res.converged:
                log.warning("warm start of %s did not converge in %d iterations (primal %.2e, dual %.2e)",
                            inst.name, max_iter, res.primal_residuals[-1], res.dual_residuals[-1])
            warm = res.state.shifted() if inst.t0 > 0 else res.state
            out.append(TuneInstance(inst.x0, inst.scenario, inst.t0, inst.noise, inst.name, _detached_state(warm)))
    return out


def _separate(x: Tensor, r_safe: float, iters: int = 20) -> Tensor:
    """Push pairs closer than ``1.05 r_safe`` apart symmetrically (a few sweeps)."""
    x = x.clone()
    for _ in range(iters):
        moved = False
        for i in range(x.shape[0]):
            for j in range(i + 1, x.shape[0]):
                d = x[i] - x[j]
                dist = float(d.norm())
                if dist < 1.05 * r_safe:
                    direction = d / dist if dist > 1e-12 else torch.eye(x.shape[1], dtype=x.dtype)[0]
                    push = 0.5 * (1.05 * r_safe - dist) + 1e-9
                    x[i] += push * direction
                    x[j] -= push * direction
                    moved = True
        if not moved:
            break
    return x


def head_on_instance(distance: float = 3.0, offset: float = 0.1, dim: int = 2, ref_points: int = 31) -> TuneInstance:
    """Two agents approaching each other on (almost) the same line.

    Agent 0 starts at ``(-distance/2, offset/2)`` and agent 1 at
    ``(distance/2, -offset/2)``; each one's target is the other's start, so their
    straight-line references collide half-way (the collision rows are active).

    Args:
        distance: start distance.
        offset: lateral offset (breaks the symmetry of the head-on encounter).
        dim: D.
        ref_points: points of the straight-line reference.
    """
    starts = torch.zeros(2, dim, dtype=torch.float64)
    starts[0, 0], starts[0, 1] = -distance / 2, offset / 2
    starts[1, 0], starts[1, 1] = distance / 2, -offset / 2
    targets = starts.flip(0).clone()
    scenario = Scenario(starts, targets, "line", ref_points, "head-on")
    return TuneInstance(x0=starts, scenario=scenario, t0=0, noise=torch.zeros(1, 2, dim), name="head-on")


# --------------------------------------------------------------------------- unrolled ADMM
@dataclass
class UnrolledStep:
    """ADMM at one time step, unrolled for a fixed number of iterations.

    Attributes:
        result: the last iteration's :class:`StepResult` (``result.solution`` and
            ``result.state`` carry gradients).
        primal: per unrolled iteration, ``r_p`` (see the module docstring), shape (I,).
        dual: per unrolled iteration, ``r_d``, shape (I,).
    """

    result: StepResult
    primal: Tensor
    dual: Tensor


def unroll_admm(
    admm: ADMM,
    x0: Tensor,
    xref: Tensor,
    graph: Graph,
    iters: int,
    rho: Tensor,
    split: Tensor | float,
    warm: ADMMState | None = None,
    warmup_iters: int = 0,
) -> UnrolledStep:
    """Run exactly ``warmup_iters`` (no gradient) + ``iters`` (differentiable) ADMM iterations.

    Args:
        admm: the ADMM (its config gives horizon, eps, r_safe, relinearize).
        x0: (K, D) states.
        xref: (K, T+1, D) reference window.
        graph: the communication graph.
        iters: unrolled iterations (>= 1).
        rho: 0-d tensor penalty.
        split: scalar or (K, K) risk split.
        warm: warm start (already shifted), or ``None`` for a cold start.
        warmup_iters: iterations run first under ``torch.no_grad`` at the same parameters.

    Returns:
        The :class:`UnrolledStep`.
    """
    if iters < 1:
        raise GpmpcError(f"unroll_admm: iters must be >= 1, got {iters}")
    state = initial_state(x0.detach(), admm.cfg.horizon, graph) if warm is None else adapt_state(warm, graph)
    lin_plans, lin_inputs = state.plans, state.inputs  # relinearize=False keeps these
    if warmup_iters > 0:
        with torch.no_grad():
            res = admm.solve_step(x0.detach(), xref, graph, warm=state, rho=rho.detach(),
                                  risk_split=_detach(split), max_iter=warmup_iters, tol=0.0)
        state = _detached_state(res.state)
        if not admm.cfg.relinearize:
            state = ADMMState(lin_plans.detach(), lin_inputs.detach(), state.edges, state.z, state.lam)
    primal, dual = [], []
    res = None
    for _ in range(iters):
        z_prev = state.z
        with warnings.catch_warnings():  # solve_step logs float() of residuals that carry gradients
            warnings.filterwarnings("ignore", message="Converting a tensor with requires_grad=True")
            res = admm.solve_step(x0, xref, graph, warm=state, rho=rho, risk_split=split, max_iter=1, tol=0.0)
        new = res.state
        if graph.num_edges:
            copies = admm._edge_copies(res.solution, graph)  # (E, 2, 2, T+1, D)
            gap = copies - new.z.unsqueeze(1)
            primal.append(torch.sqrt(gap.pow(2).sum(dim=(2, 3, 4)).mean() + _SQRT_FLOOR))
            dual.append(rho * torch.sqrt((new.z - z_prev).pow(2).sum(dim=(1, 2, 3)).mean() + _SQRT_FLOOR))
        else:
            primal.append(x0.new_zeros(()))
            dual.append(x0.new_zeros(()))
        state = new if admm.cfg.relinearize else ADMMState(lin_plans, lin_inputs, new.edges, new.z, new.lam)
    res.state = new
    return UnrolledStep(result=res, primal=torch.stack(primal), dual=torch.stack(dual))


def _detach(x: Tensor | float) -> Tensor | float:
    return x.detach() if isinstance(x, Tensor) else x


def _detached_state(s: ADMMState) -> ADMMState:
    return ADMMState(s.plans.detach(), s.inputs.detach(), s.edges, s.z.detach(), s.lam.detach())


def distance_penalty(plans: Tensor, r_safe: float, width: float) -> Tensor:
    """Smooth penalty on planned pair distances below ``r_safe``.

    ``sum_{tau=1..T} sum_{k<j} width * softplus((r_safe - ||X_k^tau - X_j^tau||) / width)``
    divided by the number of pairs.

    Args:
        plans: (K, T+1, D) planned states.
        r_safe: safety radius.
        width: softplus width beta > 0.

    Returns:
        0-d tensor (0 for K < 2).
    """
    K = plans.shape[0]
    if K < 2:
        return plans.new_zeros(())
    i, j = torch.triu_indices(K, K, 1)
    diff = plans[i, 1:] - plans[j, 1:]  # (P, T, D)
    dist = torch.sqrt(diff.pow(2).sum(-1) + _SQRT_FLOOR)
    return width * torch.nn.functional.softplus((r_safe - dist) / width).sum() / i.numel()


# --------------------------------------------------------------------------- objective
@dataclass
class ObjectiveValue:
    """One evaluation of :class:`TuningObjective`.

    Attributes:
        loss: the weighted objective, 0-d tensor (differentiable).
        parts: unweighted parts ``primal``, ``dual``, ``cost``, ``distance_penalty``
            (0-d tensors, means over instances and MPC steps).
    """

    loss: Tensor
    parts: dict[str, Tensor]

    def floats(self) -> dict[str, float]:
        """``loss`` and the parts as floats."""
        return {"loss": float(self.loss), **{k: float(v) for k, v in self.parts.items()}}


class TuningObjective:
    """The tuning objective over a batch of instances (definition: module docstring).

    Args:
        admm: the ADMM (its config: horizon, eps, r_safe, alpha, method, ...).
        instances: training instances.
        weights: objective weights (default :class:`ObjectiveWeights`).
        admm_iters: unrolled ADMM iterations per MPC step (fixed count).
        mpc_steps: closed-loop MPC steps per instance (at most the instance's noise length).
        warmup_iters: gradient-free iterations before the unrolled ones.
        system: the true system stepped between MPC steps (default from the config).

    Attributes:
        evaluations: number of objective evaluations so far.
    """

    def __init__(
        self,
        admm: ADMM,
        instances: Sequence[TuneInstance],
        weights: ObjectiveWeights | None = None,
        admm_iters: int = 6,
        mpc_steps: int = 1,
        warmup_iters: int = 0,
        system: TrueSystem | None = None,
    ) -> None:
        if not instances:
            raise GpmpcError("TuningObjective needs at least one instance")
        for inst in instances:
            if inst.noise.shape[0] < mpc_steps - 1:
                raise GpmpcError(f"instance {inst.name}: noise for {inst.noise.shape[0]} steps, "
                                 f"mpc_steps={mpc_steps} needs {mpc_steps - 1}")
        self.admm = admm
        self.cfg = admm.cfg
        self.instances = list(instances)
        self.weights = weights or ObjectiveWeights()
        self.admm_iters = int(admm_iters)
        self.mpc_steps = int(mpc_steps)
        self.warmup_iters = int(warmup_iters)
        self.system = system or make_system(self.cfg.dim, self.cfg.noise_std, self.cfg.wind_scale)
        self.evaluations = 0

    def __call__(self, params: TuningParameters | None = None, rho: Tensor | None = None,
                 split: Tensor | float | None = None) -> ObjectiveValue:
        """Evaluate at ``params`` (or at explicit ``rho`` (0-d) and ``split``).

        Gradients flow to whatever of ``rho``/``split`` requires them (use
        ``torch.no_grad()`` for a cheaper forward-only evaluation).
        """
        if params is not None:
            rho, split = params.rho(), params.split()
        rho = torch.as_tensor(self.cfg.rho if rho is None else rho, dtype=torch.float64)
        split = self.cfg.risk_split if split is None else split
        self.evaluations += 1
        w = self.weights
        sums = {name: rho.new_zeros(()) for name in PARTS}
        count = 0
        for inst in self.instances:
            x, warm = inst.x0, inst.warm
            for step in range(self.mpc_steps):
                graph = communication_graph(x.detach(), self.cfg.comm_radius)
                xref = inst.scenario.reference_window(inst.t0 + step, self.cfg.horizon)
                un = unroll_admm(self.admm, x, xref, graph, self.admm_iters, rho, split, warm=warm,
                                 warmup_iters=self.warmup_iters)
                sol = un.result.solution
                sums["primal"] = sums["primal"] + un.primal[-1]
                sums["dual"] = sums["dual"] + un.dual[-1]
                sums["cost"] = sums["cost"] + sol.cost.mean()
                sums["distance_penalty"] = sums["distance_penalty"] + distance_penalty(
                    sol.X, self.cfg.r_safe, w.distance_width)
                count += 1
                if step + 1 < self.mpc_steps:
                    u = _clip_norm(un.result.inputs[:, 0], self.cfg.u_max)
                    x = self.system.step(x, u, noise=inst.noise[step])
                    warm = un.result.state.shifted()
        parts = {k: v / count for k, v in sums.items()}
        loss = (w.primal * parts["primal"] + w.dual * parts["dual"] + w.cost * parts["cost"]
                + w.distance * parts["distance_penalty"])
        return ObjectiveValue(loss=loss, parts=parts)


def _clip_norm(u: Tensor, u_max: float) -> Tensor:
    """Differentiable projection onto ``||u|| <= u_max``, shape preserved (K, D)."""
    norm = torch.sqrt(u.pow(2).sum(-1, keepdim=True) + _SQRT_FLOOR)
    return u * torch.clamp(u_max / norm, max=1.0)


# --------------------------------------------------------------------------- optimizer
@dataclass
class TuneRecord:
    """One tuning iteration (values at the parameters *before* the step).

    Attributes:
        iteration: 0-based iteration index.
        loss: objective value.
        parts: unweighted objective parts.
        rho: penalty.
        split: per-edge split ``{"lo_hi": s}``.
        grad_norm: Euclidean norm of the gradient w.r.t. the tuned parameters.
    """

    iteration: int
    loss: float
    parts: dict[str, float]
    rho: float
    split: dict[str, float]
    grad_norm: float

    def to_dict(self) -> dict[str, Any]:
        """JSON-serializable dict."""
        return asdict(self)


class Tuner:
    """Gradient tuning of :class:`TuningParameters` on a :class:`TuningObjective`.

    Adam (with per-iteration learning-rate decay) or L-BFGS (strong-Wolfe line
    search, one ``step`` per iteration; its evaluations are counted by the objective).

    Args:
        objective: the objective.
        params: the parameters (optimized in place).
        settings: optimizer, lr, lr_decay, tune_rho, tune_split.
        edges: edges whose split is reported (default all pairs).
    """

    def __init__(self, objective: TuningObjective, params: TuningParameters,
                 settings: TuneSettings | None = None, edges: Sequence[Sequence[int]] | None = None) -> None:
        self.objective, self.params = objective, params
        self.settings = settings or TuneSettings()
        self.edges = [tuple(e) for e in edges] if edges is not None else None
        trainable = []
        if self.settings.tune_rho:
            trainable.append(params.log_rho)
        if self.settings.tune_split:
            trainable.append(params.theta)
        if not trainable:
            raise GpmpcError("nothing to tune: set tune.tune_rho=true or tune.tune_split=true")
        for p in (params.log_rho, params.theta):
            p.requires_grad_(any(p is q for q in trainable))
        self.trainable = trainable
        if self.settings.optimizer == "adam":
            self.optimizer: torch.optim.Optimizer = torch.optim.Adam(trainable, lr=self.settings.lr)
            self.scheduler = torch.optim.lr_scheduler.ExponentialLR(self.optimizer, gamma=self.settings.lr_decay)
        else:
            self.optimizer = torch.optim.LBFGS(trainable, lr=self.settings.lr, max_iter=1, history_size=10,
                                               line_search_fn="strong_wolfe")
            self.scheduler = None
        self.history: list[TuneRecord] = []

    @property
    def iteration(self) -> int:
        """Iterations done."""
        return len(self.history)

    def _evaluate(self) -> tuple[ObjectiveValue, float]:
        self.optimizer.zero_grad()
        value = self.objective(self.params)
        value.loss.backward()
        grads = [p.grad for p in self.trainable if p.grad is not None]
        gnorm = float(torch.sqrt(sum((g ** 2).sum() for g in grads))) if grads else 0.0
        return value, gnorm

    def step(self) -> TuneRecord:
        """One optimizer iteration; returns its record (also appended to ``history``)."""
        rho, split = float(self.params.rho().detach()), self.params.split_per_edge(self.edges)
        if self.settings.optimizer == "adam":
            value, gnorm = self._evaluate()
            self.optimizer.step()
            self.scheduler.step()
        else:
            first: dict[str, Any] = {}

            def closure() -> Tensor:
                value, gnorm = self._evaluate()
                first.setdefault("value", value)
                first.setdefault("gnorm", gnorm)
                return value.loss.detach()

            self.optimizer.step(closure)
            value, gnorm = first["value"], first["gnorm"]
        f = value.floats()
        record = TuneRecord(iteration=self.iteration, loss=f.pop("loss"), parts=f, rho=rho, split=split,
                            grad_norm=gnorm)
        self.history.append(record)
        if not math.isfinite(record.loss):
            raise GpmpcError(f"tuning objective is not finite at iteration {record.iteration} "
                             f"(rho={rho:.4g}); lower tune.lr")
        return record

    def run(self, iters: int, callback: Callable[[TuneRecord], None] | None = None) -> list[TuneRecord]:
        """Iterate until ``iters`` iterations are done in total (resumed ones count).

        Args:
            iters: total number of iterations.
            callback: called with each new record (after the step).
        """
        while self.iteration < iters:
            record = self.step()
            if callback is not None:
                callback(record)
        return self.history

    def best(self) -> TuneRecord | None:
        """The record with the lowest loss (``None`` before the first iteration)."""
        return min(self.history, key=lambda r: r.loss) if self.history else None

    # ---------------------------------------------------------------- checkpoints
    def state_dict(self) -> dict[str, Any]:
        """Tensors (and plain containers of tensors/numbers) only: loads with ``weights_only=True``."""
        cols = ["loss", *PARTS, "rho", "grad_norm"]
        hist = torch.tensor([[r.loss, *[r.parts[p] for p in PARTS], r.rho, r.grad_norm] for r in self.history],
                            dtype=torch.float64).reshape(-1, len(cols))
        num = self.params.num_agents
        split_hist = torch.stack([_split_matrix(r.split, num) for r in self.history]) if self.history \
            else torch.zeros(0, num, num, dtype=torch.float64)
        return {
            "log_rho": self.params.log_rho.detach().clone(),
            "theta": self.params.theta.detach().clone(),
            "history": hist,
            "history_split": split_hist,
            "optimizer": self.optimizer.state_dict(),
            "scheduler": self.scheduler.state_dict() if self.scheduler is not None else {},
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore parameters, optimizer state and history from :meth:`state_dict`.

        Raises:
            GpmpcError: the checkpoint belongs to a different number of agents or optimizer.
        """
        theta = state["theta"]
        if tuple(theta.shape) != tuple(self.params.theta.shape):
            raise GpmpcError(f"checkpoint has a split for {theta.shape[0]} agents, this run has "
                             f"{self.params.num_agents}; use another --out or drop --resume")
        try:
            self.optimizer.load_state_dict(state["optimizer"])
            if self.scheduler is not None and state.get("scheduler"):
                self.scheduler.load_state_dict(state["scheduler"])
        except (KeyError, ValueError) as exc:
            raise GpmpcError(f"checkpoint does not match this run's optimizer settings ({exc}); use the same "
                             "tune.optimizer/tune_rho/tune_split, another --out, or drop --resume") from exc
        with torch.no_grad():
            self.params.log_rho.copy_(state["log_rho"])
            self.params.theta.copy_(theta)
        edges = self.edges or [(i, j) for i in range(self.params.num_agents)
                               for j in range(i + 1, self.params.num_agents)]
        self.history = []
        for i, (row, split) in enumerate(zip(state["history"].tolist(), state["history_split"], strict=True)):
            parts = dict(zip(PARTS, row[1:1 + len(PARTS)], strict=True))
            self.history.append(TuneRecord(iteration=i, loss=row[0], parts=parts, rho=row[1 + len(PARTS)],
                                           split={f"{lo}_{hi}": float(split[lo, hi]) for lo, hi in edges},
                                           grad_norm=row[2 + len(PARTS)]))

    def save_checkpoint(self, path: str | Path) -> None:
        """Atomically ``torch.save`` :meth:`state_dict` to ``path``."""
        from torch_gpmpc.fileio import atomic_path

        with atomic_path(path) as tmp:
            torch.save(self.state_dict(), tmp)

    def load_checkpoint(self, path: str | Path) -> None:
        """Load a checkpoint written by :meth:`save_checkpoint` (``weights_only=True``).

        Raises:
            GpmpcError: missing or unreadable file, or a different number of agents.
        """
        path = Path(path)
        if not path.is_file():
            raise GpmpcError(f"no checkpoint at {str(path)!r}; run without --resume to start")
        try:
            state = torch.load(path, weights_only=True)
        except Exception as exc:  # noqa: BLE001 - any unreadable file is a user error
            raise GpmpcError(f"checkpoint {str(path)!r} cannot be read: {exc}") from exc
        self.load_state_dict(state)


def _split_matrix(split: Mapping[str, float], num_agents: int) -> Tensor:
    out = torch.full((num_agents, num_agents), 0.5, dtype=torch.float64)
    for key, value in split.items():
        lo, hi = (int(v) for v in key.split("_"))
        out[lo, hi] = value
    return out


# --------------------------------------------------------------------------- baselines, results
def grid_search_rho(objective: TuningObjective, rhos: Sequence[float], split: Tensor | float | None = None
                    ) -> dict[str, Any]:
    """Evaluate the objective (no gradients) at each rho with a fixed split.

    Args:
        objective: the objective.
        rhos: candidate penalties.
        split: the split (default ``cfg.risk_split``).

    Returns:
        ``{"rhos": [...], "losses": [...], "best_rho": r, "best_loss": l, "evaluations": n}``.
    """
    losses = []
    with torch.no_grad():
        for rho in rhos:
            losses.append(float(objective(rho=torch.tensor(float(rho)), split=split).loss))
    best = min(range(len(losses)), key=losses.__getitem__)
    return {"rhos": [float(r) for r in rhos], "losses": losses, "best_rho": float(rhos[best]),
            "best_loss": losses[best], "evaluations": len(losses)}


def equalizing_split(sigma_lo: float, sigma_hi: float, eps: float, tol: float = 1e-14) -> float:
    """The split ``s`` with ``Phi^-1(1 - eps s) sigma_lo = Phi^-1(1 - eps (1 - s)) sigma_hi``.

    It minimizes the larger of the two agents' margins ``max_k Phi^-1(1 - eps_k) sigma_k``
    over splits with ``eps_lo + eps_hi = eps``: the lower agent's margin decreases in
    ``s`` and the higher one's increases, so the minimum of their max is where they meet
    (found by bisection; the ends are used if they never meet).

    Args:
        sigma_lo: the lower-indexed agent's standard deviation along the normal (>= 0).
        sigma_hi: the higher-indexed agent's (>= 0).
        eps: the pair's total risk, in (0, 1).
        tol: bisection tolerance on ``s``.
    """
    from statistics import NormalDist

    q = NormalDist().inv_cdf

    def excess(s: float) -> float:  # decreasing in s
        return q(1 - eps * s) * sigma_lo - q(1 - eps * (1 - s)) * sigma_hi

    lo, hi = 1e-15, 1 - 1e-15
    if excess(lo) <= 0:
        return lo
    if excess(hi) >= 0:
        return hi
    while hi - lo > tol:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if excess(mid) > 0 else (lo, mid)
    return 0.5 * (lo + hi)


def tuned_payload(cfg: Config, params: TuningParameters, tuner: Tuner | None = None,
                  edges: Sequence[Sequence[int]] | None = None, extra: Mapping[str, Any] | None = None
                  ) -> dict[str, Any]:
    """The content of ``tuned.json``.

    ``config`` holds every flat config key with ``rho`` the tuned penalty and
    ``risk_split`` the mean tuned split over ``edges`` (``Config`` has one scalar
    split), so ``gpmpc run --config tuned.json`` accepts it; the per-edge splits are in
    ``risk_split_per_edge`` (``"lo_hi"`` keys; read them with :func:`load_risk_split`).
    """
    rho = float(params.rho().detach())
    mean_split = min(max(params.mean_split(edges), 1e-9), 1 - 1e-9)
    config = cfg.replace(rho=rho, risk_split=mean_split).to_dict()
    payload: dict[str, Any] = {
        "config": config,
        "risk_split_per_edge": params.split_per_edge(edges),
        "history": [r.to_dict() for r in tuner.history] if tuner is not None else [],
    }
    if extra:
        payload.update(extra)
    return payload


def load_risk_split(path: str | Path, num_agents: int) -> Tensor:
    """The per-edge split of a ``tuned.json`` as a (K, K) tensor for ``ADMM.solve_step``.

    Pairs missing from ``risk_split_per_edge`` get the file's scalar ``risk_split``.

    Raises:
        GpmpcError: unreadable file or a key naming an agent >= ``num_agents``.
    """
    try:
        data = json.loads(Path(path).read_text())
        default = float(data["config"]["risk_split"])
        per_edge = data.get("risk_split_per_edge", {})
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise GpmpcError(f"{str(path)!r} is not a tuned.json from gpmpc tune: {exc}") from exc
    out = torch.full((num_agents, num_agents), default, dtype=torch.float64)
    for key, value in per_edge.items():
        lo, hi = (int(v) for v in key.split("_"))
        if max(lo, hi) >= num_agents:
            raise GpmpcError(f"{str(path)!r}: risk_split_per_edge has pair {key} but the run has {num_agents} agents")
        out[lo, hi] = float(value)
    return out
