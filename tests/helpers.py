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


def lag_model(dim: int = 2, dt: float = 0.1) -> dict:
    """The double integrator in ``dim`` dimensions with the last command as ``dim`` more states."""
    n = 3 * dim
    A = [[0.0] * n for _ in range(n)]
    B = [[0.0] * dim for _ in range(n)]
    for i in range(dim):
        A[i][i], A[i][dim + i], A[dim + i][dim + i] = 1.0, dt, 1.0
        B[i][i], B[dim + i][i], B[2 * dim + i][i] = dt * dt / 2, dt, 1.0
    return {"A": A, "B": B, "position": list(range(dim)), "residual": list(range(dim, 2 * dim)),
            "gp_inputs": [f"x{i}" for i in range(dim, n)] + [f"u{j}" for j in range(dim)],
            "input_bound": {"box": [2.0] * dim}}
