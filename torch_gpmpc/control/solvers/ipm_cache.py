"""The compiled kernel's on-disk cache, kept in step with every source it is compiled from.

numba's cache (``cache=True``) checks only the source file of the function it caches, so an entry
point of :mod:`~.ipm_kernel` (or :mod:`~.ipm_active`) keeps its machine code when only a file it calls into changes
(:mod:`~.ipm_residuals`, :mod:`~.ipm_linalg`: their functions are compiled into the caller's
code). Seen here: after an edit of ``ipm_residuals.initial_point`` in an editable install, the
kernel ran the old start until its cache files were removed. So before the first solve of a
process, :func:`ensure_fresh` removes the cache files that are older than the newest kernel source,
and numba compiles afresh (once). Only numba's default cache next to the sources
(``__pycache__``) is looked at; ``NUMBA_CACHE_DIR`` is left to its owner.
"""

from __future__ import annotations

import logging
from pathlib import Path

logger = logging.getLogger(__name__)

#: The modules whose numba functions the kernel is compiled from.
KERNEL_MODULES = ("ipm_kernel", "ipm_active", "ipm_residuals", "ipm_linalg")

_fresh_in_this_process = False


def newest_source_time(directory: Path, modules: tuple[str, ...] = KERNEL_MODULES) -> float:
    """The latest modification time (s) of the modules' source files in ``directory``."""
    return max((directory / f"{name}.py").stat().st_mtime for name in modules)


def stale_cache_files(directory: Path, modules: tuple[str, ...] = KERNEL_MODULES) -> list[Path]:
    """The modules' numba cache files (index ``.nbi`` and data ``.nbc`` in ``directory/__pycache__``)
    written before the newest of their sources changed."""
    newest = newest_source_time(directory, modules)
    cache = directory / "__pycache__"
    return sorted(p for name in modules for p in cache.glob(f"{name}.*.nb[ic]") if p.stat().st_mtime < newest)


def remove_stale_cache(directory: Path, modules: tuple[str, ...] = KERNEL_MODULES) -> int:
    """Remove :func:`stale_cache_files`; returns how many were removed (a file another process
    removed first counts as removed)."""
    stale = stale_cache_files(directory, modules)
    for path in stale:
        path.unlink(missing_ok=True)
    if stale:
        logger.info("removed %d stale compiled-kernel cache files (a kernel source changed); it compiles again",
                    len(stale))
    return len(stale)


def ensure_fresh() -> None:
    """Once per process, before the kernel's first call: drop cache files older than its sources."""
    global _fresh_in_this_process
    if _fresh_in_this_process:
        return
    try:
        remove_stale_cache(Path(__file__).parent)
    except OSError as err:  # a read-only install: numba caches elsewhere, nothing of ours to drop
        logger.debug("kernel cache check skipped: %s", err)
    _fresh_in_this_process = True
