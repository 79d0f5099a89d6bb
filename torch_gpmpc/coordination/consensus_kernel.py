"""ADMM's per-iteration arithmetic around the local solves, compiled by numba (the compiled
iterations of :mod:`~torch_gpmpc.coordination.steady`).

Two passes over the edges and slots, each the same arithmetic as the torch path, in the same order:

- :func:`slot_terms`: from each edge's consensus ``z_e``, duals ``lam_e`` and penalty ``rho_e`` to
  each slot's consensus terms (what :class:`~torch_gpmpc.control.problem.ConsensusTerms` computes);
- :func:`consensus_step`: the edges' copies from the plans, the consensus and dual updates (eqs.
  28-29), the residuals and tolerances of :mod:`~.penalty` and residual balancing.

The updates are elementwise with the torch path's operations (so the same plans give the same
``z``, ``lam`` and ``rho`` bit for bit); the residual norms are sums of squares in index order, which
may differ from torch's vectorized sums in the last bits (they decide only where a ratio sits at
exactly 1 or a balance at exactly 10). Serial float64, no fastmath; cached on disk (``cache=True``;
this module calls into no other numba module, so numba's own check of its source keeps the cache
fresh).
"""

from __future__ import annotations

import math
from pathlib import Path

import numba
import numpy as np

_jit = numba.njit(cache=True, error_model="numpy", nogil=True)


@_jit
def slot_terms(z, lam, rho_edge, slot_edge, slot_side, active, rho_own, w_own, rho_y, w_y, y0) -> None:
    """Write every slot's consensus terms (0 on inactive slots, as ``ConsensusTerms``).

    The sums over an agent's slots (``c_x = 1 + sum_m rho_own / 2`` and the slots' part of ``l_x``,
    ``sum_m w_own``) are left to the caller, in torch: torch sums 5 or more terms in an order of its
    own, and the same order keeps the local problems the torch path's bit for bit.

    Args:
        z: (E, 2, T+1, n) consensus. lam: (E, 2, 2, T+1, n) duals (``lam[e, a]`` held by end a).
        rho_edge: (E,) penalties. slot_edge, slot_side: (K, M) int64. active: (K, M) bool.
        rho_own: (K, M) out, each slot's penalty (0 inactive).
        w_own: (K, M, T+1, n) out, ``rho z_own - lam_own`` (0 inactive).
        rho_y: (K, M') out on its first M columns, the copies' weight (1 inactive).
        w_y: (K, M', T, n) out on its first M slots, ``rho z_nbr - lam_nbr`` at tau = 1..T (0 inactive).
        y0: (K, M, n) out, ``(rho z_nbr - lam_nbr) / rho_y`` at tau = 0 (0 inactive).
    """
    K, M = active.shape
    T1, n = z.shape[2], z.shape[3]
    for k in range(K):
        for m in range(M):
            if not active[k, m]:
                rho_own[k, m] = 0.0
                rho_y[k, m] = 1.0
                w_own[k, m] = 0.0
                w_y[k, m] = 0.0
                y0[k, m] = 0.0
                continue
            e, a = slot_edge[k, m], slot_side[k, m]
            r = rho_edge[e]
            rho_own[k, m] = r
            rho_y[k, m] = r
            for t in range(T1):
                for d in range(n):
                    w_own[k, m, t, d] = r * z[e, a, t, d] - lam[e, a, a, t, d]
                    nbr = r * z[e, 1 - a, t, d] - lam[e, a, 1 - a, t, d]
                    if t == 0:
                        y0[k, m, d] = nbr / r
                    else:
                        w_y[k, m, t - 1, d] = nbr


@_jit
def consensus_step(X, Y, slot_edge, slot_side, active, z, lam, rho_edge, adaptive, tolerances, checks_dual,
                   z_new, lam_new, rho_new, report) -> None:
    """One consensus, dual and penalty update of every edge, with its residuals.

    Args:
        X: (K, T+1, n) plans. Y: (K, M, T+1, n) each agent's copies of its neighbours' plans.
        slot_edge, slot_side: (K, M) int64. active: (K, M) bool.
        z: (E, 2, T+1, n), lam: (E, 2, 2, T+1, n), rho_edge: (E,): the iterate.
        adaptive: residual balancing on (else ``rho_new = rho_edge``).
        tolerances: (9,) the stopping test's absolute primal and dual tolerances, the balancing's
            (the configured ones), the relative tolerance, and the balancing's factor, trigger and
            bounds (:data:`~.penalty.RHO_FACTOR`, :data:`~.penalty.RHO_BALANCE`, :data:`~.penalty.RHO_BOUNDS`).
        checks_dual: the stopping test tests the dual residual.
        z_new, lam_new, rho_new: outputs, shaped like ``z``, ``lam``, ``rho_edge``.
        report: (5,) output: the largest primal and dual residuals, the largest primal and dual
            ratios of the stopping test, and the count of edges that have not met it.
    """
    K, M = active.shape
    E = z.shape[0]
    T1, n = z.shape[2], z.shape[3]
    copies = np.zeros((E, 2, 2, T1, n))
    for k in range(K):
        for m in range(M):
            if active[k, m]:
                e, a = slot_edge[k, m], slot_side[k, m]
                copies[e, a, a] = X[k]
                copies[e, a, 1 - a] = Y[k, m]
    tol_p, tol_d, bal_p, bal_d = tolerances[0], tolerances[1], tolerances[2], tolerances[3]
    rel, factor, trigger, low, high = tolerances[4], tolerances[5], tolerances[6], tolerances[7], tolerances[8]
    worst_p = worst_d = ratio_p = ratio_d = 0.0
    unconverged = 0
    for e in range(E):
        r = rho_edge[e]
        gap0 = gap1 = change = size0 = size1 = size_z = lam0 = 0.0
        for h in range(2):
            for t in range(T1):
                for d in range(n):
                    c0, c1 = copies[e, 0, h, t, d], copies[e, 1, h, t, d]
                    mean = (c0 + c1) / 2.0
                    g0, g1 = c0 - mean, c1 - mean
                    new0 = lam[e, 0, h, t, d] + r * g0
                    lam_new[e, 0, h, t, d] = new0
                    lam_new[e, 1, h, t, d] = lam[e, 1, h, t, d] + r * g1
                    step = mean - z[e, h, t, d]
                    z_new[e, h, t, d] = mean
                    gap0 += g0 * g0
                    gap1 += g1 * g1
                    change += step * step
                    size0 += c0 * c0
                    size1 += c1 * c1
                    size_z += mean * mean
                    lam0 += new0 * new0
        primal = max(math.sqrt(gap0), math.sqrt(gap1))
        dual = r * math.sqrt(change)
        size = max(max(math.sqrt(size0), math.sqrt(size1)), math.sqrt(size_z))
        lam_norm = math.sqrt(lam0)
        p = primal / (tol_p + rel * size)
        q = dual / (tol_d + rel * lam_norm)
        worst_p, worst_d = max(worst_p, primal), max(worst_d, dual)
        ratio_p, ratio_d = max(ratio_p, p), max(ratio_d, q)
        if not (p < 1.0) or (checks_dual and not (q < 1.0)):
            unconverged += 1
        rho_new[e] = r
        if adaptive:
            pb = primal / (bal_p + rel * size)
            qb = dual / (bal_d + rel * lam_norm)
            step_factor = factor if pb > trigger * qb else (1.0 / factor if qb > trigger * pb else 1.0)
            rho_new[e] = r * min(max(step_factor, low / r), high / r)
    report[0], report[1], report[2], report[3], report[4] = worst_p, worst_d, ratio_p, ratio_d, unconverged


def warm_up() -> None:
    """Compile (or load from the on-disk cache) both passes on a one-edge problem."""
    K, M, T1, n = 2, 1, 2, 1
    slot_edge, slot_side = np.zeros((K, M), dtype=np.int64), np.array([[0], [1]], dtype=np.int64)
    active = np.ones((K, M), dtype=np.bool_)
    z, lam, rho = np.zeros((1, 2, T1, n)), np.zeros((1, 2, 2, T1, n)), np.ones(1)
    slot_terms(z, lam, rho, slot_edge, slot_side, active, np.empty((K, M)), np.empty((K, M, T1, n)), np.ones((K, M)),
               np.zeros((K, M, T1 - 1, n)), np.empty((K, M, n)))
    consensus_step(np.zeros((K, T1, n)), np.zeros((K, M, T1, n)), slot_edge, slot_side, active, z, lam, rho, True,
                   np.ones(9), True, np.empty_like(z), np.empty_like(lam), np.empty_like(rho), np.empty(5))


def is_cached() -> bool:
    """Whether numba's on-disk cache next to this module holds both passes, newer than this source
    (if not, the first compiled iteration compiles them: about 5 s, once)."""
    source = Path(__file__)
    wanted = {f"{source.stem}.{fn.py_func.__name__}-{fn.py_func.__code__.co_firstlineno}"
              for fn in (slot_terms, consensus_step)}
    index = {p.name.rsplit(".", 2)[0]: p for p in (source.parent / "__pycache__").glob(f"{source.stem}.*.nbi")}
    return wanted <= set(index) and all(index[key].stat().st_mtime >= source.stat().st_mtime for key in wanted)
