"""Research script: residual GPs on a real flight log, sparse (all rows) against exact (a subset).

For each held-out split (contiguous time blocks, random rows) it fits the default model
(``fit-gp``'s ``auto``: SGPR on all training rows) and an exact GP on a seeded subset of
``--exact-rows`` training rows (what an exact GP can handle), and reports held-out RMSE,
R^2, 95 % coverage (predictive, noise included) and the fit time. Run from the repository
root::

    python eval/gp_real_log.py --transitions examples/crazyflie/nanobench_transitions.csv \\
        --model examples/crazyflie/model.toml --out runs/gp_real_log
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from torch_gpmpc.config.model_spec import resolve_model
from torch_gpmpc.data.transitions import Transitions
from torch_gpmpc.dynamics.systems import NominalModel
from torch_gpmpc.fileio import write_json, write_text
from torch_gpmpc.gp import fit_residual_gp, gp_input_label, holdout_metrics


def fit_and_score(X, Y, X_test, Y_test, label: str, method: str) -> dict:
    """Fit one model; its held-out metrics and fit time."""
    started = time.perf_counter()
    gp = fit_residual_gp(X, Y, gp_inputs=label, method=method)
    seconds = time.perf_counter() - started
    return {**holdout_metrics(gp, X_test, Y_test), "fit_seconds": seconds, "n_train": int(X.shape[0]),
            "method": gp.method}


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--transitions", required=True)
    parser.add_argument("--model", required=True)
    parser.add_argument("--holdout", type=float, default=0.2)
    parser.add_argument("--exact-rows", type=int, default=1000)
    parser.add_argument("--out", default="runs/gp_real_log")
    args = parser.parse_args(argv)
    data = Transitions.load(args.transitions)
    nominal = NominalModel(resolve_model(args.model, 3, 0.1, 2.0))
    label = gp_input_label(nominal)
    results = {}
    for split in ("blocks", "random"):
        train, test = data.split(args.holdout, seed=0, mode=split)
        X, Y = train.residuals(nominal)
        X_test, Y_test = test.residuals(nominal)
        subset = torch.randperm(X.shape[0], generator=torch.Generator().manual_seed(0))[:args.exact_rows]
        results[split] = {"sgpr (all rows)": fit_and_score(X, Y, X_test, Y_test, label, "auto"),
                          f"exact ({args.exact_rows}-row subset)": fit_and_score(X[subset], Y[subset], X_test,
                                                                                  Y_test, label, "exact")}
        print(split, {k: (v["r2"], v["coverage95"], round(v["fit_seconds"], 1)) for k, v in results[split].items()},
              flush=True)
    fmt = lambda xs: ", ".join(f"{x:.3f}" for x in xs)  # noqa: E731
    lines = ["| split | model | training rows | R^2 per axis (x3, x4, x5) | 95 % coverage per axis | RMSE per axis | "
             "fit s |", "|---|---|---|---|---|---|---|"]
    for split, rows in results.items():
        for name, r in rows.items():
            lines.append(f"| {split} | {name} | {r['n_train']} | {fmt(r['r2'])} | {fmt(r['coverage95'])} | "
                         f"{', '.join(f'{x:.2e}' for x in r['rmse'])} | {r['fit_seconds']:.1f} |")
    write_json(Path(args.out) / "gp_real_log.json", results)
    write_text(Path(args.out) / "gp_real_log.md", "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
