"""Local-problem solvers: each maps :class:`~torch_gpmpc.control.problem.LocalProblemData`
to :class:`~torch_gpmpc.control.problem.LocalSolution` for a batch of agents.

:func:`make_local_solver` is the only place that names the backends: ``fast`` (the
structure-exploiting interior point, :mod:`.interior_point`) and ``clarabel`` /
``reference`` (cvxpylayers, :mod:`.conic`, imported only when asked for).
"""

from __future__ import annotations

import functools

from torch import nn

from torch_gpmpc.dynamics.systems import NominalModel


@functools.lru_cache(maxsize=32)
def make_local_solver(
    horizon: int,
    dim: int,
    num_neighbors: int,
    nominal: NominalModel,
    u_max: float | None,
    alpha: float,
    slack_penalty: float = 1e4,
    solver: str = "clarabel",
) -> nn.Module:
    """A shared local-problem module per (T, D, M, model, constants, solver) (building one is slow).

    ``u_max`` overrides the model's norm input bound (``None``: the model's bound).

    ``solver='fast'`` gives :class:`~torch_gpmpc.control.solvers.interior_point.FastLocalMPC`;
    ``clarabel`` and ``reference`` give the cvxpylayers
    :class:`~torch_gpmpc.control.solvers.conic.LocalMPC` (same problem, same inputs and
    outputs). The returned module is shared between callers: do not modify it.
    """
    if solver == "fast":
        from torch_gpmpc.control.solvers.interior_point import FastLocalMPC

        return FastLocalMPC(horizon, dim, num_neighbors, nominal, None if u_max is None else float(u_max), float(alpha),
                            float(slack_penalty))
    # cvxpy and cvxpylayers are imported only when a cvxpylayers path is asked for
    from torch_gpmpc.control.solvers.conic import LocalMPC

    return LocalMPC(horizon, dim, num_neighbors, nominal, None if u_max is None else float(u_max), float(alpha),
                    float(slack_penalty), solver)
