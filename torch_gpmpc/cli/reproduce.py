"""``gpmpc reproduce``: the paper's six methods x N seeds, Figures 1-6 and a results table.

Seed s gives every method the same GP data and the same noise sequence. Runs go to
worker processes (one torch thread each); finished runs are cached under
``DIR/cache`` by (method, seed, rho, config hash), so a second call, or a call after
an interruption, only computes what is missing.
"""

from __future__ import annotations

import os
from pathlib import Path


from torch_gpmpc.config.schema import METHODS, Config
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.sim.experiments import (
    PAPER_COST, PAPER_FORMULATION, SOUND_LABEL, Task, mean_residual_profile, summarize, sweep_config,
)
from torch_gpmpc.fileio import write_text
from torch_gpmpc.report.tables import table_csv, table_markdown
from torch_gpmpc.sim.rollout import Rollout

from torch_gpmpc.cli.cached_runs import parse_list, run_uncached
from torch_gpmpc.cli.run import config_from_args, output_dir


def _tasks(cfg, args, cache: Path) -> tuple[list[Task], list[Task]]:
    methods = parse_list(args.methods, str, "methods")
    for m in methods:
        if m not in METHODS:
            raise GpmpcError(f"--methods: unknown method {m!r}; choose from {', '.join(METHODS)}")
    rhos = parse_list(args.rho_values, float, "rho-values")
    if args.runs < 1:
        raise GpmpcError(f"--runs must be >= 1, got {args.runs}")
    if args.rho_start < 0:
        raise GpmpcError(f"--rho-start must be >= 0, got {args.rho_start}")
    sound = {**cfg.to_dict(), **PAPER_COST}  # the sound margins under the paper's cost
    paper = {**sound, **PAPER_FORMULATION}
    runs = [Task("run", m, cfg.seed + s, cfg.rho, paper, str(cache)) for m in methods for s in range(args.runs)]
    runs += [Task("run", "gp-chance", cfg.seed + s, cfg.rho, sound, str(cache), SOUND_LABEL) for s in range(args.runs)]
    sweep = sweep_config(Config(**paper), args.rho_start + args.rho_steps, args.rho_iterations)
    sweeps = [Task("sweep", m, cfg.seed, rho, sweep, str(cache)) for m in methods for rho in rhos]
    return runs, sweeps


def _fig1(cfg, path: Path) -> None:
    """Fig. 1: the wind field beside the GP mean of agent 0 (seed ``cfg.seed``)."""
    from torch_gpmpc.report.gp_figures import plot_gp_field
    from torch_gpmpc.gp import fit_agent_gps
    from torch_gpmpc.dynamics.systems import system_from_config

    system = system_from_config(cfg)
    gp = fit_agent_gps(cfg, system, 1)[0]
    plot_gp_field(gp, system.wind, gp.train_inputs_raw, path, box=cfg.gp_fit_settings().box,
                  title=f"wind g vs GP mean (agent 0, seed {cfg.seed}, N = {cfg.gp_samples})")


def main(args) -> int:
    from torch_gpmpc.report import figures as plots

    cfg = config_from_args(args)
    if cfg.dim != 2:
        raise GpmpcError("config key 'dim': the paper's figures are 2D; use dim=2")
    out = output_dir(args.out)
    runs, sweeps = _tasks(cfg, args, out / "cache")
    workers = args.workers or os.cpu_count() or 1
    run_uncached(runs + sweeps, workers)

    by_method: dict[str, list[Rollout]] = {}
    for task in runs:
        by_method.setdefault(task.row, []).append(Rollout.load(task.path))
    rows = {m: summarize(rs) for m, rs in by_method.items()}
    write_text(out / "table.md", table_markdown(rows))
    write_text(out / "table.csv", table_csv(rows))

    fig = out / "figures"
    _fig1(cfg, fig / "fig1_gp_field.png")
    for number, method in ((2, "nominal"), (3, "gp-chance")):
        if method in by_method:
            plots.plot_trajectories(by_method[method][0], fig / f"fig{number}_trajectories_{method}.png")
    profiles: dict[str, dict[float, object]] = {}
    for task in sweeps:
        profiles.setdefault(task.method, {})[task.rho] = mean_residual_profile(Rollout.load(task.path), args.rho_start)
    plots.plot_admm_rho_sweep(profiles, fig / "fig4_admm_rho.png")
    plots.plot_distance_bands(by_method, fig / "fig5_distances.png", cfg.r_safe)
    plots.plot_path_lengths(by_method, fig / "fig6_path_lengths.png")
    print(table_markdown(rows))
    print(f"wrote {out / 'table.md'}, {out / 'table.csv'} and {fig}/")
    return 0
