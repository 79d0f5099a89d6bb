"""``gpmpc bench``: performance workloads with ratios against baselines measured in the same run.

Each section lives in its own module ``eval/bench_<name>.py`` exposing
``run(quick: bool) -> dict`` (JSON-serializable, with a ``"table"`` list of rows
``{"workload": str, ...numbers...}`` for printing). Results go to ``DIR/bench.json``.
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
    if not rows:
        return
    keys = list(rows[0])
    widths = {k: max(len(k), *(len(_fmt(r.get(k))) for r in rows)) for k in keys}
    print(f"\n[{name}]")
    print("  ".join(k.ljust(widths[k]) for k in keys))
    for r in rows:
        print("  ".join(_fmt(r.get(k)).ljust(widths[k]) for k in keys))


def _sub_table(section: dict, key: str) -> list[dict]:
    """The rows of a section's sub-table ``key`` (a dict with a ``table``), else none: sections may use
    the same key for a number (``gp``'s ``threads`` is its thread count, ``scale``'s a table)."""
    value = section.get(key)
    return value.get("table", []) if isinstance(value, dict) else []


def _fmt(v) -> str:
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
        _print_table(name, section.get("table", []))
        _print_table(f"{name}: agent models", section.get("models", []))
        _print_table(f"{name}: default ADMM stopping", section.get("default_stopping", []))
        _print_table(f"{name}: whole runs of a crowd", section.get("whole_runs", []))
        _print_table(f"{name}: one thread vs every core", _sub_table(section, "threads"))
        _print_table(f"{name}: random 3D transitions", _sub_table(section, "transitions"))
        _print_table(f"{name}: constraint families", _sub_table(section, "families"))
        _print_table(f"{name}: warm active-set solves vs cold", section.get("warm_start", []))
    write_json(out / "bench.json", result)
    print(f"\nwrote {out / 'bench.json'}")
    return 0
