"""Agent dynamics: the nominal model f, the vortex wind g and the true system.

True system (paper eq. 1): ``x' = f(x, u) + g(x) + w`` with ``f(x, u) = A x + B u``,
``A = I``, ``B = 0.1 I`` and ``w ~ N(0, s^2 I)``.

The wind (paper eq. 32) in 2D is ``g(x) = scale * [sin(x_2), cos(x_1)]``. In 3D we
extend it by a vertical component ``scale * sin(x_1) cos(x_2)`` (an updraft pattern
over the same vortex cells); the horizontal components are unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass(frozen=True)
class NominalModel:
    """Linear nominal model ``f(x, u) = A x + B u`` with ``A = a I``, ``B = b I``.

    Attributes:
        dim: state dimension D (inputs have dimension D too).
        a: diagonal of A (paper: 1.0).
        b: diagonal of B (paper: 0.1).
    """

    dim: int = 2
    a: float = 1.0
    b: float = 0.1

    def A(self, dtype: torch.dtype = torch.float64, device=None) -> Tensor:
        """State matrix, shape (D, D)."""
        return self.a * torch.eye(self.dim, dtype=dtype, device=device)

    def B(self, dtype: torch.dtype = torch.float64, device=None) -> Tensor:
        """Input matrix, shape (D, D)."""
        return self.b * torch.eye(self.dim, dtype=dtype, device=device)

    def __call__(self, x: Tensor, u: Tensor) -> Tensor:
        """Nominal next state.

        Args:
            x: states, shape (..., D).
            u: inputs, shape (..., D).

        Returns:
            ``A x + B u``, shape (..., D).
        """
        return self.a * x + self.b * u


@dataclass(frozen=True)
class VortexWind:
    """The unknown residual ``g`` of the paper (eq. 32), optionally in 3D.

    Attributes:
        scale: amplitude (paper: 0.1).
    """

    scale: float = 0.1

    def __call__(self, x: Tensor) -> Tensor:
        """Wind at states ``x``.

        Args:
            x: states, shape (..., D) with D in {2, 3}.

        Returns:
            g(x), shape (..., D).
        """
        parts = [self.scale * torch.sin(x[..., 1]), self.scale * torch.cos(x[..., 0])]
        if x.shape[-1] == 3:
            parts.append(self.scale * torch.sin(x[..., 0]) * torch.cos(x[..., 1]))
        elif x.shape[-1] != 2:
            raise ValueError(f"VortexWind is defined for D = 2 or 3, got D = {x.shape[-1]}")
        return torch.stack(parts, dim=-1)

    def jacobian(self, x: Tensor) -> Tensor:
        """Closed-form Jacobian dg/dx.

        Args:
            x: states, shape (n, D).

        Returns:
            Jacobians, shape (n, D, D); entry [i, d, e] = d g_d / d x_e at x[i].
        """
        n, dim = x.shape
        jac = x.new_zeros(n, dim, dim)
        jac[:, 0, 1] = self.scale * torch.cos(x[:, 1])
        jac[:, 1, 0] = -self.scale * torch.sin(x[:, 0])
        if dim == 3:
            jac[:, 2, 0] = self.scale * torch.cos(x[:, 0]) * torch.cos(x[:, 1])
            jac[:, 2, 1] = -self.scale * torch.sin(x[:, 0]) * torch.sin(x[:, 1])
        return jac


@dataclass(frozen=True)
class TrueSystem:
    """``x' = f(x, u) + g(x) + w``, ``w ~ N(0, noise_std^2 I)``.

    Attributes:
        nominal: the known model f.
        wind: the unknown residual g.
        noise_std: standard deviation of each noise component.
    """

    nominal: NominalModel
    wind: VortexWind
    noise_std: float = 0.1

    def step(self, x: Tensor, u: Tensor, noise: Tensor | None = None,
             generator: torch.Generator | None = None) -> Tensor:
        """One step of the true system.

        Args:
            x: states, shape (..., D).
            u: inputs, shape (..., D).
            noise: standard-normal draws, shape (..., D), scaled by ``noise_std`` here;
                drawn from ``generator`` when ``None``.
            generator: source of the noise (seeded by the caller for reproducibility).

        Returns:
            next states, shape (..., D).
        """
        if noise is None:
            noise = torch.randn(x.shape, generator=generator, dtype=x.dtype, device=x.device)
        return self.nominal(x, u) + self.wind(x) + self.noise_std * noise


def make_system(dim: int = 2, noise_std: float = 0.1, wind_scale: float = 0.1) -> TrueSystem:
    """The paper's true system (A = I, B = 0.1 I, vortex wind) in ``dim`` dimensions."""
    return TrueSystem(NominalModel(dim=dim), VortexWind(scale=wind_scale), noise_std=noise_std)


def clip_norm(u: Tensor, u_max: float) -> Tensor:
    """Project inputs (..., Du) onto the ball ``||u|| <= u_max`` (guards solver tolerance and
    fallback plans before an input is applied to the system)."""
    norm = u.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    return u * torch.clamp(u_max / norm, max=1.0)
