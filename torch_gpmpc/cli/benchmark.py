"""``gpmpc benchmark``: success rate and failure causes over scenarios, team sizes and seeds ->
DIR/benchmark.csv (one row per run), DIR/table.md and DIR/benchmark.png.

Runs go to worker processes and are cached under ``DIR/cache`` (an interrupted call resumes).
Scenarios are built-in names (``random``, ``circle``, ``forest``, ...) or scenario files (a file
fixes its team size). ``--quick`` is the smoke form: the first team size, at most 2 seeds and
60 steps.
"""

from __future__ import annotations

import csv
import io
import os
import warnings

from torch_gpmpc.cli.cached_runs import parse_list, run_uncached
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.fileio import write_text

#: What ``--quick`` keeps: team sizes, seeds and the step cap.
QUICK_AGENTS, QUICK_SEEDS, QUICK_STEPS = 1, 2, 60


def main(args) -> int:
    from torch_gpmpc.cli.run import config_from_args, output_dir
    from torch_gpmpc.report.figures import plot_benchmark
    from torch_gpmpc.sim.benchmark import CSV_COLUMNS, benchmark_tasks, markdown_table, run_outcome, summary_rows
    from torch_gpmpc.sim.metrics import compute_metrics
    from torch_gpmpc.sim.rollout import Rollout

    with warnings.catch_warnings():  # keys for one scenario only (min_separation, num_obstacles): no warning
        warnings.simplefilter("ignore", UserWarning)
        cfg = config_from_args(args)
    agents = parse_list(args.agents, int, "agents")
    if not agents or min(agents) < 1:
        raise GpmpcError(f"--agents: give team sizes >= 1, got {args.agents!r}")
    if args.seeds < 1:
        raise GpmpcError(f"--seeds must be >= 1, got {args.seeds}")
    seeds = args.seeds
    if args.quick:
        agents, seeds = agents[:QUICK_AGENTS], min(seeds, QUICK_SEEDS)
        cfg = cfg.replace(max_steps=min(cfg.max_steps, QUICK_STEPS))
    out = output_dir(args.out)
    tasks = benchmark_tasks(cfg, args.scenario, agents, seeds, str(out / "cache"))  # checks the scenarios
    (out / "cache").mkdir(parents=True, exist_ok=True)  # only then: a refused command leaves nothing
    run_uncached([task for *_, task in tasks], args.workers or os.cpu_count() or 1)
    dt = cfg.model_spec().dt  # a model file's own dt (cfg.dt shapes the built-in models only)
    rows = [run_outcome(compute_metrics(Rollout.load(task.path)), label, dt) for label, _, task in tasks]
    summary = summary_rows(rows)
    write_text(out / "benchmark.csv", _csv(rows, CSV_COLUMNS))
    table = markdown_table(summary)
    write_text(out / "table.md", table + "\n")
    plot_benchmark(summary, out / "benchmark.png")
    print(table)
    print(f"wrote {out / 'benchmark.csv'}, {out / 'table.md'} and {out / 'benchmark.png'}")
    return 0


def _csv(rows, columns) -> str:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(columns), lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: "" if row[k] is None else row[k] for k in columns})
    return buffer.getvalue()
