"""Rank-one updates and downdates of Cholesky factors, batched over independent outputs.

``L L^T + sign x x^T = L' L'^T`` in O(n^2) instead of a new O(n^3) factorization (the classic
algorithm, e.g. Golub & Van Loan §6.5.4; what ``cholupdate`` does in MATLAB). Compiled by numba:
the loop runs over n columns, too fine-grained for torch ops.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from torch import Tensor


@numba.njit(cache=True, nogil=True)
def _rank_one(L: np.ndarray, x: np.ndarray, sign: float) -> bool:  # pragma: no cover - compiled
    D, n = x.shape
    for d in range(D):
        for k in range(n):
            lkk = L[d, k, k]
            xk = x[d, k]
            r2 = lkk * lkk + sign * xk * xk
            if not r2 > 0.0:
                return False
            r = math.sqrt(r2)
            c = r / lkk
            s = xk / lkk
            L[d, k, k] = r
            for i in range(k + 1, n):
                L[d, i, k] = (L[d, i, k] + sign * s * x[d, i]) / c
                x[d, i] = c * x[d, i] - s * L[d, i, k]
    return True


def cholesky_rank_one(L: Tensor, x: Tensor, sign: float = 1.0) -> Tensor | None:
    """The lower factor of ``L L^T + sign x x^T``.

    Args:
        L: (D, n, n) lower Cholesky factors (not modified).
        x: (D, n) the update vectors.
        sign: +1 (update) or -1 (downdate).

    Returns:
        (D, n, n) the new factors, or ``None`` when a downdate would lose positive definiteness.
    """
    out = L.detach().cpu().numpy().copy()
    ok = _rank_one(out, x.detach().cpu().numpy().copy(), float(sign))
    return torch.from_numpy(out).to(L) if ok else None


def cholesky_append(L: Tensor, k: Tensor, diag: Tensor) -> Tensor:
    """The factor of ``[[K, k], [k^T, diag]]`` from the factor L of K: one new row, O(n^2).

    Args:
        L: (D, n, n). k: (D, n) the new column. diag: (D,) the new diagonal entry.

    Returns:
        (D, n+1, n+1); the new pivot is clamped at a tiny positive value (a duplicate point with
        zero noise would make it zero).
    """
    row = torch.linalg.solve_triangular(L, k.unsqueeze(-1), upper=False).squeeze(-1)  # (D, n)
    pivot = (diag - row.square().sum(-1)).clamp_min(1e-12 * diag.abs().clamp_min(1.0)).sqrt()
    D, n = k.shape
    out = L.new_zeros(D, n + 1, n + 1)
    out[:, :n, :n] = L
    out[:, n, :n] = row
    out[:, n, n] = pivot
    return out


def cholesky_drop_first(L: Tensor) -> Tensor:
    """The factor of K without its first row and column, from the factor L of K: O(n^2).

    With ``L = [[a, 0], [b, C]]``, ``K[1:, 1:] = C C^T + b b^T``: a rank-one update of C (always
    positive definite).
    """
    out = cholesky_rank_one(L[:, 1:, 1:], L[:, 1:, 0], 1.0)
    assert out is not None  # an update never fails
    return out
