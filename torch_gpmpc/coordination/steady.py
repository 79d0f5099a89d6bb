"""ADMM's compiled iterations: a control step's iterations after its second (after its first where
no variances are exchanged), where only the consensus, the duals and the penalties change.

With a frozen linearization (``relinearize = false``, the default) every local problem of a step
keeps its dynamics, rows and margins from the second iteration on (the margins read the variances
the neighbours reported at the first; without exchanged variances from the first), so an iteration is: consensus terms from ``z, lam, rho``
(:func:`~.consensus_kernel.slot_terms`, their sums over slots in torch), the local solves on the
kept problems (:class:`~torch_gpmpc.control.solvers.repeated.RepeatedSolve`: warm active-set
solves from the last points), then consensus, duals, residuals and residual balancing
(:func:`~.consensus_kernel.consensus_step`). Through the torch path (:meth:`~.admm.ADMM.iterate`)
the same iteration re-assembles and re-validates everything and costs about three times as much on
the README's quadrotor demo.

The compiled iterations compute the same numbers (the plans, consensus, duals and penalties bit for
bit; the residual norms to the last bits, see :mod:`~.consensus_kernel`) and hand back to the torch
path whenever anything is unusual (:meth:`SteadyIterations.iterate` returns ``None``): a local
problem that does not converge or whose plan the acceptance rule rejects, non-finite terms, an
exception in the solve (the torch path solves that iteration again and counts what fails there).
:meth:`~.admm.ADMM.solve_step` also runs each step's last iteration through the torch path, so what
a step reports (its solution, problems, margins, the safety check's data) is that path's.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from torch_gpmpc.config.settings import ControllerSettings
from torch_gpmpc.control.numpy_views import as_array
from torch_gpmpc.control.solvers.interior_point import InteriorPointMPC
from torch_gpmpc.control.solvers.repeated import RepeatedSolution, RepeatedSolve
from torch_gpmpc.coordination.consensus_kernel import consensus_step, slot_terms
from torch_gpmpc.coordination.graph import Graph
from torch_gpmpc.coordination.penalty import DUAL_TOL_FACTOR, RHO_BALANCE, RHO_BOUNDS, RHO_FACTOR, checks_dual
from torch_gpmpc.coordination.state import ADMMState

logger = logging.getLogger(__name__)


@dataclass
class SteadyResult:
    """One compiled iteration: the next iterate and what the torch path's
    :class:`~.state.IterationStats` would report of it (no solve failed).

    Attributes:
        state: the next :class:`~.state.ADMMState`.
        primal, dual: the largest edge residuals. primal_ratio, dual_ratio: the largest ratios of
            the stopping test. unconverged_edges: edges that have not met it.
        infeasible_solves: local solves that softened a collision row.
    """

    state: ADMMState
    primal: float
    dual: float
    primal_ratio: float
    dual_ratio: float
    unconverged_edges: int
    infeasible_solves: int


def repeatable(layer, tensors: tuple) -> bool:
    """Whether ``layer``'s problems can be kept and solved again with new consensus terms (a
    :class:`~torch_gpmpc.control.solvers.interior_point.InteriorPointMPC` with warm starts), given the
    iterate's ``tensors`` (``None`` entries skipped): float64 on the CPU, none wanting gradients."""
    if type(layer) is not InteriorPointMPC or not layer.warm_start:
        return False
    present = [t for t in tensors if t is not None]
    if any(t.dtype != torch.float64 or t.device.type != "cpu" for t in present):
        return False
    return not (torch.is_grad_enabled() and any(t.requires_grad for t in present))


def solve_or_hand_back(solve: RepeatedSolve, guess) -> RepeatedSolution | None:
    """``solve.solve(guess)``, or ``None`` when it declines or raises (the torch path then solves the
    iteration again, and counts what fails)."""
    try:
        return solve.solve(guess)
    except Exception as exc:  # noqa: BLE001 - handed to the torch path, which reports it
        logger.debug("compiled iteration handed to the torch path: %s: %s", type(exc).__name__, exc)
        return None


class SteadyIterations:
    """The compiled iterations of one control step (module docstring).

    Args:
        settings: the controller settings (tolerances, penalty rule, stopping rule).
        graph: the step's communication graph (with at least one edge).
        xref: (K, T+1, n) the step's reference windows (float64, CPU).
        rho: the step's penalty, 0-d (every edge's with ``rho_update = fixed``).
        tol: the stopping test's absolute primal tolerance.
        solve: the step's local problems as a :class:`RepeatedSolve`.
    """

    def __init__(self, settings: ControllerSettings, graph: Graph, xref: Tensor, rho: Tensor, tol: float,
                 solve: RepeatedSolve) -> None:
        self.solve = solve
        self.edges = graph.edges
        self.slot_edge, self.slot_side = as_array(graph.slot_edge, np.int64), as_array(graph.slot_side, np.int64)
        self.active = as_array(graph.active, np.bool_)
        self.xref = xref
        K, M = self.active.shape
        self.rho_own = np.empty((K, M))
        self.w_own = np.empty((K, M, *xref.shape[1:]))
        self.adaptive = settings.rho_update == "adaptive"
        self.rho = float(rho)
        rel = settings.admm_rel_tol if settings.admm_stop == "primal-dual" else 0.0

        def dual_abs(primal_tol: float) -> float:
            return settings.admm_dual_tol if settings.admm_dual_tol is not None else DUAL_TOL_FACTOR * primal_tol

        self.tolerances = np.array([tol, dual_abs(tol), settings.admm_tol, dual_abs(settings.admm_tol), rel,
                                    RHO_FACTOR, RHO_BALANCE, *RHO_BOUNDS], dtype=np.float64)
        self.checks_dual = checks_dual(settings)

    def iterate(self, state: ADMMState) -> SteadyResult | None:
        """One compiled iteration from ``state`` (the step's previous iterate), or ``None`` where
        the torch path must take it (module docstring)."""
        z, lam = as_array(state.z), as_array(state.lam)
        rho = as_array(state.rho) if self.adaptive else np.full(z.shape[0], self.rho)
        buf = self.solve.buffers
        slot_terms(z, lam, rho, self.slot_edge, self.slot_side, self.active, self.rho_own, self.w_own, buf.rho_y,
                   buf.w_y, buf.y0)
        # the sums over slots as canonicalize's (torch's summation order)
        w_own = torch.from_numpy(self.w_own)
        buf.l_x[:] = (2.0 * self.xref[:, 1:] + w_own[:, :, 1:].sum(dim=1)).flatten(1).numpy()
        buf.c_x[:] = (1.0 + 0.5 * torch.from_numpy(self.rho_own).sum(dim=1)).numpy()
        sol = solve_or_hand_back(self.solve, state.solver_point)
        if sol is None:
            return None
        z_new, lam_new, rho_new, report = np.empty_like(z), np.empty_like(lam), np.empty_like(rho), np.empty(5)
        consensus_step(as_array(sol.X), as_array(sol.Y), self.slot_edge, self.slot_side, self.active, z, lam, rho,
                       self.adaptive, self.tolerances, self.checks_dual, z_new, lam_new, rho_new, report)
        nxt = ADMMState(sol.X, sol.U, self.edges, torch.from_numpy(z_new), torch.from_numpy(lam_new), state.pvar,
                        torch.from_numpy(rho_new) if self.adaptive else None, state.risk_left,
                        solver_point=sol.point)
        return SteadyResult(nxt, float(report[0]), float(report[1]), float(report[2]), float(report[3]),
                            int(report[4]), sol.slack_active)
