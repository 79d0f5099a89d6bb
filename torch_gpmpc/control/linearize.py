"""Linearization of the residual dynamics along a plan (paper section 3.2, Table 1).

Around the linearization points ``xbar_tau`` every method uses the affine model
(paper eqs. 14, 17b)::

    x_{tau+1} = (A + J_tau) x_tau + B u_tau + (mu_tau - J_tau xbar_tau)
              =      dyn_A_tau x_tau + B u_tau + dyn_c_tau,

with ``mu_tau``, ``J_tau`` the residual and its Jacobian at ``xbar_tau``:

=====================  ===================  ======================  =================
method                 mu, J                 sigma (margin)          needs
=====================  ===================  ======================  =================
``nominal``            0, 0                  none                    -
``nominal-chance``     0, 0                  GP latent variance      gps
``nonlinear``          g(xbar), dg/dx        none                    wind
``nonlinear-chance``   g(xbar), dg/dx        GP latent variance      wind, gps
``gp``                 GP mean, d mean/dx    none                    gps
``gp-chance``          GP mean, d mean/dx    GP latent variance      gps
=====================  ===================  ======================  =================

``nonlinear`` linearizes the known wind exactly as the GP mean is linearized (it is
non-convex otherwise). The ``-chance`` variants take sigma from the GP (paper Table 1).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import torch
from torch import Tensor

from torch_gpmpc.dynamics.methods import Dynamics, Method
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.dynamics.systems import NominalModel, VortexWind


@dataclass
class LinearizedPlan:
    """Affine dynamics and variances along B plans of horizon T.

    Attributes:
        dyn_A: state matrices ``A + J(xbar_tau)``, shape (B, T, D, D).
        dyn_c: offsets ``mu(xbar_tau) - J(xbar_tau) xbar_tau``, shape (B, T, D).
        var: variance at every linearization point, shape (B, T+1, D); GP latent
            variance (plus observation noise if requested) for ``-chance`` methods,
            zeros otherwise.
        method: the method that produced it.
    """

    dyn_A: Tensor
    dyn_c: Tensor
    var: Tensor
    method: str


def linearize_plan(
    method: str | Method,
    xbar: Tensor,
    nominal: NominalModel,
    wind: VortexWind | None = None,
    gps: Sequence[Any] | None = None,
    include_noise: bool = False,
) -> LinearizedPlan:
    """Linearize the dynamics of B agents around their planned trajectories.

    Args:
        method: one of ``nominal, nominal-chance, nonlinear, nonlinear-chance, gp, gp-chance``.
        xbar: linearization points (one plan per agent), shape (B, T+1, D).
        nominal: the known model ``f(x, u) = A x + B u``.
        wind: the known residual ``g``; required by ``nonlinear*``.
        gps: one residual GP per agent (length B), each with
            ``linearize(x (n, D)) -> (mean (n, D), jac (n, D, D), var (n, D))`` and
            attribute ``noise`` (D,); required by ``gp*`` and all ``-chance`` methods.
        include_noise: add each GP's observation-noise variance to ``var``.

    Returns:
        The :class:`LinearizedPlan` (differentiable w.r.t. ``xbar`` and GP tensors).

    Raises:
        GpmpcError: unknown method, missing or mismatched wind/GPs, bad shapes.
    """
    method = Method.parse(method)
    if xbar.dim() != 3 or xbar.shape[1] < 2:
        raise GpmpcError(f"xbar must have shape (B, T+1, D) with T >= 1, got {tuple(xbar.shape)}")
    batch, steps, dim = xbar.shape
    if dim != nominal.dim:
        raise GpmpcError(f"xbar has D = {dim} but the nominal model has dim = {nominal.dim}")
    base, chance = method.dynamics, method.chance

    gp_out = None
    if method.needs_gp:
        gp_out = _gp_linearizations(gps, xbar, method)

    if base is Dynamics.NOMINAL:
        mean = xbar.new_zeros(batch, steps, dim)
        jac = xbar.new_zeros(batch, steps, dim, dim)
    elif base is Dynamics.NONLINEAR:
        mean, jac = _wind_linearization(wind, xbar, method)
    else:
        mean, jac = gp_out[0], gp_out[1]

    if chance:
        var = gp_out[2]
        if include_noise:
            var = var + torch.stack([_gp_noise(gp, dim, xbar) for gp in gps])[:, None, :]
    else:
        var = xbar.new_zeros(batch, steps, dim)

    a_nom = nominal.A(dtype=xbar.dtype, device=xbar.device)
    jac_t = jac[:, :-1]
    dyn_A = a_nom + jac_t
    dyn_c = mean[:, :-1] - (jac_t @ xbar[:, :-1].unsqueeze(-1)).squeeze(-1)
    return LinearizedPlan(dyn_A=dyn_A, dyn_c=dyn_c, var=var, method=method.value)


def _wind_linearization(wind: VortexWind | None, xbar: Tensor, method: Method) -> tuple[Tensor, Tensor]:
    """g(xbar) (B, T+1, D) and dg/dx (B, T+1, D, D) of the known wind."""
    if wind is None:
        raise GpmpcError(f"method {method.value!r} needs the wind model g (wind=None was given)")
    batch, steps, dim = xbar.shape
    if dim not in (2, 3):
        raise GpmpcError(f"the vortex wind is defined for D = 2 or 3, got D = {dim}")
    flat = xbar.reshape(batch * steps, dim)
    return wind(flat).reshape(batch, steps, dim), wind.jacobian(flat).reshape(batch, steps, dim, dim)


def _gp_linearizations(gps, xbar: Tensor, method: Method) -> tuple[Tensor, Tensor, Tensor]:
    """Stacked GP mean (B, T+1, D), Jacobian (B, T+1, D, D), latent variance (B, T+1, D)."""
    batch, steps, dim = xbar.shape
    if gps is None:
        raise GpmpcError(f"method {method.value!r} needs one residual GP per agent (gps=None was given)")
    if len(gps) != batch:
        raise GpmpcError(f"method {method.value!r}: got {len(gps)} GPs for {batch} agents")
    means, jacs, variances = [], [], []
    for k, gp in enumerate(gps):
        mean, jac, var = gp.linearize(xbar[k])
        expected = {"mean": (steps, dim), "jac": (steps, dim, dim), "var": (steps, dim)}
        for name, value in (("mean", mean), ("jac", jac), ("var", var)):
            if tuple(value.shape) != expected[name]:
                raise GpmpcError(
                    f"GP of agent {k} returned {name} of shape {tuple(value.shape)}, expected "
                    f"{expected[name]} (is the GP trained on D = {dim} states?)"
                )
        means.append(mean)
        jacs.append(jac)
        variances.append(var)
    return torch.stack(means), torch.stack(jacs), torch.stack(variances)


def _gp_noise(gp, dim: int, like: Tensor) -> Tensor:
    """A GP's observation-noise variance as a (D,) tensor."""
    noise = torch.as_tensor(gp.noise, dtype=like.dtype, device=like.device).reshape(-1)
    if noise.shape[0] != dim:
        raise GpmpcError(f"GP noise has {noise.shape[0]} entries, expected D = {dim}")
    return noise
