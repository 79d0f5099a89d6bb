"""Training and held-out instances of the tuning objective: start states near the crossing,
references and fixed noise, optionally warm-started from a converged ADMM iterate."""

from __future__ import annotations

import logging

from dataclasses import dataclass
from typing import Sequence
import torch
from torch import Tensor
from torch_gpmpc.coordination.admm import ADMM, ADMMState
from torch_gpmpc.config.schema import Config
from torch_gpmpc.coordination.bodies import pair_distances
from torch_gpmpc.coordination.graph import communication_graph
from torch_gpmpc.dynamics.systems import NominalModel
from torch_gpmpc.sim.scenarios import Scenario, make_scenario
from torch_gpmpc.config.tune_settings import TuneSettings

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class TuneInstance:
    """One training situation: a start, a reference and fixed closed-loop noise.

    Attributes:
        x0: start states, shape (K, D) (at rest: positions set, other states 0).
        scenario: gives the reference windows.
        t0: reference time index of the start.
        noise: standard-normal process noise of the closed-loop steps, shape (S, K, R) (R residual rows)
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
    than their collision distance (``r_safe``, or ``r_k + r_j`` with ``radii``) are pushed apart
    along their difference (so the local problems start feasible).

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
    nominal = NominalModel(cfg.model_spec())
    t0 = crossing_index(scenario, settings.crossing_distance)
    base = scenario.reference_window(t0, 0)[:, 0]  # (K, P) positions
    distances = pair_distances(cfg.radii, cfg.r_safe, base.shape[0])
    out = []
    for seed in seeds:
        gen = torch.Generator().manual_seed(int(seed))
        p0 = base + settings.perturb_std * torch.randn(base.shape, generator=gen, dtype=torch.float64)
        x0 = nominal.states_at(_separate(p0, distances))
        noise = torch.randn(settings.mpc_steps, base.shape[0], len(nominal.residual), generator=gen,
                            dtype=torch.float64)
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
    dual = {"admm_dual_tol": tol} if admm.settings.admm_coupling == "copies" else {}  # the planes have none
    solver = admm.with_settings(admm_tol=tol, admm_max_iter=max_iter, **dual)
    cfg, nominal = solver.settings, admm.nominal
    out = []
    with torch.no_grad():
        for inst in instances:
            t_prev = max(inst.t0 - 1, 0)
            step = inst.scenario.reference_window(inst.t0, 0)[:, 0] - inst.scenario.reference_window(t_prev, 0)[:, 0]
            x_prev = inst.x0 - nominal.states_at(step)
            graph = communication_graph(nominal.positions(x_prev), cfg.comm_radius)
            xref = nominal.reference_states(inst.scenario.reference_window(t_prev, cfg.horizon))
            res = solver.solve_step(x_prev, xref, graph,
                                    rho=float(rho), safety_fallback=False)
            if not res.converged:
                log.warning("warm start of %s did not converge in %d iterations (primal %.2e, dual %.2e)",
                            inst.name, max_iter, res.primal_residuals[-1], res.dual_residuals[-1])
            warm = res.state.shifted() if inst.t0 > 0 else res.state
            out.append(TuneInstance(inst.x0, inst.scenario, inst.t0, inst.noise, inst.name, warm.detached()))
    return out


def _separate(x: Tensor, distances: Tensor, iters: int = 20) -> Tensor:
    """Push pairs closer than 1.05 times their distance apart symmetrically (a few sweeps).

    Args:
        x: (K, P) positions.
        distances: (K, K) each pair's collision distance ``r_k + r_j`` (``r_safe`` without radii).
    """
    x = x.clone()
    for _ in range(iters):
        moved = False
        for i in range(x.shape[0]):
            for j in range(i + 1, x.shape[0]):
                d = x[i] - x[j]
                dist = float(d.norm())
                need = 1.05 * float(distances[i, j])
                if dist < need:
                    direction = d / dist if dist > 1e-12 else torch.eye(x.shape[1], dtype=x.dtype)[0]
                    push = 0.5 * (need - dist) + 1e-9
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
