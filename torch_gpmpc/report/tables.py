"""The results table of ``gpmpc reproduce`` (Markdown and CSV): one row per method, mean +- std over runs."""

from __future__ import annotations

import math


TABLE_COLUMNS = [
    ("method", "method"),
    ("runs", "runs"),
    ("reached_fraction", "reached"),
    ("time_to_target", "all within tol at once"),
    ("arrival_step_max", "every agent arrived (last)"),
    ("min_distance_mean", "min dist (mean)"),
    ("min_distance_worst", "min dist (worst)"),
    ("violations_total", "violations"),
    ("runs_with_violations", "runs w/ violations"),
    ("unsafe_plan_steps_total", "unsafe plans"),
    ("path_length_mean", "path length"),
    ("admm_iterations_mean", "ADMM it (mean)"),
    ("admm_iterations_max", "ADMM it (max)"),
    ("wall_time_s_mean", "wall s"),
]


def _cell(row: dict, key: str) -> str:
    if key in ("time_to_target", "arrival_step_max"):
        mean, std = row[f"{key}_mean"], row[f"{key}_std"]
        return "never" if mean is None else f"{mean:.1f} ± {std:.1f}"
    value = row[key]
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.3f}" if abs(value) < 100 and not math.isclose(value, round(value)) else f"{value:.1f}"
    return str(value)


def table_markdown(rows: dict[str, dict]) -> str:
    """Markdown table, one row per method."""
    header = "| " + " | ".join(title for _, title in TABLE_COLUMNS) + " |"
    rule = "|" + "---|" * len(TABLE_COLUMNS)
    lines = [header, rule]
    for method, row in rows.items():
        row = {"method": method, **row}
        lines.append("| " + " | ".join(_cell(row, key) for key, _ in TABLE_COLUMNS) + " |")
    return "\n".join(lines) + "\n"


def table_csv(rows: dict[str, dict]) -> str:
    """CSV with every summary field (machine-readable twin of the markdown table)."""
    keys = ["method"] + list(next(iter(rows.values())).keys()) if rows else ["method"]
    lines = [",".join(keys)]
    for method, row in rows.items():
        values = [method] + ["" if row[k] is None else str(row[k]) for k in keys[1:]]
        lines.append(",".join(values))
    return "\n".join(lines) + "\n"
