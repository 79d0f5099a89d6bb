"""Starting and reaping agent processes on this host (the local launch of a distributed run)."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

log = logging.getLogger(__name__)

#: The module an agent process runs.
AGENT_MODULE = "torch_gpmpc.coordination.distributed.agent_process"


def spawn_agents(world_size: int, port: int, setup_timeout_s: float, log_dir: Path) -> dict[int, subprocess.Popen]:
    """Start agent ranks ``1..world_size-1`` on 127.0.0.1:``port``, each logging to ``log_dir/rank{r}.log``.

    Returns:
        ``{rank: process}``.
    """
    env = {**os.environ, "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port),
           "WORLD_SIZE": str(world_size), "GPMPC_SETUP_TIMEOUT": str(setup_timeout_s),
           "OMP_NUM_THREADS": "1"}
    if sys.platform.startswith("linux"):
        env.setdefault("GLOO_SOCKET_IFNAME", "lo")
    procs = {}
    for r in range(1, world_size):
        with open(Path(log_dir) / f"rank{r}.log", "wb") as fh:
            procs[r] = subprocess.Popen([sys.executable, "-m", AGENT_MODULE], env={**env, "RANK": str(r)},
                                        stdout=fh, stderr=subprocess.STDOUT)
    return procs


def reap(procs: dict[int, subprocess.Popen], wait_s: float, exit_codes: dict[int, int | None]) -> None:
    """Wait for the agent processes we started; terminate (then kill) any left, by pid."""
    deadline = time.monotonic() + wait_s
    for r, p in procs.items():
        try:
            exit_codes[r] = p.wait(timeout=max(deadline - time.monotonic(), 0.1))
        except subprocess.TimeoutExpired:
            log.warning("agent process rank %d (pid %d) did not exit; terminating it", r, p.pid)
            p.send_signal(signal.SIGTERM)
            try:
                exit_codes[r] = p.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                p.kill()
                exit_codes[r] = p.wait()
