"""A small TensorBoard helper.

:class:`TBLogger` wraps ``torch.utils.tensorboard.SummaryWriter``; with
``logdir=None`` it is a no-op, so library code can log unconditionally. Tags used in
the package start with ``gp/``, ``admm/``, ``safety/``, ``tune/`` or ``perf/``
. :func:`read_scalars` reads the scalars back (used by tests).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping

TAG_PREFIXES = ("gp/", "admm/", "safety/", "tune/", "perf/")


class TBLogger:
    """Scalar logging to TensorBoard event files under ``logdir`` (no-op when ``None``).

    Usable as a context manager; :meth:`close` flushes the events.

    Args:
        logdir: directory for the event files (created), or ``None`` to disable logging.
    """

    def __init__(self, logdir: str | Path | None):
        self.logdir = None if logdir is None else Path(logdir)
        self._writer = None
        if self.logdir is not None:
            from torch.utils.tensorboard import SummaryWriter  # slow import: only when used

            self.logdir.mkdir(parents=True, exist_ok=True)
            self._writer = SummaryWriter(log_dir=str(self.logdir))

    @property
    def enabled(self) -> bool:
        """Whether events are written."""
        return self._writer is not None

    def scalar(self, tag: str, value: float, step: int) -> None:
        """Log one scalar (non-finite values are skipped).

        Args:
            tag: e.g. ``"gp/loss"``.
            value: a number (or a 0-d tensor).
            step: the global step.
        """
        if self._writer is None:
            return
        value = float(value)
        if math.isfinite(value):
            self._writer.add_scalar(tag, value, global_step=int(step))

    def scalars_from_dict(self, prefix: str, values: Mapping[str, Any], step: int) -> None:
        """Log every number in a (possibly nested) dict as ``prefix/key[/subkey]``.

        Lists are logged element-wise as ``prefix/key/i``; strings and None are skipped.
        """
        if self._writer is None:
            return
        for key, value in _flatten(prefix.rstrip("/"), values):
            self.scalar(key, value, step)

    def flush(self) -> None:
        """Write pending events to disk."""
        if self._writer is not None:
            self._writer.flush()

    def close(self) -> None:
        """Flush and close the writer (idempotent)."""
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    def __enter__(self) -> "TBLogger":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def _flatten(prefix: str, value: Any):
    """Yield ``(tag, number)`` pairs from nested dicts/lists of numbers."""
    if isinstance(value, Mapping):
        for k, v in value.items():
            yield from _flatten(f"{prefix}/{k}", v)
    elif isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            yield from _flatten(f"{prefix}/{i}", v)
    elif isinstance(value, bool):
        yield prefix, float(value)
    elif isinstance(value, (int, float)):
        yield prefix, float(value)
    elif hasattr(value, "item") and getattr(value, "ndim", None) == 0:
        yield prefix, float(value.item())


def read_scalars(logdir: str | Path) -> dict[str, list[tuple[int, float]]]:
    """All scalar events in the event files directly under ``logdir``.

    Returns:
        ``{tag: [(step, value), ...]}`` in file order.
    """
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(logdir), size_guidance={"scalars": 0})
    acc.Reload()
    return {tag: [(int(e.step), float(e.value)) for e in acc.Scalars(tag)]
            for tag in acc.Tags().get("scalars", [])}
