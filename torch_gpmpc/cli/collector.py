"""The cyclic garbage collector of a ``gpmpc`` process (a program that imports torch_gpmpc keeps
its own: these functions act only once :func:`own_process` has been called, which only the
console script does).

A command imports torch, gpytorch, numba, tensorboard and matplotlib: over a million objects that
live until the process ends. CPython's cyclic collector walks all of them in every full
collection: several times while they are imported (about 0.45 s in the README's quadrotor demo),
at times during the closed loop, and once more at exit (about 1 s after a command that fitted a
GP when ``torch.optim`` still imported ``torch._dynamo``). The objects of a command's setup (modules,
compiled kernels, fitted GPs, the scenario) never become garbage before the process ends, so the
collections find nothing among them; ``gc.freeze`` moves them out of the collector's reach: the
entry point freezes torch and the command's module once imported, ``gpmpc run`` its modules,
kernel and scenario, then its fitted GPs, and the console script skips the final collection.
"""

from __future__ import annotations

import gc
from contextlib import contextmanager
from typing import Iterator

_process_owned = False


def own_process() -> None:
    """Let the functions below act: called by the console script, whose process this is."""
    global _process_owned
    _process_owned = True


@contextmanager
def setup_phase(collect: bool = False) -> Iterator[None]:
    """Run a part of a command's setup whose objects live until the process ends, then freeze
    everything alive, so later collections walk only the objects made after it.

    Args:
        collect: keep collecting inside (for work that makes garbage as it goes, such as fitting GPs
            or flying excitation flights); without it the collector is off inside (imports and
            compiled kernels, which make little garbage: a run's setup leaves a few hundred
            objects).

    Outside the console script's process this does nothing.
    """
    if not _process_owned:
        yield
        return
    was_enabled = gc.isenabled()
    if not collect:
        gc.disable()
    try:
        yield
    finally:
        gc.freeze()
        if was_enabled:
            gc.enable()


def skip_final_collection() -> None:
    """Freeze everything alive before the process exits: the interpreter's last full collection
    would free only what the operating system frees anyway. Outputs are written and closed by
    then, and the standard streams are still flushed. Outside the console script's process this
    does nothing."""
    if _process_owned:
        gc.freeze()
