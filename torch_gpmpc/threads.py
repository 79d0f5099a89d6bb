"""Torch's intra-op thread count, set for a block and restored after it."""

from __future__ import annotations

from contextlib import contextmanager
from typing import Iterator

import torch


@contextmanager
def torch_threads(count: int) -> Iterator[int]:
    """Run the block with ``torch.set_num_threads(count)``; the caller's count is restored on exit,
    also when the block raises. Yields the caller's count."""
    before = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield before
    finally:
        torch.set_num_threads(before)
