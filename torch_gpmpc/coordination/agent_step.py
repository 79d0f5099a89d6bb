"""The per-agent part of one ADMM iteration, shared by the in-process ADMM and a
distributed agent: assemble the local problems, solve them with failures isolated, fall
back to the previous plan where a solve failed, and form the copies sent to neighbours.

Every function works on a batch of agents (rows of the graph); a distributed agent
passes its own row, the in-process :class:`~torch_gpmpc.coordination.admm.ADMM` all rows,
so both compute the same thing.
"""

from __future__ import annotations

import logging

import torch
from torch import Tensor, nn

from torch_gpmpc.config.schema import Config
from torch_gpmpc.control.linearize import linearize_plan
from torch_gpmpc.control.problem import (
    FAIL_EXCEPTION, FAIL_INACCURATE, FAIL_NONFINITE, FAILURE_KINDS, LocalProblemData, LocalSolution,
)
from torch_gpmpc.control.risk import chance_margins, collision_normals, pair_risks, state_covariances
from torch_gpmpc.control.solvers import make_local_solver
from torch_gpmpc.coordination.graph import Graph
from torch_gpmpc.coordination.state import ADMMState, StepResult
from torch_gpmpc.dynamics.methods import Method
from torch_gpmpc.dynamics.systems import NominalModel, VortexWind
from torch_gpmpc.errors import GpmpcError

log = logging.getLogger(__name__)


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
    split = torch.as_tensor(risk_split, dtype=torch.float64)
    if split.dim() == 2:
        lo, hi = graph.edges[graph.slot_edge, 0], graph.edges[graph.slot_edge, 1]
        split = split[lo, hi] if graph.num_edges else split.new_full(graph.active.shape, 0.5)
    eps_lo, eps_hi = pair_risks(torch.as_tensor(eps, dtype=split.dtype), split)
    eps_lo = eps_lo.expand(graph.active.shape)
    eps_hi = eps_hi.expand(graph.active.shape)
    return torch.where(graph.slot_side == 0, eps_lo, eps_hi)


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


class LocalStep:
    """What each agent does at one ADMM iteration, for a batch of agents.

    Args:
        cfg: run configuration.
        method: the controller method (name or :class:`~torch_gpmpc.dynamics.methods.Method`).
        nominal: the known model f.
        wind: the known wind (``nonlinear`` methods), else ``None``.
        gps: residual GPs indexed by agent id (``gp`` and chance methods), else ``None``;
            a distributed agent holds ``None`` for every agent but itself.
    """

    def __init__(self, cfg: Config, method: str | Method, nominal: NominalModel,
                 wind: VortexWind | None = None, gps: list | None = None) -> None:
        self.cfg = cfg
        self.method = Method.parse(method)
        self.nominal = nominal
        self.wind = wind
        self.gps = gps
        #: failure kinds already warned about (one warning per kind per run)
        self._warned: set[str] = set()

    def solver(self, num_slots: int) -> nn.Module:
        """The shared batched local solver for ``num_slots`` neighbour slots (cached per size)."""
        cfg = self.cfg
        return make_local_solver(
            horizon=cfg.horizon, dim=cfg.dim, num_neighbors=num_slots, nominal=self.nominal,
            u_max=cfg.u_max, alpha=cfg.alpha, slack_penalty=cfg.slack_penalty, solver=cfg.solver,
        )

    def assemble(
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
        if self.method.chance:
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

    def solve(self, layer: nn.Module, data: LocalProblemData) -> LocalSolution:
        """One batched local solve; an exception escaping the layer fails every agent (kind
        ``exception``) instead of ending the run. Input errors (GpmpcError) still raise."""
        try:
            return layer(data)
        except GpmpcError:
            raise
        except Exception as exc:  # noqa: BLE001 - counted and warned by count_failures
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

    def count_failures(self, sol: LocalSolution, result: StepResult) -> None:
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


def fall_back_to_previous(sol: LocalSolution, state: ADMMState, graph: Graph) -> LocalSolution:
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


def edge_copies(sol: LocalSolution, graph: Graph) -> Tensor:
    """Each edge end's copy ``y_{e,a}`` of ``z_e`` (eq. 19): its own plan in its own half, its copy of
    the neighbour's plan in the other; shape (E, 2 [holder], 2 [half], T+1, D).

    Args:
        sol: the local solutions of all agents of ``graph`` (batch K).
        graph: the communication graph.
    """
    copies = sol.X.new_zeros(graph.num_edges, 2, 2, *sol.X.shape[1:])
    k_idx, m_idx = torch.nonzero(graph.active, as_tuple=True)
    e_idx = graph.slot_edge[k_idx, m_idx]
    a_idx = graph.slot_side[k_idx, m_idx]
    copies = copies.index_put((e_idx, a_idx, a_idx), sol.X[k_idx])
    copies = copies.index_put((e_idx, a_idx, 1 - a_idx), sol.Y[k_idx, m_idx])
    return copies
