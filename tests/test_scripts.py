"""training/ and eval/ are scripts over the library, not installed packages."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("script, command", [("training/collect.py", "collect"), ("training/fit_gp.py", "fit-gp"),
                                             ("training/tune.py", "tune"), ("eval/run.py", "run"),
                                             ("eval/reproduce.py", "reproduce"), ("eval/bench.py", "bench")])
def test_script_is_the_gpmpc_command(script, command):
    out = subprocess.run([sys.executable, str(ROOT / script), "--help"], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith(f"usage: gpmpc {command}")


@pytest.mark.parametrize("name", ["eval", "training"])
def test_no_generic_top_level_package_is_installed(name):
    out = subprocess.run([sys.executable, "-c", f"import {name}"], capture_output=True, text=True, cwd="/")
    assert out.returncode != 0 and "No module named" in out.stderr


def test_importing_the_package_leaves_torch_defaults_alone():
    code = ("import torch; torch.set_default_dtype(torch.float32); import torch_gpmpc, torch_gpmpc.sim.closed_loop; "
            "assert torch.get_default_dtype() == torch.float32")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd="/")
    assert out.returncode == 0, out.stderr


def test_rotorpy_study_runs_short(tmp_path):
    """The short version of eval/rotorpy_flights.py: every study, two steps a run."""
    pytest.importorskip("rotorpy")
    out = subprocess.run([sys.executable, str(ROOT / "eval" / "rotorpy_flights.py"), "--seeds", "0", "--workers", "1",
                          "--change-step", "1", "--holdout-samples", "20", "--set", "max_steps=2",
                          "--set", "gp_samples=15", "--set", "gp_iters=2", "--out", str(tmp_path)],
                         capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "swap/gp-chance" in (tmp_path / "table.md").read_text()
    assert (tmp_path / "figures" / "rotorpy_online_gp.png").is_file()
    assert (tmp_path / "figures" / "rotorpy_swap_3d.png").is_file()


def test_admm_tail_counts_the_edges_that_hold_each_step(tmp_path):
    """The short version of eval/admm_tail.py: a capped crossing, where every step stops unconverged."""
    import json

    out = subprocess.run([sys.executable, str(ROOT / "eval" / "admm_tail.py"), "--steps", "4", "--set", "method=nominal",
                          "--set", "scenario=circle", "--set", "num_agents=4", "--set", "circle_radius=1",
                          "--set", "admm_max_iter=12", "--set", "admm_coupling=copies", "--out", str(tmp_path)], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    rows = json.loads((tmp_path / "admm_tail.json").read_text())["rows"]
    assert len(rows) == 4
    for row in rows:
        assert (row["unconverged_at_stop"] == 0) == row["converged"]
        assert 0 <= row["unconverged_at_stop"] <= row["edges"] == 6
    assert any(not row["converged"] for row in rows)
    assert "| at the stop |" in (tmp_path / "admm_tail.md").read_text()
