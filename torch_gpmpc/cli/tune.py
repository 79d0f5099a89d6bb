"""``gpmpc tune``: gradient tuning of rho and the per-pair risk split -> DIR/tuned.json, DIR/tb/.

Thin over :mod:`torch_gpmpc.tuning` (the objective, the parameters, the optimizer loop).

Settings: run-config keys as everywhere (``--config FILE``, ``--set NAME=VALUE``), and
tuning settings (:class:`~torch_gpmpc.config.TuneSettings`) as ``--set tune.NAME=VALUE``
or in a ``[tune]`` table of the config file (a ``tuned.json`` is accepted too: its
``config`` and ``tune`` tables are used). ``--iters N`` is the *total* number of
optimizer iterations: with ``--resume`` the run continues from ``DIR/checkpoint.pt``
until N iterations are done (the objective is deterministic, so a resumed run follows
the same path as an uninterrupted one).

Outputs (all written atomically):

* ``DIR/checkpoint.pt`` after every iteration (tensors only; ``torch.load(...,
  weights_only=True)``);
* ``DIR/tb/``: ``tune/loss``, ``tune/rho``, ``tune/risk_split/<lo>_<hi>``,
  ``tune/grad_norm`` and the objective's unweighted parts ``tune/primal``,
  ``tune/dual``, ``tune/cost``, ``tune/distance_penalty`` per iteration (the values at
  the parameters before the step; step N holds the final parameters' evaluation);
* ``DIR/tuned.json``: ``{"config": {...}, "risk_split_per_edge": {...}, "history":
  [...], "tune": {...}, "final": {...}, "evaluation": {...}, "closed_loop": {...}}``;
  ``config`` has every flat key with ``rho`` tuned and ``risk_split`` the mean tuned
  split, so ``gpmpc run --config DIR/tuned.json`` runs with them; ``closed_loop`` compares
  the default and the tuned ``config`` in whole runs on ``tune.closed_loop_seeds``, noisy
  and noiseless (``{"default": {...}, "tuned": {...}}``, each with
  ``arrival_step_max_mean``, ``violations_total``, ``admm_iterations_mean``, ``runs``).
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from torch_gpmpc.cli.run import output_dir
from torch_gpmpc.config import load_settings, parse_overrides
from torch_gpmpc.dynamics.methods import Method
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.fileio import write_json

log = logging.getLogger(__name__)

def main(args) -> int:
    """Run ``gpmpc tune`` (see the module docstring)."""
    from torch_gpmpc import tuning
    from torch_gpmpc.coordination.controller import Controller
    from torch_gpmpc.gp import fit_agent_gps
    from torch_gpmpc.sim.scenarios import make_scenario
    from torch_gpmpc.dynamics.team import team_system_from_config
    from torch_gpmpc.report.tensorboard import TBLogger

    if args.iters < 0:
        raise GpmpcError(f"--iters must be >= 0, got {args.iters}")
    cfg, settings = load_settings(args.config, parse_overrides(args.set))
    out = output_dir(args.out)
    ckpt = out / "checkpoint.pt"
    if args.resume and not ckpt.is_file():
        raise GpmpcError(f"--resume: no checkpoint at {str(ckpt)!r}; run without --resume to start")
    if cfg.pair_margin == "joint" and settings.tune_split:
        raise GpmpcError("pair_margin=joint has no risk split (its margin depends on the pair's total eps "
                         "only); set --set tune.tune_split=false, or use pair_margin=sum to tune a split")
    if cfg.risk_mode == "mission" and settings.tune_split:
        raise GpmpcError("risk_mode=mission allots each agent's risk from its own budget, so there is no risk "
                         "split to tune; set --set tune.tune_split=false (rho still tunes), or risk_mode=pair_step")
    if not Method.parse(cfg.method).chance and settings.tune_split:
        log.warning("method %s has no chance margins: the risk split gets no gradient", cfg.method)
    if cfg.offset_drift > 0:
        log.warning("disturbance_drift: the gradient objective plans from recorded states without the agents' "
                    "offset estimates (they need a run's history); the closed-loop evaluation uses them")

    started = time.perf_counter()
    scenario = make_scenario(cfg)
    num_agents = scenario.num_agents
    system = team_system_from_config(cfg)
    gps = fit_agent_gps(cfg, system, num_agents) if Method.parse(cfg.method).needs_gp else None
    admm = Controller.for_run(cfg, system, gps).admm

    def build_objective(seeds) -> tuning.TuningObjective:
        instances = tuning.make_instances(cfg, seeds, settings, scenario)
        if settings.warm_start:
            instances = tuning.with_warm_starts(admm, instances, settings.warm_rho, settings.warm_tol,
                                                settings.warm_max_iter)
        return tuning.TuningObjective(admm, instances, tuning.ObjectiveWeights.from_settings(settings), settings.admm_iters,
                                      settings.mpc_steps, settings.warmup_iters, system)

    objective = build_objective(settings.seeds)
    params = tuning.TuningParameters(num_agents, cfg.rho, cfg.risk_split)
    tuner = tuning.Tuner(objective, params, settings)
    if args.resume:
        tuner.load_checkpoint(ckpt)
        log.info("resumed from %s at iteration %d", ckpt, tuner.iteration)

    with TBLogger(out / "tb") as tb, tqdm(total=args.iters, initial=min(tuner.iteration, args.iters),
                                          desc="tune", unit="it", leave=False) as bar:
        def on_record(record: tuning.TuneRecord) -> None:
            log_record(tb, record)
            tuner.save_checkpoint(ckpt)
            bar.update(1)
            bar.set_postfix(loss=f"{record.loss:.4g}", rho=f"{record.rho:.3g}")

        tuner.run(args.iters, on_record)
        with torch.no_grad():
            final = objective(params).floats()
        parts = {k: v for k, v in final.items() if k != "loss"}
        log_record(tb, tuning.TuneRecord(iteration=tuner.iteration, loss=final["loss"], parts=parts,
                                         rho=float(params.rho().detach()), split=params.split_per_edge(),
                                         grad_norm=float("nan")))
    if tuner.iteration == 0:
        tuner.save_checkpoint(ckpt)
    evaluation = _evaluate(settings, objective, params, cfg, build_objective)
    payload = tuning.tuned_payload(cfg, params, tuner, extra={
        "tune": settings.to_dict(),
        "final": {**final, "rho": float(params.rho().detach()), "risk_split_per_edge": params.split_per_edge()},
        "evaluation": evaluation,
        "objective_evaluations": objective.evaluations,
        "wall_time_s": time.perf_counter() - started,
        "note": ("config.risk_split is the mean of risk_split_per_edge (Config has one scalar split); "
                 "ADMM.solve_step accepts the per-edge split as a (K, K) tensor: "
                 "torch_gpmpc.tuning.load_risk_split(path, K)"),
    })
    if settings.closed_loop_seeds:
        payload["closed_loop"] = _closed_loop(cfg, payload["config"], settings)
    write_json(out / "tuned.json", payload)
    print(_summary(payload, out))
    return 0


def log_record(tb, record) -> None:
    """Write one tuning record to TensorBoard under ``tune/``."""
    from torch_gpmpc.tuning import PARTS

    step = record.iteration
    tb.scalar("tune/loss", record.loss, step)
    tb.scalar("tune/rho", record.rho, step)
    tb.scalar("tune/grad_norm", record.grad_norm, step)
    for key, value in record.split.items():
        tb.scalar(f"tune/risk_split/{key}", value, step)
    for name in PARTS:
        tb.scalar(f"tune/{name}", record.parts[name], step)


def _evaluate(settings, objective, params, cfg, build_objective) -> dict[str, Any]:
    """Held-out comparison (defaults vs tuned) and the optional rho grid search."""
    from torch_gpmpc.tuning import grid_search_rho

    result: dict[str, Any] = {}
    default_split = torch.tensor(float(cfg.risk_split))
    with torch.no_grad():
        tuned_train = float(objective(params).loss)
        default_train = float(objective(rho=torch.tensor(float(cfg.rho)), split=default_split).loss)
    result["train"] = {"seeds": list(settings.seeds), "default": default_train, "tuned": tuned_train}
    heldout = build_objective(settings.heldout_seeds) if settings.heldout_seeds else None
    if heldout is not None:
        with torch.no_grad():
            result["heldout"] = {
                "seeds": list(settings.heldout_seeds),
                "default": float(heldout(rho=torch.tensor(float(cfg.rho)), split=default_split).loss),
                "tuned": float(heldout(params).loss),
            }
    if settings.grid_points > 0:
        n = settings.grid_points
        lo, hi = math.log(settings.grid_min), math.log(settings.grid_max)
        rhos = [math.exp(lo + (hi - lo) * i / max(n - 1, 1)) for i in range(n)]
        grid = grid_search_rho(objective, rhos, default_split)
        if heldout is not None:
            with torch.no_grad():
                grid["heldout_best"] = float(heldout(rho=torch.tensor(grid["best_rho"]), split=default_split).loss)
        result["grid"] = grid
    return result


def _closed_loop(cfg, tuned_config: dict, settings) -> dict[str, Any]:
    """Default vs tuned settings in whole closed-loop runs (:mod:`torch_gpmpc.tuning.closed_loop`)."""
    from torch_gpmpc.config import load_config
    from torch_gpmpc.sim.closed_loop import simulate
    from torch_gpmpc.sim.metrics import compute_metrics
    from torch_gpmpc.tuning.closed_loop import closed_loop_comparison

    noise = (cfg.noise_std, 0.0) if cfg.noise_std > 0 else (0.0,)
    bar = tqdm(total=2 * len(settings.closed_loop_seeds) * len(noise), desc="closed loop", unit="run", leave=False)

    def run(run_cfg) -> dict:
        metrics = compute_metrics(simulate(run_cfg))
        bar.update(1)
        return metrics

    started = time.perf_counter()
    with bar:
        result = closed_loop_comparison(cfg, load_config(None, tuned_config), settings.closed_loop_seeds, noise, run)
    result["wall_time_s"] = time.perf_counter() - started
    return result


def _summary(payload: dict, out: Path) -> str:
    cfg, ev = payload["config"], payload["evaluation"]
    split = ", ".join(f"{k}: {v:.3f}" for k, v in payload["risk_split_per_edge"].items())
    lines = [f"tune: rho = {cfg['rho']:.4g}, risk split per edge {{{split}}} "
             f"after {len(payload['history'])} iterations ({payload['objective_evaluations']} objective "
             f"evaluations, {payload['wall_time_s']:.0f} s)",
             f"  training objective: default {ev['train']['default']:.4g} -> tuned {ev['train']['tuned']:.4g}"]
    if "heldout" in ev:
        lines.append(f"  held-out objective (seeds {ev['heldout']['seeds']}): default {ev['heldout']['default']:.4g}"
                     f" -> tuned {ev['heldout']['tuned']:.4g}")
    if "grid" in ev:
        g = ev["grid"]
        extra = f", held-out {g['heldout_best']:.4g}" if "heldout_best" in g else ""
        lines.append(f"  grid search ({g['evaluations']} rho values): best rho {g['best_rho']:.4g}, "
                     f"objective {g['best_loss']:.4g}{extra}")
    if "closed_loop" in payload:
        cl = payload["closed_loop"]
        for name in ("default", "tuned"):
            c = cl[name]
            lines.append(f"  closed loop, {name:7s} ({c['runs']} runs, seeds {cl['seeds']}, noise {cl['noise_std']}): "
                         f"arrival {c['arrival_step_max_mean']:.1f}, violations {c['violations_total']}, "
                         f"{c['admm_iterations_mean']:.1f} ADMM it/step")
        if not cl["not_worse"]:
            lines.append("  WARNING: the tuned settings are worse than the defaults in closed loop "
                         "(later arrival by > 5 % or more violations); keep the defaults")
    lines.append(f"wrote {out / 'tuned.json'}")
    return "\n".join(lines)
