"""Local-problem solvers: each maps :class:`~torch_gpmpc.control.problem.LocalProblemData`
to :class:`~torch_gpmpc.control.problem.LocalSolution` for a batch of agents.

:func:`make_local_solver` is the only place that names the backends: ``fast`` (the
structure-exploiting interior point :class:`~.interior_point.InteriorPointMPC`, compiled with
numba), ``clarabel`` / ``reference`` (the cvxpylayers reference path
:class:`~.conic.CvxpyLayerMPC`, imported only when asked for) and ``direct`` (Clarabel without cvxpy
and without gradients, :class:`~.direct_clarabel.DirectClarabelMPC`: the fast solver's last rescue).
"""

from __future__ import annotations

from torch import nn

from torch_gpmpc.control.constraints import LocalConstraints
from torch_gpmpc.dynamics.systems import NominalModel
from torch_gpmpc.errors import GpmpcError

#: The backends :func:`make_local_solver` builds.
BACKENDS = ("fast", "clarabel", "reference", "direct")


def make_local_solver(
    horizon: int,
    dim: int,
    num_neighbors: int,
    nominal: NominalModel,
    u_max: float | None,
    alpha: float,
    slack_penalty: float = 1e4,
    solver: str = "fast",
    constraints: LocalConstraints | None = None,
    num_halfspaces: int = 0,
    input_rate_weight: float = 0.0,
    warm_start: bool = True,
    tol: float | None = None,
    max_iter: int | None = None,
) -> nn.Module:
    """A new batched local-problem module for (T, n, M, model, constants, backend).

    ``u_max`` overrides the model's norm input bound (``None``: the model's bound).
    ``constraints`` are the input bounds and soft state constraints (``None``: the model's,
    :meth:`~torch_gpmpc.control.constraints.LocalConstraints.of`; give one to add a workspace);
    ``num_halfspaces`` is the number L of per-problem half-space rows the data carries;
    ``input_rate_weight`` (beta >= 0) adds ``beta sum_t ||U_t - U_{t-1}||^2`` to the cost, with
    ``U_{-1}`` the data's ``u_prev`` (smooth plans for vehicles that cannot jump their acceleration).
    ``warm_start`` (``fast`` only): solve first by the exact active-set method from the previous
    call's solutions when no gradient is wanted (:mod:`~torch_gpmpc.control.solvers.ipm_active`).
    ``tol``, ``max_iter`` (``fast`` only): the interior point's KKT tolerance and Newton-step cap
    (``None``: 1e-10 and 100).

    ``solver='fast'`` (the default, as in the run configuration) gives the compiled interior
    point :class:`~torch_gpmpc.control.solvers.interior_point.InteriorPointMPC`; ``clarabel`` and
    ``reference`` give the cvxpylayers reference path
    :class:`~torch_gpmpc.control.solvers.conic.CvxpyLayerMPC` (same problem, inputs and outputs;
    building one takes about a second, so keep it). Each call builds a new module, owned by the
    caller (a :class:`~torch_gpmpc.coordination.agent_step.LocalStep` keeps one per slot count).
    ``direct`` gives :class:`~torch_gpmpc.control.solvers.direct_clarabel.DirectClarabelMPC`: the same
    problem handed to Clarabel without cvxpy, nothing to build, no gradients.

    Examples:
        >>> import torch
        >>> from torch_gpmpc import make_local_solver, NominalModel
        >>> from torch_gpmpc.control.examples import crossing_instance
        >>> solver = make_local_solver(horizon=13, dim=2, num_neighbors=2, nominal=NominalModel(2),
        ...                            u_max=2.0, alpha=1e-3)
        >>> sol = solver(crossing_instance(batch=3, num_neighbors=2, method="nominal").problem_data())
        >>> tuple(sol.X.shape), tuple(sol.U.shape), bool(sol.ok.all())
        ((3, 14, 2), (3, 13, 2), True)
    """
    if solver not in BACKENDS:
        raise GpmpcError(f"solver: {solver!r} is not a local solver; choose from {', '.join(BACKENDS)}")
    if solver == "fast":
        from torch_gpmpc.control.solvers.interior_point import InteriorPointMPC

        stops = {name: value for name, value in (("tol", tol), ("max_iter", max_iter)) if value is not None}
        return InteriorPointMPC(horizon, dim, num_neighbors, nominal, None if u_max is None else float(u_max),
                                float(alpha), float(slack_penalty), constraints=constraints,
                                num_halfspaces=num_halfspaces, input_rate_weight=float(input_rate_weight),
                                warm_start=warm_start, **stops)
    if solver == "direct":
        from torch_gpmpc.control.solvers.direct_clarabel import DirectClarabelMPC

        return DirectClarabelMPC(horizon, dim, num_neighbors, nominal, None if u_max is None else float(u_max),
                                 float(alpha), float(slack_penalty), constraints=constraints,
                                 num_halfspaces=num_halfspaces, input_rate_weight=float(input_rate_weight))
    # cvxpy and cvxpylayers are imported only when a cvxpylayers path is asked for
    from torch_gpmpc.control.solvers.conic import CvxpyLayerMPC

    return CvxpyLayerMPC(horizon, dim, num_neighbors, nominal, None if u_max is None else float(u_max), float(alpha),
                         float(slack_penalty), solver, constraints=constraints, num_halfspaces=num_halfspaces,
                         input_rate_weight=float(input_rate_weight))
