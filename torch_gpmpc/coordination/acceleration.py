"""Anderson acceleration of a control step's consensus ADMM (``admm_acceleration = anderson``).

One ADMM iteration maps the consensus and the duals ``v = (z, lam)`` to new ones, ``v -> F(v)``
(the local solves, consensus and dual updates of :meth:`~.admm.ADMM.iterate`), and a step's ADMM
is the fixed-point iteration of F. Where many agents meet it converges slowly and linearly; type-II
Anderson acceleration (Walker & Ni 2011; for ADMM and Douglas-Rachford splitting: Zhang,
O'Donoghue & Boyd 2020, the acceleration of SCS 3) takes the next point as the mix of the last
``memory + 1`` images ``F(v_i)`` whose residuals ``g_i = F(v_i) - v_i`` combine to the smallest
norm::

    gamma = argmin ||g_k - dG gamma||^2 + reg ||dG||^2 ||gamma||^2,   v_(k+1) = F(v_k) - dF gamma

(``dG``, ``dF``: differences of consecutive residuals and images). Only the next iteration's input
changes: the local problems, the stopping test (whose residuals certify the KKT conditions at the
point the agents solved from, whatever it was) and the plans are ADMM's own, so a stopped step
meets the same tolerances. Safeguards: the history restarts when an edge's penalty changes
(residual balancing changes the map) or the residual grows more than :data:`GROWTH_RESTART`
times; a step that ends at its iteration cap returns its last plain iterate, never a mix.

The least squares needs the Gram matrix ``dG^T dG`` (memory x memory) and ``dG^T g_k``: sums over
every edge, a reduction like the stopping test's maximum of the residual ratios, which the
in-process ADMM forms directly.
"""

from __future__ import annotations

import dataclasses

import torch
from torch import Tensor

from torch_gpmpc.coordination.state import ADMMState

#: Restart the history when the fixed-point residual grows more than this factor in one iteration.
GROWTH_RESTART = 2.0
#: Tikhonov weight of the least squares, relative to ``||dG||_F^2`` (keeps nearly dependent
#: residual differences from producing huge mixing weights).
REGULARIZATION = 1e-6


def anderson_mix(images: list[Tensor], points: list[Tensor], regularization: float = REGULARIZATION) -> Tensor:
    """The type-II Anderson point from the last points ``v_i`` and their images ``F(v_i)``.

    Args:
        images: ``F(v_i)``, each of shape (d,), oldest first (at least one).
        points: ``v_i``, the same count and shapes.
        regularization: Tikhonov weight relative to ``||dG||_F^2``.

    Returns:
        (d,) ``F(v_k) - dF gamma``; with a single pair, ``F(v_k)`` (plain iteration).

    Example:
        >>> import torch
        >>> v = [torch.tensor([0.0]), torch.tensor([1.0])]                 # F(v) = 0.5 v + 1, affine:
        >>> anderson_mix([0.5 * x + 1 for x in v], v, regularization=0.0)  # one mix is its fixed point
        tensor([2.])
    """
    if len(images) < 2:
        return images[-1]
    g = torch.stack([f - v for f, v in zip(images, points)], 1)  # (d, L)
    f = torch.stack(images, 1)
    dG, dF = g[:, 1:] - g[:, :-1], f[:, 1:] - f[:, :-1]  # (d, L - 1)
    gram = dG.T @ dG
    scale = gram.diagonal().sum()
    if not bool(scale > 0) or not bool(torch.isfinite(scale)):
        return images[-1]
    eye = torch.eye(gram.shape[0], dtype=gram.dtype, device=gram.device)
    gamma = torch.linalg.solve(gram + regularization * scale * eye, dG.T @ g[:, -1])
    mixed = images[-1] - dF @ gamma
    return mixed if bool(torch.isfinite(mixed).all()) else images[-1]


class AndersonAcceleration:
    """The history of one control step's ADMM iterates and the accelerated next input.

    Args:
        memory: how many residual differences the mix uses (``admm_anderson_memory``), >= 1.
    """

    def __init__(self, memory: int) -> None:
        self.memory = int(memory)
        self._points: list[Tensor] = []
        self._images: list[Tensor] = []
        self._rho: Tensor | None = None
        self._residual: float | None = None
        #: how many times the history restarted (penalty change or residual growth)
        self.restarts = 0

    @property
    def history(self) -> int:
        """How many past iterates the next mix can use (1 right after a restart)."""
        return len(self._points)

    def next_input(self, before: ADMMState, after: ADMMState) -> ADMMState:
        """The state the next iteration starts from: ``after`` (the iteration's result from
        ``before``) with its consensus ``z`` and duals ``lam`` replaced by the Anderson mix."""
        if not after.z.numel():
            return after
        v, f = _flat(before), _flat(after)
        residual = float((f - v).norm())
        changed_rho = after.rho is not None and self._rho is not None and not torch.equal(after.rho, self._rho)
        grew = self._residual is not None and residual > GROWTH_RESTART * self._residual
        if changed_rho or grew:
            self._points, self._images = [], []
            self.restarts += 1
        self._rho = None if after.rho is None else after.rho.detach().clone()
        self._residual = residual
        self._points = (self._points + [v])[-(self.memory + 1):]
        self._images = (self._images + [f])[-(self.memory + 1):]
        return _with_flat(after, anderson_mix(self._images, self._points))


def _flat(state: ADMMState) -> Tensor:
    """(d,) the state's consensus and duals, concatenated."""
    return torch.cat([state.z.reshape(-1), state.lam.reshape(-1)])


def _with_flat(state: ADMMState, v: Tensor) -> ADMMState:
    """``state`` with its ``z`` and ``lam`` read back from ``v`` (as :func:`_flat` wrote them)."""
    nz = state.z.numel()
    return dataclasses.replace(state, z=v[:nz].view_as(state.z), lam=v[nz:].view_as(state.lam))
