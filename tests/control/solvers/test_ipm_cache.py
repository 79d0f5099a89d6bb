"""The kernel's numba cache is dropped when any kernel source is newer than it (numba itself only
checks the file of the function it caches)."""

from __future__ import annotations

import os

from torch_gpmpc.control.solvers import ipm_kernel
from torch_gpmpc.control.solvers.ipm_cache import KERNEL_MODULES, remove_stale_cache, stale_cache_files


def _tree(tmp_path, cache_time: float):
    """Three kernel sources at time 100 and, for each, an index and a data file at ``cache_time``."""
    (tmp_path / "__pycache__").mkdir()
    files = []
    for name in KERNEL_MODULES:
        src = tmp_path / f"{name}.py"
        src.write_text("# source\n")
        os.utime(src, (100.0, 100.0))
        for suffix in ("nbi", "1.nbc"):
            cached = tmp_path / "__pycache__" / f"{name}.solve-12.py311.{suffix}"
            cached.write_bytes(b"machine code")
            os.utime(cached, (cache_time, cache_time))
            files.append(cached)
    other = tmp_path / "__pycache__" / "other.f-1.py311.nbi"  # another module's cache is not ours
    other.write_bytes(b"")
    os.utime(other, (50.0, 50.0))
    return files, other


def test_a_cache_newer_than_every_source_is_kept(tmp_path):
    files, _ = _tree(tmp_path, cache_time=200.0)
    assert stale_cache_files(tmp_path) == [] and remove_stale_cache(tmp_path) == 0
    assert all(f.exists() for f in files)


def test_an_edit_of_a_called_module_drops_the_whole_kernel_cache(tmp_path):
    files, other = _tree(tmp_path, cache_time=200.0)
    os.utime(tmp_path / "ipm_residuals.py", (300.0, 300.0))  # edited after the kernel was compiled
    assert stale_cache_files(tmp_path) == sorted(files)
    assert remove_stale_cache(tmp_path) == len(files)
    assert not any(f.exists() for f in files) and other.exists()


def test_the_package_kernel_is_fresh_after_warm_up():
    ipm_kernel.warm_up()
    assert ipm_kernel.is_cached()
