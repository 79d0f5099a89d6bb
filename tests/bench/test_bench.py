"""Short versions of the ``gpmpc bench`` sections ``local``, ``scale`` and ``run`` (the full ones are
measurements, run by hand; see the README's performance section)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from torch_gpmpc.cli import main


def test_bench_local_short(monkeypatch):
    import torch_gpmpc.bench.local as bench_local
    import torch_gpmpc.bench.warm as bench_warm
    from torch_gpmpc.config.schema import Config

    monkeypatch.setattr(bench_warm, "WORKLOADS", {"paper, 4 steps": (Config(max_steps=4), 4)})
    monkeypatch.setattr(bench_local, "BATCHES", (2, 4))
    monkeypatch.setattr(bench_local, "THREAD_BATCHES", (8,))
    monkeypatch.setattr(bench_local, "available_cores", lambda: 2)
    result = bench_local.run(quick=True)
    threads = result["threads"]["table"]
    assert [(r["workload"], r["pass"]) for r in threads] == [
        ("fast, all", "forward"), ("fast, all", "forward+backward"),
        ("fast, crossing", "forward"), ("fast, crossing", "forward+backward")]
    assert all(r["same_plans"] and r["threads"] == 2 and r["speedup_vs_one_thread"] > 0 for r in threads)
    families = result["families"]
    assert {r["family"] for r in families["table"]} == set(bench_local.FAMILIES + bench_local.STRESS_FAMILIES)
    assert {r["family"] for r in families["table"] if not r["in_target"]} == set(bench_local.STRESS_FAMILIES)
    in_target = [r["speedup_vs_default"] for r in families["table"] if r["in_target"]]
    assert families["target"]["speedup_vs_default_min"] == min(in_target)
    slack = {(c["family"], c["batch"]): c["state_slack_max"] for c in families["checks"]}
    assert all(slack[f, b] < 1e-9 for f in bench_local.FAMILIES for b in (2, 4))  # feasible instances
    assert all(slack[f, b] > 1e-3 for f in bench_local.STRESS_FAMILIES for b in (2, 4))  # must open its slack
    assert all(r["speedup_vs_default"] > 0 and r["speedup_all_cores_vs_default"] > 0 for r in families["table"])
    cores_worst = min(r["speedup_all_cores_vs_default"] for r in families["table"] if r["in_target"])
    assert families["target"]["met_all_cores"] is (cores_worst >= families["target"]["target"])
    paths = {(r["path"], r["batch"], r["pass"]) for r in result["table"]}
    for path in ("fast", "cvxpylayers-default", "clarabel"):
        for batch in (2, 4):
            assert {(path, batch, "forward"), (path, batch, "forward+backward")} <= paths
    assert ("reference", 2, "forward") in paths and ("reference", 4, "forward") not in paths  # quick
    for check in result["checks"]:  # the fast path agrees with the cvxpylayers paths
        assert check["fast_ok_fraction"] == 1.0
        assert check["fast_vs_clarabel"]["max_abs_plan_diff"] < 1e-6
        assert check["fast_vs_clarabel"]["max_rel_grad_diff"] < 1e-5
    assert result["checks"][0]["fast_vs_reference"]["max_abs_plan_diff"] < 1e-6
    [warm] = result["warm_start"]  # the warm active-set solves: the cold path's plans, most problems warm
    assert warm["workload"] == "paper, 4 steps" and warm["local_problems"] > 0
    assert warm["max_abs_plan_diff"] < 1e-6 and warm["same_acceptance"] and warm["warm_fraction"] > 0.5
    assert warm["admm_iterations_warm"] == warm["admm_iterations_cold"]
    assert warm["speedup"] == pytest.approx(warm["ms_per_problem_cold"] / warm["ms_per_problem_warm"])
    targets = result["targets"]
    assert set(targets) == {"fast_batch4_forward", "fast_batch4_forward+backward"}
    table = {(r["path"], r["batch"], r["pass"]): r for r in result["table"]}
    for name, t in targets.items():  # each target's ratio is its table row's, judged against its bar
        pass_name = name.split("_", 2)[2]
        assert t["speedup_vs_default"] == table["fast", max(b for _, b, _ in table), pass_name]["speedup_vs_default"]
        assert t["met"] is (t["speedup_vs_default"] >= t["target"])


def test_bench_cli_scale_short(tmp_path, monkeypatch):
    import torch_gpmpc.bench.scale as bench_scale

    monkeypatch.setattr(bench_scale, "TEAM_SIZES", (3, 6))
    monkeypatch.setattr(bench_scale, "QUICK_CROWD_AGENTS", 4)
    monkeypatch.setattr(bench_scale, "QUICK_CROWD_STEPS", 3)
    monkeypatch.setattr(bench_scale, "QUICK_TRANSITION_AGENTS", 3)
    assert main(["bench", "--sections", "scale", "--quick", "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "bench.json").read_text())
    rows = result["sections"]["scale"]["table"]
    assert [r["agents"] for r in rows] == [3, 6]
    assert all(r["ms_per_step_per_agent"] > 0 for r in rows)
    assert result["sections"]["scale"]["per_agent_1000_over_100"] is None  # neither size measured here
    runs = result["sections"]["scale"]["whole_runs"]
    assert [(r["method"], r["agents"], r["steps"]) for r in runs] == [("gp-chance", 4, 3), ("nonlinear", 4, 3)]
    assert all(0 < r["step_s_median"] <= r["step_s_max"] and r["step_s_mean"] <= r["step_s_max"] for r in runs)
    assert all(isinstance(r["bars_unmet"], str) for r in runs)
    assert result["sections"]["scale"]["crowd_bars_met"] is None  # not the 100-agent crowd
    cores = result["sections"]["scale"]["threads"]
    assert cores["cores"] >= 1
    [row] = cores["table"]
    assert row["same_plans"] and row["s_per_step_1_thread"] > 0 and row["s_per_step"] > 0
    transitions = result["sections"]["scale"]["transitions"]
    assert [r["workload"].split(", ", 1)[1] for r in transitions["table"]][:2] == ["copies, 1 thread",
                                                                                  "planes, 1 thread (default)"]
    assert transitions["met"] is None and transitions["table"][0]["speedup_vs_copies"] == 1.0
    assert all(r["compute_ms_per_agent_step"] > 0 and 0 <= r["success"] <= 1 for r in transitions["table"])
    assert (tmp_path / "figures" / "bench_scale.png").stat().st_size > 0


def test_bench_unknown_section_is_refused(tmp_path, capsys):
    assert main(["bench", "--sections", "nope", "--out", str(tmp_path)]) == 2
    assert "unknown section 'nope'" in capsys.readouterr().err
    assert not (tmp_path / "bench.json").exists()


def test_bench_section_alias_fast_runs_the_local_section_once(tmp_path, monkeypatch):
    """``fast`` is the old name of ``local``: it runs the local workload, once, recorded as ``local``."""
    import json

    import torch_gpmpc.bench.local as bench_local

    calls = []
    monkeypatch.setattr(bench_local, "run", lambda quick, out: calls.append(quick) or {"table": []})
    assert main(["bench", "--sections", "fast,local", "--quick", "--out", str(tmp_path)]) == 0
    assert calls == [True]
    assert list(json.loads((tmp_path / "bench.json").read_text())["sections"]) == ["local"]


def test_bench_run_short_breakdown_times_every_iteration_once():
    import torch_gpmpc.bench.run as bench_run

    result = bench_run.run(quick=True)  # 10 steps, no child process
    rows = {r["part"]: r for r in result["table"]}
    assert result["steps"] == 10 and result["admm_iterations"] >= 10
    # the timers saw the rollout's own ADMM iterations: each through the torch path (one solve, one
    # assembly, one canonicalization; each step's first and its last; a step with edges assembles once
    # more for its variances, which the planes agree on first) or as a compiled iteration (which also
    # computes a step's last iteration once before the torch path repeats it, and its problems are
    # canonicalized once per step); one ADMM step per closed-loop step; fit 1 time; every solve after
    # the first starts warm (one warm kernel call), and the cold kernel (the solve with its polish, one
    # call) runs only for what the warm one leaves
    calls = result["calls"]
    iterations, torch_path, compiled = result["admm_iterations"], calls["solve"], calls["compiled"]
    assert torch_path <= calls["assembly"] <= torch_path + result["steps"]
    assert torch_path <= calls["canonicalize"] <= torch_path + result["steps"]
    assert torch_path <= iterations <= torch_path + compiled <= iterations + result["steps"]
    assert calls["kernel_warm"] + calls["kernel_warm@compiled"] == torch_path + compiled - 1
    assert 1 <= calls["kernel"] + calls["kernel@compiled"] <= torch_path + compiled
    # the linearization points are held within a step (relinearize=false): one linearization per step
    assert calls["linearize"] == result["steps"]
    assert calls["admm_step"] == 10 and calls["gp_fit"] == 1
    rows.pop("closed loop")
    rows.pop("GP fit (3 agents)")
    assert all(r["total_s"] >= 0 for r in rows.values())  # nested timers: remainders are not negative
    assert rows["solve: kernel (warm active set)"]["total_s"] > 0 and rows["linearize"]["total_s"] > 0


def test_the_transition_benchmarks_model_is_the_example_files():
    """The bench's random-transition agent is examples/transition/di3d.toml (the README's command)."""
    from torch_gpmpc.bench.scale import transition_config
    from torch_gpmpc.config import Config

    example = Path(__file__).resolve().parents[2] / "examples" / "transition" / "di3d.toml"
    assert transition_config(4, 0, "copies").model_spec() == Config(model=str(example)).model_spec()


def test_unmet_bars_holds_gp_chance_to_every_bar_and_nonlinear_to_the_speed_bar():
    from torch_gpmpc.bench.scale import unmet_bars

    good = {"method": "gp-chance", "every_agent_arrived": True, "violations": 2, "min_pair_distance": 0.45,
            "converged_fraction": 0.95, "step_s_mean": 0.1}
    assert unmet_bars(good) == []
    bad = dict(good, every_agent_arrived=False, violations=3, min_pair_distance=0.449, converged_fraction=0.9,
               step_s_mean=0.11)
    assert unmet_bars(bad) == ["arrival", "violations", "worst_distance", "converged", "step_time"]
    # the 'nonlinear' run (no margins) is held to the speed bar alone
    assert unmet_bars(dict(bad, method="nonlinear")) == ["step_time"]
    assert unmet_bars(dict(good, method="nonlinear", violations=400)) == []


def test_bench_prints_a_section_whose_threads_is_a_number(tmp_path, monkeypatch):
    """The ``gp`` section's ``threads`` is its thread count, ``scale``'s a table: the printing crashed
    on the number (after the measurements, so that no ``bench.json`` was written)."""
    import torch_gpmpc.bench.gp as bench_gp

    monkeypatch.setattr(bench_gp, "run", lambda quick, out: {"table": [{"workload": "w", "ours_ms": 1.0}],
                                                             "threads": 1})
    assert main(["bench", "--sections", "gp", "--quick", "--out", str(tmp_path)]) == 0
    assert json.loads((tmp_path / "bench.json").read_text())["sections"]["gp"]["threads"] == 1
