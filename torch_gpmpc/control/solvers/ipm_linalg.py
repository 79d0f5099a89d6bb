"""Small dense linear algebra for the interior-point kernel, compiled by numba.

Explicit loops rather than array expressions or LAPACK: at the kernel's sizes (tens of
unknowns) numba compiles them several times faster and LAPACK's per-call overhead dominates.
Everything is float64, serial and IEEE, so results are reproducible.
"""

from __future__ import annotations

import numba
import numpy as np

# error_model="numpy": float division by zero gives inf/nan (checked), never an exception.
_jit = numba.njit(cache=True, error_model="numpy", nogil=True)


@_jit
def absmax(x: np.ndarray) -> float:
    """``max |x|`` of a 1-D array (0 if empty, NaN if any entry is NaN)."""
    v = 0.0
    for i in range(x.shape[0]):
        a = abs(x[i])
        if a > v:
            v = a
        elif a != a:
            return np.nan
    return v


@_jit
def absmax2(x: np.ndarray) -> float:
    """``max |x|`` of a 2-D array (0 if empty, NaN if any entry is NaN)."""
    v = 0.0
    for i in range(x.shape[0]):
        a = absmax(x[i])
        if a != a:
            return a
        v = max(v, a)
    return v


@_jit
def fill(x: np.ndarray, value: float) -> None:
    """``x[:] = value`` for a 1-D array."""
    for i in range(x.shape[0]):
        x[i] = value


@_jit
def copy_into(src: np.ndarray, dst: np.ndarray) -> None:
    """``dst[:] = src`` for 1-D arrays."""
    for i in range(src.shape[0]):
        dst[i] = src[i]


@_jit
def cholesky(S: np.ndarray, size: int) -> bool:
    """In place: the lower triangle of ``S[:size, :size]`` becomes L with S = L L^T.

    Only the lower triangle of S is read. Returns False if S is not (numerically)
    positive definite (a pivot <= 0 or NaN).
    """
    for j in range(size):
        d = S[j, j]
        for k in range(j):
            d -= S[j, k] * S[j, k]
        if not d > 0.0:
            return False
        d = np.sqrt(d)
        S[j, j] = d
        inv = 1.0 / d
        for i in range(j + 1, size):
            v = S[i, j]
            for k in range(j):
                v -= S[i, k] * S[j, k]
            S[i, j] = v * inv
    return True


@_jit
def forward_solve(L: np.ndarray, x: np.ndarray, size: int, first: int) -> None:
    """In place ``x <- L^-1 x`` for lower-triangular L, where ``x[:first] == 0``."""
    for i in range(first, size):
        v = x[i]
        for k in range(first, i):
            v -= L[i, k] * x[k]
        x[i] = v / L[i, i]


@_jit
def backward_solve(L: np.ndarray, x: np.ndarray, size: int) -> None:
    """In place ``x <- L^-T x`` for lower-triangular L."""
    for i in range(size - 1, -1, -1):
        v = x[i]
        for k in range(i + 1, size):
            v -= L[k, i] * x[k]
        x[i] = v / L[i, i]
