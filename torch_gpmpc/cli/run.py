"""``gpmpc run``: one closed-loop scenario -> metrics.json, rollout.npz, figures/, tb/."""

from __future__ import annotations

import logging
import sys
import time
from pathlib import Path

from tqdm import tqdm

from torch_gpmpc.cli import collector
from torch_gpmpc.config import load_config, parse_overrides
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.fileio import write_json

log = logging.getLogger(__name__)


def config_from_args(args):
    """Defaults < --config file < --set overrides < explicit flags (--method, --seed)."""
    overrides = parse_overrides(args.set)
    if getattr(args, "method", None):
        overrides["method"] = args.method
    if getattr(args, "seed", None) is not None:
        overrides["seed"] = args.seed
    if getattr(args, "plant", None):
        overrides["plant"] = args.plant
    return load_config(args.config, overrides)


def output_dir(text: str) -> Path:
    """The ``--out`` directory of a command (it may not exist yet).

    Raises:
        GpmpcError: the path is an existing file.
    """
    out = Path(text)
    if out.exists() and not out.is_dir():
        raise GpmpcError(f"--out {str(out)!r} is an existing file; give a directory path")
    return out


def main(args) -> int:
    from torch_gpmpc.coordination.distributed.transport import is_agent_rank

    started = time.perf_counter()
    distributed = args.backend == "distributed"
    if distributed and is_agent_rank():  # torchrun / env launch: ranks > 0 serve agents, rank 0 writes
        from torch_gpmpc.coordination.distributed.agent_process import agent_main

        return agent_main(threads=getattr(args, "threads", 1))
    with collector.setup_phase():  # the modules and kernel it loads live until the process ends
        from torch_gpmpc.gp import check_gp_inputs, load_model_gp
        from torch_gpmpc.report.tensorboard import TBLogger
        from torch_gpmpc.sim.closed_loop import needs_gp, simulate
        from torch_gpmpc.sim.metrics import compute_metrics
        from torch_gpmpc.sim.scenarios import make_scenario, with_scenario_world

        # validate everything (config, scenario, model, output path) before any work or output
        cfg = config_from_args(args)
        scenario = make_scenario(cfg, args.scenario)
        cfg = with_scenario_world(cfg, scenario)  # its workspace, obstacles, radii and models
        gps = [load_model_gp(args.gp_model, cfg.model_spec())] if args.gp_model else None
        if gps is None and needs_gp(cfg.method):
            check_gp_inputs(cfg)
        if cfg.cost is not None and cfg.models is None:  # its sizes against the model, before the GP fits
            from torch_gpmpc.coordination.agent_step import cost_weights
            from torch_gpmpc.dynamics.systems import NominalModel

            cost_weights(None, cfg.controller_settings(), NominalModel(cfg.model_spec()))
        out = output_dir(args.out)
        if distributed:
            from torch_gpmpc.sim.distributed import check_distributed

            check_distributed(cfg, scenario.num_agents, getattr(args, "agents_per_process", 1), args.timeout)
        if not distributed and cfg.solver == "fast":  # agent processes compile and fit their own
            prepare_solver_kernel()
    if not distributed and gps is None and needs_gp(cfg.method):  # before the progress bar: its rate is the loop's
        from torch_gpmpc.dynamics.team import team_system_from_config
        from torch_gpmpc.gp import fit_agent_gps

        print(f"gpmpc: fitting {scenario.num_agents} residual GPs ({cfg.gp_samples} transitions each; "
              f"--gp-model loads a fitted one) ...", file=sys.stderr, flush=True)
        with collector.setup_phase(collect=True):  # fits (and flights) make garbage as they go
            gps = fit_agent_gps(cfg, team_system_from_config(cfg), scenario.num_agents)
    tb = TBLogger(out / "tb")
    bar = tqdm(total=cfg.max_steps, desc=f"{cfg.method} seed {cfg.seed}", unit="step", leave=False)

    def on_step(t: int, info) -> None:
        bar.update(1)
        bar.set_postfix(admm_it=info.iterations, min_dist=f"{info.min_distance:.3f}")

    try:
        if distributed:  # every agent process loads --gp-model (or trains its own GP) itself
            from torch_gpmpc.sim.distributed import simulate_distributed

            rollout, report = simulate_distributed(
                cfg, scenario, gp_model=args.gp_model, on_step=on_step, tb=tb,
                agents_per_process=getattr(args, "agents_per_process", 1),
                timeout_s=args.timeout, log_dir=out / "agent_logs")
        else:
            rollout = simulate(cfg, scenario, gps=gps, on_step=on_step, tb=tb)
    finally:
        bar.close()
        tb.close()
    metrics = compute_metrics(rollout)
    if distributed:
        metrics.update(report.metrics(rollout, cfg))
    rollout.save(out / "rollout.npz")
    write_json(out / "metrics.json", metrics)
    if not args.no_figures:
        from torch_gpmpc.report.figures import save_run_figures

        save_run_figures(rollout, out / "figures", reference_paths=scenario.reference_path().numpy())
    print(_summary(metrics, out, time.perf_counter() - started, figures=not args.no_figures))
    if distributed and report.lost_agents:
        print(f"gpmpc run: warning: {report.summary()}", file=sys.stderr)
        return 3
    return 0


def prepare_solver_kernel() -> None:
    """Compile the kernels (the interior point's and ADMM's) before the progress bar starts (so its
    ETA is honest from step 1), saying so when they are not in numba's cache yet (the first run
    after install)."""
    from torch_gpmpc.coordination import kernels

    if not kernels.is_cached():
        print("gpmpc: compiling the solver kernel (numba, once per installation; about 20-30 s) ...",
              file=sys.stderr, flush=True)
    kernels.warm_up()


def _risk_note(m: dict) -> str:
    """``, risk spent X`` (of budget delta under a mission budget), or nothing without margins."""
    if m.get("risk_spent") is None:
        return ""
    budget = f" of budget {m['risk_budget']:g}" if m.get("risk_budget") is not None else ""
    short = m.get("risk_spent_shortfall")
    short = f" ({short:.3g} of it where plans fell short of their rows)" if short else ""
    return f", risk spent {m['risk_spent']:.3g}{budget}{short}"


def _obstacle_note(m: dict) -> str:
    """``, obstacle distance X (N hits)`` for runs with obstacles, else nothing."""
    if m.get("min_obstacle_distance") is None:
        return ""
    return f", obstacle distance {m['min_obstacle_distance']:.3f} ({m['obstacle_violations']} hits)"


def _clearance_note(m: dict) -> str:
    """The closest pair's clearance (its distance less the pair's required one: ``r_safe``, or
    ``r_k + r_j`` with ``radii``)."""
    clearance = m.get("min_pair_clearance")
    return "" if clearance is None else f", closest clearance {clearance:+.3f}"


def _summary(m: dict, out: Path, total_s: float, figures: bool = True) -> str:
    """The run's result in two lines: the outcome, then where its files went and its times (the
    closed loop's and the whole command's, GP fits and figures included)."""
    def num(value, fmt: str) -> str:  # null when K = 1 (no pairs) or no step was taken
        return "-" if value is None else format(value, fmt)

    ttt, last = m["time_to_target"], m.get("arrival_step_max")
    arrival = "every agent arrived by t = " + str(last) if last is not None else "not every agent arrived"
    return (
        f"{m['method']} seed {m['seed']}: {arrival}, {'all at once at t = ' + str(ttt) if m['reached'] else 'never all at once'} "
        f"in {m['steps']} steps; min distance {num(m['min_pair_distance'], '.3f')} "
        f"({m['violations']} violating step-pairs{_clearance_note(m)}{_risk_note(m)}){_obstacle_note(m)}; "
        f"ADMM iterations mean {num(m['admm_iterations_mean'], '.1f')} "
        f"max {num(m['admm_iterations_max'], 'd')}\n"
        f"wrote {out}/metrics.json, rollout.npz{', figures/' if figures else ''} and tb/ (tensorboard --logdir "
        f"{out / 'tb'}); closed loop {m['wall_time_s']:.1f} s, whole command {total_s:.1f} s"
    )
