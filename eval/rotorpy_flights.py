"""Research script: a team of RotorPy quadrotors, GPs learned from flights, and online GPs.

Three studies, every run cached in ``OUT/runs`` (rerunning resumes), results in ``OUT/table.md``,
``OUT/results.json`` and figures in ``OUT/figures``:

1. ``swap``: the four-Crazyflie swap of ``examples/rotorpy/swap.toml`` (constant wind) with
   ``nominal``, ``gp`` (GPs learned from excitation flights) and ``gp-chance`` (the same GPs, sound
   chance constraints) on the same seeds: arrival, path length, true-position violations, minimum
   distance, plan tracking error (planned vs flown next state).
2. ``holdout``: the flight GPs' held-out accuracy (contiguous time blocks of agent 0's flights).
3. ``change``: the wind turns 90 degrees at ``--change-step``: frozen GPs against online GPs
   (``gp_online``), one-step prediction error and coverage before and after the change, violations,
   arrival, and the update's share of a control step.
4. ``replay``: the online update without feedback, on the transitions of the first seed's frozen run.

Run from the repository root (about 2 minutes per run on one core; ``--workers 2`` on two)::

    python eval/rotorpy_flights.py --seeds 0,1,2,3,4 --out runs/rotorpy
"""

from __future__ import annotations

import argparse
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

CONFIG = str(Path(__file__).resolve().parents[1] / "examples" / "rotorpy" / "swap.toml")  # from any directory
#: The wind-change runs are longer than the swap's 150 steps: the change comes at the end of the
#: crossing and both GPs get 50 steps after it and time to settle at the goals.
CHANGE_MAX_STEPS = 200


def run_one(job: dict) -> dict:
    """One closed-loop flight -> its metrics (+ the rollout file), cached by name."""
    from torch_gpmpc import compute_metrics, simulate
    from torch_gpmpc.config import load_config
    from torch_gpmpc.fileio import write_json

    path = Path(job["out"]) / "runs" / f"{job['name']}.json"
    if path.is_file():
        return json.loads(path.read_text())
    cfg = load_config(CONFIG, {**job["overrides"], "seed": job["seed"]})
    rollout = simulate(cfg)
    metrics = compute_metrics(rollout)
    metrics["step_s"] = rollout.wall_time_s / max(metrics["steps"], 1)
    metrics["name"], metrics["study"], metrics["label"] = job["name"], job["study"], job["label"]
    rollout.save(path.with_suffix(".npz"))
    write_json(path, metrics)
    return metrics


def jobs(out: str, seeds: list[int], change_step: int, budget: int, sets: dict) -> list[dict]:
    """Every run of the closed-loop studies (``sets``: config overrides of every run)."""
    out_jobs = []
    for seed in seeds:
        for method in ("nominal", "gp", "gp-chance"):
            out_jobs.append({"study": "swap", "label": method, "seed": seed, "overrides": {**sets, "method": method}})
        for label, extra in (("frozen", {}), ("online", {"gp_online": True, "gp_online_budget": budget})):
            out_jobs.append({"study": "change", "label": label, "seed": seed,
                             "overrides": {"max_steps": CHANGE_MAX_STEPS, **sets, "wind_change_step": change_step, **extra}})
    for job in out_jobs:
        job["out"], job["name"] = out, f"{job['study']}_{job['label']}_seed{job['seed']}"
    return out_jobs


def holdout(sets: dict, samples: int) -> dict:
    """Agent 0's flight GP on 70 % of ``samples`` logged steps, scored on the held-out 30 % (time blocks)."""
    from torch_gpmpc.config import load_config
    from torch_gpmpc.data.flights import collect_flights
    from torch_gpmpc.dynamics.rotorpy_plant import PlantSettings
    from torch_gpmpc.dynamics.systems import NominalModel
    from torch_gpmpc.gp import fit_residual_gp, gp_input_label, holdout_metrics

    cfg = load_config(CONFIG, sets)
    nominal = NominalModel(cfg.model_spec())
    data = collect_flights(nominal, PlantSettings.from_config(cfg, seed=1), num_agents=1, samples=samples)
    train, test = data.split(0.3, seed=0, mode="blocks")
    gp = fit_residual_gp(*train.residuals(nominal), iters=cfg.gp_iters, gp_inputs=gp_input_label(nominal))
    scores = holdout_metrics(gp, *test.residuals(nominal))
    scores["residual_rms"] = test.residuals(nominal)[1].square().mean(0).sqrt().tolist()
    return scores


def replay(out: Path, seed: int, change_step: int, budgets=(50, 100)) -> list[dict]:
    """The online update without feedback: the transitions of the frozen run of ``seed`` (wind change)
    fed to online copies of the same GPs (their learners, without the guard); one-step prediction over
    the 50 steps after the change."""
    import torch

    from torch_gpmpc.config import load_config
    from torch_gpmpc.dynamics.systems import system_from_config
    from torch_gpmpc.gp.fit import fit_agent_gps
    from torch_gpmpc.gp.online import OnlineLearning, online_gps
    from torch_gpmpc.sim.rollout import Rollout

    run = Rollout.load(out / "runs" / f"change_frozen_seed{seed}.npz")
    cfg = load_config(None, {**run.config, "seed": seed})
    system = system_from_config(cfg)
    gps = fit_agent_gps(cfg, system, run.num_agents)
    x, u = torch.as_tensor(np.asarray(run.states)), torch.as_tensor(np.asarray(run.inputs))
    after = slice(change_step, change_step + 50)
    rows = []
    for budget in budgets:
        frozen = OnlineLearning(gps, system.nominal, online=False)
        # the learners alone, without the guard: what the update itself learns
        online = OnlineLearning([guarded.learner for guarded in online_gps(gps, budget, 0)], system.nominal, online=True)
        pairs = [(frozen.observe(x[t], u[t], x[t + 1]), online.observe(x[t], u[t], x[t + 1])) for t in range(len(u))]
        err_f = torch.stack([f[0] for f, _ in pairs])[after]
        err_o, var_o = (torch.stack([o[i] for _, o in pairs])[after] for i in (0, 1))
        rows.append({"budget": budget, "frozen_rmse_after": float(err_f.square().mean().sqrt()),
                     "online_rmse_after": float(err_o.square().mean().sqrt()),
                     "online_coverage95_after": float((err_o.abs() <= 1.96 * var_o.sqrt()).double().mean()),
                     "update_s_per_step": float(np.mean(online.update_seconds))})
    return rows


def _mean(rows: list[dict], key: str) -> float | None:
    values = [r[key] for r in rows if r.get(key) is not None]
    return float(np.mean(values)) if values else None


def summarize(results: list[dict], seeds: list[int]) -> dict:
    """Per (study, label): means over seeds, and the counts that matter for safety."""
    out = {}
    for study, label in sorted({(r["study"], r["label"]) for r in results}):
        rows = [r for r in results if r["study"] == study and r["label"] == label]
        out[f"{study}/{label}"] = {
            "runs": len(rows),
            "arrived": sum(r["arrival_step_max"] is not None for r in rows),
            "arrival_step_max_mean": _mean(rows, "arrival_step_max"),
            "violations_total": int(sum(r["violations"] for r in rows)),
            "min_pair_distance": min(r["min_pair_distance"] for r in rows),
            "path_length_mean": float(np.mean([np.sum(r["path_length"]) for r in rows])),
            "plan_tracking_rmse_mean": _mean(rows, "plan_tracking_rmse"),
            "online_prediction_rmse_mean": _mean(rows, "online_prediction_rmse"),
            "online_prediction_rmse_before_change_mean": _mean(rows, "online_prediction_rmse_before_change"),
            "online_prediction_rmse_after_change_mean": _mean(rows, "online_prediction_rmse_after_change"),
            "online_coverage95_after_change_mean": _mean(rows, "online_coverage95_after_change"),
            "gp_update_share_of_step": _mean([{"v": r["gp_update_s_per_step"] / r["step_s"]} for r in rows
                                              if r.get("gp_update_s_per_step") is not None], "v"),
            "step_s_mean": _mean(rows, "step_s"),
        }
    return out


def table(summary: dict, scores: dict, replays: list[dict]) -> str:
    """The markdown table of the README."""
    def f(v, fmt="{:.3f}"):
        return "-" if v is None else fmt.format(v)

    lines = ["| study / GP | arrived | last arrival (mean) | violations | min distance | path (sum, m) | "
             "plan tracking RMSE | prediction RMSE before / after change | coverage after | update / step |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for key, s in summary.items():
        lines.append(f"| {key} | {s['arrived']}/{s['runs']} | {f(s['arrival_step_max_mean'], '{:.1f}')} | "
                     f"{s['violations_total']} | {f(s['min_pair_distance'])} | {f(s['path_length_mean'], '{:.2f}')} | "
                     f"{f(s['plan_tracking_rmse_mean'], '{:.4f}')} | "
                     f"{f(s['online_prediction_rmse_before_change_mean'], '{:.4f}')} / "
                     f"{f(s['online_prediction_rmse_after_change_mean'], '{:.4f}')} | "
                     f"{f(s['online_coverage95_after_change_mean'], '{:.2f}')} | "
                     f"{f(s['gp_update_share_of_step'], '{:.1%}')} |")
    lines.append("")
    lines.append(f"Flight GP, held-out time blocks (agent 0, {scores['num']} rows): RMSE "
                 f"{[round(v, 4) for v in scores['rmse']]} (residual RMS {[round(v, 4) for v in scores['residual_rms']]}), "
                 f"R^2 {[round(v, 2) for v in scores['r2']]}, 95 % coverage {scores['coverage95_all']:.2f}")
    for r in replays:
        lines.append("")
        lines.append(f"Replay without feedback (budget {r['budget']}): prediction RMSE after the change, frozen "
                     f"{r['frozen_rmse_after']:.4f}, online {r['online_rmse_after']:.4f} "
                     f"({r['online_rmse_after'] / r['frozen_rmse_after'] - 1:+.0%}), online coverage "
                     f"{r['online_coverage95_after']:.2f}, update {1e3 * r['update_s_per_step']:.1f} ms per step")
    return "\n".join(lines) + "\n"


def figures(out: Path, results: list[dict], change_step: int) -> None:
    """The 3D flight of gp-chance (first seed) and the learning curves of frozen vs online GPs."""
    from torch_gpmpc.report.figures import plot_trajectories_3d
    from torch_gpmpc.report.gp_figures import plot_prediction_error
    from torch_gpmpc.sim.rollout import Rollout

    seed = min(r["seed"] for r in results)
    runs = out / "runs"
    plot_trajectories_3d(Rollout.load(runs / f"swap_gp-chance_seed{seed}.npz"), out / "figures" / "rotorpy_swap_3d.png")
    plot_prediction_error({label: Rollout.load(runs / f"change_{label}_seed{seed}.npz") for label in ("frozen", "online")},
                          out / "figures" / "rotorpy_online_gp.png", change_step)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="0,1,2,3,4")
    parser.add_argument("--change-step", type=int, default=60)
    parser.add_argument("--budget", type=int, default=100, help="gp_online_budget of the online runs")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--holdout-samples", type=int, default=300, help="logged steps of the hold-out study")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="a config key of every run (e.g. --set plant_wind_speed=[2.5,0,0])")
    parser.add_argument("--out", default="runs/rotorpy")
    args = parser.parse_args(argv)
    from torch_gpmpc.config import parse_overrides
    from torch_gpmpc.fileio import write_json, write_text

    seeds = [int(s) for s in args.seeds.split(",")]
    sets = parse_overrides(args.set)
    out = Path(args.out)
    (out / "runs").mkdir(parents=True, exist_ok=True)
    todo = jobs(str(out), seeds, args.change_step, args.budget, sets)
    if args.workers > 1:
        with ProcessPoolExecutor(max_workers=args.workers) as pool:
            results = list(pool.map(run_one, todo))
    else:
        results = [run_one(job) for job in todo]
    scores = holdout(sets, args.holdout_samples)
    replays = replay(out, seeds[0], args.change_step)
    summary = summarize(results, seeds)
    write_json(out / "results.json", {"summary": summary, "holdout": scores, "replay": replays, "runs": results})
    write_text(out / "table.md", table(summary, scores, replays))
    figures(out, results, args.change_step)
    print(table(summary, scores, replays))
    return 0


if __name__ == "__main__":
    sys.exit(main())
