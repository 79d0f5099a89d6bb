"""``gpmpc benchmark`` end to end in its quick form, and the outcome rules by hand."""

from __future__ import annotations

import csv
import json

import pytest

from torch_gpmpc.cli import main
from torch_gpmpc.sim.benchmark import CSV_COLUMNS, run_outcome, summary_rows


def _metrics(**changes):
    base = {"seed": 0, "steps": 50, "num_agents": 2, "violations": 0, "obstacle_violations": 0, "failed_local_solves": 0,
            "deadlock_steps": 0, "arrival_steps": [40, 45], "arrival_step_max": 45, "path_length": [5.0, 6.0],
            "straight_line_length": [4.0, 5.0], "wall_time_s": 2.0, "min_pair_distance": 0.6,
            "min_obstacle_distance": None}
    return {**base, **changes}


def test_outcome_rules_by_hand():
    ok = run_outcome(_metrics(), "random", dt=0.1)
    assert ok["success"] and ok["cause"] == "" and ok["transition_time_s"] == pytest.approx(4.5)
    assert ok["path_length_total"] == 11.0 and ok["compute_ms_per_agent_step"] == pytest.approx(20.0)
    # the first cause that applies, in order collision > obstacle > solver > deadlock > timeout
    assert run_outcome(_metrics(violations=2, obstacle_violations=1), "r", 0.1)["cause"] == "collision"
    assert run_outcome(_metrics(obstacle_violations=1, failed_local_solves=3), "r", 0.1)["cause"] == "obstacle"
    stuck = _metrics(arrival_steps=[40, None], arrival_step_max=None, deadlock_steps=30)
    assert run_outcome(stuck, "r", 0.1)["cause"] == "deadlock"
    assert run_outcome({**stuck, "deadlock_steps": 0}, "r", 0.1)["cause"] == "timeout"
    rows = [ok, run_outcome(stuck, "random", 0.1)]
    summary = summary_rows(rows)
    assert summary == [{"scenario": "random", "agents": 2, "runs": 2, "success_rate": 0.5, "fail_collision": 0,
                        "fail_obstacle": 0, "fail_solver": 0, "fail_deadlock": 1, "fail_timeout": 0,
                        "transition_time_s": pytest.approx(4.5), "path_length_total": 11.0,
                        "compute_ms_per_agent_step": pytest.approx(20.0)}]


def test_quick_benchmark_of_a_built_in_and_a_file_scenario_resumes_from_its_cache(tmp_path, capsys):
    scenario = tmp_path / "pass_the_disc.json"
    scenario.write_text(json.dumps({"starts": [[-3, 0, 0], [3, 0.3, 0]], "targets": [[3, 0, 0], [-3, 0.3, 0]],
                                    "obstacles": [{"center": [0, 0.05, 0], "radius": 0.5}]}))
    out = tmp_path / "bench"
    argv = ["benchmark", "--scenario", "random", str(scenario), "--agents", "3,8", "--seeds", "3", "--quick",
            "--workers", "1", "--set", "method=nominal", "--set", "noise_std=0", "--set", "dim=3", "--set", "max_steps=25", "--out", str(out)]
    assert main(argv) == 0
    with open(out / "benchmark.csv") as f:
        rows = list(csv.DictReader(f))
    assert tuple(rows[0]) == CSV_COLUMNS
    # quick: the first team size and two seeds of random; the file's own two agents, two seeds
    assert [(r["scenario"], r["agents"], r["seed"]) for r in rows] == [
        ("random", "3", "0"), ("random", "3", "1"), ("pass_the_disc", "2", "0"), ("pass_the_disc", "2", "1")]
    assert {r["success"] for r in rows} <= {"True", "False"}
    assert all(r["cause"] in ("", "collision", "obstacle", "solver", "deadlock", "timeout") for r in rows)
    table = (out / "table.md").read_text()
    assert "| random | 3 | 2 |" in table and "| pass_the_disc | 2 | 2 |" in table
    assert (out / "benchmark.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    capsys.readouterr()
    assert main(argv) == 0
    assert "4 of 4 runs cached" in capsys.readouterr().out


def test_benchmark_refuses_bad_team_sizes(tmp_path, capsys):
    assert main(["benchmark", "--agents", "0", "--out", str(tmp_path)]) == 2
    assert "--agents" in capsys.readouterr().err


def test_transition_time_uses_the_model_files_own_dt(tmp_path):
    """The random-transition agent (examples/transition/di3d.toml) samples at dt = 0.2; the
    config's dt (0.1) shapes the built-in models only, so it must not time this run."""
    from pathlib import Path

    from torch_gpmpc.sim.metrics import compute_metrics
    from torch_gpmpc.sim.rollout import Rollout

    model = Path(__file__).resolve().parents[2] / "examples" / "transition" / "di3d.toml"
    out = tmp_path / "bench"
    argv = ["benchmark", "--scenario", "random", "--agents", "3", "--seeds", "1", "--workers", "1",
            "--set", f"model={model}", "--set", 'workspace={"min": [-0.97, -0.97, -0.97], "max": [0.97, 0.97, 0.97]}',
            "--set", "r_safe=0.35", "--set", "min_separation=0.35", "--set", "reference=target",
            "--set", "method=nominal", "--set", "noise_std=0", "--set", "wind_scale=0", "--set", "max_steps=40",
            "--out", str(out)]
    assert main(argv) == 0
    with open(out / "benchmark.csv") as f:
        row = next(csv.DictReader(f))
    arrival = compute_metrics(Rollout.load(next((out / "cache").glob("*.npz"))))["arrival_step_max"]
    assert arrival is not None and float(row["transition_time_s"]) == pytest.approx(arrival * 0.2)
