"""``gpmpc bench``: performance workloads with ratios against baselines measured in the same run.

Each section lives in its own module ``torch_gpmpc/bench/<name>.py`` exposing
``run(quick: bool, out: Path) -> dict`` (JSON-serializable, with a ``"table"`` list of rows
``{"workload": str, ...numbers...}`` and optional sub-tables, :func:`section_tables`). Results go to
``DIR/bench.json``; the docs' benchmark page renders the same tables from a committed copy.
"""

from __future__ import annotations

import importlib
import platform
import time

import torch

from torch_gpmpc.cli.run import output_dir
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.fileio import write_json

SECTIONS = ("gp", "local", "scale", "run")
#: Former section names, still accepted (``fast`` was merged into ``local``).
ALIASES = {"fast": "local"}


def _print_table(name: str, rows: list[dict]) -> None:
    keys = list(rows[0])
    widths = {k: max(len(k), *(len(format_value(r.get(k))) for r in rows)) for k in keys}
    print(f"\n[{name}]")
    print("  ".join(k.ljust(widths[k]) for k in keys))
    for r in rows:
        print("  ".join(format_value(r.get(k)).ljust(widths[k]) for k in keys))


#: A section's sub-tables beyond its ``table``: (key, title). ``threads``, ``transitions`` and
#: ``families`` are dicts holding a ``table`` (sections may use the same key for a number: ``gp``'s
#: ``threads`` is its thread count, ``scale``'s a table); the others are lists of rows.
SUB_TABLES = (("models", "agent models"), ("default_stopping", "default ADMM stopping"),
              ("whole_runs", "whole runs of a crowd"), ("threads", "one thread vs every core"),
              ("transitions", "random 3D transitions"), ("families", "constraint families"),
              ("warm_start", "warm active-set solves vs cold"))


def section_tables(name: str, section: dict) -> list[tuple[str, list[dict]]]:
    """A ``bench.json`` section's non-empty tables as ``(title, rows)``: its ``table`` titled ``name``,
    then its sub-tables (:data:`SUB_TABLES`) titled ``name: title``."""
    tables = [(name, section.get("table", []))]
    for key, title in SUB_TABLES:
        value = section.get(key)
        rows = value.get("table", []) if isinstance(value, dict) else value if isinstance(value, list) else []
        tables.append((f"{name}: {title}", rows))
    return [(title, rows) for title, rows in tables if rows]


def format_value(v) -> str:
    """A table cell: floats to 4 significant digits."""
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def main(args) -> int:
    names = [ALIASES.get(s.strip(), s.strip()) for s in args.sections.split(",") if s.strip()]
    names = list(dict.fromkeys(names))  # drop repeats, keep order
    for name in names:
        if name not in SECTIONS:
            raise GpmpcError(f"--sections: unknown section {name!r}; choose from {', '.join(SECTIONS)}")
    out = output_dir(args.out)
    result = {
        "machine": {"platform": platform.platform(), "torch": torch.__version__,
                    "threads": torch.get_num_threads()},
        "quick": bool(args.quick),
        "sections": {},
    }
    for name in names:
        module = importlib.import_module(f"torch_gpmpc.bench.{name}")
        t0 = time.perf_counter()
        section = module.run(quick=args.quick, out=out)
        section["section_wall_s"] = time.perf_counter() - t0
        result["sections"][name] = section
        for title, rows in section_tables(name, section):
            _print_table(title, rows)
    write_json(out / "bench.json", result)
    print(f"\nwrote {out / 'bench.json'}")
    return 0
