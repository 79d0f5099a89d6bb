"""The centralized solve of one convexified step problem: the optimum ADMM should reach.

Consensus ADMM splits one joint problem over the agents; this module states that joint
problem directly, with cvxpy, from the same per-agent data the local solvers get
(:class:`~torch_gpmpc.control.problem.LocalProblemData`), with every neighbour copy
``Y_{k,j}`` replaced by agent j's own plan ``X_j``::

    minimize    sum_k ||X_k - Xref_k||^2 + alpha ||U_k||^2 (or each agent's stated cost) [+ beta sum_t ||U_k,t - U_k,t-1||^2] + slack_penalty sum(s)
    subject to  X_k,0 = x0_k,  X_k,tau+1 = dyn_A X_k,tau + dyn_B U_k,tau + dyn_c
                input bounds, soft state constraints (:mod:`torch_gpmpc.control.constraints`)
                n_{k,m,tau}^T (X_k,tau - X_j,tau) + s_{k,m,tau} >= bound_{k,m,tau},  s >= 0

for every agent k, active slot m (neighbour j) and tau = 1..T. It is the independent
answer for tests and, as :class:`CentralizedPlanner`, the baseline of the evaluation; it is
not a controller an agent could run (it needs every agent's data in one place).
"""

from __future__ import annotations

from dataclasses import dataclass

import cvxpy as cp
import numpy as np
import torch
from torch import Tensor

from torch_gpmpc.control.constraints import LocalConstraints
from torch_gpmpc.control.cost import plan_tracking_cost
from torch_gpmpc.control.problem import LocalProblemData, input_rate_cost
from torch_gpmpc.control.solvers.conic import input_changes, state_constraints
from torch_gpmpc.coordination.admm import ADMM
from torch_gpmpc.coordination.agent_step import LocalStep, edge_variances, slot_risks
from torch_gpmpc.coordination.graph import Graph
from torch_gpmpc.coordination.state import ADMMState, StepResult, adapt_state, initial_state
from torch_gpmpc.dynamics.systems import NominalModel
from torch_gpmpc.errors import GpmpcError


@dataclass
class CentralizedSolution:
    """Optimum of the joint problem.

    Attributes:
        plans: (K, T+1, n) states.
        inputs: (K, T, m) inputs.
        cost: the optimal objective (tracking + effort + slack penalty).
    """

    plans: Tensor
    inputs: Tensor
    cost: float


def plan_cost(plans: Tensor, inputs: Tensor, xref: Tensor, alpha: float, input_rate_weight: float = 0.0,
              u_prev: Tensor | None = None, problem: LocalProblemData | None = None) -> float:
    """The agents' summed MPC cost ``sum_k ||X_k - Xref_k||^2 + alpha ||U_k||^2`` (no slack), or the
    stated cost of ``problem`` (its ``cost_Q``, ...), plus ``beta sum_t ||U_k,t - U_k,t-1||^2`` with
    ``beta = input_rate_weight``.

    Args:
        plans: (K, T+1, n); inputs: (K, T, m); xref: (K, T+1, n); u_prev: (K, m) ``U_{-1}`` (``None``: 0).
    """
    rate = input_rate_cost(inputs, u_prev, input_rate_weight).sum()
    weights = (None,) * 4 if problem is None else (problem.cost_Q, problem.cost_R, problem.cost_P, problem.u_ref)
    return float(plan_tracking_cost(plans, inputs, xref, alpha, *weights).sum() + rate)


def tracking_cost(X: cp.Variable, U: cp.Variable, xref: np.ndarray, alpha: float, Q: np.ndarray | None = None,
                  R: np.ndarray | None = None, P: np.ndarray | None = None, u_ref: np.ndarray | None = None):
    """One agent's tracking cost in cvxpy: ``||X - Xref||^2 + alpha ||U||^2``, or the stated cost
    (:mod:`~torch_gpmpc.control.cost`) when Q, R, P ((n, n), (m, m), (n, n)) are given."""
    if Q is None:
        return cp.sum_squares(X - xref) + alpha * cp.sum_squares(U)
    T = U.shape[0]
    du = U if u_ref is None else U - np.ones((T, 1)) @ u_ref[None, :]
    psd = cp.psd_wrap
    return sum(cp.quad_form(X[t] - xref[t], psd(Q)) + cp.quad_form(du[t], psd(R)) for t in range(T)) \
        + cp.quad_form(X[T] - xref[T], psd(P))


def solve_centralized(data: LocalProblemData, graph: Graph, nominal: NominalModel, u_max: float | None = None,
                      alpha: float = 1e-3, slack_penalty: float = 1e4,
                      constraints: LocalConstraints | None = None, input_rate_weight: float = 0.0) -> CentralizedSolution:
    """Solve the joint problem (module docstring) with Clarabel.

    Args:
        data: the K agents' convexified local problems (the consensus fields are ignored).
        graph: the communication graph the slots refer to.
        nominal: the model (input bound, state bound, B where ``data.dyn_B`` is None).
        u_max: input norm bound (``None``: the model's; ignored if the model has only a box).
        alpha, slack_penalty: the local problems' weights (a stated cost in ``data`` replaces alpha's).
        constraints: input bounds and soft state constraints (``None``: the model's with ``u_max``).
        input_rate_weight: beta of the input-rate term (``U_{-1}`` is ``data.u_prev``).

    Raises:
        GpmpcError: the solver did not find an optimum.
    """
    constraints = constraints or LocalConstraints.of(nominal.spec, u_max)
    K, T, n = data.xref.shape[0], data.xref.shape[1] - 1, data.xref.shape[2]
    m = nominal.input_dim
    npy = lambda t: t.detach().cpu().numpy()  # noqa: E731
    dyn_A, dyn_c, xref, x0 = npy(data.dyn_A), npy(data.dyn_c), npy(data.xref), npy(data.x0)
    dyn_B = npy(data.dyn_B) if data.dyn_B is not None else np.broadcast_to(npy(nominal.B()), (K, T, n, m))
    X = [cp.Variable((T + 1, n)) for _ in range(K)]
    U = [cp.Variable((T, m)) for _ in range(K)]
    cost, cons = 0, []
    u_prev = np.zeros((K, m)) if data.u_prev is None else npy(data.u_prev)
    for k in range(K):
        cost += tracking_cost(X[k], U[k], xref[k], alpha, *[None if w is None else npy(w[k]) for w in
                                                            (data.cost_Q, data.cost_R, data.cost_P, data.u_ref)])
        if input_rate_weight:
            cost += input_rate_weight * input_changes(U[k], u_prev[k])
        cons.append(X[k][0] == x0[k])
        cons += [X[k][t + 1] == dyn_A[k, t] @ X[k][t] + dyn_B[k, t] @ U[k][t] + dyn_c[k, t] for t in range(T)]
        halfspaces = [] if data.halfspace_normals is None else \
            [(npy(data.halfspace_normals[k, j]), npy(data.halfspace_bounds[k, j]))
             for j in range(data.halfspace_normals.shape[1])]
        local, penalty = state_constraints(X[k], U[k], constraints, slack_penalty, halfspaces)
        cons += local
        cost += penalty
    normals, bounds = npy(data.normals), npy(data.bounds)
    active = data.active.cpu().numpy()
    for k in range(K):
        for slot in range(active.shape[1]):
            if not active[k, slot]:
                continue
            j = int(graph.slot_nbr[k, slot])
            s = cp.Variable(T, nonneg=True)
            gap = cp.sum(cp.multiply(normals[k, slot], X[k][1:] - X[j][1:]), axis=1)
            cons.append(gap + s >= bounds[k, slot])
            cost += slack_penalty * cp.sum(s)
    problem = cp.Problem(cp.Minimize(cost), cons)
    problem.solve(solver=cp.CLARABEL)
    if problem.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE):
        raise GpmpcError(f"centralized step problem: solver status {problem.status}")
    as_t = lambda v: torch.as_tensor(np.stack([x.value for x in v]), dtype=data.x0.dtype)  # noqa: E731
    return CentralizedSolution(as_t(X), as_t(U), float(problem.value))


class CentralizedPlanner:
    """Closed-loop baseline: every step, the joint problem solved centrally, re-linearized
    around its own solution ``relinearizations`` times (sequential convex programming).

    It convexifies exactly as the agents do (:meth:`~torch_gpmpc.coordination.agent_step.
    LocalStep.assemble`: GP linearization, collision normals, pair margins) and follows the
    :class:`~torch_gpmpc.sim.closed_loop.Planner` protocol, so ``run_closed_loop`` runs it.
    ``StepResult.iterations`` counts the centralized solves.

    Args:
        step: the agents' per-agent step (its settings, model and convexification are used;
            an :class:`~torch_gpmpc.coordination.admm.ADMM` passes its own).
        relinearizations: joint solves per control step.
    """

    def __init__(self, step: LocalStep | ADMM, relinearizations: int = 3) -> None:
        if relinearizations < 1:
            raise GpmpcError(f"relinearizations must be >= 1, got {relinearizations}")
        self.step = step.agent_step if isinstance(step, ADMM) else step
        self.relinearizations = int(relinearizations)
        self.warm: ADMMState | None = None

    def plan(self, t: int, x: Tensor, xref: Tensor, graph: Graph) -> StepResult:
        """Solve step ``t`` centrally; keep the shifted plans as the next linearization point."""
        cfg, local = self.step.settings, self.step
        state = initial_state(x, cfg.horizon, graph, local.nominal.input_dim) if self.warm is None \
            else adapt_state(self.warm, graph)
        eps_self = slot_risks(graph, cfg.eps, cfg.risk_split)
        rho = torch.as_tensor(cfg.rho, dtype=x.dtype)
        with torch.no_grad():
            for _ in range(self.relinearizations):
                assembled = local.assemble(x, xref, state, graph, rho, eps_self,
                                           u_prev=None if self.warm is None else self.warm.applied)
                sol = solve_centralized(assembled.data, graph, local.nominal, None, cfg.alpha, cfg.slack_penalty,
                                        local.constraints, cfg.input_rate_weight)
                pvar = state.pvar if assembled.own_variance is None else \
                    edge_variances(assembled.own_variance, graph, state.pvar)
                z = sol.plans[graph.edges] if graph.num_edges else state.z
                state = ADMMState(sol.plans, sol.inputs, graph.edges, z, torch.zeros_like(state.lam), pvar)
        self.warm = state.shifted()
        return StepResult(plans=sol.plans, inputs=sol.inputs, state=state, iterations=self.relinearizations,
                          converged=True, problem=assembled.data, messages=torch.zeros(graph.num_agents))
