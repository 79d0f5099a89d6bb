"""Pages generated when the docs build (mkdocs-gen-files): the configuration reference from the schema,
the command-line reference from the argument parser, the benchmark pages from the JSON and CSV files the
commands wrote (docs/benchmarks/data), and the changelog from CHANGELOG.md."""

from __future__ import annotations

from pathlib import Path

import mkdocs_gen_files

from torch_gpmpc.cli.bench import format_value, section_tables
from torch_gpmpc.cli.parser import build_parser
from torch_gpmpc.config.reference import config_keys, strip_roles
from torch_gpmpc.config.schema import RULES

ROOT = Path(__file__).resolve().parents[1]


def cell(text: str) -> str:
    return strip_roles(text, "`").replace("``", "`").replace("|", "\\|").replace("\n", " ")


def config_page() -> str:
    keys = config_keys()
    lines = ["# Configuration keys", "",
             "Every key of a run, generated from the schema (`torch_gpmpc.config`; `gpmpc keys` prints the same",
             "in a terminal). Keys are flat and the same in a TOML/JSON/YAML file (`gpmpc run --config FILE`) and",
             "on the command line (`--set NAME=VALUE`); an unknown key fails with the nearest valid one. A key that",
             "matters only under another key's value says so in the last column; set while it does not apply, it",
             "warns, naming the key that decides.", ""]
    for title, group in (("Controller keys (also `ControllerSettings`)", [k for k in keys if k.controller]),
                         ("Run keys (`Config` only)", [k for k in keys if not k.controller])):
        lines += [f"## {title}", "", "| key | type | default | allowed | applies | meaning |", "|---|---|---|---|---|---|"]
        for k in group:
            default = repr(k.default)
            choices = ", ".join(f"`{c}`" for c in RULES.choices[k.name]) if k.name in RULES.choices else k.allowed
            lines.append(f"| `{k.name}` | `{cell(k.type)}` | `{default}` | {cell(choices)} | {cell(k.applies)} | "
                         f"{cell(k.meaning)} |")
        lines.append("")
    return "\n".join(lines)


def cli_page() -> str:
    import argparse

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    lines = ["# Command line", "", "`gpmpc --help` and every command's `--help`, as they print.", "",
             "```text", parser.format_help().rstrip(), "```", ""]
    for name, p in sub.choices.items():
        lines += [f"## `gpmpc {name}`", "", "```text", p.format_help().rstrip(), "```", ""]
    return "\n".join(lines)


TRANSITIONS_COMMAND = """gpmpc benchmark --scenario random --agents 4,8,20 --seeds 3 --set model=examples/transition/di3d.toml \\
  --set 'workspace={"min": [-0.97, -0.97, -0.97], "max": [0.97, 0.97, 0.97]}' --set r_safe=0.35 \\
  --set min_separation=0.35 --set horizon=15 --set reference=target --set method=nominal \\
  --set noise_std=0 --set wind_scale=0 --set pair_buffer=0.001 --workers 1 --out DIR"""


def transitions_page() -> str:
    """Today's random 3D transitions, from the benchmark.csv files the command wrote (docs/benchmarks/data)."""
    import csv
    from statistics import mean

    def rows(name: str) -> list[dict]:
        return list(csv.DictReader((ROOT / "docs" / "benchmarks" / "data" / name).read_text().splitlines()))

    lines = ["# Random 3D transitions", "",
             "The random-transition setting of the DMPC line of work (3D double integrators at dt 0.2, a per-axis",
             "acceleration bound 1, starts and goals in a cube of side 1.59 m, r_safe 0.35, horizon 15, reference =",
             "target, noiseless), with the default cost (its terminal weight the LQR cost-to-go) and with the paper's",
             "cost (`--set terminal_cost=stage`). The tables are generated from the `benchmark.csv` files the command",
             "wrote (`docs/benchmarks/data/`), measured on this project's 2-core machine, one worker:", "",
             "```bash", TRANSITIONS_COMMAND, "```", ""]
    for title, name in (("default cost (`terminal_cost = lqr`)", "transitions_default.csv"),
                        ("the paper's cost (`terminal_cost = stage`)", "transitions_paper_cost.csv")):
        data = rows(name)
        lines += [f"## {title}", "", "| agents | runs | success | transition time, mean over all runs (s) | closest pair (worst) | "
                  "compute per agent-step (ms) |", "|---|---|---|---|---|---|"]
        for agents in sorted({int(r["agents"]) for r in data}):
            group = [r for r in data if int(r["agents"]) == agents]
            ok = [r for r in group if r["success"] == "True"]
            times = [float(r["transition_time_s"]) for r in group if r["transition_time_s"]]
            lines.append(f"| {agents} | {len(group)} | {100 * len(ok) / len(group):.0f} % | {mean(times):.2f} | "
                         f"{min(float(r['min_pair_distance']) for r in group):.4f} | "
                         f"{mean(float(r['compute_ms_per_agent_step']) for r in group):.1f} |")
        lines.append("")
    lines += ["The default plane coupling keeps every pair at every iterate; [Benchmark](benchmark.md) compares the",
              "paper's copies, whose failures are pairs closer than r_safe by less than the consensus tolerance.", ""]
    return "\n".join(lines)


BENCH_COMMAND = "gpmpc bench --sections gp,local,run --out DIR"


def bench_page() -> str:
    """Today's ``gpmpc bench`` tables, from the bench.json the command wrote (docs/benchmarks/data)."""
    import json

    data = json.loads((ROOT / "docs" / "benchmarks" / "data" / "bench.json").read_text())
    machine = data["machine"]
    lines = ["# Today's `gpmpc bench`", "",
             "Every table `gpmpc bench` printed, generated from the `bench.json` it wrote",
             "(`docs/benchmarks/data/bench.json`), on this project's 2-core CPU machine, alone on it",
             f"(`{machine['platform']}`, torch {machine['torch']}, {machine['threads']} torch thread). Ratios are",
             "same-run; absolute times move by about 20 % between runs. Times are ms unless a column says `_s`;",
             "`speedup_*` and `ratio` are how many times faster than the named baseline. What each table",
             "measures, and why the solver is built as it is: [Performance](performance.md). The `scale` section (whole 100-agent",
             "runs, about half an hour) is on [Scale](scale.md).", "",
             "```bash", BENCH_COMMAND, "```", ""]
    for name, section in data["sections"].items():
        lines += [f"## `{name}` ({section.get('section_wall_s', 0):.0f} s)", ""]
        notes = section.get("notes") or section.get("note")
        if isinstance(notes, str):
            lines += [f"*{cell(notes)}*", ""]
        tables = section_tables(name, section)
        if isinstance(section.get("checks"), list):  # accuracy against the reference paths
            tables.append((f"{name}: accuracy checks", [_flat(r) for r in section["checks"]]))
        if isinstance(section.get("targets"), dict):
            tables.append((f"{name}: targets", [{"target": k, **v} for k, v in section["targets"].items()]))
        for title, rows in tables:
            keys = list(dict.fromkeys(k for r in rows for k in r))
            if title != name:
                lines += [f"**{title}**", ""]
            lines += ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
            lines += ["| " + " | ".join("–" if r.get(k) is None else cell(format_value(r[k])) for k in keys) + " |"
                      for r in rows]
            lines.append("")
    return "\n".join(lines)


def _flat(row: dict, prefix: str = "") -> dict:
    """A row with nested dicts as ``outer.inner`` columns."""
    out = {}
    for k, v in row.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


with mkdocs_gen_files.open("benchmarks/bench.md", "w") as f:
    f.write(bench_page())
with mkdocs_gen_files.open("benchmarks/transitions.md", "w") as f:
    f.write(transitions_page())
with mkdocs_gen_files.open("reference/config.md", "w") as f:
    f.write(config_page())
with mkdocs_gen_files.open("reference/cli.md", "w") as f:
    f.write(cli_page())
with mkdocs_gen_files.open("changelog.md", "w") as f:
    f.write((ROOT / "CHANGELOG.md").read_text())
