"""The ``gpmpc`` argument parser: every command, flag and default (the entry point that runs
them is :mod:`~torch_gpmpc.cli.entry`)."""

from __future__ import annotations

import argparse

from torch_gpmpc import __version__
from torch_gpmpc.config.schema import METHODS

class _Defaults(argparse.ArgumentDefaultsHelpFormatter):
    """Help that shows each argument's default, where it has one (not for flags and optional values)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        default = action.default
        if default is None or default is False or default == [] or default is argparse.SUPPRESS \
                or "%(default)" in (action.help or ""):
            return action.help or ""
        return super()._get_help_string(action)


class _Parser(argparse.ArgumentParser):
    """argparse that reports a usage error as one line (no usage dump) and shows every default."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("formatter_class", _Defaults)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> None:  # noqa: D102 - argparse API
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _add_config_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", help="TOML/JSON/YAML file of flat config keys (or a tuned.json)")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="override one config key; repeatable (e.g. --set rho=5)")


def build_parser() -> argparse.ArgumentParser:
    """The full ``gpmpc`` argument parser."""
    parser = _Parser(prog="gpmpc", description="Cooperative GP-MPC for safe multi-agent navigation. "
                     "Start with `gpmpc run` (the paper scenario); `gpmpc COMMAND --help` tells more.")
    parser.add_argument("--version", action="version", version=f"gpmpc {__version__}")
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    parser.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")
    parser.add_argument("--threads", type=int, default=1,
                        help="the threads the compiled solver splits a batch of local problems over, "
                             "and torch's intra-op threads outside the closed loop (inside it, and for a run's "
                             "GP fits, torch runs on one, so a run's outcome does not depend on it; "
                             "1: parallel commands already use one process per core)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)

    p = sub.add_parser("collect", help="log transitions of the true system (paper data recipe)")
    p.add_argument("--out", required=True, help="output file, .npz or .csv")
    p.add_argument("--agents", type=int, default=3, help="number of agents K")
    p.add_argument("--samples", type=int, default=None,
                   help="samples per agent N (default: 100 on the model plant, 400 per RotorPy vehicle)")
    p.add_argument("--seed", type=int, default=0, help="seed of the sampled states, inputs and noise")
    p.add_argument("--dim", type=int, default=2, help="position dimension of the built-in models (2 or 3)")
    p.add_argument("--model", default="single-integrator",
                   help="agent model: single-integrator, double-integrator or a model file (.toml/.json)")
    p.add_argument("--dt", type=float, default=0.1, help="sampling time of the double integrator")
    p.add_argument("--noise-std", type=float, default=0.1, help="process noise std s")
    p.add_argument("--wind-scale", type=float, default=0.1, help="vortex wind amplitude")
    p.add_argument("--u-max", type=float, default=2.0,
                   help="input norm bound of the built-in models")
    p.add_argument("--box", type=float, default=4.0, help="positions uniform in [-box, box]^P")
    p.add_argument("--plant", choices=("model", "rotorpy"), default="model",
                   help="model: the model's true system; rotorpy: excitation flights of RotorPy "
                        "vehicles (a 3D double-integrator --model; vehicle and wind by --set plant_*=...)")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="--plant rotorpy: config keys plant_vehicle, plant_wind, plant_wind_speed, plant_rate_hz, "
                        "plant_sensor_noise (e.g. --set plant_wind=constant --set plant_wind_speed=[1,0,0])")

    p = sub.add_parser("fit-gp", help="fit one residual GP per state dimension")
    p.add_argument("--transitions", required=True, help="transitions file (.npz or .csv)")
    p.add_argument("--out", help="model file to write (.pt); without it the model is only evaluated")
    p.add_argument("--logdir", help="TensorBoard directory")
    p.add_argument("--holdout", type=float, default=0.0, help="fraction held out for RMSE/R^2/coverage")
    p.add_argument("--holdout-split", choices=("blocks", "random"), default="blocks",
                   help="hold out contiguous time blocks (logs are autocorrelated) or random rows")
    p.add_argument("--report", help="write the held-out metrics and fit time to this JSON file")
    p.add_argument("--gp-method", choices=("auto", "exact", "sgpr"), default="auto",
                   help="exact GP, sparse SGPR, or auto (exact up to 1000 rows)")
    p.add_argument("--holdout-figure", help="PNG of held-out predictions vs measured residuals over time")
    p.add_argument("--agent", type=int, help="fit only rows of this agent id")
    p.add_argument("--model", help="agent model (double-integrator or a model file): its residual rows are the GP "
                                   "outputs and its gp_inputs the GP inputs (default: the paper's model)")
    p.add_argument("--dim", type=int, default=None, help="position dimension of --model double-integrator")
    p.add_argument("--dt", type=float, default=0.1, help="sampling time of --model double-integrator")
    p.add_argument("--gp-inputs", "--inputs", dest="gp_inputs", choices=("state", "state_input"), default=None,
                   help="without --model: the state (the paper) or state and input")
    p.add_argument("--optimizer", choices=("lbfgs", "adam"), default="lbfgs",
                   help="marginal-likelihood optimizer (L-BFGS: the paper's)")
    p.add_argument("--iters", type=int, default=50, help="optimizer iterations")
    p.add_argument("--seed", type=int, default=0, help="seed of the fit (and of the hold-out split)")
    p.add_argument("--figure", help="also write a PNG of the learned mean vs. the wind field (2D)")

    p = sub.add_parser(
        "run", help="one closed-loop scenario",
        description="One closed-loop run (default: the paper scenario, 3 agents, the proposed gp-chance "
                    "method): DIR/metrics.json, DIR/rollout.npz, DIR/figures/ and TensorBoard logs in DIR/tb/. "
                    "Every config key works as --set NAME=VALUE (e.g. --set scenario=circle --set num_agents=8 "
                    "for another team size); `gpmpc keys` lists the keys with their defaults and ranges, as does "
                    "the docs' configuration reference.")
    _add_config_args(p)
    p.add_argument("--scenario", help="scenario file (JSON/TOML with starts, targets[, reference]); default: the "
                                      "config key scenario")
    p.add_argument("--method", help="nominal, nominal-chance, nonlinear, nonlinear-chance, gp, gp-chance; "
                                    "default: the config key method (gp-chance)")
    p.add_argument("--seed", type=int, help="run seed (data, noise, scenario); default: the config key seed (0)")
    p.add_argument("--gp-model", help="a model file from fit-gp (used by every agent)")
    p.add_argument("--plant", choices=("model", "rotorpy"),
                   help="what the loop steps (the config key plant): model (default) or rotorpy vehicles")
    p.add_argument("--backend", choices=("inprocess", "distributed"), default="inprocess",
                   help="inprocess: all agents in this process; distributed: one process per agent (torch.distributed)")
    p.add_argument("--agents-per-process", type=int, default=1,
                   help="distributed backend: agents hosted by one process")
    p.add_argument("--timeout", type=float, default=30.0,
                   help="distributed backend: seconds to wait for a peer before treating it as lost")
    p.add_argument("--out", default="runs/run", help="output directory")
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures")

    p = sub.add_parser("tune", help="gradient tuning of rho and the risk split")
    _add_config_args(p)
    p.add_argument("--out", default="runs/tune", help="output directory (tuned.json, tb/, checkpoint.pt)")
    p.add_argument("--iters", type=int, default=20, help="tuning iterations (gradient steps)")
    p.add_argument("--resume", action="store_true", help="continue from DIR/checkpoint.pt")

    p = sub.add_parser("reproduce", help="the paper's six methods, figures 1-6 and a table")
    _add_config_args(p)
    p.add_argument("--runs", type=int, default=10, help="seeds per method (the paper averages 10 runs)")
    p.add_argument("--out", default="runs/reproduce", help="output directory (table.md, table.csv, figures/)")
    p.add_argument("--workers", type=int, help="parallel processes; default: the number of cores")
    p.add_argument("--methods", default=",".join(METHODS), help="comma-separated subset of the six methods")
    p.add_argument("--rho-values", default="1,5,20,50,100", help="rho values of the Fig. 4 study")
    p.add_argument("--rho-start", type=int, default=18,
                   help="first closed-loop step averaged in Fig. 4")
    p.add_argument("--rho-steps", type=int, default=10, help="closed-loop steps averaged per Fig. 4 run")
    p.add_argument("--rho-iterations", type=int, default=60, help="ADMM iterations per step in Fig. 4 runs")

    p = sub.add_parser("calibrate", help="Monte Carlo calibration of the chance constraints")
    _add_config_args(p)
    p.add_argument("--runs", type=int, default=20, help="seeds per formulation and eps")
    p.add_argument("--eps", default="0.01,0.05,0.1,0.2", help="comma-separated risks per pair")
    p.add_argument("--steps", type=int, default=45, help="closed-loop steps per run (the crossing)")
    p.add_argument("--mission", action="store_true",
                   help="whole runs under risk_mode=mission: the fraction of runs with any violation against "
                        "risk_budget (--runs and --budgets; --eps and --steps do not apply)")
    p.add_argument("--budgets", help="with --mission: comma-separated mission budgets (default: risk_budget)")
    p.add_argument("--baseline-runs", type=int, default=0,
                   help="with --mission: also this many runs under risk_mode=pair_step at eps")
    p.add_argument("--workers", type=int, help="parallel processes; default: the number of cores")
    p.add_argument("--out", default="runs/calibrate", help="output directory (calibration.json, figures)")

    p = sub.add_parser("benchmark", help="success rate and failure causes over scenarios, team sizes and seeds")
    _add_config_args(p)
    p.add_argument("--scenario", nargs="+", default=["random"],
                   help="built-in scenario names (random, circle, forest, ...) and/or scenario files")
    p.add_argument("--agents", default="4,8,16", help="comma-separated team sizes of built-in scenarios")
    p.add_argument("--seeds", type=int, default=10, help="seeds per scenario and team size")
    p.add_argument("--quick", action="store_true", help="smoke form: the first team size, <= 2 seeds, <= 60 steps")
    p.add_argument("--workers", type=int, help="parallel processes; default: the number of cores")
    p.add_argument("--out", default="runs/benchmark", help="output directory (benchmark.csv, table.md, cache/)")

    p = sub.add_parser("bench", help="performance workloads, ratios against baselines")
    p.add_argument("--out", default="runs/bench", help="output directory (bench.json, figures/)")
    p.add_argument("--sections", default="gp,local,scale,run", help="comma-separated: gp, local, scale, run")
    p.add_argument("--quick", action="store_true", help="fewer repetitions (for CI smoke runs)")

    p = sub.add_parser("keys", help="the config keys: defaults, allowed values, what each means",
                       description="Every config key (for --set NAME=VALUE and config files) with its default, "
                                   "allowed values, when it applies and what it means.")
    p.add_argument("word", nargs="?", help="show only keys whose name or meaning contains WORD (e.g. admm); "
                                           "default: every key")
    return parser
