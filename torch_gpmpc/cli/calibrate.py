"""``gpmpc calibrate``: Monte Carlo calibration of the chance constraints -> DIR/calibration.json, .png.

Runs the crossing for every formulation (``sound``: the defaults; ``paper``: eq. 24 with the
latent variance), every eps and ``--runs`` seeds, in parallel over the cores, with the runs
cached under ``DIR/cache`` (an interrupted call resumes).
"""

from __future__ import annotations

import os

from torch_gpmpc.cli.cached_runs import parse_list, run_uncached
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.fileio import write_json


def main(args) -> int:
    from torch_gpmpc.cli.run import config_from_args, output_dir
    from torch_gpmpc.report.figures import plot_calibration
    from torch_gpmpc.sim.calibration import active_outcomes, calibration_rows, calibration_tasks
    from torch_gpmpc.sim.rollout import Rollout

    cfg = config_from_args(args)
    eps_values = _eps_list(args.eps)
    if args.runs < 1:
        raise GpmpcError(f"--runs must be >= 1, got {args.runs}")
    out = output_dir(args.out)
    (out / "cache").mkdir(parents=True, exist_ok=True)
    tasks = calibration_tasks(cfg, eps_values, args.runs, str(out / "cache"), steps=args.steps)
    workers = args.workers or os.cpu_count() or 1
    run_uncached([task for *_, task in tasks], workers)
    outcomes: dict = {}
    for name, eps, task in tasks:
        outcomes.setdefault((name, eps), []).append(active_outcomes(Rollout.load(task.path)))
    rows = calibration_rows(outcomes)
    write_json(out / "calibration.json", {"rows": rows, "runs": args.runs, "steps": args.steps,
                                          "noise_std": cfg.noise_std, "method": cfg.method})
    plot_calibration(rows, out / "calibration.png")
    print(_table(rows))
    return 0


def _eps_list(text: str) -> list[float]:
    values = parse_list(text, float, "eps")
    if not values or not all(0 < v < 1 for v in values):
        raise GpmpcError(f"--eps: every value must be in (0, 1), got {text!r}")
    return values


def _table(rows: list[dict]) -> str:
    lines = ["| formulation | eps | active rows | violations | rate | 95 % interval |", "|---|---|---|---|---|---|"]
    for r in rows:
        rate = "-" if r["rate"] is None else f"{r['rate']:.3f}"
        lines.append(f"| {r['formulation']} | {r['eps']:g} | {r['active']} | {r['violations']} | {rate} | "
                     f"[{r['rate_low']:.3f}, {r['rate_high']:.3f}] |")
    return "\n".join(lines)
