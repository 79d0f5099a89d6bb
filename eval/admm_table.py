"""Research script: consensus ADMM on copies (``admm_coupling = copies``) against the centralized
solve, noiseless, per scenario.

For each scenario it runs, with the proposed method and the package's default models:

* ``centralized``: the joint problem solved centrally every step, re-linearized 3 times
  (:class:`~torch_gpmpc.coordination.centralized.CentralizedPlanner`);
* ``paper rule``: rho 20 fixed, primal-only stop, re-linearized every iterate (the paper);
* ``defaults``: the copies' defaults (adaptive rho from 20, primal-dual stop);
* ``from rho 1`` and ``from rho 100``: the defaults started at another rho.

and writes ``OUT/admm_table.json`` and ``OUT/admm_table.md`` (arrival step of the last
agent, mean ADMM iterations per step, minimum pair distance, violations). Run from the
repository root::

    python eval/admm_table.py --out runs/admm_table
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from torch_gpmpc.config import load_config
from torch_gpmpc.coordination.centralized import CentralizedPlanner
from torch_gpmpc.coordination.controller import Controller
from torch_gpmpc.dynamics.systems import system_from_config
from torch_gpmpc.fileio import write_json, write_text
from torch_gpmpc.gp import fit_agent_gps
from torch_gpmpc.sim.closed_loop import ADMMPlanner, run_closed_loop
from torch_gpmpc.sim.metrics import compute_metrics
from torch_gpmpc.sim.scenarios import make_scenario

SCENARIOS = {
    "paper (3 agents)": {"scenario": "paper"},
    "circle, 4 agents meet at the centre": {"scenario": "circle", "num_agents": 4},
    "circle, 6 agents": {"scenario": "circle", "num_agents": 6},
}
VARIANTS = {
    "centralized": None,
    "paper rule (rho 20, primal stop)": {"rho_update": "fixed", "admm_stop": "primal", "relinearize": True},
    "defaults": {},
    "defaults from rho 1": {"rho": 1.0},
    "defaults from rho 100": {"rho": 100.0},
}


def run_case(scenario: dict, variant: dict | None) -> dict:
    """One noiseless closed-loop run; its metrics."""
    cfg = load_config(None, {**scenario, "admm_coupling": "copies", **(variant or {}), "noise_std": 0.0})
    system = system_from_config(cfg)
    controller = Controller.for_run(cfg, system, fit_agent_gps(cfg, system, cfg.num_agents))
    planner = CentralizedPlanner(controller.agent_step) if variant is None else ADMMPlanner(controller)
    return compute_metrics(run_closed_loop(cfg, make_scenario(cfg), system, planner))


def cell(m: dict, centralized: bool) -> str:
    arrival = m["arrival_step_max"] if m["arrival_step_max"] is not None else "never"
    its = "" if centralized else f", {m['admm_iterations_mean']:.1f} it/step"
    return f"t = {arrival}{its}, min {m['min_pair_distance']:.4f}, {m['violations']} viol."


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="runs/admm_table")
    args = parser.parse_args(argv)
    rows = {}
    for name, scenario in SCENARIOS.items():
        rows[name] = {v: run_case(scenario, spec) for v, spec in VARIANTS.items()}
        print(name, {v: cell(m, v == "centralized") for v, m in rows[name].items()}, flush=True)
    keys = ("arrival_step_max", "admm_iterations_mean", "min_pair_distance", "violations")
    write_json(Path(args.out) / "admm_table.json",
               {s: {v: {k: m[k] for k in keys} for v, m in r.items()} for s, r in rows.items()})
    lines = ["| scenario (noiseless, gp-chance) | " + " | ".join(VARIANTS) + " |",
             "|---" * (len(VARIANTS) + 1) + "|"]
    lines += [f"| {s} | " + " | ".join(cell(m, v == "centralized") for v, m in r.items()) + " |"
              for s, r in rows.items()]
    write_text(Path(args.out) / "admm_table.md", "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
