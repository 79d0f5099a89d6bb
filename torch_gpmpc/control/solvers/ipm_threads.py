"""Run the compiled interior-point kernel on several cores: contiguous blocks of the batch, one
per thread.

The kernel's entry points solve their B problems one after another and release the GIL
(``nogil=True``), and every problem reads and writes only its own rows of the per-problem
arrays. So splitting the batch into blocks and calling the kernel on each block from its own
thread gives the same bits as one call, in about 1/threads of the time when the batch is
large enough (the 100 agents of a crowd, the families' batch of 64). The thread count follows
``torch.get_num_threads()`` (``gpmpc --threads N``; the command line's default is 1), so
processes that already run in parallel (``--workers``) do not oversubscribe the cores.

A closed loop plans under :func:`planning_threads`: the kernel keeps that count while torch's own
intra-op threads drop to 1. torch's OpenMP threads keep spinning for a while after each parallel
operation and take the core a kernel block needs: with torch and the kernel both on 2 threads the
100-agent crowd's first 10 steps took 0.69 s per step, with torch on 1 and the kernel on 2 0.42 s
(1 and 1: 0.66 s); the N = 20 random-transition run 9.1 against 6.0 ms per agent-step (1 and 1:
8.4 ms). The plans are the same bits whatever the count.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Callable, Iterator, Sequence

import torch

from torch_gpmpc.control.solvers import ipm_active, ipm_cache
from torch_gpmpc.control.solvers import ipm_kernel as ipm

#: Argument positions of :func:`~.ipm_kernel.solve_polish_batch` (and of
#: :func:`~.ipm_active.solve_batch`, up to its ``kkt_error``) that are per-problem arrays (first
#: axis B): the ten canonical arrays and their structure ``GtG, A``, the iterate ``u, y, w, z``
#: and the outputs ``converged, iterations, kkt_error``; the rest (``couple``, weights, limits,
#: tolerances, ``warm``) are shared by every problem.
SOLVE_ROWS = frozenset(range(12)) | {22, 23, 24, 25, 27, 28, 29}
#: The same for :func:`~.ipm_kernel.solve_polish_batch` with its polished point and its outputs.
POLISH_ROWS = SOLVE_ROWS | frozenset(range(32, 39))
#: The same for :func:`~.ipm_kernel.adjoint_batch`: the canonical arrays, the point
#: ``u, w, z``, the right-hand side ``g_u, g_y, g_s`` and the outputs.
ADJOINT_ROWS = frozenset(range(10)) | frozenset(range(17, 28))
#: The same for :func:`~.ipm_kernel.structure_batch`: all four.
STRUCTURE_ROWS = frozenset(range(4))
#: Fewest problems worth a thread of their own (a problem takes ~0.3-1 ms; a hand-off ~20 us).
MIN_ROWS_PER_THREAD = 4

#: Worker pools by (process id, workers): a process forked from one that had a pool gets new
#: threads instead of a copy whose threads did not survive the fork.
_pools: dict[tuple[int, int], ThreadPoolExecutor] = {}
#: The kernel's thread count inside :func:`planning_threads` (``None`` outside: torch's count).
_planning: dict[str, int | None] = {"threads": None}


def kernel_threads() -> int:
    """Threads the kernel's batch calls split over: the count :func:`planning_threads` holds, else
    ``torch.get_num_threads()``."""
    held = _planning["threads"]
    return torch.get_num_threads() if held is None else held


@contextmanager
def planning_threads(threads: int | None = None) -> Iterator[int]:
    """Plan on ``threads`` cores (default :func:`kernel_threads`): the kernel's batch calls split over
    them while torch's intra-op threads are held at 1 (module docstring: why). Both are restored on
    exit; nested uses keep the outer count unless given one. Yields the kernel's thread count."""
    count = kernel_threads() if threads is None else threads
    if count < 1:
        raise ValueError(f"planning_threads: threads must be >= 1, got {count}")
    held, torch_threads = _planning["threads"], torch.get_num_threads()
    _planning["threads"] = count
    torch.set_num_threads(1)
    try:
        yield count
    finally:
        _planning["threads"] = held
        torch.set_num_threads(torch_threads)


def structure_batch(*args) -> None:
    """:func:`~.ipm_kernel.structure_batch` (same arguments, outputs written in place) on the
    available threads."""
    ipm_cache.ensure_fresh()
    run_in_blocks(ipm.structure_batch, args, STRUCTURE_ROWS)


def solve_polish_batch(*args) -> None:
    """:func:`~.ipm_kernel.solve_polish_batch` (same arguments, outputs written in place) on the
    available threads."""
    ipm_cache.ensure_fresh()
    run_in_blocks(ipm.solve_polish_batch, args, POLISH_ROWS)


def active_set_batch(*args) -> None:
    """:func:`~.ipm_active.solve_batch` (the warm-started active-set solves; the arguments of
    :func:`~.ipm_kernel.solve_polish_batch` at the same positions) on the available threads."""
    ipm_cache.ensure_fresh()
    run_in_blocks(ipm_active.solve_batch, args, SOLVE_ROWS)


def adjoint_batch(*args) -> None:
    """:func:`~.ipm_kernel.adjoint_batch` (same arguments, outputs written in place) on the
    available threads."""
    ipm_cache.ensure_fresh()
    run_in_blocks(ipm.adjoint_batch, args, ADJOINT_ROWS)


def block_bounds(rows: int, threads: int) -> list[tuple[int, int]]:
    """Contiguous ``[lo, hi)`` blocks covering ``rows`` problems, at most ``threads`` of them and
    each at least ``MIN_ROWS_PER_THREAD`` long (one block when the batch is small)."""
    parts = max(1, min(threads, rows // MIN_ROWS_PER_THREAD))
    edges = [rows * i // parts for i in range(parts + 1)]
    return list(zip(edges[:-1], edges[1:]))


def run_in_blocks(kernel: Callable, args: Sequence, batched: frozenset[int],
                  threads: int | None = None) -> None:
    """Call ``kernel`` on row blocks of the arguments at the positions ``batched`` (views, so the
    outputs land in the caller's arrays), the first block in this thread.

    Args:
        kernel: a compiled entry point that writes its outputs into its arguments.
        args: its arguments; those at ``batched`` have the batch on axis 0 (B rows).
        batched: the positions of the per-problem arrays.
        threads: how many threads at most (default :func:`kernel_threads`).
    """
    rows = args[min(batched)].shape[0]
    blocks = block_bounds(rows, kernel_threads() if threads is None else threads)
    if len(blocks) == 1:
        kernel(*args)
        return

    def block(lo: int, hi: int) -> list:
        return [a[lo:hi] if i in batched else a for i, a in enumerate(args)]

    key = (os.getpid(), len(blocks) - 1)
    pool = _pools.get(key)
    if pool is None:
        pool = _pools[key] = ThreadPoolExecutor(len(blocks) - 1, thread_name_prefix="gpmpc-ipm")
    others = [pool.submit(kernel, *block(lo, hi)) for lo, hi in blocks[1:]]
    try:
        kernel(*block(*blocks[0]))
    finally:
        for future in others:
            future.result()
