"""``gpmpc bench --sections gp``: the residual GP's hot paths against GPyTorch's own.

Workloads (synthetic data from the paper recipe, one agent, seed 0):

* ``linearize`` of 42 points (3 agents x 14 horizon points, one ADMM iteration) with
  N = 100, 1000, 5000 training points: our cached closed form
  (:meth:`ResidualGP.linearize`: mean, Jacobian, latent variance) vs GPyTorch's
  predictive path in eval mode (``model(x)`` mean/variance, exact variances, Cholesky
  forced via ``max_cholesky_size``) plus the Jacobian by ``torch.autograd`` (one
  backward pass per output dimension). Both run warm (caches built by a first call).
* ``fit``: L-BFGS, 50 iterations, N = 100.
* online GP (:mod:`~torch_gpmpc.gp.online`): one new row into a full window (exact N = 200;
  SGPR M = 512 on N = 2000), against factoring the window afresh; ``team_of_4_per_step_ms`` is
  what a K = 4 team pays per control step.
* ``linearize`` of the same 42 points with the sparse (SGPR) model of
  :mod:`~torch_gpmpc.gp.sparse` (512 inducing points) on N = 1000, 5000 and 10000 rows,
  against the exact model on the same rows (the exact N = 10000 model is skipped: its
  Cholesky factor alone is 1.6 GB for two outputs); the ratio is exact / sparse.

Only N = 100 is fitted; the N = 1000 / 5000 models reuse its hyperparameters and
normalization on their own data and only build the prediction cache (fitting them is
not what the controller pays per iteration). Numbers are medians of repeated calls;
``quick`` uses fewer repetitions. Ratios are measured in the same run.
"""

from __future__ import annotations

import statistics
import time
from typing import Callable

import torch

from torch_gpmpc.data import collect_transitions
from torch_gpmpc.gp import ResidualGP, fit_residual_gp
from torch_gpmpc.gp.normalization import Standardization
from torch_gpmpc.gp.sparse import NUM_INDUCING, kmeans_centers
from torch_gpmpc.dynamics.systems import NominalModel, make_system
from torch_gpmpc.threads import torch_threads

NUM_POINTS = 42
SIZES = (100, 1000, 5000)
SPARSE_SIZES = (1000, 5000, 10000)
#: Largest N whose exact model the sparse rows are compared with.
EXACT_COMPARE_MAX = 5000


def _median_time(fn: Callable[[], object], reps: int) -> tuple[float, object]:
    """Median wall time of ``fn()`` in seconds over ``reps`` calls (after one warm-up call).

    Returns:
        ``(seconds, result of the last call)``.
    """
    result = fn()
    times = []
    for _ in range(max(1, reps)):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), result


def _data(n: int, seed: int):
    tr = collect_transitions(make_system(), num_agents=1, samples=n, seed=seed)
    return tr.residuals(NominalModel())


def _reuse_hyperparameters(base: ResidualGP, X: torch.Tensor, Y: torch.Tensor, sparse: bool = False) -> ResidualGP:
    """A model on (X, Y) with ``base``'s hyperparameters and normalization (cache only);
    ``sparse``: the SGPR model with k-means inducing points."""
    scale = Standardization(base.x_mean, base.x_std, base.y_mean, base.y_std)
    inducing = kmeans_centers(scale.inputs(X), NUM_INDUCING, 0) * scale.x_std + scale.x_mean if sparse else None
    gp = ResidualGP(X, Y, normalization=scale, inducing_points=inducing)
    gp.model.load_state_dict(base.model.state_dict())
    return gp.refresh()


def gpytorch_linearize(gp: ResidualGP, x: torch.Tensor):
    """Baseline: GPyTorch predictive mean/variance + autograd Jacobian of the mean.

    Returns:
        ``(mean (n, D), jac (n, D, Din), var (n, D))``.
    """
    x = x.detach().clone().requires_grad_(True)
    mean, var = gp.gpytorch_predict(x)
    rows = [torch.autograd.grad(mean[:, d].sum(), x, retain_graph=d + 1 < gp.output_dim)[0]
            for d in range(gp.output_dim)]
    return mean.detach(), torch.stack(rows, dim=1), var.detach()


def _default_threads_row(gp: ResidualGP, xq: torch.Tensor, quick: bool, default_threads: int) -> dict:
    """N = 100 again, at the thread count the process started with."""
    threads = torch.get_num_threads()
    torch.set_num_threads(default_threads)
    try:
        reps_ours, reps_base = _reps(100, quick)
        t_ours, _ = _median_time(lambda: gp.linearize(xq), reps_ours)
        t_base, _ = _median_time(lambda: gpytorch_linearize(gp, xq), reps_base)
    finally:
        torch.set_num_threads(threads)
    return {"workload": f"linearize {NUM_POINTS} pts, N=100, {default_threads} thread{'s' if default_threads != 1 else ''}",
            "ours_ms": 1e3 * t_ours, "gpytorch_ms": 1e3 * t_base, "ratio": t_base / t_ours,
            "max_abs_diff": None}


def _sparse_rows(base: ResidualGP, xq: torch.Tensor, quick: bool) -> list[dict]:
    """linearize with the SGPR model vs the exact model on the same N rows."""
    rows = []
    for n in SPARSE_SIZES[:2] if quick else SPARSE_SIZES:
        X, Y = _data(n, seed=2)
        sparse = _reuse_hyperparameters(base, X, Y, sparse=True)
        t_sparse, _ = _median_time(lambda gp=sparse: gp.linearize(xq), 3 if quick else 30)
        t_exact = None
        if n <= EXACT_COMPARE_MAX:
            exact = _reuse_hyperparameters(base, X, Y)
            t_exact, _ = _median_time(lambda gp=exact: gp.linearize(xq), 2 if quick else 10)
        rows.append({"workload": f"linearize {NUM_POINTS} pts, SGPR M={NUM_INDUCING} vs exact, N={n}",
                     "ours_ms": 1e3 * t_sparse, "gpytorch_ms": None,
                     "exact_ms": None if t_exact is None else 1e3 * t_exact,
                     "ratio": None if t_exact is None else t_exact / t_sparse, "max_abs_diff": None})
    return rows


def _online_rows(base: ResidualGP, xq: torch.Tensor, quick: bool) -> list[dict]:
    """One new row into a full window (drop the oldest, add the newest; :mod:`~torch_gpmpc.gp.online`)
    against factoring the same window afresh (``refresh``); the per-step cost of a K = 4 team is 4 of
    them. ``max_abs_diff``: the two posteriors' linearization at the query points."""
    from torch_gpmpc.gp.online import OnlineGP

    rows = []
    for label, n, sparse in (("exact N=200", 200, False), (f"SGPR M={NUM_INDUCING} N=2000", 2000, True)):
        X, Y = _data(n + 50, seed=3)
        online = OnlineGP(_reuse_hyperparameters(base, X[:n], Y[:n], sparse=sparse), budget=n)
        new = iter(range(n, n + 50))

        def add_one():
            i = next(new)
            online.add(X[i:i + 1], Y[i:i + 1])

        t_add, _ = _median_time(add_one, 5 if quick else 40)
        updated = [t.clone() for t in online.linearize(xq)]
        t_refit, _ = _median_time(lambda: online.gp.refresh(), 2 if quick else 10)
        refreshed = online.gp.linearize(xq)
        diff = max(float((a - b).abs().max()) for a, b in zip(updated, refreshed, strict=True))
        rows.append({"workload": f"online GP: add 1 row to a full window, {label} (baseline: refactor)",
                     "ours_ms": 1e3 * t_add, "gpytorch_ms": None, "refactor_ms": 1e3 * t_refit,
                     "ratio": t_refit / t_add, "max_abs_diff": diff,
                     "team_of_4_per_step_ms": 4e3 * t_add})
    return rows


def _reps(n: int, quick: bool) -> tuple[int, int]:
    """(ours, baseline) repetitions for N = n."""
    table = {100: (200, 30), 1000: (30, 5), 5000: (5, 2)}
    ours, base = table.get(n, (5, 2))
    return (max(1, ours // 10), 1) if quick else (ours, base)


def run(quick: bool, out=None) -> dict:
    """Run the GP workloads single-threaded (plus one row at the default thread count).

    The workloads are tiny; on a shared 2-core machine intra-op threading made them
    up to 30x slower and very noisy, so the table is measured with
    ``torch.set_num_threads(1)`` (restored afterwards).

    Args:
        quick: fewer repetitions (CI smoke run).
        out: output directory (unused; results are returned).

    Returns:
        ``{"table": [rows], "threads": int, ...}``; rows have ``workload``, ``ours_ms``,
        ``gpytorch_ms``, ``ratio`` (gpytorch / ours) and ``max_abs_diff``.
    """
    with torch_threads(1) as default_threads:
        result = _run(quick, default_threads)
    result["default_threads"] = default_threads
    return result


def _run(quick: bool, default_threads: int) -> dict:
    gen = torch.Generator().manual_seed(123)
    xq = (torch.rand(NUM_POINTS, 2, generator=gen, dtype=torch.float64) * 2 - 1) * 4.0
    X100, Y100 = _data(100, seed=0)
    fit_residual_gp(X100, Y100, iters=2)  # warm-up: first-call overheads of gpytorch/torch
    t0 = time.perf_counter()
    base = fit_residual_gp(X100, Y100, optimizer="lbfgs", iters=50, seed=0)
    fit_s = time.perf_counter() - t0
    rows = [{"workload": "fit N=100 (L-BFGS, 50 iters)", "ours_ms": 1e3 * fit_s,
             "gpytorch_ms": None, "ratio": None, "max_abs_diff": None}]
    for n in SIZES:
        gp = base if n == 100 else _reuse_hyperparameters(base, *_data(n, seed=1))
        reps_ours, reps_base = _reps(n, quick)
        t_ours, ours = _median_time(lambda gp=gp: gp.linearize(xq), reps_ours)
        t_base, ref = _median_time(lambda gp=gp: gpytorch_linearize(gp, xq), reps_base)
        diff = max(float((a - b).abs().max()) for a, b in zip(ours, ref, strict=True))
        rows.append({"workload": f"linearize {NUM_POINTS} pts, N={n}", "ours_ms": 1e3 * t_ours,
                     "gpytorch_ms": 1e3 * t_base, "ratio": t_base / t_ours, "max_abs_diff": diff})
    rows.append(_default_threads_row(base, xq, quick, default_threads))
    rows += _sparse_rows(base, xq, quick)
    rows += _online_rows(base, xq, quick)
    return {
        "table": rows,
        "threads": 1,
        "num_points": NUM_POINTS,
        "note": "N=1000/5000 reuse the N=100 hyperparameters (cache only); gpytorch baseline: "
                "eval-mode model(x) with exact variances + autograd Jacobian, warm; SGPR rows: ratio is "
                "exact / sparse linearize on the same rows (exact skipped at N=10000)",
    }
