"""The fast solver's backward: the closed-form vector-Jacobian product of its stationarity pairing
(``interior_point._stationarity_vjp``, NumPy) against torch autograd of the pairing written out, on
random data of every shape the kernel sees (with and without a state-norm bound)."""

import numpy as np
import pytest
import torch
from torch import Tensor

from torch_gpmpc.control.solvers.interior_point import _stationarity_vjp


def _mv(mat: Tensor, vec: Tensor) -> Tensor:
    return torch.bmm(mat, vec.unsqueeze(-1)).squeeze(-1)


def pairing(G, h, c_x, l_x, rho_y, w_y, normals, bounds, g_u, H_cost, u, y, zc, a_u, a_y, xi, norm_idx, zv, xi_v):
    """``a^T grad_v L + xi^T g`` summed over the batch, its data-dependent terms (the reference)."""
    B, M, T, D = normals.shape
    x1 = _mv(G, u) + h
    dx1 = _mv(G, a_u)
    if zv.shape[1]:
        xs, dxs = x1.view(B, T, D)[..., norm_idx], dx1.view(B, T, D)[..., norm_idx]
        extra = (zv * (xs * dxs).sum(-1)).sum() - 0.5 * (xi_v * (xs * xs).sum(-1)).sum()
    else:
        extra = x1.new_zeros(())
    obj = ((2.0 * c_x[:, None] * x1 - l_x) * dx1).sum() + (g_u * a_u).sum() + (a_u * _mv(H_cost, u)).sum()
    rho = rho_y[:, :, None].expand(B, M, T).reshape(B, -1, 1)
    obj = obj + ((rho * y - w_y.reshape(B, -1, D)) * a_y).sum()
    N = normals.reshape(B, -1, D)
    x_rows = x1.view(B, 1, T, D).expand(B, M, T, D).reshape(B, -1, D)
    dx_rows = dx1.view(B, 1, T, D).expand(B, M, T, D).reshape(B, -1, D)
    obj = obj - (zc * (N * (dx_rows - a_y)).sum(-1)).sum()
    return obj + (xi * ((N * (x_rows - y)).sum(-1) - bounds.reshape(B, -1))).sum() + extra


@pytest.mark.parametrize("norm_idx", [[], [3, 4, 5], [1]])
def test_closed_form_matches_autograd(norm_idx):
    g = np.random.default_rng(len(norm_idx))
    B, M, T, D, Du = 3, 4, 5, 6, 3
    nx, n, R, Ts = T * D, T * Du, M * T, T if norm_idx else 0

    def rand(*shape):
        return g.standard_normal(shape)

    arrays = [rand(B, nx, n), rand(B, nx), 1.0 + g.random(B), rand(B, nx), 1.0 + g.random((B, M)), rand(B, M, T, D),
              rand(B, M, T, D), rand(B, M, T), rand(B, n), rand(B, n, n)]
    point = [rand(B, n), rand(B, R, D), rand(B, R), rand(B, n), rand(B, R, D), rand(B, R)]
    zv, xi_v = rand(B, Ts), rand(B, Ts)
    got = _stationarity_vjp(arrays, *point, np.asarray(norm_idx, dtype=np.int64), zv, xi_v)
    leaves = [torch.tensor(a, requires_grad=True) for a in arrays]
    value = pairing(*leaves, *(torch.tensor(p) for p in point), norm_idx, torch.tensor(zv), torch.tensor(xi_v))
    want = torch.autograd.grad(value, leaves)
    for k, (a, b) in enumerate(zip(got, want)):
        assert a.shape == tuple(b.shape), k
        np.testing.assert_allclose(a, -b.numpy(), rtol=1e-12, atol=1e-12, err_msg=f"input {k}")

