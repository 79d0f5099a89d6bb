"""``gpmpc calibrate``: Monte Carlo calibration of the chance constraints -> DIR/calibration.json, .png.

Runs the crossing for every formulation (``sound``: the defaults; ``paper``: eq. 24 with the
latent variance), every eps and ``--runs`` seeds, in parallel over the cores, with the runs
cached under ``DIR/cache`` (an interrupted call resumes).

With ``--mission``: whole runs under ``risk_mode = mission`` at each budget (and, with
``--baseline-runs``, under ``pair_step``), reported as the fraction of runs with any violation
and its Clopper-Pearson interval: the ``mission`` entry of ``calibration.json`` (merged into
an existing file, so the pair-step rows stay beside it) and ``DIR/mission.png``.
"""

from __future__ import annotations

import json
import os

from torch_gpmpc.cli.cached_runs import parse_list, run_uncached
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.fileio import write_json


def main(args) -> int:
    from torch_gpmpc.cli.run import config_from_args, output_dir

    cfg = config_from_args(args)
    if args.runs < 1:
        raise GpmpcError(f"--runs must be >= 1, got {args.runs}")
    out = output_dir(args.out)
    workers = args.workers or os.cpu_count() or 1
    if args.mission:
        return _mission(args, cfg, out, workers)
    if args.budgets:
        raise GpmpcError("--budgets sets the mission budgets of --mission runs; add --mission (or drop --budgets "
                         "and give per-pair risks with --eps)")
    from torch_gpmpc.report.figures import plot_calibration
    from torch_gpmpc.sim.calibration import active_outcomes, calibration_rows, calibration_tasks
    from torch_gpmpc.sim.rollout import Rollout

    eps_values = _unit_list(args.eps, "eps")
    tasks = calibration_tasks(cfg, eps_values, args.runs, str(out / "cache"), steps=args.steps)
    (out / "cache").mkdir(parents=True, exist_ok=True)  # only after every argument is checked
    run_uncached([task for *_, task in tasks], workers)
    outcomes: dict = {}
    for name, eps, task in tasks:
        outcomes.setdefault((name, eps), []).append(active_outcomes(Rollout.load(task.path)))
    rows = calibration_rows(outcomes)
    payload = {**_existing(out), "rows": rows, "runs": args.runs, "steps": args.steps,
               "noise_std": cfg.noise_std, "method": cfg.method}
    write_json(out / "calibration.json", payload)
    plot_calibration(rows, out / "calibration.png")
    print(_table(rows))
    print(f"wrote {out / 'calibration.json'} and {out / 'calibration.png'}")
    return 0


def _mission(args, cfg, out, workers: int) -> int:
    """``--mission``: whole runs per budget (and the pair-step baseline), the mission entries."""
    from torch_gpmpc.report.figures import plot_mission_calibration
    from torch_gpmpc.sim.calibration import mission_entry, mission_tasks
    from torch_gpmpc.sim.rollout import Rollout

    budgets = _unit_list(args.budgets, "budgets") if args.budgets else [cfg.risk_budget]
    if args.baseline_runs < 0:
        raise GpmpcError(f"--baseline-runs must be >= 0, got {args.baseline_runs}")
    cfg = cfg.replace(risk_mode="mission")  # checks the method and pair margin can carry a budget
    tasks = mission_tasks(cfg, budgets, args.runs, str(out / "cache"), args.baseline_runs)
    (out / "cache").mkdir(parents=True, exist_ok=True)  # only after every argument is checked
    run_uncached([task for *_, task in tasks], workers)
    groups: dict = {}
    for mode, level, task in tasks:
        groups.setdefault((mode, level), []).append(Rollout.load(task.path))
    entries = [mission_entry(mode, level, rollouts) for (mode, level), rollouts in groups.items()]
    payload = {**_existing(out), "mission": entries[0], "mission_rows": entries,
               "mission_setup": {"scenario": cfg.scenario, "num_agents": cfg.num_agents, "noise_std": cfg.noise_std,
                                 "method": cfg.method, "pair_margin": cfg.pair_margin,
                                 "risk_pacing": cfg.risk_pacing, "max_steps": cfg.max_steps}}
    write_json(out / "calibration.json", payload)
    plot_mission_calibration(entries, out / "mission.png")
    print(_mission_table(entries))
    print(f"wrote {out / 'calibration.json'} (mission, mission_rows) and {out / 'mission.png'}")
    return 0


def _existing(out) -> dict:
    """The entries of an earlier ``calibration.json`` in ``out`` (kept beside the new ones)."""
    path = out / "calibration.json"
    if not path.exists():
        return {}
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise GpmpcError(f"{str(path)!r} exists but cannot be read ({exc}); move it away or choose another --out") from exc
    return data if isinstance(data, dict) else {}


def _unit_list(text: str, name: str) -> list[float]:
    values = parse_list(text, float, name)
    if not values or not all(0 < v < 1 for v in values):
        raise GpmpcError(f"--{name}: every value must be in (0, 1), got {text!r}")
    return values


def _table(rows: list[dict]) -> str:
    lines = ["| formulation | eps | active rows | violations | rate | 95 % interval |", "|---|---|---|---|---|---|"]
    for r in rows:
        rate = "-" if r["rate"] is None else f"{r['rate']:.3f}"
        lines.append(f"| {r['formulation']} | {r['eps']:g} | {r['active']} | {r['violations']} | {rate} | "
                     f"[{r['rate_low']:.3f}, {r['rate_high']:.3f}] |")
    return "\n".join(lines)


def _mission_table(entries: list[dict]) -> str:
    lines = ["| risk | runs | runs with a violation | rate | 95 % interval (Clopper-Pearson) | risk spent (mean) "
             "| every agent arrived | arrival (mean) | path length (mean) |", "|---|---|---|---|---|---|---|---|---|"]
    for e in entries:
        risk = f"mission delta={e['risk_budget']:g}" if e["risk_mode"] == "mission" else f"pair_step eps={e['eps']:g}"
        spent = "-" if e["risk_spent_mean"] is None else f"{e['risk_spent_mean']:.3g}"
        arrival = "-" if e["arrival_mean"] is None else f"{e['arrival_mean']:.1f}"
        lines.append(f"| {risk} | {e['runs']} | {e['runs_with_violation']} | {e['rate']:.3f} | "
                     f"[{e['ci95'][0]:.3f}, {e['ci95'][1]:.3f}] | {spent} | {e['runs_every_agent_arrived']} of "
                     f"{e['runs']} | {arrival} | {e['path_length_mean']:.2f} |")
    return "\n".join(lines)
