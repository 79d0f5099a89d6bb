"""The compiled interior-point kernels called on a batch of canonical problems as NumPy arrays
(:class:`~torch_gpmpc.control.solvers.canonical.CanonicalData` made contiguous): warm active-set
solves from a previous point where one fits, the interior point (polished) for the rest. Shared by
the torch layer :class:`~torch_gpmpc.control.solvers.interior_point.InteriorPointMPC` and by
:class:`~torch_gpmpc.control.solvers.repeated.RepeatedSolve` (ADMM's repeated solves of one step).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from torch_gpmpc.control.constraints import LocalConstraints
from torch_gpmpc.control.numpy_views import as_array
from torch_gpmpc.control.solvers import ipm_threads

#: The forward pass returns, and the backward pass differentiates at, a point polished to
#: ``POLISH_FACTOR * tol`` (at most ``POLISH_ITERATIONS`` extra iterations; :func:`cold_solve`).
POLISH_FACTOR = 1e-2
POLISH_ITERATIONS = 6
#: Rounds (one linear solve each) the warm active-set solve may take before a problem is solved
#: cold: a right guess needs one, a norm row one or two more Newton rounds, a few changed rows one
#: round each.
ACTIVE_SET_ROUNDS = 8


def batched_mv(mat: Tensor, vec: Tensor) -> Tensor:
    """Batched matrix-vector product, (B, p, q) x (B, q) -> (B, p)."""
    return torch.bmm(mat, vec.unsqueeze(-1)).squeeze(-1)


def kernel_arrays(tensors: tuple[Tensor, ...]) -> list[np.ndarray]:
    """The canonical tensors as C-contiguous float64 NumPy arrays (zero-copy when possible)."""
    return [as_array(t) for t in tensors]


class StructureCache:
    """The kernel's :func:`~.ipm_kernel.structure_batch` (``G^T G`` and the rows' gradients) of the
    last batch, reused while its condensed dynamics and row normals are equal (compared by value):
    within a control step ADMM poses the same ones at every iteration, and rebuilding them was about
    a third of a warm solve (19 neighbours, horizon 15)."""

    def __init__(self) -> None:
        self._key: tuple[np.ndarray, np.ndarray] | None = None
        self._value: tuple[np.ndarray, np.ndarray] | None = None

    def __call__(self, G: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(GtG (B, n, n), A (B, R, n))`` for G (B, nx, n) and normals (B, M, T, D)."""
        key = self._key
        if key is not None and key[0].shape == G.shape and key[1].shape == normals.shape \
                and np.array_equal(key[0], G) and np.array_equal(key[1], normals):
            return self._value
        B, n = G.shape[0], G.shape[2]
        value = (np.empty((B, n, n)), np.empty((B, normals.shape[1] * normals.shape[2], n)))
        ipm_threads.structure_batch(G, normals, *value)
        self._key, self._value = (G.copy(), normals.copy()), value
        return value


@dataclass
class KernelPoint:
    """Primal-dual point of B problems (NumPy): u (B, n), y (B, R, D), w and z (B, m)."""

    u: np.ndarray
    y: np.ndarray
    w: np.ndarray
    z: np.ndarray

    def copy(self) -> "KernelPoint":
        return KernelPoint(self.u.copy(), self.y.copy(), self.w.copy(), self.z.copy())


def row_multipliers(point: KernelPoint, num_neighbors: int, horizon: int) -> Tensor:
    """(B, M, T) the collision rows' multipliers of the kernel's ``point`` (its first ``M T`` rows,
    slot-major: :mod:`~.ipm_kernel`)."""
    z = point.z[:, :num_neighbors * horizon]
    return torch.from_numpy(z.copy()).view(z.shape[0], num_neighbors, horizon)


def where_rows(rows: np.ndarray, a: KernelPoint, b: KernelPoint) -> KernelPoint:
    """Per batch row (B,), ``a`` where ``rows`` else ``b`` (``a`` or ``b`` itself when ``rows`` is
    uniform)."""
    if rows.all():
        return a
    if not rows.any():
        return b
    return KernelPoint(*(np.where(rows.reshape(-1, *[1] * (x.ndim - 1)), x, y)
                      for x, y in zip((a.u, a.y, a.w, a.z), (b.u, b.y, b.w, b.z))))


@dataclass(frozen=True)
class KernelLimits:
    """The constraint constants the kernel reads (from :class:`LocalConstraints`) and the slot flags.

    Attributes:
        u_max: input norm bound (``inf``: none). box: input box (Du,) or empty.
        norm_idx: state indices of the soft norm bound (p,) int64 or empty. v_max: that bound.
        couple: per slot, 1 for a neighbour slot, 0 for a state row, shape (M + L,).
    """

    u_max: float
    box: np.ndarray
    norm_idx: np.ndarray
    v_max: float
    couple: np.ndarray

    @classmethod
    def of(cls, constraints: LocalConstraints, num_neighbors: int, num_rows: int) -> "KernelLimits":
        """The kernel's view of ``constraints`` for M neighbour slots and L state rows."""
        return cls(u_max=math.inf if constraints.input_norm is None else float(constraints.input_norm),
                   box=np.asarray(constraints.input_box or (), dtype=np.float64),
                   norm_idx=np.asarray(constraints.norm_indices or (), dtype=np.int64),
                   v_max=1.0 if constraints.norm_bound is None else float(constraints.norm_bound),
                   couple=np.concatenate([np.ones(num_neighbors), np.zeros(num_rows)]))

    def args(self) -> tuple:
        """The kernel arguments after ``couple, alpha``: ``(u_max, box, norm_idx, v_max)``."""
        return self.u_max, self.box, self.norm_idx, self.v_max

    def sizes(self, R: int, n: int, T: int) -> tuple[int, int, int]:
        """``(m, ov, Ts)``: inequality count, offset and count of the state-norm rows (as the kernel)."""
        Tq = T if self.u_max < math.inf else 0
        nb = n if self.box.size else 0
        Ts = T if self.norm_idx.size else 0
        ov = 2 * R + Tq + 2 * nb
        return ov + 2 * Ts, ov, Ts


def cold_solve(arrays: list[np.ndarray], weights: tuple[float, float], limits: KernelLimits, penalty: float,
                tol: float, max_iter: int) -> tuple[KernelPoint, KernelPoint, np.ndarray, np.ndarray, np.ndarray]:
    """The interior point from its default start on the B problems of ``arrays``, each then polished:
    continued to ``POLISH_FACTOR * tol`` (at most ``POLISH_ITERATIONS`` more iterations). Gradients
    are more sensitive than solutions to the barrier perturbation (a nearly degenerate row counts
    as half active).

    Returns:
        ``(point, at, converged (B,), iterations (B,), kkt_error (B,))``: ``point`` is returned (the
        polished point where the solve converged and the polish reached its tolerance or did not
        make the KKT error worse), ``at`` differentiated (the polished point, also where the main
        solve did not converge).
    """
    B, n = arrays[1].shape[0], arrays[0].shape[2]
    _, M, T, D = arrays[6].shape
    R = M * T
    m, _, _ = limits.sizes(R, n, T)

    def new_point() -> KernelPoint:
        return KernelPoint(np.empty((B, n)), np.empty((B, R, D)), np.empty((B, m)), np.empty((B, m)))

    point, polished = new_point(), new_point()
    converged, iterations, kkt_error = np.empty(B, dtype=np.bool_), np.empty(B, dtype=np.int64), np.empty(B)
    p_conv, p_iter, p_err = np.empty(B, dtype=np.bool_), np.empty(B, dtype=np.int64), np.empty(B)
    ipm_threads.solve_polish_batch(*arrays, limits.couple, *weights, *limits.args(), penalty, tol, max_iter,
                                   point.u, point.y, point.w, point.z, False, converged, iterations, kkt_error,
                                   POLISH_FACTOR * tol, POLISH_ITERATIONS, polished.u, polished.y, polished.w,
                                   polished.z, p_conv, p_iter, p_err)
    # Return (and differentiate at) the polished point: the backward differentiates the exact
    # KKT conditions, and the returned point must be the one they hold at, else a nearly
    # degenerate row (active, multiplier ~1e-3) makes the returned map's derivative differ
    # from the gradient by O(tol / multiplier^2) (measured: 1.6e-4 relative at tol 1e-10).
    improved = p_conv | (p_err <= kkt_error)
    better = converged & improved
    # an unconverged row (flagged as failed) is returned as solved but differentiated polished
    at = where_rows(~converged | improved, polished, point)
    point = where_rows(better, polished, point)
    return point, at, converged, iterations + np.where(better, p_iter, 0), np.where(better, p_err, kkt_error)


def fits(guess: KernelPoint, point: KernelPoint) -> bool:
    """Whether a guess (a previous solve's points) has the shapes of ``point`` (the same batch and
    problem size): only then can it start the warm active-set solves."""
    return all(a.shape == b.shape for a, b in zip((guess.u, guess.y, guess.w, guess.z),
                                                  (point.u, point.y, point.w, point.z)))


def solve_points(settings: tuple, keep_at: bool) -> tuple[KernelPoint, KernelPoint | None, np.ndarray]:
    """Solve the problems of ``settings`` (the tuple :class:`_LocalQpFunction` takes; its ``arrays``
    hold the canonical data): warm active-set solves from ``guess`` where it fits, the interior point
    for the rest.

    Returns:
        ``(point, at, converged (B,))``: the returned points, the points to differentiate at (the
        polished ones; ``None`` unless ``keep_at``) and which problems converged. ``stats`` gets
        ``iterations``, ``warm_rows`` and ``point``.
    """
    weights, limits, penalty, tol, max_iter, stats, guess, arrays = settings
    B, M, T, D = arrays[6].shape
    R, n = M * T, arrays[0].shape[2]
    m, _, _ = limits.sizes(R, n, T)
    point = KernelPoint(np.empty((B, n)), np.empty((B, R, D)), np.empty((B, m)), np.empty((B, m)))
    converged, iterations, kkt_error = np.zeros(B, dtype=np.bool_), np.zeros(B, dtype=np.int64), np.empty(B)
    if isinstance(guess, KernelPoint) and fits(guess, point):
        # exact solves from the previous points' active sets; what they miss is solved cold
        point = guess.copy()
        ipm_threads.active_set_batch(*arrays, limits.couple, *weights, *limits.args(), penalty,
                                     POLISH_FACTOR * tol, ACTIVE_SET_ROUNDS, point.u, point.y, point.w, point.z,
                                     False, converged, iterations, kkt_error)
    stats["warm_rows"] = int(converged.sum())
    at = point.copy() if keep_at else None
    cold = np.flatnonzero(~converged)
    if cold.size:
        sub = [a[cold] for a in arrays] if cold.size < B else arrays
        c_point, c_at, c_conv, c_iter, c_err = cold_solve(sub, weights, limits, penalty, tol, max_iter)
        point.u[cold], point.y[cold], point.w[cold], point.z[cold] = c_point.u, c_point.y, c_point.w, c_point.z
        if keep_at:
            at.u[cold], at.y[cold], at.w[cold], at.z[cold] = c_at.u, c_at.y, c_at.w, c_at.z
        converged[cold], iterations[cold], kkt_error[cold] = c_conv, c_iter, c_err
    stats["iterations"] = int(iterations.max(initial=0))
    stats["point"] = point
    return point, at, converged


def point_outputs(point: KernelPoint, converged: np.ndarray, shape: torch.Size,
                   like: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``(u (B, n), y (B, M, T, D), s (B, M, T), converged (B,))`` as tensors of ``like``'s dtype and
    device, for ``shape = (B, M, T, D)``."""
    B, M, T, D = shape
    R = M * T

    def out(a: np.ndarray, *dims: int) -> Tensor:
        return torch.from_numpy(np.ascontiguousarray(a)).to(dtype=like.dtype, device=like.device).reshape(*dims)

    return (out(point.u, B, point.u.shape[1]), out(point.y, B, M, T, D), out(point.w[:, R:2 * R], B, M, T),
            torch.from_numpy(converged).to(like.device))

