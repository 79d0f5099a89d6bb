"""Consensus ADMM over the neighbour graph (paper §3.3-3.5, Algorithm 1).

Per edge ``e = (lo, hi)`` the shared vector is ``z_e = [X_lo; X_hi]`` (eq. 18),
shape (2, T+1, D). Agent k keeps a copy ``y_{e,k}`` of it: its own plan in its own
half and its copy of the neighbour's plan in the other. One iteration:

1. linearize: dynamics around each agent's own current plan, collision rows around
   the current plans of both agents of the pair (Algorithm 1, step 9);
2. local solves: all K local problems (27) as **one batched** :class:`LocalMPC` call;
3. consensus ``z_e = (y_{e,lo} + y_{e,hi}) / 2`` (eq. 28);
4. duals ``lam_{e,k} += rho (y_{e,k} - z_e)`` (eq. 29).

Stopping: the largest per-edge primal residual ``||y_{e,k} - z_e||`` is below
``admm_tol`` (the paper's criterion) and, when ``admm_dual_tol`` is set, the dual
residual ``rho ||z_e - z_e_prev||`` is below it too; or ``admm_max_iter``.

Messages: per iteration agent k sends its copy ``y_{e,k}`` (``2 (T+1) D`` numbers)
to each neighbour, i.e. ``2 (T+1) D |N_k|`` numbers. The paper counts
``2 D_x T |N_k|`` because its T indexes the T+1 points ``t..t+T`` as T vectors; we
report ours.

Everything is torch: with gradients enabled, an unrolled ADMM is differentiable in
rho, the risk split and the problem data (used by ``gpmpc tune``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import torch
from torch import Tensor

from torch_gpmpc.config.schema import Config
from torch_gpmpc.coordination.graph import Graph
from torch_gpmpc.control.linearize import linearize_plan
from torch_gpmpc.dynamics.methods import Method
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.control.problem import FAILURE_KINDS, FAIL_EXCEPTION, FAIL_INACCURATE, FAIL_NONFINITE, LocalProblemData, \
    LocalSolution, get_local_mpc
from torch_gpmpc.control.risk import chance_margins, collision_normals, pair_risks, state_covariances
from torch_gpmpc.dynamics.systems import NominalModel, VortexWind

log = logging.getLogger(__name__)


@dataclass
class ADMMState:
    """Warm-startable iterate of one time step.

    Attributes:
        plans: (K, T+1, D) each agent's own planned states (also the linearization points).
        inputs: (K, T, D) each agent's planned inputs.
        edges: (E, 2) the edges ``z`` and ``lam`` belong to.
        z: (E, 2, T+1, D) consensus trajectories ``[X_lo; X_hi]`` per edge.
        lam: (E, 2, 2, T+1, D) duals; ``lam[e, a]`` is held by the edge's end ``a``
            (0 = lo, 1 = hi) and has the shape of ``z_e``.
    """

    plans: Tensor
    inputs: Tensor
    edges: Tensor
    z: Tensor
    lam: Tensor

    def shifted(self) -> "ADMMState":
        """Shift everything one step forward in time (drop the first point, hold the last)."""
        return ADMMState(
            plans=_shift(self.plans, dim=1),
            inputs=_shift(self.inputs, dim=1),
            edges=self.edges,
            z=_shift(self.z, dim=2),
            lam=_shift(self.lam, dim=3),
        )


@dataclass
class StepResult:
    """Outcome of ADMM at one time step.

    Attributes:
        plans: (K, T+1, D) final planned states.
        inputs: (K, T, D) final planned inputs (apply ``inputs[:, 0]``).
        state: the final :class:`ADMMState` (shift it to warm-start the next step).
        iterations: ADMM iterations run.
        converged: whether the stopping criterion was met.
        primal_residuals: per iteration, largest ``||y_{e,k} - z_e||``.
        dual_residuals: per iteration, largest ``rho ||z_e - z_e_prev||``.
        slack_max: largest collision slack of the final iterate.
        infeasible_solves: local solves with active slack or failure, summed over iterations.
        failed_solves: local solves that failed (fallback plan used), summed over iterations.
        failed_by_kind: ``failed_solves`` split by kind, ``{kind: count}`` for every kind
            in :data:`~torch_gpmpc.control.solvers.conic.FAILURE_KINDS` (exception, non-finite, inaccurate).
        solve_time_s: seconds spent in local solves.
        max_margin: largest chance margin of the final iterate (0 for deterministic methods).
        messages: (K,) numbers each agent sends per iteration.
        solution: the final :class:`LocalSolution` (kept for gradients and diagnostics).
    """

    plans: Tensor
    inputs: Tensor
    state: ADMMState
    iterations: int
    converged: bool
    primal_residuals: list[float] = field(default_factory=list)
    dual_residuals: list[float] = field(default_factory=list)
    slack_max: float = 0.0
    infeasible_solves: int = 0
    failed_solves: int = 0
    failed_by_kind: dict[str, int] = field(default_factory=lambda: dict.fromkeys(FAILURE_KINDS, 0))
    solve_time_s: float = 0.0
    max_margin: float = 0.0
    messages: Tensor | None = None
    solution: LocalSolution | None = None


def _shift(x: Tensor, dim: int) -> Tensor:
    """Drop index 0 along ``dim`` and repeat the last entry (warm start by one step)."""
    if x.shape[dim] == 0:
        return x
    last = x.narrow(dim, x.shape[dim] - 1, 1)
    return torch.cat([x.narrow(dim, 1, x.shape[dim] - 1), last], dim=dim)


def initial_state(x0: Tensor, horizon: int, graph: Graph) -> ADMMState:
    """Cold start: every agent plans to stay where it is; z from those plans, lam = 0.

    Args:
        x0: (K, D) current states.
        horizon: T.
        graph: the communication graph.
    """
    plans = x0.unsqueeze(1).expand(-1, horizon + 1, -1).clone()
    inputs = x0.new_zeros(x0.shape[0], horizon, x0.shape[1])
    z = plans[graph.edges].clone() if graph.num_edges else x0.new_zeros(0, 2, horizon + 1, x0.shape[1])
    lam = x0.new_zeros(graph.num_edges, 2, 2, horizon + 1, x0.shape[1])
    return ADMMState(plans, inputs, graph.edges, z, lam)


def adapt_state(state: ADMMState, graph: Graph) -> ADMMState:
    """Carry ``z``/``lam`` over to a new graph: kept edges keep theirs, new edges start
    from the current plans with zero duals."""
    if torch.equal(state.edges, graph.edges):
        return state
    old = {tuple(e.tolist()): i for i, e in enumerate(state.edges)}
    z = state.plans[graph.edges].clone() if graph.num_edges else state.z[:0]
    lam = state.lam.new_zeros(graph.num_edges, *state.lam.shape[1:])
    for i, e in enumerate(graph.edges.tolist()):
        if tuple(e) in old:
            z[i] = state.z[old[tuple(e)]]
            lam[i] = state.lam[old[tuple(e)]]
    return ADMMState(state.plans, state.inputs, graph.edges, z, lam)


def slot_risks(graph: Graph, eps: float | Tensor, risk_split: float | Tensor) -> Tensor:
    """Each agent's own risk ``eps_k`` on each of its edges (eq. 21).

    Args:
        graph: the communication graph.
        eps: total risk per pair.
        risk_split: share of the lower-indexed agent; a scalar or a (K, K) tensor whose
            entry ``[lo, hi]`` is used for edge ``(lo, hi)``.

    Returns:
        (K, M) risk of agent k on slot m (padding slots get ``eps / 2``).
    """
    split = torch.as_tensor(risk_split, dtype=torch.get_default_dtype())
    if split.dim() == 2:
        lo, hi = graph.edges[graph.slot_edge, 0], graph.edges[graph.slot_edge, 1]
        split = split[lo, hi] if graph.num_edges else split.new_full(graph.active.shape, 0.5)
    eps_lo, eps_hi = pair_risks(torch.as_tensor(eps, dtype=split.dtype), split)
    eps_lo = eps_lo.expand(graph.active.shape)
    eps_hi = eps_hi.expand(graph.active.shape)
    return torch.where(graph.slot_side == 0, eps_lo, eps_hi)


def consensus_update(copies: Tensor, z: Tensor, lam: Tensor, rho: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Consensus (eq. 28) and dual (eq. 29) updates of every edge.

    Args:
        copies: (E, 2 [holder], 2 [half], T+1, D) both ends' copies ``y_{e,a}`` of ``z_e``.
        z: (E, 2, T+1, D) previous consensus.
        lam: (E, 2, 2, T+1, D) previous duals, ``lam[e, a]`` held by end ``a``.
        rho: ADMM penalty.

    Returns:
        ``(z_new (E, 2, T+1, D), lam_new (E, 2, 2, T+1, D), primal (E, 2), dual (E,))`` with
        ``primal[e, a] = ||y_{e,a} - z_new_e||`` and ``dual[e] = rho ||z_new_e - z_e||``.
    """
    z_new = copies.mean(dim=1)
    gap = copies - z_new.unsqueeze(1)
    lam_new = lam + rho * gap
    primal = gap.flatten(2).norm(dim=2)
    dual = rho * (z_new - z).flatten(1).norm(dim=1)
    return z_new, lam_new, primal, dual


def _wrapped_interrupt(exc: BaseException) -> BaseException | None:
    """The KeyboardInterrupt (or other non-``Exception``) in ``exc``'s cause/context chain, if any.

    C extensions can turn a signal that arrives while they call back into Python into an
    ordinary error (CPython: "SystemError: ... returned a result with an exception set").
    """
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if not isinstance(exc, Exception):
            return exc
        exc = exc.__cause__ or exc.__context__
    return None


def should_stop(primal: float, dual: float, tol: float, dual_tol: float | None) -> bool:
    """The stopping rule: largest primal residual below ``tol`` (the paper's criterion) and,
    when ``dual_tol`` is set, largest dual residual below it too."""
    return primal < tol and (dual_tol is None or dual < dual_tol)


class ADMM:
    """Consensus ADMM for K agents' local MPC problems (Algorithm 1, all agents batched).

    Args:
        cfg: run configuration (horizon, rho, r_safe, eps, risk_split, tolerances, ...).
        method: one of the six method names.
        nominal: the known model f.
        wind: the known wind (needed by the ``nonlinear`` methods).
        gps: one residual GP per agent (needed by ``gp*`` and ``*-chance`` methods).
    """

    def __init__(
        self,
        cfg: Config,
        method: str | None = None,
        nominal: NominalModel | None = None,
        wind: VortexWind | None = None,
        gps: list | None = None,
    ) -> None:
        self.cfg = cfg
        self.method = method or cfg.method
        self.nominal = nominal or NominalModel(dim=cfg.dim)
        self.wind = wind
        self.gps = gps
        self.chance = Method.parse(self.method).chance
        #: failure kinds already warned about (one warning per kind per ADMM object, i.e. per run)
        self._warned: set[str] = set()

    def _layer(self, num_slots: int):
        cfg = self.cfg
        return get_local_mpc(
            horizon=cfg.horizon, dim=cfg.dim, num_neighbors=num_slots, nominal=self.nominal,
            u_max=cfg.u_max, alpha=cfg.alpha, slack_penalty=cfg.slack_penalty, solver=cfg.solver,
        )

    def _problem_data(
        self, x0: Tensor, xref: Tensor, state: ADMMState, graph: Graph, rho: Tensor, eps_self: Tensor,
        rows: slice = slice(None),
    ) -> tuple[LocalProblemData, Tensor]:
        """Linearize around the current plans and assemble the local problems of agents ``rows``.

        Args:
            x0, xref: measured states and reference windows of the selected agents,
                shapes (B, D) and (B, T+1, D).
            state: current iterate; ``plans`` must hold the selected agents and their neighbours.
            graph: communication graph.
            rho: ADMM penalty.
            eps_self: (B, M) own risk per slot of the selected agents.
            rows: which agents (B of them): all by default; an agent process passes its own row.
                ``self.gps`` is indexed by agent id (an agent process may hold ``None`` for others).

        Returns:
            ``(data with batch B, largest chance margin of an active row (scalar))``.
        """
        cfg = self.cfg
        xbar = state.plans[rows]
        gps = None if self.gps is None else self.gps[rows]
        lin = linearize_plan(self.method, xbar, self.nominal, self.wind, gps,
                             include_noise=cfg.gp_noise_in_margin)
        slot_nbr, side, active = graph.slot_nbr[rows], graph.slot_side[rows], graph.active[rows]
        agent_ids = torch.arange(graph.num_agents)[rows]
        normals = collision_normals(xbar, state.plans[slot_nbr], agent_ids, slot_nbr)
        if self.chance:
            sigma = state_covariances(cfg.uncertainty, lin.var, lin.dyn_A)
            margins = chance_margins(normals, sigma, eps_self)
        else:
            margins = normals.new_zeros(normals.shape[:3])
        bounds = cfg.r_safe + margins
        r = torch.arange(agent_ids.shape[0])[:, None]
        c = torch.arange(graph.num_slots)[None, :]
        z_slot = state.z[graph.slot_edge[rows]]  # (B, M, 2, T+1, D)
        lam_mine = state.lam[graph.slot_edge[rows]][r, c, side]  # (B, M, 2, T+1, D): this agent's duals
        data = LocalProblemData(
            x0=x0,
            xref=xref,
            dyn_A=lin.dyn_A,
            dyn_c=lin.dyn_c,
            normals=normals[:, :, 1:],
            bounds=bounds[:, :, 1:],
            active=active,
            rho=rho,
            z_own=z_slot[r, c, side],
            z_nbr=z_slot[r, c, 1 - side],
            lam_own=lam_mine[r, c, side],
            lam_nbr=lam_mine[r, c, 1 - side],
        )
        max_margin = margins[:, :, 1:][active].max() if bool(active.any()) else margins.new_zeros(())
        return data, max_margin

    def _edge_copies(self, sol: LocalSolution, graph: Graph) -> Tensor:
        """Each edge end's copy ``y_{e,a}`` of ``z_e``, shape (E, 2 [holder], 2 [half], T+1, D)."""
        copies = sol.X.new_zeros(graph.num_edges, 2, 2, *sol.X.shape[1:])
        k_idx, m_idx = torch.nonzero(graph.active, as_tuple=True)
        e_idx = graph.slot_edge[k_idx, m_idx]
        a_idx = graph.slot_side[k_idx, m_idx]
        copies = copies.index_put((e_idx, a_idx, a_idx), sol.X[k_idx])
        copies = copies.index_put((e_idx, a_idx, 1 - a_idx), sol.Y[k_idx, m_idx])
        return copies

    def _solve(self, layer, data: LocalProblemData) -> LocalSolution:
        """One batched local solve; an exception escaping the layer fails every agent (kind
        ``exception``) instead of ending the run. Input errors (GpmpcError) still raise."""
        try:
            return layer(data)
        except GpmpcError:
            raise
        except Exception as exc:  # noqa: BLE001 - counted and warned by _fallback
            interrupt = _wrapped_interrupt(exc)
            if interrupt is not None:  # Ctrl-C that C code turned into an error: stop, do not fall back
                raise interrupt
            batch, T, D = data.xref.shape[0], data.xref.shape[1] - 1, data.xref.shape[2]
            M = data.active.shape[1]
            nan = data.xref.new_full((), float("nan"))
            return LocalSolution(
                X=nan.expand(batch, T + 1, D).clone(), U=nan.expand(batch, T, D).clone(),
                Y=nan.expand(batch, M, T + 1, D).clone(), slack=nan.expand(batch, M, T).clone(),
                slack_active=torch.zeros(batch, dtype=torch.bool), ok=torch.zeros(batch, dtype=torch.bool),
                cost=nan.expand(batch).clone(), failure=torch.full((batch,), FAIL_EXCEPTION),
                failure_detail=f"{type(exc).__name__}: {exc}")

    def _count_failures(self, sol: LocalSolution, result: StepResult) -> None:
        """Add this iteration's failed solves to ``result`` and warn once per kind per run."""
        bad = ~sol.ok
        if not bool(bad.any()):
            return
        if sol.failure is not None:
            codes = sol.failure
        else:  # a layer that does not report kinds: infer them
            finite = torch.isfinite(sol.X).flatten(1).all(1) & torch.isfinite(sol.U).flatten(1).all(1)
            codes = torch.where(finite, torch.full_like(bad, FAIL_INACCURATE, dtype=torch.int64),
                                torch.full_like(bad, FAIL_NONFINITE, dtype=torch.int64))
        result.failed_solves += int(bad.sum())
        for i, kind in enumerate(FAILURE_KINDS):
            agents = (bad & (codes == i + 1)).nonzero().flatten().tolist()
            if not agents:
                continue
            result.failed_by_kind[kind] += len(agents)
            if kind not in self._warned:
                self._warned.add(kind)
                detail = f" ({sol.failure_detail})" if kind == "exception" and sol.failure_detail else ""
                log.warning("local MPC solve failed (%s%s) for agent(s) %s; using their previous (shifted) "
                            "plans. Further %s failures are not logged again; they are counted in "
                            "metrics.json 'failed_local_solves'", kind, detail, agents, kind)
            else:
                log.debug("local MPC solve failed (%s) for agent(s) %s; previous plans used", kind, agents)

    def _fallback(self, sol: LocalSolution, state: ADMMState, graph: Graph) -> LocalSolution:
        """Replace failed agents' solutions by their previous plans (a safe, feasible guess).

        At the first ADMM iteration of a step the previous plan is the last step's plan
        shifted by one step (the warm start); later it is the previous iterate.
        """
        bad = ~sol.ok
        if not bool(bad.any()):
            return sol
        X = torch.where(bad[:, None, None], state.plans, sol.X)
        U = torch.where(bad[:, None, None], state.inputs, sol.U)
        nbr_prev = state.plans[graph.slot_nbr]
        Y = torch.where(bad[:, None, None, None], nbr_prev, sol.Y)
        return LocalSolution(X=X, U=U, Y=Y, slack=torch.where(bad[:, None, None], torch.zeros_like(sol.slack), sol.slack),
                             slack_active=sol.slack_active, ok=sol.ok, cost=sol.cost, failure=sol.failure,
                             failure_detail=sol.failure_detail)

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
    ) -> StepResult:
        """Run ADMM for one time step.

        Args:
            x0: (K, D) measured states.
            xref: (K, T+1, D) reference window.
            graph: communication graph at this step.
            warm: previous step's state, already shifted (cold start if ``None``).
            rho: penalty (defaults to ``cfg.rho``); a tensor keeps gradients.
            risk_split: scalar or (K, K) split (defaults to ``cfg.risk_split``).
            max_iter: iteration cap (defaults to ``cfg.admm_max_iter``).
            tol: primal tolerance (defaults to ``cfg.admm_tol``).
        """
        cfg = self.cfg
        rho_t = torch.as_tensor(cfg.rho if rho is None else rho, dtype=x0.dtype)
        eps_self = slot_risks(graph, cfg.eps, cfg.risk_split if risk_split is None else risk_split)
        max_iter = cfg.admm_max_iter if max_iter is None else max_iter
        tol = cfg.admm_tol if tol is None else tol
        state = initial_state(x0, cfg.horizon, graph) if warm is None else adapt_state(warm, graph)
        layer = self._layer(graph.num_slots)
        result = StepResult(plans=state.plans, inputs=state.inputs, state=state, iterations=0, converged=False)
        frozen_plans = state.plans
        for it in range(1, max_iter + 1):
            lin_state = state if cfg.relinearize else ADMMState(frozen_plans, state.inputs, state.edges, state.z, state.lam)
            data, max_margin = self._problem_data(x0, xref, lin_state, graph, rho_t, eps_self)
            t0 = time.perf_counter()
            sol = self._solve(layer, data)
            result.solve_time_s += time.perf_counter() - t0
            self._count_failures(sol, result)
            sol = self._fallback(sol, state, graph)
            result.infeasible_solves += int((sol.slack_active | ~sol.ok).sum())
            if graph.num_edges:
                z_new, lam, gap_norms, dual_norms = consensus_update(
                    self._edge_copies(sol, graph), state.z, state.lam, rho_t)
                primal, dual = gap_norms.max(), dual_norms.max()
            else:
                z_new, lam = state.z, state.lam
                primal = dual = x0.new_zeros(())
            state = ADMMState(sol.X, sol.U, graph.edges, z_new, lam)
            result.primal_residuals.append(float(primal.detach()))
            result.dual_residuals.append(float(dual.detach()))
            result.iterations = it
            result.solution = sol
            result.max_margin = float(max_margin.detach())
            if should_stop(result.primal_residuals[-1], result.dual_residuals[-1], tol, cfg.admm_dual_tol):
                result.converged = True
                break
        result.plans, result.inputs, result.state = state.plans, state.inputs, state
        result.slack_max = float(result.solution.slack.max()) if result.solution.slack.numel() else 0.0
        result.messages = 2 * (cfg.horizon + 1) * cfg.dim * graph.degrees()
        return result
