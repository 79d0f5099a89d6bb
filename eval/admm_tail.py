"""Research script: which edges hold ADMM at a control step, iteration by iteration.

A step's consensus ADMM stops when every edge meets its stopping test. This runs one closed loop
(default: the scale issue's 100-agent crowd, ``gp-chance``) and records, per step, how many edges
had not met it after 10, 25, 50 and 100 iterations and at the stop
(:attr:`~torch_gpmpc.coordination.state.StepResult.unconverged_edges`). It writes
``OUT/admm_tail.json`` (one row per step) and ``OUT/admm_tail.md`` (a summary). Run from the
repository root::

    python eval/admm_tail.py --out runs/admm_tail --steps 20
    python eval/admm_tail.py --out runs/admm_tail_circle --set scenario=circle --set num_agents=6

Single-model teams only (it builds one model's controller, as ``eval/admm_table.py`` does).
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import torch

from torch_gpmpc.config import load_config
from torch_gpmpc.config.reader import parse_overrides
from torch_gpmpc.coordination.controller import Controller
from torch_gpmpc.dynamics.systems import system_from_config
from torch_gpmpc.fileio import write_json, write_text
from torch_gpmpc.gp import fit_agent_gps
from torch_gpmpc.sim.closed_loop import ADMMPlanner, needs_gp, run_closed_loop
from torch_gpmpc.sim.metrics import compute_metrics
from torch_gpmpc.sim.scenarios import make_scenario, with_scenario_world

#: The scale issue's 100-agent crowd (README "Scale").
CROWD = {"scenario": "random", "num_agents": 100, "circle_radius": 10.0, "comm_radius": 2.5}
#: Iterations after which the script reports the edges still unconverged.
CHECKPOINTS = (10, 25, 50, 100)


class RecordingPlanner(ADMMPlanner):
    """The in-process planner, keeping every step's per-iteration count of unconverged edges."""

    def __init__(self, controller) -> None:
        super().__init__(controller)
        self.rows: list[dict] = []

    def plan(self, t, x, xref, graph):  # noqa: D102 (ADMMPlanner.plan)
        res = super().plan(t, x, xref, graph)
        left = res.unconverged_edges
        self.rows.append({
            "step": t, "edges": graph.num_edges, "iterations": res.iterations, "converged": res.converged,
            "fallback": res.fallback, "unconverged_at_stop": left[-1] if left else 0,
            **{f"unconverged_after_{c}": left[c - 1] if len(left) >= c else 0 for c in CHECKPOINTS},
        })
        return res


def run(overrides: dict, steps: int | None) -> tuple[list[dict], dict]:
    """One closed loop with ``overrides`` on the crowd; the per-step rows and the run's metrics."""
    cfg = load_config(None, {**CROWD, **overrides, **({} if steps is None else {"max_steps": steps})})
    scenario = make_scenario(cfg)
    cfg = with_scenario_world(cfg, scenario)
    system = system_from_config(cfg)
    gps = fit_agent_gps(cfg, system, scenario.num_agents) if needs_gp(cfg.method) else None
    planner = RecordingPlanner(Controller.for_run(cfg, system, gps))
    return planner.rows, compute_metrics(run_closed_loop(cfg, scenario, system, planner))


def summary(rows: list[dict], metrics: dict) -> str:
    """Markdown: how many steps stopped at the cap, and how many edges held each of them."""
    capped = [r for r in rows if not r["converged"]]
    lines = [f"{len(rows)} steps, {len(capped)} stopped unconverged; ADMM iterations per step "
             f"{metrics['admm_iterations_mean']:.1f}, violations {metrics['violations']}, "
             f"closest pair {metrics['min_pair_distance']:.3f}", ""]
    if capped:
        edges = statistics.median(r["edges"] for r in capped)
        lines += [f"Edges not yet converged, median over the {len(capped)} unconverged steps (median {edges:g} edges):",
                  "", "| after iteration | unconverged edges |", "|---|---|"]
        lines += [f"| {c} | {statistics.median(r[f'unconverged_after_{c}'] for r in capped):g} |" for c in CHECKPOINTS]
        lines.append(f"| at the stop | {statistics.median(r['unconverged_at_stop'] for r in capped):g} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="output directory")
    parser.add_argument("--steps", type=int, default=None, help="control steps (default: the config's max_steps)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="config override on the 100-agent crowd (repeatable)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    rows, metrics = run(parse_overrides(args.overrides), args.steps)
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / "admm_tail.json", {"rows": rows, "metrics": {k: metrics[k] for k in (
        "violations", "min_pair_distance", "converged_fraction", "admm_iterations_mean")}})
    text = summary(rows, metrics)
    write_text(args.out / "admm_tail.md", text)
    print(text, end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
