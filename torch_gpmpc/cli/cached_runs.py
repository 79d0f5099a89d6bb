"""What the multi-run commands (``reproduce``, ``calibrate``) share: their list flags and
running the uncached runs with a progress bar."""

from __future__ import annotations

from typing import Callable, Sequence

from tqdm import tqdm

from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.sim.experiments import Task, run_tasks


def parse_list(text: str, cast: Callable[[str], object], name: str) -> list:
    """The values of a comma-separated flag ``--name`` (e.g. ``--rho-values 1,5,20``).

    Raises:
        GpmpcError: a value ``cast`` refuses, naming the flag.
    """
    try:
        return [cast(v) for v in text.split(",") if v.strip()]
    except ValueError as exc:
        raise GpmpcError(f"--{name}: {text!r} is not a comma-separated list ({exc})") from exc


def run_uncached(tasks: Sequence[Task], workers: int) -> None:
    """Say how many runs are cached, then compute the rest in ``workers`` processes."""
    todo = [task for task in tasks if not task.path.exists()]
    print(f"{len(tasks) - len(todo)} of {len(tasks)} runs cached; computing {len(todo)} with {workers} worker(s)")
    with tqdm(total=len(todo), unit="run") as bar:
        run_tasks(todo, workers, on_done=lambda task: bar.update(1))
