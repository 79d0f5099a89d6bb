"""Every compiled (numba) kernel a closed loop runs: the local solver's
(:mod:`~torch_gpmpc.control.solvers.ipm_kernel`, with the acceptance check). numba compiles them at
their first call and caches them on disk (once per installation, and again after a kernel source
changes); call :func:`warm_up` before timing or starting worker processes, so that they load the
cache instead.
"""

from __future__ import annotations

from torch_gpmpc.control.solvers import ipm_kernel


def warm_up() -> None:
    """Compile (or load from the on-disk cache) every kernel."""
    ipm_kernel.warm_up()


def is_cached() -> bool:
    """Whether every kernel is in numba's on-disk cache and newer than its sources."""
    return ipm_kernel.is_cached()
