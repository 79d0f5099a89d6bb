"""Small stand-ins shared by several test modules."""

from __future__ import annotations

import torch


class ConstantVarianceGP:
    """A stand-in residual model: zero mean, constant latent variance ``v`` per dimension."""

    def __init__(self, var: float, dim: int = 2) -> None:
        self.var, self.input_dim, self.output_dim = var, dim, dim
        self.noise = torch.zeros(dim, dtype=torch.float64)

    def linearize(self, x):
        n, d = x.shape
        return x.new_zeros(n, d), x.new_zeros(n, d, d), x.new_full((n, d), self.var)
