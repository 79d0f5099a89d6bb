"""Reproducible local problems for tests and benchmarks: agents crossing a disc.

Each agent starts on a circle and heads through its centre; its neighbours start
further round the circle and head through the centre too, so every collision row
matters. Linearization, covariances, normals and margins go through the library's own
chain (:func:`~torch_gpmpc.control.linearize.linearize_plan` ->
:func:`~torch_gpmpc.control.risk.state_covariances` -> :func:`~torch_gpmpc.control.risk.projected_variances`
-> :func:`~torch_gpmpc.control.risk.pair_margins`: the one margin path the controller runs),
so gradients reach rho, the risk split and the consensus variables.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from torch_gpmpc.control.linearize import linearize_plan
from torch_gpmpc.control.problem import LocalProblemData, mask_inactive_rows
from torch_gpmpc.control.risk import (
    collision_normals, pair_margins, pair_risks, projected_variances, state_covariances,
)
from torch_gpmpc.dynamics.systems import NominalModel, VortexWind


@dataclass
class CrossingInstance:
    """B crossing agents with M neighbours each: linearization data and an ADMM iterate.

    Attributes:
        xbar: own linearization points, shape (B, T+1, D).
        xbar_nbr: neighbours' linearization points, shape (B, M, T+1, D).
        xref: references, shape (B, T+1, D).
        x0: measured states, shape (B, D).
        dyn_A, dyn_c: linearized dynamics, shapes (B, T, D, D) and (B, T, D).
        sigma: state covariances, shape (B, T+1, D, D).
        normals: collision normals, shape (B, M, T+1, D).
        active: which slots hold a neighbour, shape (B, M), bool.
        z_own, z_nbr, lam_own, lam_nbr: consensus variables and duals, shape (B, M, T+1, D).
    """

    xbar: Tensor
    xbar_nbr: Tensor
    xref: Tensor
    x0: Tensor
    dyn_A: Tensor
    dyn_c: Tensor
    sigma: Tensor
    normals: Tensor
    active: Tensor
    z_own: Tensor
    z_nbr: Tensor
    lam_own: Tensor
    lam_nbr: Tensor

    def problem_data(self, rho: float | Tensor = 20.0, split: float | Tensor = 0.5, eps: float | Tensor = 0.1,
                     r_safe: float = 0.5, x0: Tensor | None = None, z_own: Tensor | None = None,
                     z_nbr: Tensor | None = None) -> LocalProblemData:
        """The local problems, margins through ``pair_risks -> pair_margins("own")`` (each agent
        takes the lower-indexed share ``eps * split``: the paper's eq. 24, as the controller
        computes it with ``pair_margin = own``)."""
        eps_low, eps_high = pair_risks(torch.as_tensor(eps, dtype=torch.float64),
                                       torch.as_tensor(split, dtype=torch.float64))
        ones = torch.ones(self.active.shape, dtype=torch.float64)
        var = projected_variances(self.normals[:, :, 1:], self.sigma[:, 1:])
        margins = pair_margins("own", var, var, eps_low * ones, eps_high * ones)
        normals, bounds = mask_inactive_rows(self.normals[:, :, 1:], r_safe + margins, self.active)
        return LocalProblemData(
            x0=self.x0 if x0 is None else x0, xref=self.xref, dyn_A=self.dyn_A, dyn_c=self.dyn_c,
            normals=normals, bounds=bounds, active=self.active, rho=torch.as_tensor(rho, dtype=torch.float64),
            z_own=self.z_own if z_own is None else z_own, z_nbr=self.z_nbr if z_nbr is None else z_nbr,
            lam_own=self.lam_own, lam_nbr=self.lam_nbr,
        )


def straight_lines(start: Tensor, direction: Tensor, speed: float, horizon: int) -> Tensor:
    """Points ``start + tau * speed * direction`` for tau = 0..T; (..., D) -> (..., T+1, D)."""
    steps = torch.arange(horizon + 1, dtype=torch.float64)[:, None]
    return start[..., None, :] + speed * steps * direction[..., None, :]


def crossing_instance(batch: int, num_neighbors: int, *, horizon: int = 13, radius: float = 0.9,
                      speed: float = 0.12, ref_speed: float = 0.18, spread: float = 0.2,
                      method: str = "gp-chance", mode: str = "pointwise", gps: Sequence | None = None,
                      variance: float | None = None, seed: int = 0, active: Tensor | None = None) -> CrossingInstance:
    """B agents crossing a disc of ``radius`` (2-D), each with ``num_neighbors`` crossing neighbours.

    Args:
        batch: B. num_neighbors: M. horizon: T.
        radius: start circle; speed / ref_speed: plan and reference speed per step.
        spread: random extra angle of the neighbours' starts (uniform in [0, spread)).
        method: the linearization method (the wind is the paper's vortex).
        mode: ``pointwise`` or ``propagated`` covariances.
        gps: one residual model per agent for ``gp`` and chance methods.
        variance: if given, covariances from this constant per-dimension variance instead.
        seed: seeds every random draw.
        active: which slots hold a neighbour (default all), shape (B, M).
    """
    g = torch.Generator().manual_seed(seed)
    T, D, M = horizon, 2, num_neighbors

    def rand(*shape: int) -> Tensor:
        return torch.rand(*shape, generator=g, dtype=torch.float64)

    def noise(*shape: int) -> Tensor:
        return torch.randn(*shape, generator=g, dtype=torch.float64)

    angle = 2 * torch.pi * rand(batch)
    start = radius * torch.stack([torch.cos(angle), torch.sin(angle)], -1)
    xbar = straight_lines(start, -start / radius, speed, T)
    xref = straight_lines(start, -start / radius, ref_speed, T)
    nbr_angle = angle[:, None] + 2 * torch.pi * (torch.arange(M) + 1) / (M + 1) + spread * rand(batch, M)
    nbr_start = radius * torch.stack([torch.cos(nbr_angle), torch.sin(nbr_angle)], -1)
    xbar_nbr = straight_lines(nbr_start, -nbr_start / radius, speed, T)
    lin = linearize_plan(method, xbar, NominalModel(D), VortexWind(), gps)
    var = lin.var if variance is None else torch.full_like(xbar, variance)
    sigma = state_covariances(mode, var, lin.dyn_A)
    ids = torch.arange(batch)
    normals = collision_normals(xbar, xbar_nbr, ids, ids[:, None] + 100 + torch.arange(M))
    if active is None:
        active = torch.ones(batch, M, dtype=torch.bool)
    return CrossingInstance(
        xbar=xbar, xbar_nbr=xbar_nbr, xref=xref, x0=start.clone(), dyn_A=lin.dyn_A, dyn_c=lin.dyn_c,
        sigma=sigma, normals=normals, active=active,
        z_own=xbar[:, None].expand(batch, M, T + 1, D) + 0.02 * noise(batch, M, T + 1, D),
        z_nbr=xbar_nbr + 0.02 * noise(batch, M, T + 1, D),
        lam_own=0.1 * noise(batch, M, T + 1, D), lam_nbr=0.1 * noise(batch, M, T + 1, D),
    )
