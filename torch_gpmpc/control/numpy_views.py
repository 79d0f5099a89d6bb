"""Tensors as the C-contiguous NumPy arrays the compiled (numba) kernels read."""

from __future__ import annotations

import numpy as np
from torch import Tensor


def as_array(t: Tensor, dtype=np.float64) -> np.ndarray:
    """``t`` detached, on the CPU, C-contiguous and of ``dtype`` (zero-copy when it already is)."""
    return np.ascontiguousarray(t.detach().cpu().numpy(), dtype=dtype)
