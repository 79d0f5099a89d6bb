"""The fast solver's rescue of its own inaccurate solves.

The compiled interior point (``solver = fast``) stops at 100 Newton steps or at a KKT error of 1e-10.
A few problems with heavily softened rows or inputs at their bound do not get there (the
Reliability page's cases). :class:`SolveRescue` solves those rows again: first by the compiled
solver, cold, at :data:`RESCUE_TOL` with up to :data:`RESCUE_MAX_ITER` Newton steps (milliseconds),
then what that leaves by Clarabel: handed the same condensed problem directly
(:class:`~torch_gpmpc.control.solvers.direct_clarabel.DirectClarabelMPC`, a few milliseconds a
problem, nothing to build; its collision multipliers reach the plane updates like the fast solver's)
when no gradient is wanted, else through cvxpylayers (the differentiable reference path: cvxpy's
import on first use, then a layer per neighbour-slot count, about 0.7 s for 18 slots). Rows neither
rung solves stay failed for the caller's fallback.
"""

from __future__ import annotations

import logging
from typing import Callable

from torch import nn

from torch_gpmpc.control.problem import (
    FAIL_INACCURATE, LocalProblemData, LocalSolution, replace_rows, select_problems, select_solution, wants_grad,
)

log = logging.getLogger(__name__)

#: The compiled solver's KKT tolerance and Newton-step cap when it solves again a problem it left
#: inaccurate at its 1e-10 and 100 steps. Measured: a crowd's problem whose error stalled above 1e-10
#: converged at 1e-9, its plan within 5e-8 of clarabel's; a forest's that wandered converged after
#: 223 steps.
RESCUE_TOL, RESCUE_MAX_ITER = 1e-8, 500


class SolveRescue:
    """The rescue solvers of one per-agent step (built on first use, one per kind and slot count).

    Args:
        build: ``build(num_slots, solver, **stops)``, a new local solver of the step's problems
            (:meth:`~.agent_step.LocalStep.build_solver`).
    """

    def __init__(self, build: Callable[..., nn.Module]) -> None:
        self._build = build
        self._solvers: dict[tuple[str, int], nn.Module] = {}
        #: problems the fast solver left inaccurate and a rescue solved (a run's count)
        self.rescued = 0
        self._logged = False

    def __call__(self, data: LocalProblemData, sol: LocalSolution) -> LocalSolution:
        """``sol`` (the fast solver's solution of the B problems ``data``) with its inaccurate rows
        solved again where a rescue succeeds; unchanged when no row is inaccurate."""
        if sol.failure is None:
            return sol
        rows = (sol.failure == FAIL_INACCURATE).nonzero().flatten()
        for kind in ("fast", "clarabel" if wants_grad(data) else "direct"):
            if not rows.numel():
                break
            again = self.solver(kind, data.active.shape[1])(select_problems(data, rows))
            if not bool(again.ok.any()):
                continue
            self.rescued += int(again.ok.sum())
            log.log(logging.DEBUG if self._logged else logging.INFO,
                    "the fast local solver did not converge for agent(s) %s; re-solved with %s. Further re-solves "
                    "are logged at debug level", rows[again.ok].tolist(),
                    f"its tolerance relaxed to {RESCUE_TOL:g}" if kind == "fast" else
                    "clarabel (direct)" if kind == "direct" else "clarabel (cvxpylayers, for gradients)")
            self._logged = True
            sol = replace_rows(sol, rows[again.ok], select_solution(again, again.ok.nonzero().flatten()))
            rows = rows[~again.ok]
        return sol

    def solver(self, kind: str, num_slots: int) -> nn.Module:
        """The rescue solver ``kind`` (``fast``: first; ``direct`` or, for gradients, ``clarabel``: last)
        for ``num_slots`` neighbour slots."""
        key = (kind, num_slots)
        if key not in self._solvers:
            stops = {"tol": RESCUE_TOL, "max_iter": RESCUE_MAX_ITER} if kind == "fast" else {}
            self._solvers[key] = self._build(num_slots, kind, **stops)
        return self._solvers[key]

