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
from torch_gpmpc.gp.batch import linearize_models
from torch_gpmpc.dynamics.systems import PAPER_DT, NominalModel, VortexWind


@dataclass
class LinearizedPlan:
    """Affine dynamics and variances along B plans of horizon T (state dimension D, input Du).

    Attributes:
        dyn_A: state matrices ``A + E J_x(zbar_tau)``, shape (B, T, D, D).
        dyn_c: offsets ``E (mu(zbar_tau) - J(zbar_tau) zbar_tau)``, shape (B, T, D).
        var: variance at every linearization point on the state rows, shape (B, T+1, D):
            the residual rows' GP variance (plus observation noise if requested) for
            ``-chance`` methods, zeros elsewhere.
        method: the method that produced it.
        dyn_B: input matrices ``B + E J_u`` when the GP reads the input, shape (B, T, D, Du);
            ``None`` when the input matrix is the nominal B.
    """

    dyn_A: Tensor
    dyn_c: Tensor
    var: Tensor
    method: str
    dyn_B: Tensor | None = None


def linearize_plan(
    method: str | Method,
    xbar: Tensor,
    nominal: NominalModel,
    wind: VortexWind | None = None,
    gps: Sequence[Any] | None = None,
    include_noise: bool = False,
    ubar: Tensor | None = None,
) -> LinearizedPlan:
    """Linearize the dynamics of B agents around their planned trajectories.

    The residual ``r`` lives on the model's residual rows (``E``, R of them) and is a function
    of the GP input ``zeta = S_x x + S_u u`` (the model's ``gp_inputs``); around ``zetabar``
    ``r ~ mu + J (zeta - zetabar)``, so ``x' = (A + E J S_x) x + (B + E J S_u) u + E (mu - J zetabar)``.

    Args:
        method: one of ``nominal, nominal-chance, nonlinear, nonlinear-chance, gp, gp-chance``.
        xbar: linearization points (one plan per agent), shape (B, T+1, D).
        nominal: the known model ``f(x, u) = A x + B u`` with its residual rows and GP inputs.
        wind: the known residual ``g`` of the position; required by ``nonlinear*``.
        gps: one residual GP per agent (length B), each with
            ``linearize(zeta (n, Din)) -> (mean (n, R), jac (n, R, Din), var (n, R))`` and
            attribute ``noise`` (R,); required by ``gp*`` and all ``-chance`` methods.
        include_noise: add each GP's observation-noise variance to ``var``.
        ubar: planned inputs, shape (B, T, Du); needed when the GP reads the input (the
            last point reuses the last input).

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
    R = len(nominal.residual)
    opts = {"dtype": xbar.dtype, "device": xbar.device}
    Sx, Su = nominal.gp_selectors(**opts)
    uses_input = method.needs_gp and nominal.gp_uses_input
    if uses_input and ubar is None:
        raise GpmpcError("the GP reads the input (gp_inputs has u columns): pass the planned inputs ubar")
    zbar = _gp_points(nominal, xbar, ubar) if method.needs_gp else None

    gp_out = None
    if method.needs_gp:
        gp_out = _gp_linearizations(gps, zbar, method, R, include_noise)

    jac_u = None
    if base is Dynamics.NOMINAL:
        mean, jac_x, offset = xbar.new_zeros(batch, steps, R), xbar.new_zeros(batch, steps, R, dim), None
    elif base is Dynamics.NONLINEAR:
        mean, jac_x = _wind_linearization(wind, xbar, method, nominal)
        offset = (jac_x @ xbar.unsqueeze(-1)).squeeze(-1)
    else:
        mean, jac = gp_out[0], gp_out[1]
        jac_x = jac @ Sx
        if uses_input:
            jac_u = jac @ Su
        offset = (jac @ zbar.unsqueeze(-1)).squeeze(-1)

    if chance:
        var = gp_out[2]
    else:
        var = xbar.new_zeros(batch, steps, R)

    E = nominal.residual_embedding(**opts)
    dyn_A = nominal.A(**opts) + E @ jac_x[:, :-1]
    resid_c = mean[:, :-1] if offset is None else mean[:, :-1] - offset[:, :-1]
    dyn_c = resid_c @ E.T
    dyn_B = None if jac_u is None else nominal.B(**opts) + E @ jac_u[:, :-1]
    return LinearizedPlan(dyn_A=dyn_A, dyn_c=dyn_c, var=var @ E.T, method=method.value, dyn_B=dyn_B)


def _gp_points(nominal: NominalModel, xbar: Tensor, ubar: Tensor | None) -> Tensor:
    """GP inputs along the plans, (B, T+1, Din); the last point reuses the last input."""
    if ubar is None:
        return nominal.gp_input(xbar, None)
    u_ext = torch.cat([ubar, ubar[:, -1:]], dim=1)
    return nominal.gp_input(xbar, u_ext)


def _wind_linearization(wind: VortexWind | None, xbar: Tensor, method: Method,
                        nominal: NominalModel) -> tuple[Tensor, Tensor]:
    """The known residual ``(dt / 0.1) g(p)`` (B, T+1, R) and its Jacobian in x (B, T+1, R, D)."""
    if wind is None:
        raise GpmpcError(f"method {method.value!r} needs the wind model g (wind=None was given)")
    batch, steps, dim = xbar.shape
    pos = nominal.position
    if len(pos) not in (2, 3) or len(nominal.residual) != len(pos):
        raise GpmpcError(f"the vortex wind is defined for 2 or 3 positions on as many residual rows; model "
                         f"{nominal.spec.name!r} has {len(pos)} and {len(nominal.residual)}")
    gain = nominal.spec.dt / PAPER_DT
    flat = xbar[..., pos].reshape(batch * steps, len(pos))
    mean = gain * wind(flat).reshape(batch, steps, len(pos))
    jac_p = gain * wind.jacobian(flat).reshape(batch, steps, len(pos), len(pos))
    jac = xbar.new_zeros(batch, steps, len(pos), dim)
    jac[..., pos] = jac_p
    return mean, jac


def _gp_linearizations(gps, zbar: Tensor, method: Method, R: int,
                       include_noise: bool) -> tuple[Tensor, Tensor, Tensor]:
    """Stacked GP mean (B, T+1, R), Jacobian (B, T+1, R, Din), latent variance (B, T+1, R) (plus each
    GP's observation noise with ``include_noise``)."""
    batch, steps, din = zbar.shape
    if gps is None:
        raise GpmpcError(f"method {method.value!r} needs one residual GP per agent (gps=None was given)")
    if len(gps) != batch:
        raise GpmpcError(f"method {method.value!r}: got {len(gps)} GPs for {batch} agents")
    for k, gp in enumerate(gps):
        if getattr(gp, "output_dim", R) != R:
            raise GpmpcError(f"the GP of agent {k} has {gp.output_dim} outputs but the model has {R} residual rows; "
                             "fit it on the model's residual rows")
    mean, jac, var = linearize_models(gps, zbar, include_noise=include_noise)
    expected = {"mean": (batch, steps, R), "jac": (batch, steps, R, din), "var": (batch, steps, R)}
    for name, value in (("mean", mean), ("jac", jac), ("var", var)):
        if tuple(value.shape) != expected[name]:
            raise GpmpcError(f"the GPs returned {name} of shape {tuple(value.shape)}, expected {expected[name]} "
                             f"(are they trained on the model's {din} GP inputs and {R} residual rows?)")
    return mean, jac, var
