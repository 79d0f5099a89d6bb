"""Worker processes of `gpmpc reproduce` / `gpmpc benchmark` end with the process that started them."""

import os
import subprocess
import sys
import textwrap
import time

import pytest

SCRIPT = textwrap.dedent("""
    import multiprocessing, os, time
    from torch_gpmpc.sim.experiments import end_with_parent

    def work(parent):
        end_with_parent(parent)
        print("armed", flush=True)
        time.sleep(120)

    if __name__ == "__main__":
        worker = multiprocessing.get_context("spawn").Process(target=work, args=(os.getpid(),))
        worker.start()
        print(worker.pid, flush=True)
        time.sleep(120)
""")


def _alive(pid: int) -> bool:
    """Running (a zombie, dead but not yet reaped by whoever adopted it, counts as ended)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_worker_ends_when_the_process_that_started_it_is_killed(tmp_path):
    script = tmp_path / "parent.py"
    script.write_text(SCRIPT)
    parent = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    worker = None
    try:
        worker = int(parent.stdout.readline())
        assert parent.stdout.readline().strip() == "armed"  # the worker shares the parent's stdout
        assert _alive(worker)
        parent.kill()  # SIGKILL: no Python cleanup in the parent
        parent.wait(timeout=30)
        deadline = time.monotonic() + 30
        while _alive(worker) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not _alive(worker)
    finally:
        parent.kill()
        parent.wait(timeout=30)
        parent.stdout.close()
        if worker is not None and _alive(worker):
            os.kill(worker, 9)
