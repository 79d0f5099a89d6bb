"""The one file reader for settings-like files (config, tune settings, scenario files) and
the parser of ``--set NAME=VALUE`` overrides."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Any

from torch_gpmpc.errors import GpmpcError

#: File suffixes a settings table can be read from.
TABLE_SUFFIXES = (".toml", ".json", ".yaml", ".yml")


def read_table(path: str | Path, what: str, suffixes: tuple[str, ...] = TABLE_SUFFIXES,
               expect: str = "a table of NAME = VALUE pairs") -> dict[str, Any]:
    """Read a table (dict) from a TOML, JSON or YAML file.

    Args:
        path: the file.
        what: its kind in messages (``config file``, ``scenario file``).
        suffixes: the suffixes accepted for this kind of file.
        expect: what the file should hold, for the message when it holds no table.

    Raises:
        GpmpcError: missing file, unknown suffix, or unparsable content; one line naming the file.
    """
    path = Path(path)
    where = f"{what} {str(path)!r}"
    if not path.is_file():
        raise GpmpcError(f"{where} does not exist; check the path")
    suffix = path.suffix.lower()
    if suffix not in suffixes:
        names = [s for s in suffixes if s != ".yml"]
        listed = ", ".join(names[:-1]) + f" or {names[-1]}" if len(names) > 1 else names[0]
        raise GpmpcError(f"{where}: unknown suffix {suffix!r}; use {listed}")
    try:
        text = path.read_text()
        if suffix == ".toml":
            data = tomllib.loads(text)
        elif suffix == ".json":
            data = json.loads(text)
        else:
            data = _load_yaml(text, where)
    except (tomllib.TOMLDecodeError, json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise GpmpcError(f"{where} cannot be parsed: {exc}") from exc
    if not isinstance(data, dict):
        raise GpmpcError(f"{where}: expected {expect}")
    return data


def _load_yaml(text: str, where: str) -> Any:
    try:
        import yaml  # optional dependency
    except ImportError as exc:  # pragma: no cover - depends on environment
        raise GpmpcError(f"{where}: YAML needs PyYAML (pip install pyyaml), or use TOML/JSON") from exc
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise GpmpcError(f"{where} cannot be parsed: {exc}") from exc


def parse_value(text: str) -> Any:
    """Parse the VALUE of ``--set NAME=VALUE``: JSON literals (numbers, true/false, null) or a bare string."""
    lowered = text.strip().lower()
    if lowered in ("none", "null"):
        return None
    if lowered in ("true", "false"):
        return lowered == "true"
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def parse_overrides(items: list[str] | None) -> dict[str, Any]:
    """Turn ``["rho=5", "method=gp"]`` into ``{"rho": 5, "method": "gp"}``."""
    out: dict[str, Any] = {}
    for item in items or []:
        if "=" not in item:
            raise GpmpcError(f"--set {item!r}: expected NAME=VALUE, e.g. --set rho=20")
        key, text = item.split("=", 1)
        out[key.strip()] = parse_value(text)
    return out
