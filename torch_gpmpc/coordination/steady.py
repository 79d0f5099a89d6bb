"""ADMM's compiled iterations with ``admm_coupling = copies``: a control step's iterations after its
second (after its first where no variances are exchanged), where only the consensus, the duals and
the penalties change.

With a frozen linearization (``relinearize = false``, the default) every local problem of a step
keeps its dynamics, rows and margins from the second iteration on (the margins read the variances
the neighbours reported at the first; without exchanged variances from the first), so an iteration
is: the consensus terms (:func:`~.consensus.slot_consensus` and
:class:`~torch_gpmpc.control.problem.ConsensusTerms`, as canonicalization computes them) written into
the kept problems, the local solves on them
(:class:`~torch_gpmpc.control.solvers.repeated.RepeatedSolve`: warm active-set solves from the last
points), then the edges' update (:func:`~.consensus.copies_update`, the torch path's function). Through
the torch path (:meth:`~.admm.ADMM.iterate`) the same iteration re-assembles and re-validates
everything.

The compiled iterations compute the torch path's numbers bit for bit and hand back to the torch path
whenever anything is unusual (:meth:`SteadyIterations.iterate` returns ``None``): a local problem that
does not converge or whose plan the acceptance rule rejects, non-finite terms, an exception in the
solve (the torch path solves that iteration again and counts what fails there).
:meth:`~.admm.ADMM.solve_step` also runs each step's last iteration through the torch path, so what
a step reports (its solution, problems, margins, the safety check's data) is that path's.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import torch
from torch import Tensor

from torch_gpmpc.config.settings import ControllerSettings
from torch_gpmpc.control.problem import ConsensusTerms, LocalProblemData
from torch_gpmpc.control.solvers.canonical import consensus_weights
from torch_gpmpc.control.solvers.interior_point import InteriorPointMPC
from torch_gpmpc.control.solvers.repeated import RepeatedSolution, RepeatedSolve
from torch_gpmpc.coordination.agent_step import edge_copies
from torch_gpmpc.coordination.consensus import copies_update, slot_consensus
from torch_gpmpc.coordination.graph import Graph
from torch_gpmpc.coordination.penalty import unconverged_edges
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
        problem: the step's kept local problems (batch K), as last assembled.
        rho: the step's penalty, 0-d (every edge's with ``rho_update = fixed``).
        tol: the stopping test's absolute primal tolerance.
        solve: the step's local problems as a :class:`RepeatedSolve`.
    """

    def __init__(self, settings: ControllerSettings, graph: Graph, problem: LocalProblemData, rho: Tensor,
                 tol: float, solve: RepeatedSolve) -> None:
        self.settings, self.graph, self.problem = settings, graph, problem
        self.rho, self.tol, self.solve = rho, tol, solve
        self.adaptive = settings.rho_update == "adaptive"

    def write_terms(self, state: ADMMState) -> None:
        """Write the consensus terms of ``state`` into the kept problems, with the functions
        :meth:`~.agent_step.LocalStep.assemble` and canonicalization use (the same bits)."""
        graph, buf, M = self.graph, self.solve.buffers, self.graph.num_slots
        rho = state.rho[graph.slot_edge] if self.adaptive else self.rho
        slots = slot_consensus(state.z, state.lam, graph)
        terms = ConsensusTerms.of(dataclasses.replace(self.problem, rho=rho, z_own=slots.z_own, z_nbr=slots.z_nbr,
                                                      lam_own=slots.lam_own, lam_nbr=slots.lam_nbr))
        c_x, l_x, rho_y, w_y, y0 = consensus_weights(terms, self.problem.xref)
        buf.c_x[:], buf.l_x[:], buf.y0[:] = c_x.numpy(), l_x.numpy(), y0.numpy()
        buf.rho_y[:, :M], buf.w_y[:, :M] = rho_y.numpy(), w_y.numpy()  # the state-row slots stay

    def iterate(self, state: ADMMState) -> SteadyResult | None:
        """One compiled iteration from ``state`` (the step's previous iterate), or ``None`` where
        the torch path must take it (module docstring)."""
        self.write_terms(state)
        sol = solve_or_hand_back(self.solve, state.solver_point)
        if sol is None:
            return None
        rho_now = state.rho if self.adaptive else self.rho
        update = copies_update(edge_copies(sol, self.graph), state.z, state.lam, rho_now, self.settings, self.tol)
        nxt = ADMMState(sol.X, sol.U, self.graph.edges, update.z, update.lam, state.pvar, update.rho,
                        state.risk_left, solver_point=sol.point)
        return SteadyResult(nxt, float(update.residuals.primal.max()), float(update.residuals.dual.max()),
                            float(update.stop.primal_ratio.max()), float(update.stop.dual_ratio.max()),
                            unconverged_edges(update.stop, self.settings), sol.slack_active)
