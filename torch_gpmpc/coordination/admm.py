"""Consensus ADMM over the neighbour graph (paper §3.3-3.5, Algorithm 1).

Per edge ``e = (lo, hi)`` the shared vector is ``z_e = [X_lo; X_hi]`` (eq. 18),
shape (2, T+1, D). Agent k keeps a copy ``y_{e,k}`` of it: its own plan in its own
half and its copy of the neighbour's plan in the other. One iteration:

1. linearize: dynamics around each agent's own plan, collision rows around the plans of
   both agents of the pair: once per control step at the warm start (default), or at every
   iterate with ``relinearize = true`` (Algorithm 1, step 9; the moving convexification then
   keeps ADMM from settling: measured on the six-agent circle with admm_rel_tol = 0, 42.5
   instead of 28.4 iterations per step and 17 steps at the iteration cap);
2. local solves: all K local problems (27) as **one batched** :class:`LocalMPC` call;
3. consensus ``z_e = (y_{e,lo} + y_{e,hi}) / 2`` (eq. 28);
4. duals ``lam_{e,k} += rho_e (y_{e,k} - z_e)`` (eq. 29);
5. with ``rho_update = adaptive`` (default), each edge's ``rho_e`` by residual balancing.

Stopping (:mod:`~torch_gpmpc.coordination.penalty`): with ``admm_stop = primal-dual``
(default) every edge's primal residual ``||y_{e,k} - z_e||`` and dual residual
``rho_e ||z_e - z_e_prev||`` are below their absolute-plus-relative tolerances (Boyd et al.
2011 §3.3.1); with ``primal`` (the paper's rule) the primal one below ``admm_tol`` (and the
dual one below ``admm_dual_tol`` if set); or ``admm_max_iter``. The primal-only rule at a
fixed rho stops on a feasible consensus that is not yet optimal.

Messages: per iteration agent k sends its copy ``y_{e,k}`` (``2 (T+1) D`` numbers)
to each neighbour, i.e. ``2 (T+1) D |N_k|`` numbers. The paper counts
``2 D_x T |N_k|`` because its T indexes the T+1 points ``t..t+T`` as T vectors; we
report ours.

Everything is torch: with gradients enabled, an unrolled ADMM is differentiable in
rho, the risk split and the problem data (used by ``gpmpc tune``).
"""

from __future__ import annotations

import dataclasses
import time

import torch
from torch import Tensor

from torch_gpmpc.config.schema import Config
from torch_gpmpc.coordination.agent_step import (
    LocalStep, edge_copies, edge_variances, fall_back_to_previous, message_size, obstacle_problem, pair_safety,
    slot_risks,
)
from torch_gpmpc.coordination.graph import Graph
from torch_gpmpc.coordination.penalty import balance_penalty, edge_residuals, should_stop, starting_penalties
from torch_gpmpc.coordination.state import ADMMState, StepResult, adapt_state, initial_state
from torch_gpmpc.dynamics.methods import Method
from torch_gpmpc.dynamics.systems import NominalModel, VortexWind

__all__ = ["ADMM", "ADMMState", "StepResult", "adapt_state", "consensus_update", "initial_state"]


def consensus_update(copies: Tensor, z: Tensor, lam: Tensor, rho: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Consensus (eq. 28) and dual (eq. 29) updates of every edge.

    Args:
        copies: (E, 2 [holder], 2 [half], T+1, D) both ends' copies ``y_{e,a}`` of ``z_e``.
        z: (E, 2, T+1, D) previous consensus.
        lam: (E, 2, 2, T+1, D) previous duals, ``lam[e, a]`` held by end ``a``.
        rho: ADMM penalty: a scalar, or (E,) one per edge.

    Returns:
        ``(z_new (E, 2, T+1, D), lam_new (E, 2, 2, T+1, D), primal (E, 2), dual (E,))`` with
        ``primal[e, a] = ||y_{e,a} - z_new_e||`` and ``dual[e] = rho ||z_new_e - z_e||``.
    """
    z_new = copies.mean(dim=1)
    gap = copies - z_new.unsqueeze(1)
    rho_e = rho.reshape(-1, 1, *[1] * (z.dim() - 1)) if rho.dim() == 1 else rho  # per edge: (E, 1, 1, 1, 1)
    lam_new = lam + rho_e * gap
    primal = gap.flatten(2).norm(dim=2)
    dual = rho * (z_new - z).flatten(1).norm(dim=1)
    return z_new, lam_new, primal, dual


class ADMM:
    r"""Consensus ADMM for K agents' local MPC problems (Algorithm 1, all agents batched).

    Per edge ``e = (k, j)`` both agents hold a copy ``y_{e,k} = [X_k; Y_{k,j}]`` of the
    shared trajectories ``z_e = [X_k; X_j]``. One control step solves::

        minimize   sum_k J_k(X_k, U_k)   subject to   y_{e,k} = z_e  for every edge end,

    with ``J_k`` agent k's local MPC cost and constraints (dynamics, input bound, collision
    rows), by iterating, with penalty rho and duals ``lam_{e,k}``:

    1. local step (every agent, in parallel; :class:`~.agent_step.LocalStep`)::

           y_k = argmin J_k + sum_{e in N_k} lam_{e,k}^T (y_{e,k} - z_e) + rho/2 ||y_{e,k} - z_e||^2

    2. consensus ``z_e = (y_{e,k} + y_{e,j}) / 2`` (eq. 28);
    3. duals ``lam_{e,k} += rho (y_{e,k} - z_e)`` (eq. 29).

    Residuals: primal ``r_e = max_k ||y_{e,k} - z_e||``, dual ``s_e = rho_e ||z_e - z_e^prev||``.
    Stopping and the adaptation of ``rho_e`` follow :mod:`~torch_gpmpc.coordination.penalty`;
    the linearization points are the warm start's plans, or the current plans every
    iteration with ``relinearize`` (Algorithm 1, step 9).

    Args:
        cfg: run configuration (horizon, rho, r_safe, eps, risk_split, tolerances, ...).
        method: one of the six method names (default ``cfg.method``).
        nominal: the known model f.
        wind: the known wind (needed by the ``nonlinear`` methods).
        gps: one residual GP per agent (needed by ``gp*`` and ``*-chance`` methods).
    """

    def __init__(
        self,
        cfg: Config,
        method: str | Method | None = None,
        nominal: NominalModel | None = None,
        wind: VortexWind | None = None,
        gps: list | None = None,
    ) -> None:
        self.cfg = cfg
        self.local = LocalStep(cfg, method or cfg.method, nominal or NominalModel(cfg.model_spec()), wind, gps)

    @property
    def gps(self) -> list | None:
        """The agents' residual GPs (indexed by agent id), or ``None``."""
        return self.local.gps

    def with_config(self, cfg: Config) -> "ADMM":
        """The same agents' models (method, nominal model, wind, GPs) under another configuration."""
        return ADMM(cfg, self.local.method, self.local.nominal, self.local.wind, self.local.gps)

    def solve_step(
        self,
        x0: Tensor,
        xref: Tensor,
        graph: Graph,
        warm: ADMMState | None = None,
        rho: float | Tensor | None = None,
        risk_split: float | Tensor | None = None,
        max_iter: int | None = None,
        tol: float | None = None,
        safety_fallback: bool = True,
    ) -> StepResult:
        """Run ADMM for one time step.

        Args:
            x0: (K, D) measured states.
            xref: (K, T+1, D) reference window.
            graph: communication graph at this step.
            warm: previous step's state, already shifted (cold start if ``None``).
            rho: penalty (defaults to ``cfg.rho``); a tensor keeps gradients. With
                ``rho_update = adaptive`` it is the start of every edge the warm state does not
                carry a penalty for (edges carried over keep their adapted one).
            risk_split: scalar or (K, K) split (defaults to ``cfg.risk_split``).
            max_iter: iteration cap (defaults to ``cfg.admm_max_iter``).
            tol: absolute primal tolerance of the stopping rule (defaults to ``cfg.admm_tol``;
                0 never stops early). Penalty balancing always uses the configured tolerances.
            safety_fallback: when ADMM stops unconverged, re-plan the agents of every pair whose
                plans are unsafe at tau = 1 against their neighbours' latest plans as fixed
                obstacles (:func:`~.agent_step.obstacle_problem`); the unrolled ADMM of
                ``gpmpc tune`` turns it off (it stops after every iteration on purpose).
        """
        cfg = self.cfg
        rho_t = torch.as_tensor(cfg.rho if rho is None else rho, dtype=x0.dtype)
        adaptive = cfg.rho_update == "adaptive"
        eps_self = slot_risks(graph, cfg.eps, cfg.risk_split if risk_split is None else risk_split)
        max_iter = cfg.admm_max_iter if max_iter is None else max_iter
        tol = cfg.admm_tol if tol is None else tol
        state = initial_state(x0, cfg.horizon, graph, self.local.nominal.input_dim) if warm is None \
            else adapt_state(warm, graph)
        if adaptive:
            state = dataclasses.replace(state, rho=starting_penalties(state.rho, rho_t, graph.num_edges))
        layer = self.local.solver(graph.num_slots)
        result = StepResult(plans=state.plans, inputs=state.inputs, state=state, iterations=0, converged=False)
        frozen = dataclasses.replace(state)  # the linearization points unless relinearizing
        linearization = None
        for it in range(1, max_iter + 1):
            lin_state = state if cfg.relinearize else \
                dataclasses.replace(state, plans=frozen.plans, inputs=frozen.inputs)
            rho_now = state.rho if adaptive else rho_t
            rho_slots = state.rho[graph.slot_edge] if adaptive and graph.num_edges else rho_t
            assembled = self.local.assemble(x0, xref, lin_state, graph, rho_slots, eps_self,
                                            linearization=linearization)
            if not cfg.relinearize:
                linearization = assembled.linearization
            data = assembled.data
            t0 = time.perf_counter()
            sol = self.local.solve(layer, data)
            result.solve_time_s += time.perf_counter() - t0
            self.local.count_failures(sol, result)
            sol = fall_back_to_previous(sol, state, graph)
            result.infeasible_solves += int((sol.slack_active | ~sol.ok).sum())
            if graph.num_edges:
                copies = edge_copies(sol, graph)
                z_new, lam, gap_norms, dual_norms = consensus_update(copies, state.z, state.lam, rho_now)
                lam_norm = lam[:, 0].flatten(1).norm(dim=1)
                res = edge_residuals(copies, z_new, lam_norm, gap_norms, dual_norms, cfg)
                stop_res = res if tol == cfg.admm_tol else edge_residuals(copies, z_new, lam_norm, gap_norms,
                                                                        dual_norms, cfg, tol)
                primal, dual = res.primal.max(), res.dual.max()
                ratios = (float(stop_res.primal_ratio.max()), float(stop_res.dual_ratio.max()))
                if adaptive:
                    rho_now = balance_penalty(rho_now, res)
            else:
                z_new, lam = state.z, state.lam
                primal = dual = x0.new_zeros(())
                ratios = (0.0, 0.0)
            pvar = state.pvar
            if assembled.own_variance is not None:
                pvar = edge_variances(assembled.own_variance, graph, state.pvar)
            state = ADMMState(sol.X, sol.U, graph.edges, z_new, lam, pvar, rho_now if adaptive else None)
            result.primal_residuals.append(float(primal.detach()))
            result.dual_residuals.append(float(dual.detach()))
            result.iterations = it
            result.solution = sol
            result.problem = data
            result.max_margin = float(assembled.max_margin.detach())
            if should_stop(*ratios, cfg):
                result.converged = True
                break
        if graph.num_edges and result.iterations:
            state = self._check_safety(state, data, graph, layer, result, safety_fallback)
        result.plans, result.inputs, result.state = state.plans, state.inputs, state
        result.slack_max = float(result.solution.slack.max()) if result.solution.slack.numel() else 0.0
        result.messages = message_size(cfg, self.local.method) * graph.degrees()
        return result

    def _check_safety(self, state: ADMMState, data, graph: Graph, layer, result: StepResult,
                      fallback: bool) -> ADMMState:
        """Judge the applied plans at tau = 1 (own plans, not copies); after an unconverged stop,
        re-plan the agents of unsafe pairs against their neighbours' latest plans."""
        bounds = data.bounds[:, :, 0].detach()
        unsafe, sep, req = pair_safety(state.plans.detach(), graph, bounds, self.cfg.admm_tol,
                                       self.local.nominal.position)
        if fallback and not result.converged and bool(unsafe.any()):
            with torch.no_grad():
                sol = self.local.solve(layer, obstacle_problem(data, state.plans[graph.slot_nbr]))
            use = unsafe & sol.ok
            if bool(use.any()):
                state = dataclasses.replace(state, plans=torch.where(use[:, None, None], sol.X, state.plans),
                                            inputs=torch.where(use[:, None, None], sol.U, state.inputs))
                result.fallback = True
                unsafe, sep, req = pair_safety(state.plans.detach(), graph, bounds, self.cfg.admm_tol,
                                               self.local.nominal.position)
        result.unsafe_plan = bool(unsafe.any())
        result.pair_separation, result.pair_required = sep, req
        return state
