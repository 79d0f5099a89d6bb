"""The agent-local MPC problem's data contract, shared by every solver.

:class:`LocalProblemData` (inputs) and :class:`LocalSolution` (outputs) of the
agent-local problem (paper eq. 27), the collision rows, and the acceptance rule for a
returned answer. Every solver in :mod:`torch_gpmpc.control.solvers` maps the one to the
other; this module imports no solver and no cvxpy.
"""

from __future__ import annotations

from typing import Any

import dataclasses
from dataclasses import dataclass, fields

import numpy as np
import torch
from torch import Tensor

from torch_gpmpc.control.acceptance import failure_codes
from torch_gpmpc.control.constraints import LocalConstraints
from torch_gpmpc.control.cost import plan_tracking_cost
from torch_gpmpc.control.numpy_views import as_array
from torch_gpmpc.errors import GpmpcError

#: A slack above this counts as a softened (violated) collision row.
SLACK_ACTIVE_TOL = 1e-6

#: Relative residual above which a returned solution is not accepted as a solution.
FEASIBILITY_TOL = 1e-5

#: Why a local solve was rejected; :attr:`LocalSolution.failure` holds ``1 + index``
#: into this tuple (0 = accepted): the solver raised, returned NaN/inf, or returned a
#: finite answer that violates a constraint by more than :data:`FEASIBILITY_TOL`.
FAILURE_KINDS = ("exception", "non-finite", "inaccurate")
FAIL_NONE, FAIL_EXCEPTION, FAIL_NONFINITE, FAIL_INACCURATE = 0, 1, 2, 3
_CODES = np.array([FAIL_NONE, FAIL_NONFINITE, FAIL_INACCURATE], dtype=np.int64)

@dataclass
class LocalProblemData:
    """Inputs of B local problems with horizon T, state dimension D, input dimension Du and M
    neighbour slots.

    Slot j of agent b is the edge to one neighbour; unused slots (agents with fewer
    than M neighbours) have ``active[b, j] = False`` and their other entries are ignored.

    Attributes:
        x0: measured states, shape (B, D).
        xref: references, shape (B, T+1, D).
        dyn_A: linearized state matrices, shape (B, T, D, D).
        dyn_c: linearized offsets, shape (B, T, D).
        normals: collision normals for steps tau = 1..T, shape (B, M, T, D).
        bounds: right-hand sides ``r_safe + margin`` for tau = 1..T, shape (B, M, T).
        active: which slots hold a neighbour, shape (B, M), bool.
        rho: ADMM penalty, scalar tensor or shape (B, M); must be > 0.
        z_own: consensus value of the agent's own trajectory per edge, shape (B, M, T+1, D).
        z_nbr: consensus value of the neighbour's trajectory per edge, shape (B, M, T+1, D).
        lam_own: multiplier of the agent's own copy per edge, shape (B, M, T+1, D).
        lam_nbr: multiplier of the neighbour copy per edge, shape (B, M, T+1, D).
        rho_nbr: penalty of the neighbour copies alone, scalar or (B, M); ``None`` = ``rho``.
            A large ``rho_nbr`` with ``rho = 0`` pins the copies to ``z_nbr``: the neighbours'
            plans become fixed obstacles (the safety fallback's re-plan).
        dyn_B: linearized input matrices ``B + J_u`` (GPs that read the input), shape
            (B, T, D, Du); ``None`` = the nominal B at every step.
        halfspace_normals: extra soft rows ``n^T X_tau >= b`` (no neighbour copy; e.g. obstacle
            faces on the positions), shape (B, L, T, D); ``None`` = none. A row with normal 0 and
            bound <= 0 is inert. The solver's ``num_halfspaces`` fixes L.
        halfspace_bounds: their right-hand sides, shape (B, L, T).
        u_prev: the input applied at the previous step, ``U_{-1}`` of the input-rate term
            ``beta sum_t ||U_t - U_{t-1}||^2`` (solvers with ``input_rate_weight`` beta > 0),
            shape (B, Du); ``None`` = 0.
        cost_Q, cost_R, cost_P, u_ref: a stated tracking cost
            (:class:`~torch_gpmpc.control.cost.QuadraticCost`: stage weights Q (B, D, D) and
            R (B, Du, Du), terminal weight P (B, D, D), input reference u_ref (B, Du)) that replaces
            ``||X - Xref||^2 + alpha ||U||^2``; give Q, R and P together; all ``None`` = that default.

    Examples:
        >>> from torch_gpmpc.control.examples import crossing_instance
        >>> data = crossing_instance(batch=3, num_neighbors=2, method="nominal").problem_data()
        >>> tuple(data.x0.shape), tuple(data.normals.shape), tuple(data.bounds.shape)
        ((3, 2), (3, 2, 13, 2), (3, 2, 13))
    """

    x0: Tensor
    xref: Tensor
    dyn_A: Tensor
    dyn_c: Tensor
    normals: Tensor
    bounds: Tensor
    active: Tensor
    rho: Tensor
    z_own: Tensor
    z_nbr: Tensor
    lam_own: Tensor
    lam_nbr: Tensor
    rho_nbr: Tensor | None = None
    dyn_B: Tensor | None = None
    halfspace_normals: Tensor | None = None
    halfspace_bounds: Tensor | None = None
    u_prev: Tensor | None = None
    cost_Q: Tensor | None = None
    cost_R: Tensor | None = None
    cost_P: Tensor | None = None
    u_ref: Tensor | None = None

    @property
    def has_cost(self) -> bool:
        """Whether the problems state their own tracking cost (``cost_Q`` and the rest)."""
        return self.cost_Q is not None

    def validate(self, horizon: int, dim: int, num_neighbors: int, input_dim: int | None = None,
                 num_halfspaces: int = 0) -> int:
        """Check all shapes against (T, D, M[, Du], L = num_halfspaces); return the batch size B.

        Raises:
            GpmpcError: naming the first field with a wrong shape.
        """
        batch = int(self.x0.shape[0]) if self.x0.dim() == 2 else -1
        T, D, M = horizon, dim, num_neighbors
        expected = {
            "x0": (batch, D), "xref": (batch, T + 1, D), "dyn_A": (batch, T, D, D),
            "dyn_c": (batch, T, D), "normals": (batch, M, T, D), "bounds": (batch, M, T),
            "active": (batch, M), "z_own": (batch, M, T + 1, D), "z_nbr": (batch, M, T + 1, D),
            "lam_own": (batch, M, T + 1, D), "lam_nbr": (batch, M, T + 1, D),
            "dyn_B": (batch, T, D, input_dim if input_dim is not None else -1),
            "halfspace_normals": (batch, num_halfspaces, T, D), "halfspace_bounds": (batch, num_halfspaces, T),
            "u_prev": (batch, input_dim if input_dim is not None else -1),
            "cost_Q": (batch, D, D), "cost_P": (batch, D, D),
            "cost_R": (batch, input_dim if input_dim is not None else -1, input_dim if input_dim is not None else -1),
            "u_ref": (batch, input_dim if input_dim is not None else -1),
        }
        given = [self.cost_Q is not None, self.cost_R is not None, self.cost_P is not None]
        if any(given) and not all(given) or (self.u_ref is not None and not all(given)):
            raise GpmpcError("LocalProblemData: give cost_Q, cost_R and cost_P together (u_ref with them), "
                             "or none of them for the default cost")
        if (self.halfspace_normals is None) != (self.halfspace_bounds is None):
            raise GpmpcError("LocalProblemData: give halfspace_normals and halfspace_bounds together (or neither)")
        if self.halfspace_normals is None and num_halfspaces:
            raise GpmpcError(f"LocalProblemData: this solver has num_halfspaces = {num_halfspaces}; give "
                             f"halfspace_normals {(batch, num_halfspaces, T, D)} and halfspace_bounds")
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name in OPTIONAL_FIELDS and value is None:
                continue
            if f.name == "dyn_B" and input_dim is None:
                expected["dyn_B"] = (batch, T, D, value.shape[-1])
            if f.name in ("u_prev", "u_ref") and input_dim is None:
                expected[f.name] = (batch, value.shape[-1])
            if f.name == "cost_R" and input_dim is None:
                expected[f.name] = (batch, value.shape[-1], value.shape[-1])
            if f.name in ("rho", "rho_nbr"):
                if value.dim() != 0 and tuple(value.shape) != (batch, M):
                    raise GpmpcError(f"LocalProblemData.{f.name} must be a scalar or have shape {(batch, M)}, "
                                     f"got {tuple(value.shape)}")
                continue
            if batch < 0 or tuple(value.shape) != expected[f.name]:
                raise GpmpcError(f"LocalProblemData.{f.name} must have shape (T={T}, D={D}, M={M}) "
                                 f"{expected[f.name]}, got {tuple(value.shape)}")
        return batch


@dataclass
class LocalSolution:
    """Solutions of B local problems.

    Attributes:
        X: planned states, shape (B, T+1, D).
        U: planned inputs, shape (B, T, D).
        Y: the agent's copies of its neighbours' trajectories, shape (B, M, T+1, D).
        slack: collision-row slacks for tau = 1..T, shape (B, M, T).
        slack_active: some collision slack of the agent exceeds 1e-6 (a softened row), shape (B,).
        ok: finite solution, no solver error, constraints met, shape (B,); rows with
            ``ok = False`` are NaN.
        cost: planned tracking + control cost ``||X - Xref||^2 + alpha ||U||^2``, or the problems'
            stated cost (:mod:`~torch_gpmpc.control.cost`), plus the input-rate term
            ``beta sum_t ||U_t - U_{t-1}||^2`` when beta > 0, shape (B,).
        failure: why a row was rejected, int64 shape (B,): 0 if ``ok``, else ``1 + i`` for
            ``FAILURE_KINDS[i]`` (exception, non-finite, inaccurate); ``None`` if unknown.
        failure_detail: the first solver exception message of the batch, if any.
        state_slack: how far the plan leaves the soft state constraints (state box, rows, norm
            bound, workspace, half-spaces) at tau = 1..T, shape (B, T) (0 inside; see
            :meth:`~torch_gpmpc.control.constraints.LocalConstraints.state_violation`); ``None`` if
            not computed.
        solver_point: the solver's primal-dual points of this batch (opaque; the fast solver's),
            to pass as the next solve's ``guess`` (its warm start); ``None`` if the solver keeps none.
        multipliers: the collision rows' multipliers, shape (B, M, T) (the fast solver's and the
            direct Clarabel solver's; NaN rows where a solver without them answered); ``None`` where
            the solver does not report them.

    Examples:
        >>> from torch_gpmpc import NominalModel, make_local_solver
        >>> from torch_gpmpc.control.examples import crossing_instance
        >>> data = crossing_instance(batch=2, num_neighbors=1, method="nominal").problem_data()
        >>> sol = make_local_solver(13, 2, 1, NominalModel(2), 2.0, 1e-3)(data)
        >>> tuple(sol.X.shape), tuple(sol.U.shape), tuple(sol.Y.shape), sol.ok.tolist()
        ((2, 14, 2), (2, 13, 2), (2, 1, 14, 2), [True, True])
    """

    X: Tensor
    U: Tensor
    Y: Tensor
    slack: Tensor
    slack_active: Tensor
    ok: Tensor
    cost: Tensor
    failure: Tensor | None = None
    failure_detail: str | None = None
    state_slack: Tensor | None = None
    solver_point: Any = None
    multipliers: Tensor | None = None


#: LocalProblemData fields that may be ``None``
OPTIONAL_FIELDS = ("rho_nbr", "dyn_B", "halfspace_normals", "halfspace_bounds", "u_prev", "cost_Q", "cost_R",
                   "cost_P", "u_ref")

#: LocalProblemData fields that may be a scalar shared by the whole batch
SHARED_SCALARS = ("rho", "rho_nbr")


def select_problems(data: LocalProblemData, rows: Tensor) -> LocalProblemData:
    """The problems ``rows`` (int64 (B',)) of a batch (scalar penalties stay shared)."""
    changes = {}
    for f in fields(data):
        value = getattr(data, f.name)
        if value is not None and not (f.name in SHARED_SCALARS and value.dim() == 0):
            changes[f.name] = value[rows]
    return dataclasses.replace(data, **changes)


def select_solution(solution: LocalSolution, rows: Tensor) -> LocalSolution:
    """The solutions ``rows`` (int64 (B',)) of a batch."""
    def pick(value: Tensor | None) -> Tensor | None:
        return None if value is None else value[rows]

    return LocalSolution(X=pick(solution.X), U=pick(solution.U), Y=pick(solution.Y), slack=pick(solution.slack),
                         slack_active=pick(solution.slack_active), ok=pick(solution.ok), cost=pick(solution.cost),
                         failure=pick(solution.failure), failure_detail=solution.failure_detail,
                         state_slack=pick(solution.state_slack), multipliers=pick(solution.multipliers))


def check_layer_sizes(name: str, horizon: int, dim: int, num_neighbors: int, num_halfspaces: int,
                      nominal_dim: int, alpha: float, slack_penalty: float, input_rate_weight: float) -> None:
    """The checks every local solver ``name`` makes of its sizes and weights (one message per kind).

    Raises:
        GpmpcError: a size out of range (T, D >= 1; M, L >= 0), a model of another dimension, or
            ``alpha``, ``slack_penalty`` not > 0 or ``input_rate_weight`` < 0.
    """
    if horizon < 1 or dim < 1 or num_neighbors < 0 or num_halfspaces < 0:
        raise GpmpcError(f"{name} needs horizon >= 1, dim >= 1, num_neighbors >= 0, num_halfspaces >= 0; "
                         f"got {horizon}, {dim}, {num_neighbors}, {num_halfspaces}")
    if nominal_dim != dim:
        raise GpmpcError(f"nominal model has dim {nominal_dim}, {name} dim is {dim}")
    if alpha <= 0 or slack_penalty <= 0 or input_rate_weight < 0:
        raise GpmpcError(f"{name}: alpha and slack_penalty must be > 0 and input_rate_weight >= 0; got "
                         f"{alpha}, {slack_penalty}, {input_rate_weight}")


def wants_grad(data: LocalProblemData) -> bool:
    """Whether a gradient is to reach one of ``data``'s tensors (autograd on, one requires it)."""
    return torch.is_grad_enabled() and any(isinstance(v, Tensor) and v.requires_grad
                                           for v in (getattr(data, f.name) for f in fields(data)))


def replace_rows(solution: LocalSolution, rows: Tensor, other: LocalSolution) -> LocalSolution:
    """``solution`` with its rows ``rows`` (int64 (B',)) taken from ``other`` (B' rows), out of place
    (gradients flow to both); a field ``other`` lacks keeps ``solution``'s."""
    def put(mine: Tensor | None, theirs: Tensor | None) -> Tensor | None:
        return mine if mine is None or theirs is None else mine.index_put((rows,), theirs.to(mine.dtype))

    return LocalSolution(X=put(solution.X, other.X), U=put(solution.U, other.U), Y=put(solution.Y, other.Y),
                         slack=put(solution.slack, other.slack), slack_active=put(solution.slack_active, other.slack_active),
                         ok=put(solution.ok, other.ok), cost=put(solution.cost, other.cost),
                         failure=put(solution.failure, other.failure), failure_detail=solution.failure_detail,
                         state_slack=put(solution.state_slack, other.state_slack), solver_point=solution.solver_point,
                         multipliers=put(solution.multipliers, unreported_as_nan(other.multipliers, solution.multipliers,
                                                                                 len(rows))))


def unreported_as_nan(theirs: Tensor | None, mine: Tensor | None, rows: int) -> Tensor | None:
    """``theirs``, or NaN rows shaped as ``mine``'s where another solver reported no multipliers (so
    the replaced rows do not keep the first solver's)."""
    if theirs is not None or mine is None:
        return theirs
    return mine.new_full((rows, *mine.shape[1:]), float("nan"))


def planned_cost(data: LocalProblemData, X: Tensor, U: Tensor, xref: Tensor, alpha: float, beta: float) -> Tensor:
    """The plans' tracking cost (the data's stated cost, else ``||X - Xref||^2 + alpha ||U||^2``) plus
    the input-rate term, (B,); X (B, T+1, D), U (B, T, Du), xref (B, T+1, D)."""
    return plan_tracking_cost(X, U, xref, alpha, data.cost_Q, data.cost_R, data.cost_P, data.u_ref) \
        + input_rate_cost(U, data.u_prev, beta)


def input_rate_cost(U: Tensor, u_prev: Tensor | None, beta: float) -> Tensor:
    """``beta sum_t ||U_t - U_{t-1}||^2`` per problem, U (B, T, Du), u_prev (B, Du) or ``None`` (0)."""
    if beta == 0.0:
        return U.new_zeros(U.shape[0])
    prev = torch.zeros_like(U[:, :1]) if u_prev is None else u_prev[:, None].to(U)
    return beta * (torch.diff(U, dim=1, prepend=prev) ** 2).sum(dim=(1, 2))


def mask_inactive_rows(normals: Tensor, bounds: Tensor, active: Tensor) -> tuple[Tensor, Tensor]:
    """Collision rows of inactive slots made trivially satisfied: normal 0, bound -1.

    Args:
        normals: (B, M, T, D). bounds: (B, M, T). active: (B, M), bool.

    Returns:
        ``(normals, bounds)`` of the same shapes.
    """
    act = active.to(torch.bool)[:, :, None]
    return (torch.where(act[..., None], normals, torch.zeros_like(normals)),
            torch.where(act, bounds, -torch.ones_like(bounds)))


@dataclass
class ConsensusTerms:
    """The local problem's consensus terms, with inactive slots neutralised (they add nothing).

    Attributes:
        w_own: ``rho z_own - lam_own`` per slot, 0 on inactive slots, shape (B, M, T+1, D).
        w_nbr: ``rho z_nbr - lam_nbr`` per slot, 0 on inactive slots, shape (B, M, T+1, D).
        c_x: quadratic weight of the own plan, ``1 + sum_{active j} rho_j / 2``, shape (B,).
        rho_y: quadratic weight of each neighbour copy (1 on inactive slots), shape (B, M).
        normals: collision normals (0 on inactive slots), shape (B, M, T, D).
        bounds: collision bounds (-1 on inactive slots), shape (B, M, T).
    """

    w_own: Tensor
    w_nbr: Tensor
    c_x: Tensor
    rho_y: Tensor
    normals: Tensor
    bounds: Tensor

    @classmethod
    def of(cls, data: LocalProblemData) -> "ConsensusTerms":
        """The terms of ``data`` (differentiable)."""
        batch, M = data.active.shape
        active = data.active.to(torch.bool)
        act4 = active[:, :, None, None]
        rho = data.rho.expand(batch, M) if data.rho.dim() == 0 else data.rho
        rho_nbr = rho if data.rho_nbr is None else data.rho_nbr.expand(batch, M)
        zero = data.z_own.new_zeros(())
        normals, bounds = mask_inactive_rows(data.normals, data.bounds, active)
        return cls(w_own=torch.where(act4, rho[:, :, None, None] * data.z_own - data.lam_own, zero),
                   w_nbr=torch.where(act4, rho_nbr[:, :, None, None] * data.z_nbr - data.lam_nbr, zero),
                   c_x=1.0 + 0.5 * torch.where(active, rho, torch.zeros_like(rho)).sum(dim=1),
                   rho_y=torch.where(active, rho_nbr, torch.ones_like(rho_nbr)),
                   normals=normals, bounds=bounds)


def acceptance_failures(data: LocalProblemData, X: Tensor, U: Tensor, Y: Tensor, slack: Tensor,
                        nominal_B: Tensor, constraints: LocalConstraints) -> Tensor:
    """Failure code per problem (0 accepted, else ``FAIL_NONFINITE`` or ``FAIL_INACCURATE``), (B,).

    A finite answer is accepted when the initial condition, the dynamics (``nominal_B`` (D, Du)
    where ``data.dyn_B`` is None), the input bounds, ``slack >= 0`` and the (softened) collision
    rows of active slots hold within :data:`FEASIBILITY_TOL` relative to the plan's scale
    (``1 + max |X|``; the input bounds relative to ``1 +`` their size). The soft state constraints
    hold by construction (their slacks are free). Evaluated on detached copies by the compiled
    :func:`~torch_gpmpc.control.acceptance.failure_codes`: torch's (or NumPy's) per-call overhead on
    these small arrays would cost more than the compiled solve it checks.
    """
    return torch.from_numpy(AcceptanceCheck(data, nominal_B, constraints).codes(X, U, Y, slack)).to(X.device)


def solve_verdicts(data: LocalProblemData, X: Tensor, U: Tensor, Y: Tensor, slack: Tensor, nominal_B: Tensor,
                   constraints: LocalConstraints, converged: np.ndarray, valid: np.ndarray | None = None
                   ) -> tuple[Tensor, Tensor, Tensor]:
    """``(failure, ok, slack_active)``, each (B,), of a solver's plans for ``data``: the acceptance rule
    (:func:`acceptance_failures`), then invalid input data (``valid`` (B,) False) as non-finite and
    unconverged solves (``converged`` (B,) False) as inaccurate; ``slack_active``: an accepted solve
    that softened a collision row of an active slot. In NumPy: a dozen torch calls on (B,) flags
    cost more than the check itself."""
    failure = acceptance_failures(data, X, U, Y, slack, nominal_B, constraints).cpu().numpy()
    if valid is not None:
        failure = np.where(valid, failure, FAIL_NONFINITE)
    failure = np.where(~converged & (failure == 0), FAIL_INACCURATE, failure)
    ok = failure == 0
    used = slack.detach().cpu().numpy() * data.active.detach().cpu().numpy()[:, :, None]
    slack_active = (used > SLACK_ACTIVE_TOL).reshape(ok.shape[0], -1).any(axis=1) & ok
    device = X.device
    return (torch.from_numpy(failure).to(device), torch.from_numpy(ok).to(device),
            torch.from_numpy(slack_active).to(device))


class AcceptanceCheck:
    """:func:`acceptance_failures` for the problems of ``data``, their arrays converted once: the
    check of repeated solves of the same problems (ADMM's compiled iterations) converts only the plans.

    Args:
        data, nominal_B, constraints: as :func:`acceptance_failures`.
    """

    def __init__(self, data: LocalProblemData, nominal_B: Tensor, constraints: LocalConstraints) -> None:
        batch, T = data.xref.shape[0], data.xref.shape[1] - 1
        Bd = as_array(nominal_B) if data.dyn_B is None else as_array(data.dyn_B)
        Bd = np.ascontiguousarray(np.broadcast_to(Bd, (batch, T, *Bd.shape[-2:])))
        self._problem = (as_array(data.x0), as_array(data.dyn_A), Bd, as_array(data.dyn_c), as_array(data.normals),
                         as_array(data.bounds), as_array(data.active, np.bool_))
        self._limits = (np.asarray(constraints.input_box or (), dtype=np.float64),
                        np.inf if constraints.input_norm is None else float(constraints.input_norm),
                        float(constraints.input_scale), FEASIBILITY_TOL, _CODES)

    def codes(self, X: Tensor, U: Tensor, Y: Tensor, slack: Tensor) -> np.ndarray:
        """(B,) int64 failure codes of the plans X (B, T+1, D), U (B, T, Du), Y (B, M, T+1, D) and
        their slacks (B, M, T)."""
        code = np.empty(X.shape[0], dtype=np.int64)
        failure_codes(as_array(X), as_array(U), as_array(Y), as_array(slack), *self._problem, *self._limits, code)
        return code
