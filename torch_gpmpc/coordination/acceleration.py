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
every edge, a reduction like the stopping test's maximum of the residual ratios. The in-process ADMM
forms them directly (:class:`AndersonAcceleration`); across agent processes each agent adds its
share to its residual message (:class:`PartialAnderson`) and the world sums them, restarts and
solves (:class:`AndersonWorld`), sending the weights back with the stop decision.
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

    Examples:
        >>> import torch
        >>> v = [torch.tensor([0.0]), torch.tensor([1.0])]                 # F(v) = 0.5 v + 1, affine:
        >>> anderson_mix([0.5 * x + 1 for x in v], v, regularization=0.0)  # one mix is its fixed point
        tensor([2.])
    """
    if len(images) < 2:
        return images[-1]
    dG, dF, g_last = _differences(images, points)
    gamma = mixing_weights(dG.T @ dG, dG.T @ g_last, regularization)
    if gamma is None:
        return images[-1]
    mixed = images[-1] - dF @ gamma
    return mixed if bool(torch.isfinite(mixed).all()) else images[-1]


def mixing_weights(gram: Tensor, rhs: Tensor, regularization: float = REGULARIZATION) -> Tensor | None:
    """``gamma`` of the regularized least squares from its sums: ``gram = dG^T dG`` (c, c) and
    ``rhs = dG^T g_k`` (c,), summed over every edge (in process directly; across agent processes
    from each agent's share); ``None`` when the differences vanish or are not finite (plain step)."""
    scale = gram.diagonal().sum()
    if not bool(scale > 0) or not bool(torch.isfinite(scale)):
        return None
    eye = torch.eye(gram.shape[0], dtype=gram.dtype, device=gram.device)
    return torch.linalg.solve(gram + regularization * scale * eye, rhs)


def _differences(images: list[Tensor], points: list[Tensor]) -> tuple[Tensor, Tensor, Tensor]:
    """``(dG (d, L-1), dF (d, L-1), g_k (d,))``: consecutive differences of the residuals
    ``g_i = F(v_i) - v_i`` and of the images, and the last residual."""
    g = torch.stack([f - v for f, v in zip(images, points)], 1)  # (d, L)
    f = torch.stack(images, 1)
    return g[:, 1:] - g[:, :-1], f[:, 1:] - f[:, :-1], g[:, -1]


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


class PartialAnderson:
    """One agent process's share of the mix (the distributed backend): the history of its own
    coordinates (the consensus of its edges and its own duals), its terms of the sums the least
    squares needs, and the mixed next input once the world has solved for ``gamma``.

    The sums run over each coordinate once: ``counted`` masks the consensus of the edges another
    agent counts (the edge's lower-indexed end counts it) and the neighbours' duals (zero here).
    Both ends of an edge hold the same consensus history and receive the same ``gamma``, so they
    compute the same mixed consensus.

    Args:
        memory: ``admm_anderson_memory``.
        counted: (d,) bool, which of the agent's coordinates it contributes to the sums.
    """

    def __init__(self, memory: int, counted: Tensor) -> None:
        self.memory = int(memory)
        self.counted = counted
        self._points: list[Tensor] = []
        self._images: list[Tensor] = []

    def push(self, before: ADMMState, after: ADMMState) -> tuple[float, Tensor, Tensor]:
        """Add the iteration ``before -> after``; returns this agent's terms: the squared norm of its
        counted residual, and ``dG^T dG`` (c, c) and ``dG^T g_k`` (c,) over its counted coordinates
        for the history as it would stand without a restart (c = its length - 1, at most memory)."""
        v, f = _flat(before), _flat(after)
        self._points = (self._points + [v])[-(self.memory + 1):]
        self._images = (self._images + [f])[-(self.memory + 1):]
        r2 = float(((f - v)[self.counted] ** 2).sum())
        if len(self._images) < 2:
            return r2, f.new_zeros(0, 0), f.new_zeros(0)
        dG, _, g_last = _differences(self._images, self._points)
        dG, g_last = dG[self.counted], g_last[self.counted]
        return r2, dG.T @ dG, dG.T @ g_last

    def next_input(self, after: ADMMState, restart: bool, gamma: Tensor | None) -> ADMMState:
        """``after`` with the mix of the world's ``gamma`` (``None``: plain); a restart keeps only
        the latest pair."""
        if restart:
            self._points, self._images = self._points[-1:], self._images[-1:]
        if gamma is None or restart or len(self._images) < 2:
            return after
        _, dF, _ = _differences(self._images, self._points)
        mixed = self._images[-1] - dF @ gamma
        return _with_flat(after, mixed) if bool(torch.isfinite(mixed).all()) else after


class AndersonWorld:
    """The world process's part of the distributed mix: it sums the agents' terms (their residual
    messages, :func:`~.distributed.protocol.residual_size`), restarts the history on the rules of
    :class:`AndersonAcceleration` (any edge's penalty changed, or the residual grew more than
    :data:`GROWTH_RESTART` times) and solves for the mixing weights, which it broadcasts with the
    stop decision.

    Args:
        memory: ``admm_anderson_memory``.
    """

    def __init__(self, memory: int) -> None:
        self.memory = int(memory)
        self._residual: float | None = None

    def decide(self, messages: list[Tensor], stopping: bool) -> list[float]:
        """``[restart, c, gamma_1..gamma_memory]`` (weights past c are 0; c = 0: a plain step) from
        the live agents' residual messages of this iteration."""
        m = self.memory
        residual = sum(float(v[4]) for v in messages) ** 0.5
        changed = any(float(v[5]) > 0.5 for v in messages)
        grew = self._residual is not None and residual > GROWTH_RESTART * self._residual
        self._residual = residual
        restart = changed or grew
        c = int(messages[0][6]) if messages else 0
        gamma = None
        if not (restart or stopping) and c > 0:
            gram = sum(v[7:7 + m * m].reshape(m, m)[:c, :c] for v in messages)
            rhs = sum(v[7 + m * m:7 + m * m + c] for v in messages)
            gamma = mixing_weights(gram, rhs)
        weights = [0.0] * m
        if gamma is not None:
            weights[:c] = gamma.tolist()
        return [float(restart), float(0 if gamma is None else c), *weights]
