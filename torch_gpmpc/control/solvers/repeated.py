"""One batch of local problems solved again and again with new consensus terms only.

Within a control step with a frozen linearization, every ADMM iteration after the first two poses
the same local problems but for the consensus terms: the dynamics, the rows with their margins,
the input bounds and the input-rate term stay; ``c_x, l_x, rho_y, w_y`` and the copies' closed-form
step-0 points ``y0`` change (:class:`~.canonical.CanonicalData`). :class:`RepeatedSolve` keeps the
fixed part as the kernel's arrays, with its structure, and solves each new set of terms with the
warm active-set method from the last points (the cold interior point where that fails): the same
kernel calls and the same torch operations on the outputs as
:meth:`~.interior_point.InteriorPointMPC.forward`, without re-deriving the fixed part, so the same
terms give the same plans bit for bit. Anything unusual (non-finite terms, a problem not converged,
a plan the acceptance rule rejects) returns ``None``: the caller then solves through the layer,
which reports and handles it.

Made by :meth:`~.interior_point.InteriorPointMPC.repeated`; used by ADMM's compiled iterations
(:mod:`~torch_gpmpc.coordination.steady`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from torch_gpmpc.control.constraints import LocalConstraints
from torch_gpmpc.control.problem import SLACK_ACTIVE_TOL, AcceptanceCheck, LocalProblemData
from torch_gpmpc.control.solvers.canonical import CanonicalData
from torch_gpmpc.control.solvers.ipm_batch import (
    KernelLimits, batched_mv, kernel_arrays, point_outputs, row_multipliers, solve_points,
)


@dataclass
class KernelSettings:
    """The kernel's settings of a layer: ``weights = (alpha, beta)``, its limits, the slack
    penalty, the interior point's tolerance and iteration cap."""

    weights: tuple[float, float]
    limits: KernelLimits
    penalty: float
    tol: float
    max_iter: int


@dataclass
class ConsensusBuffers:
    """The terms one repeated solve reads: at first those of the problems it was made from, then
    written in place by the caller before each solve.

    Attributes:
        c_x: (B,). l_x: (B, T*D). rho_y: (B, M + L), the L state-row slots fixed at 1.
        w_y: (B, M + L, T, D), the state-row slots fixed at 0. y0: (B, M, D).
    """

    c_x: np.ndarray
    l_x: np.ndarray
    rho_y: np.ndarray
    w_y: np.ndarray
    y0: np.ndarray


@dataclass
class RepeatedSolution:
    """A repeated solve's plans (every problem accepted).

    Attributes:
        X: (B, T+1, D). U: (B, T, Du). Y: (B, M, T+1, D). slack: (B, M, T).
        point: the kernel's points (the next solve's warm start).
        slack_active: how many problems softened a collision row of an active slot.
        multipliers: (B, M, T) the collision rows' multipliers.
    """

    X: Tensor
    U: Tensor
    Y: Tensor
    slack: Tensor
    point: object
    slack_active: int
    multipliers: Tensor


class RepeatedSolve:
    """The B local problems of ``data`` with replaceable consensus terms (module docstring).

    Args:
        data: the problems as last posed (their fixed part is kept; shapes as
            :class:`~torch_gpmpc.control.problem.LocalProblemData`).
        canon: ``data`` in canonical form with the soft state rows appended
            (:func:`~.canonical.with_state_rows`): G (B, T*D, T*Du), normals (B, M + L, T, D), ...
        structure: the kernel's structure of ``canon`` (``GtG (B, n, n), A (B, (M + L) T, n)``).
        nominal_B: (D, Du) the input matrix where ``data.dyn_B`` is None (the acceptance rule's).
        constraints: the layer's constraints (the acceptance rule's input bounds).
        kernel: the layer's :class:`KernelSettings`.
    """

    def __init__(self, data: LocalProblemData, canon: CanonicalData, structure: tuple[np.ndarray, np.ndarray],
                 nominal_B: Tensor, constraints: LocalConstraints, kernel: KernelSettings) -> None:
        self.x0, self.kernel = data.x0, kernel
        self.acceptance = AcceptanceCheck(data, nominal_B, constraints)
        self.G, self.h = canon.G.detach(), canon.h.detach()
        G, h, normals, bounds, g_u, H_cost = kernel_arrays((canon.G, canon.h, canon.normals, canon.bounds, canon.g_u,
                                                            canon.H_cost))
        self._fixed = (G, h, normals, bounds, g_u, H_cost)
        self._structure = structure
        B, slots, T, D = normals.shape
        self.batch, self.horizon, self.dim = B, T, D
        self.num_neighbors = int(data.active.shape[1])
        self.active = data.active.detach().cpu().numpy().astype(np.float64)
        # the terms of the problems as posed (the caller replaces those that change)
        terms = [np.array(t.detach().cpu().numpy(), dtype=np.float64) for t in
                 (canon.c_x, canon.l_x, canon.rho_y, canon.w_y, canon.y0)]
        self.buffers = ConsensusBuffers(*terms)

    @property
    def fixed_part_finite(self) -> bool:
        """Whether the kept part is finite (else every solve goes through the layer)."""
        return all(bool(np.isfinite(a).all()) for a in self._fixed)

    def solve(self, guess) -> RepeatedSolution | None:
        """Solve with the terms now in :attr:`buffers`, warm from ``guess`` (the last points).

        Returns:
            The plans, or ``None`` when the terms are not finite, some problem did not converge or
            its plan fails the acceptance rule (solve through the layer instead).
        """
        buf, k = self.buffers, self.kernel
        terms = (buf.c_x, buf.l_x, buf.rho_y, buf.w_y, buf.y0)
        if not (np.isfinite(sum(float(a.sum()) for a in terms)) and (buf.rho_y > 0).all()):
            return None
        G, h, normals, bounds, g_u, H_cost = self._fixed
        arrays = [G, h, buf.c_x, buf.l_x, buf.rho_y, buf.w_y, normals, bounds, g_u, H_cost, *self._structure]
        stats: dict = {}
        point, _, done = solve_points((k.weights, k.limits, k.penalty, k.tol, k.max_iter, stats, guess, arrays),
                                      keep_at=False)
        if not done.all():
            return None
        B, T, D, M = self.batch, self.horizon, self.dim, self.num_neighbors
        u, y1, slack, _ = point_outputs(point, done, normals.shape, self.h)
        y1, slack = y1[:, :M], slack[:, :M]
        X = torch.cat([self.x0[:, None], (batched_mv(self.G, u) + self.h).view(B, T, D)], dim=1)
        U = u.view(B, T, -1)
        Y = torch.cat([torch.from_numpy(buf.y0)[:, :, None], y1], dim=2)  # a copy: the buffers are reused
        if self.acceptance.codes(X, U, Y, slack).any():
            return None
        used = slack.numpy() * self.active[:, :, None]
        softened = int((used > SLACK_ACTIVE_TOL).reshape(B, -1).any(axis=1).sum())
        return RepeatedSolution(X=X, U=U, Y=Y, slack=slack, point=stats["point"], slack_active=softened,
                                multipliers=row_multipliers(stats["point"], M, T))
