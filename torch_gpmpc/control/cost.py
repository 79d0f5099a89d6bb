"""The tracking cost a researcher states: :class:`QuadraticCost` and its terms in the local problem.

With states ``x_tau`` (n), inputs ``u_tau`` (m) and the reference ``r_tau``, the local problem's
tracking cost over the horizon T is::

    sum_{tau=0}^{T-1} [ (x_tau - r_tau)^T Q (x_tau - r_tau) + (u_tau - u_ref)^T R (u_tau - u_ref) ]
    + (x_T - r_T)^T P (x_T - r_T)

(``x_0`` is measured, so its term is a constant). Without a stated cost the package uses
``Q = I`` (0 on the rows that hold the last input, which the input cost weighs already:
:attr:`~torch_gpmpc.config.model_spec.ModelSpec.input_memory`), ``R = alpha I`` and, by default,
the LQR cost-to-go of the nominal model as ``P`` (:func:`lqr_terminal_weight`); the paper's own cost
is ``P = Q`` (``terminal_cost = stage``).
The input-rate term, the slack penalties and the ADMM terms are added on top by the solvers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from torch_gpmpc.errors import GpmpcError


def _as_weight(value, size: int, name: str, *, dtype: torch.dtype, where: str = "QuadraticCost.",
               unit: str = "states") -> Tensor:
    """A (size, size) symmetric positive semidefinite weight from a matrix, a vector (its diagonal)
    or a number (times I); raises naming ``name`` otherwise."""
    try:
        t = torch.as_tensor(value, dtype=dtype) if not isinstance(value, Tensor) else value.to(dtype)
    except (TypeError, ValueError, RuntimeError):
        raise GpmpcError(f"{where}{name} must be a number, a vector (the diagonal) or a matrix of numbers; got "
                         f"{value!r}") from None
    if t.dim() == 0:
        t = t * torch.eye(size, dtype=dtype)
    elif t.dim() == 1:
        if t.shape[0] != size:
            raise GpmpcError(f"{where}{name}: a diagonal of {size} entries is needed (the model has "
                             f"{size} {unit}), got {t.shape[0]}")
        t = torch.diag_embed(t)
    if tuple(t.shape) != (size, size):
        raise GpmpcError(f"{where}{name} must be ({size}, {size}), a diagonal of {size} or a number; "
                         f"got shape {tuple(t.shape)}")
    d = t.detach()
    if not bool(torch.isfinite(d).all()):
        raise GpmpcError(f"{where}{name} has a non-finite entry")
    if not torch.allclose(d, d.T, rtol=1e-10, atol=1e-12):
        raise GpmpcError(f"{where}{name} must be symmetric; use (W + W.T) / 2")
    smallest = float(torch.linalg.eigvalsh(d).min())
    if smallest < -1e-9 * max(1.0, float(d.abs().max())):
        raise GpmpcError(f"{where}{name} must be positive semidefinite (smallest eigenvalue "
                         f"{smallest:.3g})")
    return 0.5 * (t + t.mT)  # symmetric in value already; so are its gradients


class _RiccatiSolution(torch.autograd.Function):
    """The stabilizing DARE solution P(Q, R) of a fixed (A, B), differentiable in Q and R.

    Its differential is ``dP = A_cl^T dP A_cl + dQ + K^T dR K`` (``K = (R + B^T P B)^{-1} B^T P A``,
    ``A_cl = A - B K``): a discrete Lyapunov equation, so the vector-Jacobian product solves its adjoint
    ``Y = A_cl Y A_cl^T + G`` and gives ``dL/dQ = Y``, ``dL/dR = K Y K^T``.
    """

    @staticmethod
    def forward(ctx, Q: Tensor, R: Tensor, A: Tensor, B: Tensor) -> Tensor:  # noqa: D102
        import scipy.linalg

        a, b, q, r = (np.asarray(t.detach().cpu().double().numpy()) for t in (A, B, Q, R))
        try:
            p = scipy.linalg.solve_discrete_are(a, b, q, r)
        except (np.linalg.LinAlgError, ValueError) as exc:
            raise GpmpcError(f"no LQR terminal weight for this model ({exc}); give the cost's P explicitly, or "
                             f"terminal_cost=stage") from None
        p = 0.5 * (p + p.T)
        k = np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a)
        ctx.closed_loop, ctx.gain, ctx.dtypes = a - b @ k, k, (Q.dtype, R.dtype)
        return torch.as_tensor(p, dtype=torch.float64, device=Q.device)

    @staticmethod
    def backward(ctx, grad: Tensor):  # noqa: D102
        import scipy.linalg

        g = grad.detach().cpu().double().numpy()
        y = scipy.linalg.solve_discrete_lyapunov(ctx.closed_loop, 0.5 * (g + g.T))
        k, (q_type, r_type) = ctx.gain, ctx.dtypes
        return (torch.as_tensor(y, dtype=q_type, device=grad.device),
                torch.as_tensor(k @ y @ k.T, dtype=r_type, device=grad.device), None, None)


def lqr_terminal_weight(A: Tensor, B: Tensor, Q: Tensor, R: Tensor) -> Tensor:
    """The infinite-horizon LQR cost-to-go ``P`` of ``x' = A x + B u`` with weights Q, R: the
    stabilizing solution of the discrete algebraic Riccati equation
    ``P = Q + A^T P A - A^T P B (R + B^T P B)^{-1} B^T P A`` (scipy's ``solve_discrete_are``),
    differentiable with respect to Q and R (implicitly, through the Riccati equation's Lyapunov
    differential).

    Args:
        A: (n, n). B: (n, m). Q: (n, n) PSD. R: (m, m) positive definite.

    Returns:
        P, shape (n, n), float64.

    Raises:
        GpmpcError: when R is singular or the pair (A, B) admits no stabilizing solution.

    Examples:
        >>> import torch
        >>> P = lqr_terminal_weight(torch.eye(1), 0.1 * torch.eye(1), torch.eye(1), 1e-3 * torch.eye(1))
        >>> round(float(P), 6)  # p^2 - p - 0.1 = 0
        1.091608
    """
    return _RiccatiSolution.apply(Q, R, A, B)


@dataclass
class QuadraticCost:
    """A quadratic tracking cost (module docstring): Q weighs the state error, R the inputs
    around ``u_ref``, P the terminal state error.

    Args:
        Q: (n, n) PSD matrix, an (n,) diagonal or a number (times I).
        R: (m, m) positive definite matrix, an (m,) diagonal or a number (times I).
        P: (n, n) terminal weight (as Q); ``None``: the model's LQR cost-to-go for Q and R.
        u_ref: (m,) the input the cost pulls towards; ``None``: 0.

    Tensors that require grad keep it: the compiled solver differentiates the plans with respect
    to Q, R, P and u_ref.

    Examples:
        >>> import torch
        >>> from torch_gpmpc import ModelSpec, NominalModel
        >>> model = NominalModel(ModelSpec.double_integrator(2, dt=0.1, u_max=2.0))
        >>> cost = QuadraticCost(Q=torch.tensor([1.0, 1.0, 0.1, 0.1]), R=0.01)
        >>> Q, R, P, u_ref = cost.resolve(model)
        >>> tuple(Q.shape), tuple(R.shape), tuple(P.shape), tuple(u_ref.shape)
        ((4, 4), (2, 2), (4, 4), (2,))
    """

    Q: object
    R: object
    P: object = None
    u_ref: object = None

    def resolve(self, nominal, where: str = "QuadraticCost.") -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The weights for a model: ``(Q (n, n), R (m, m), P (n, n), u_ref (m,))``, float64,
        validated (raises :class:`GpmpcError` naming ``<where><field>``); ``nominal`` is a
        :class:`~torch_gpmpc.dynamics.systems.NominalModel` (its A and B give the LQR ``P``)."""
        dtype = torch.float64
        A, B = nominal.A(dtype), nominal.B(dtype)  # constants: the cost's gradients are Q's, R's, P's
        n, m = A.shape[0], B.shape[1]
        Q = _as_weight(self.Q, n, "Q", dtype=dtype, where=where)
        R = _as_weight(self.R, m, "R", dtype=dtype, where=where, unit="inputs")
        if float(torch.linalg.eigvalsh(R.detach()).min()) <= 0.0:
            raise GpmpcError(f"{where}R must be positive definite (every input needs a weight > 0)")
        P = lqr_terminal_weight(A, B, Q, R) if self.P is None else _as_weight(self.P, n, "P", dtype=dtype,
                                                                              where=where)
        if self.u_ref is None:
            u_ref = torch.zeros(m, dtype=dtype)
        else:
            try:
                u_ref = torch.as_tensor(self.u_ref, dtype=dtype) if not isinstance(self.u_ref, Tensor) \
                    else self.u_ref.to(dtype)
            except (TypeError, ValueError, RuntimeError):
                raise GpmpcError(f"{where}u_ref must be {m} numbers (one per input), got {self.u_ref!r}") from None
            if tuple(u_ref.shape) != (m,) or not bool(torch.isfinite(u_ref.detach()).all()):
                raise GpmpcError(f"{where}u_ref must be {m} finite numbers (one per input), got shape "
                                 f"{tuple(u_ref.shape)}")
        return Q, R, P, u_ref


def horizon_weights(Q: Tensor, P: Tensor, horizon: int) -> Tensor:
    """The state weight of ``X_1..X_T``: Q at tau = 1..T-1, P at tau = T; Q, P (B, n, n) ->
    (B, T, n, n)."""
    stage = Q.unsqueeze(1).expand(Q.shape[0], horizon - 1, *Q.shape[1:])
    return torch.cat([stage, P.unsqueeze(1)], dim=1)


def plan_tracking_cost(X: Tensor, U: Tensor, xref: Tensor, alpha: float, Q: Tensor | None = None,
                       R: Tensor | None = None, P: Tensor | None = None, u_ref: Tensor | None = None) -> Tensor:
    """The tracking cost of plans, (B,): ``||X - Xref||^2 + alpha ||U||^2`` when Q is None, else the
    stated cost (module docstring).

    Args:
        X: (B, T+1, n). U: (B, T, m). xref: (B, T+1, n). Q, P: (B, n, n). R: (B, m, m). u_ref: (B, m).
    """
    if Q is None:
        return ((X - xref) ** 2).sum(dim=(1, 2)) + alpha * (U ** 2).sum(dim=(1, 2))
    e = X - xref
    W = torch.cat([Q.unsqueeze(1), horizon_weights(Q, P, e.shape[1] - 1)], dim=1)  # tau = 0..T
    du = U if u_ref is None else U - u_ref[:, None]
    return torch.einsum("bti,btij,btj->b", e, W, e) + torch.einsum("bti,bij,btj->b", du, R, du)
