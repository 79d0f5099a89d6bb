"""``gpmpc fit-gp``: fit one residual GP per residual dimension to logged transitions.

Thin over :mod:`torch_gpmpc.gp`: loads and validates the transitions, optionally holds
out a fraction (contiguous time blocks by default, or random rows) for RMSE, R^2 and
95 % coverage, fits (exact GP, or the sparse SGPR model above 1000 rows; the summary says
which) with a tqdm progress bar and TensorBoard logging (``gp/loss``,
``gp/lengthscale/d{d}_in{i}``, ``gp/noise/d{d}``, ``gp/outputscale/d{d}`` per optimizer
step, raw units; ``gp/holdout_rmse|r2|coverage95/d{d}``), prints a summary and writes the
model, the optional report JSON and the optional figure atomically.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from tqdm import tqdm

from torch_gpmpc.data.transitions import Transitions
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.config.model_spec import check_model_name, resolve_model
from torch_gpmpc.fileio import write_json
from torch_gpmpc.gp import check_training_size, fit_residual_gp, gp_input_label, holdout_metrics, residual_label
from torch_gpmpc.gp.fit import resolve_method
from torch_gpmpc.gp.sparse import EXACT_MAX_POINTS, HYPERPARAMETER_SUBSET
from torch_gpmpc.dynamics.systems import NominalModel, VortexWind
from torch_gpmpc.report.tensorboard import TBLogger


def log_hyperparameters(tb: TBLogger, step: int, loss: float, hp: dict) -> None:
    """Write one optimizer step's loss and raw-unit hyperparameters to TensorBoard."""
    tb.scalar("gp/loss", loss, step)
    for d, row in enumerate(hp["lengthscale"]):
        for i, value in enumerate(row):
            tb.scalar(f"gp/lengthscale/d{d}_in{i}", value, step)
    for d, value in enumerate(hp["noise"]):
        tb.scalar(f"gp/noise/d{d}", value, step)
    for d, value in enumerate(hp["outputscale"]):
        tb.scalar(f"gp/outputscale/d{d}", value, step)


def _validate_args(args) -> None:
    """Argument checks that need no data (raises GpmpcError before any work)."""
    if args.out is not None and Path(args.out).suffix.lower() != ".pt":
        raise GpmpcError(f"--out {args.out!r}: the model file must end in .pt")
    if not 0.0 <= args.holdout < 1.0:
        raise GpmpcError(f"--holdout must be in [0, 1) (a fraction such as 0.2), got {args.holdout}")
    if args.iters < 0:
        raise GpmpcError(f"--iters must be >= 0, got {args.iters}")
    if args.report is not None and Path(args.report).suffix.lower() != ".json":
        raise GpmpcError(f"--report {args.report!r}: the report file must end in .json")
    if (args.report is not None or args.holdout_figure is not None) and args.holdout <= 0:
        raise GpmpcError("--report and --holdout-figure need held-out rows: add --holdout 0.2")
    if args.holdout_figure is not None and Path(args.holdout_figure).suffix.lower() != ".png":
        raise GpmpcError(f"--holdout-figure {args.holdout_figure!r}: the figure file must end in .png")
    if args.figure is not None:
        if Path(args.figure).suffix.lower() != ".png":
            raise GpmpcError(f"--figure {args.figure!r}: the figure file must end in .png")
        if args.gp_inputs not in (None, "state") or args.model is not None:
            raise GpmpcError("--figure needs the paper's model with --inputs state (the figure is over the 2D "
                             "state plane); drop --figure")
    if args.model is not None:
        check_model_name(args.model)
        if args.gp_inputs is not None:
            raise GpmpcError("--gp-inputs: with --model the GP inputs are the model's gp_inputs; drop --gp-inputs")


def _nominal(args, data: Transitions) -> NominalModel:
    """The model whose residual the GPs learn: ``--model``, else the paper's in the data's dimension."""
    if args.model is None:
        if data.input_dim != data.state_dim:
            raise GpmpcError(f"{data.source}: input dimension Du={data.input_dim} differs from the state "
                             f"dimension D={data.state_dim}; the paper's model (A = I, B = 0.1 I) needs Du = D: "
                             "give the robot's model with --model FILE")
        return NominalModel(data.state_dim)
    dim = args.dim if args.dim is not None else (data.state_dim // 2 if args.model == "double-integrator"
                                                 else data.state_dim)
    nominal = NominalModel(resolve_model(args.model, dim, args.dt, 2.0))
    data.check_dim(nominal.dim, nominal.input_dim)
    return nominal


def _load(args) -> Transitions:
    data = Transitions.load(args.transitions)
    if args.agent is not None:
        data = data.for_agent(args.agent)
    if args.figure is not None and data.state_dim != 2:
        raise GpmpcError(f"--figure needs 2D data, but {data.source} has D={data.state_dim}; drop --figure")
    return data


def _summary(gp, train: Transitions, holdout: dict | None, final_loss: float, seconds: float) -> str:
    hp = gp.hyperparameters()
    fmt = lambda xs: "[" + ", ".join(f"{x:.4g}" for x in xs) + "]"  # noqa: E731
    if gp.method == "exact":
        how = (f"exact GP; NLL (raw units, sum over dims) = {gp.negative_log_marginal_likelihood():.4f}; "
               f"final loss (standardized, per datum) = {final_loss:.6f}")
    else:
        how = (f"sparse GP (SGPR, above {EXACT_MAX_POINTS} rows): {hp['num_inducing']} k-means inducing points, "
               f"posterior on all {gp.num_data} rows, hyperparameters by exact marginal likelihood on "
               f"{min(HYPERPARAMETER_SUBSET, gp.num_data)} of them (final loss {final_loss:.6f})")
    lines = [
        f"fit-gp: N={train.num_samples} ({train.source}), D={gp.output_dim}, inputs={gp.gp_inputs} "
        f"(Din={gp.input_dim}), fitted in {seconds:.1f} s",
        f"  method: {how}",
    ]
    for d in range(gp.output_dim):
        lines.append(f"  d{d}: lengthscale {fmt(hp['lengthscale'][d])}, outputscale {hp['outputscale'][d]:.4g}, "
                     f"noise var {hp['noise'][d]:.4g} (std {hp['noise'][d] ** 0.5:.4g})")
    if holdout is not None:
        lines.append(f"  held-out ({holdout['num']} rows, {holdout['split']} split): RMSE per dim {fmt(holdout['rmse'])}, "
                     f"R^2 {fmt(holdout['r2'])}, 95% coverage {fmt(holdout['coverage95'])} "
                     f"(all {holdout['coverage95_all']:.3f}, predictive incl. noise)")
    return "\n".join(lines)


#: Below this hold-out R^2 a residual row's GP explains little of it (a fifth of its variance).
LOW_R2 = 0.2
#: Below this share of held-out residuals inside the 95 % intervals the GP's variances understate its
#: errors, and the chance margins built on them are too small.
LOW_COVERAGE = 0.8


def fit_warnings(holdout: dict | None, residual: list[int]) -> list[str]:
    """One line per residual row whose held-out R^2 is below :data:`LOW_R2` or whose 95 % coverage is
    below :data:`LOW_COVERAGE` (``residual``: the model's residual state indices); without held-out
    rows, one line saying how to get them."""
    if holdout is None:
        return ["fit-gp: note: no held-out rows, so nothing says how much the GP explains; "
                "add --holdout 0.2 for its R^2 and coverage"]
    lines = []
    for d, (r2, cover) in enumerate(zip(holdout["r2"], holdout["coverage95"])):
        row = f"residual row d{d} (state x{residual[d]})"
        if not r2 >= LOW_R2:
            lines.append(f"fit-gp: warning: the GP explains little of {row}: hold-out R^2 {r2:.3g} "
                         f"(below {LOW_R2}); collect more varied transitions (gpmpc collect --samples), or give "
                         "it inputs that see what drives the residual (--inputs, the model's gp_inputs)")
        if not cover >= LOW_COVERAGE:
            lines.append(f"fit-gp: warning: the GP's 95 % intervals hold {cover:.0%} of {row}'s held-out "
                         f"residuals (below {LOW_COVERAGE:.0%}): its variances understate its errors, and "
                         "chance margins built on them are too small")
    return lines


def report(n_train: int, residual: list[int], holdout: dict, fit_seconds: float) -> dict:
    """The ``--report`` JSON: ``{n_train, n_holdout, residual, holdout: {rmse, r2, coverage95},
    fit_seconds}``; the lists follow ``residual`` (the model's residual state indices)."""
    return {"n_train": n_train, "n_holdout": holdout["num"], "residual": list(residual),
            "holdout": {k: holdout[k] for k in ("rmse", "r2", "coverage95")}, "fit_seconds": fit_seconds}


def main(args) -> int:
    """Run ``gpmpc fit-gp`` (see module docstring)."""
    _validate_args(args)
    data = _load(args)
    nominal = _nominal(args, data)
    train, test = data.split(args.holdout, seed=args.seed, mode=args.holdout_split) if args.holdout > 0 \
        else (data, None)
    gp_inputs = args.gp_inputs if args.model is None else None
    label = (gp_inputs or "state") if args.model is None else gp_input_label(nominal)
    X, Y = train.residuals(nominal, gp_inputs=gp_inputs)
    check_training_size(X.shape[0], resolve_method(args.gp_method, X.shape[0]))  # before any output
    last = {"loss": float("nan")}
    with TBLogger(args.logdir) as tb, tqdm(total=args.iters + 1, desc="fit-gp", unit="step",
                                           leave=False) as bar:
        def callback(step: int, loss: float, hp: dict) -> None:
            log_hyperparameters(tb, step, loss, hp)
            last["loss"] = loss
            bar.set_postfix(loss=f"{loss:.4f}")
            bar.update(1)

        started = time.perf_counter()
        gp = fit_residual_gp(X, Y, optimizer=args.optimizer, iters=args.iters, seed=args.seed,
                             callback=callback, gp_inputs=label, method=args.gp_method)
        seconds = time.perf_counter() - started
        metrics = None
        if test is not None:
            X_test, Y_test = test.residuals(nominal, gp_inputs=gp_inputs)
            metrics = {**holdout_metrics(gp, X_test, Y_test), "split": args.holdout_split}
            for name in ("rmse", "r2", "coverage95"):
                for d, value in enumerate(metrics[name]):
                    tb.scalar(f"gp/holdout_{name}/d{d}", value, args.iters)
    gp.residual_rows = residual_label(nominal.residual)  # checked when a run loads the file
    if args.out is not None:
        gp.save(args.out)
    print(_summary(gp, train, metrics, last["loss"], seconds))
    for line in fit_warnings(metrics, list(nominal.residual)):
        print(line, file=sys.stderr)
    print(f"wrote {args.out}" if args.out is not None else "no --out: the model was not saved")
    if args.report is not None:
        write_json(args.report, report(train.num_samples, list(nominal.residual), metrics, seconds))
        print(f"wrote {args.report}")
    if args.holdout_figure is not None:
        from torch_gpmpc.report.gp_figures import plot_holdout_residuals

        plot_holdout_residuals(gp, X_test, Y_test, list(nominal.residual), args.holdout_figure)
        print(f"wrote {args.holdout_figure}")
    if args.figure is not None:
        from torch_gpmpc.report.gp_figures import plot_gp_field

        plot_gp_field(gp, VortexWind(), X, args.figure)
        print(f"wrote {args.figure} (true wind: vortex, scale 0.1)")
    return 0
