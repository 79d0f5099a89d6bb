"""Closed loop: head-on agents, per-method smoke runs, TensorBoard read back over HTTP."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
import urllib.parse
import urllib.request

import numpy as np
import pytest
import torch

from torch_gpmpc.cli import main
from torch_gpmpc.config.schema import METHODS, Config
from torch_gpmpc.sim.metrics import compute_metrics
from torch_gpmpc.sim.scenarios import make_scenario
from torch_gpmpc.sim.closed_loop import noise_sequence, simulate

QUICK = ["--set", "max_steps=2", "--set", "admm_max_iter=3", "--no-figures"]  # + gp_iters=5 for GP methods
GP_QUICK = ["--set", "gp_iters=5"]


def test_two_agents_head_on_nominal_no_noise_arrive_without_violation(tmp_path):
    """Nominal model = true system (no wind, no noise). A small lateral offset: with exact
    symmetry the linearized half-space constraint cannot rotate and the agents stop
    face to face (a known limit of the paper's convexification, see README)."""
    scen = tmp_path / "headon.json"
    scen.write_text(json.dumps({"starts": [[-2.0, 0.0], [2.0, 0.05]], "targets": [[2.0, 0.0], [-2.0, 0.05]],
                                "reference": "line", "ref_points": 30}))
    cfg = Config(scenario="circle", num_agents=2, method="nominal", noise_std=0.0, wind_scale=0.0, max_steps=80)
    rollout = simulate(cfg, make_scenario(cfg, str(scen)))
    m = compute_metrics(rollout)
    assert m["reached"], m
    # ADMM stops when the copies agree within admm_tol, so the executed plan may sit
    # below r_safe by at most that much; nothing beyond it.
    assert m["min_pair_distance"] >= cfg.r_safe - cfg.admm_tol
    assert m["min_pair_distance"] < cfg.r_safe + 0.05  # they really had to avoid each other


def test_noise_sequence_is_the_same_for_every_method():
    a = noise_sequence(Config(seed=3, method="nominal"), 3)
    b = noise_sequence(Config(seed=3, method="gp-chance"), 3)
    assert torch.equal(a, b) and not torch.equal(a, noise_sequence(Config(seed=4), 3))


@pytest.mark.parametrize("method", METHODS)
def test_paper_scenario_smoke_every_method(tmp_path, method):
    out = tmp_path / method
    quick = QUICK + (GP_QUICK if method not in ("nominal", "nonlinear") else [])
    assert main(["run", "--method", method, "--out", str(out)] + quick) == 0
    m = json.loads((out / "metrics.json").read_text())
    contract = {"method", "seed", "num_agents", "steps", "reached", "time_to_target", "min_pair_distance",
                "violations", "path_length", "straight_line_length", "admm_iterations_mean",
                "admm_iterations_max", "converged_fraction", "wall_time_s", "solve_time_s_per_step",
                "infeasible_local_solves"}
    assert contract <= set(m)
    assert m["method"] == method and m["steps"] == 2 and m["num_agents"] == 3
    with np.load(out / "rollout.npz", allow_pickle=False) as r:
        assert r["states"].shape == (3, 3, 2) and r["plans"].shape == (2, 3, 14, 2)
        # each step's planning contains its local solves, and the steps fit in the run
        assert r["step_time"].shape == (2,) and np.all(r["solve_time"] <= r["step_time"])
        assert r["step_time"].sum() <= m["wall_time_s"] and m["step_time_s_max"] == r["step_time"].max()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _get_json(url: str, timeout: float = 60.0):
    deadline = time.time() + timeout
    while True:
        try:
            with urllib.request.urlopen(url, timeout=5) as resp:
                return json.loads(resp.read())
        except OSError:
            if time.time() > deadline:
                raise
            time.sleep(0.5)


def test_tensorboard_serves_our_scalar_tags(tmp_path):
    out = tmp_path / "run"
    assert main(["run", "--method", "nominal", "--out", str(out)] + QUICK) == 0
    port = _free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "tensorboard.main", "--logdir", str(out / "tb"), "--host", "127.0.0.1",
         "--port", str(port)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        base = f"http://127.0.0.1:{port}"
        tags = {}
        deadline = time.time() + 60
        while time.time() < deadline:
            tags = _get_json(f"{base}/data/plugin/scalars/tags")
            if tags:
                break
            time.sleep(0.5)
        run_tags = set().union(*(set(v) for v in tags.values()))
        for tag in ("admm/primal_residual", "admm/iterations", "admm/unconverged_edges", "safety/min_distance",
                    "perf/solve_ms", "perf/step_ms"):
            assert tag in run_tags, run_tags
        run = next(iter(tags))
        query = urllib.parse.urlencode({"run": run, "tag": "admm/iterations"})
        series = _get_json(f"{base}/data/plugin/scalars/scalars?{query}")
        assert [row[1] for row in series] == [0, 1]  # one point per closed-loop step
    finally:
        proc.terminate()
        proc.wait(timeout=20)


def test_three_dimensional_paper_scenario_runs(tmp_path):
    """D = 3: starts on the circle in the x1-x2 plane; without noise only the wind's vertical
    component g_3 = 0.1 sin(x1) cos(x2) can move an agent out of that plane."""
    def vertical(wind_scale: float) -> np.ndarray:
        out = tmp_path / f"d3_{wind_scale}"
        args = ["run", "--set", "dim=3", "--set", "noise_std=0", "--set", f"wind_scale={wind_scale}",
                "--out", str(out)]
        assert main(args + QUICK) == 0
        with np.load(out / "rollout.npz", allow_pickle=False) as r:
            states, plans = r["states"], r["plans"]
        assert states.shape == (3, 3, 3) and plans.shape == (2, 3, 14, 3)
        return states[:, :, 2]

    windy, calm = vertical(0.1), vertical(0.0)
    assert np.all(windy[0] == 0.0) and np.all(calm == 0.0)
    assert np.all(np.abs(windy[1:]) > 1e-4)  # every agent leaves the plane, pushed by g_3


def test_single_agent_run_summarizes_without_pairs(tmp_path, capsys):
    """K = 1 has no pairs (min distance null); the summary line still prints."""
    scen = tmp_path / "one.json"
    scen.write_text(json.dumps({"starts": [[0.0, 0.0]], "targets": [[1.0, 0.0]]}))
    out = tmp_path / "one"
    assert main(["run", "--method", "nominal", "--scenario", str(scen), "--out", str(out)] + QUICK) == 0
    assert "min distance -" in capsys.readouterr().out
    assert json.loads((out / "metrics.json").read_text())["min_pair_distance"] is None
