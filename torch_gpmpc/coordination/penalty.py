"""When consensus ADMM stops, and how each edge's penalty adapts (Boyd et al. 2011, §3.3-3.4).

Everything here is per edge and uses only what both agents of the edge hold (their two
copies, the consensus ``z_e``, the duals ``lam_e`` and ``rho_e``), so the in-process and the
distributed backends compute the same numbers.

Tolerances (§3.3.1, absolute plus relative)::

    eps_pri_e  = admm_tol      + admm_rel_tol * max(||y_{e,0}||, ||y_{e,1}||, ||z_e||)
    eps_dual_e = eps_dual_abs  + admm_rel_tol * ||lam_{e,a}||

with ``eps_dual_abs = admm_dual_tol`` or, when that is null, ``10 admm_tol`` (the dual
residual ``rho_e ||z_e - z_e_prev||`` carries rho's scale). A residual *ratio* is a residual
over its tolerance; ADMM stops when the largest ratio of each kind is at most 1.

Residual balancing (§3.4.1, eq. 3.13) on the ratios, as OSQP balances normalized
residuals: ``rho_e`` doubles when its primal ratio exceeds 10 times its dual ratio and
halves in the opposite case. The duals are kept unscaled (``lam = rho u``), so the scaled
duals ``u = lam / rho`` are rescaled by ``rho_old / rho_new`` implicitly on every change.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torch_gpmpc.config.settings import ControllerSettings

#: Change rho_e by RHO_FACTOR when one residual ratio exceeds RHO_BALANCE times the other
#: (Boyd et al.'s mu = 10, tau = 2); keep it within RHO_BOUNDS.
RHO_BALANCE, RHO_FACTOR, RHO_BOUNDS = 10.0, 2.0, (1e-3, 1e4)
#: Default dual tolerance as a multiple of the primal one (``admm_dual_tol`` null).
DUAL_TOL_FACTOR = 10.0


@dataclass
class EdgeResiduals:
    """One iteration's residuals and tolerances, per edge.

    Attributes:
        primal: (E,) ``max_a ||y_{e,a} - z_e||``.
        dual: (E,) ``rho_e ||z_e - z_e_prev||``.
        eps_primal: (E,) primal tolerance.
        eps_dual: (E,) dual tolerance.
    """

    primal: Tensor
    dual: Tensor
    eps_primal: Tensor
    eps_dual: Tensor

    @property
    def primal_ratio(self) -> Tensor:
        """(E,) primal residual over its tolerance."""
        return self.primal.detach() / self.eps_primal

    @property
    def dual_ratio(self) -> Tensor:
        """(E,) dual residual over its tolerance."""
        return self.dual.detach() / self.eps_dual


def checks_dual(cfg: ControllerSettings) -> bool:
    """Whether the stopping rule tests the dual residual: always for ``primal-dual`` and for the
    planes (whose dual residual is their safety grade); for the paper's ``primal`` rule only when
    ``admm_dual_tol`` is set."""
    return cfg.admm_stop == "primal-dual" or cfg.admm_dual_tol is not None or cfg.admm_coupling == "planes"


def edge_residuals(copies: Tensor, z_new: Tensor, lam_norm: Tensor, primal: Tensor, dual: Tensor, cfg: ControllerSettings,
                   tol: float | None = None) -> EdgeResiduals:
    """Residuals with their tolerances (module docstring).

    Args:
        copies: (E, 2, 2, T+1, n) both ends' copies ``y_{e,a}``.
        z_new: (E, 2, T+1, n) consensus after the update.
        lam_norm: (E,) ``||lam_{e,a}||`` of either end's duals after the update. The two ends'
            duals sum to their start, zero (each update adds ``rho (y_{e,a} - z_e)``, which sums
            to zero over the ends), so both ends have the same norm and each end knows it.
        primal: (E, 2) ``||y_{e,a} - z_e||``; dual: (E,) ``rho_e ||z_e - z_e_prev||``.
        cfg: ``admm_tol``, ``admm_dual_tol``, ``admm_rel_tol``, ``admm_stop``.
        tol: absolute primal tolerance (default ``cfg.admm_tol``).

    Returns:
        The :class:`EdgeResiduals`. With the paper's ``primal`` rule the tolerances are
        absolute only (its criterion).
    """
    tol = cfg.admm_tol if tol is None else tol
    rel = cfg.admm_rel_tol if cfg.admm_stop == "primal-dual" else 0.0
    dual_abs = cfg.admm_dual_tol if cfg.admm_dual_tol is not None else DUAL_TOL_FACTOR * tol
    with torch.no_grad():
        size = torch.maximum(copies.flatten(2).norm(dim=2).amax(dim=1), z_new.flatten(1).norm(dim=1))
        eps_primal = tol + rel * size
        eps_dual = dual_abs + rel * lam_norm
    return EdgeResiduals(primal.amax(dim=1), dual, eps_primal, eps_dual)


def should_stop(primal_ratio: float, dual_ratio: float, cfg: ControllerSettings) -> bool:
    """Stop when the largest primal residual ratio (residual / tolerance) is below 1 and, if
    the rule tests it (:func:`checks_dual`), the largest dual one too."""
    return primal_ratio < 1.0 and (dual_ratio < 1.0 or not checks_dual(cfg))


def unconverged_edges(residuals: EdgeResiduals, cfg: ControllerSettings) -> int:
    """How many edges have not met the stopping test of :func:`should_stop` on their own: the primal
    ratio, and the dual one where the rule tests it (:func:`checks_dual`), not below 1."""
    left = ~(residuals.primal_ratio < 1.0)  # NaN has not converged, as in should_stop
    if checks_dual(cfg):
        left = left | ~(residuals.dual_ratio < 1.0)
    return int(left.sum())


def starting_penalties(carried: Tensor | None, rho: Tensor, num_edges: int) -> Tensor:
    """(E,) penalties at the start of a step: carried over from the warm start where known
    (not NaN), else ``rho``."""
    start = rho.expand(num_edges) if rho.dim() == 0 else rho
    return start if carried is None else torch.where(torch.isnan(carried), start, carried)


def balance_penalty(rho: Tensor, residuals: EdgeResiduals) -> Tensor:
    """Each edge's next penalty by residual balancing on the residual ratios.

    Args:
        rho: (E,) current penalties.
        residuals: this iteration's :class:`EdgeResiduals`.

    Returns:
        (E,) ``rho * 2`` where the primal ratio exceeds 10x the dual one, ``rho / 2`` in the
        opposite case, else ``rho``; within :data:`RHO_BOUNDS`. The factor is piecewise
        constant, so gradients reach the starting rho.
    """
    p, d = residuals.primal_ratio, residuals.dual_ratio
    up, down = p > RHO_BALANCE * d, d > RHO_BALANCE * p
    factor = torch.where(up, RHO_FACTOR, torch.where(down, 1.0 / RHO_FACTOR, 1.0)).to(rho.dtype)
    low, high = RHO_BOUNDS
    r = rho.detach()
    return rho * factor.clamp(min=low / r, max=high / r)
