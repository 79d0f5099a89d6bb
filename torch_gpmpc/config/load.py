"""Loading settings: defaults, then a file, then ``--set`` overrides, parsed once for every command."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from torch_gpmpc.config.reader import read_table
from torch_gpmpc.config.schema import Config, from_mapping
from torch_gpmpc.config.tune_settings import TuneSettings

#: How a tune setting is written on the command line (``--set tune.lr=0.1``).
TUNE_PREFIX = "tune."


def read_mapping(path: str | Path) -> dict[str, Any]:
    """The table of a ``.toml``, ``.json``, ``.yaml`` or ``.yml`` config file.

    Raises:
        GpmpcError: missing file, unknown suffix, or unparsable content.
    """
    return read_table(path, "config file")


def load_settings(path: str | Path | None = None,
                  overrides: Mapping[str, Any] | None = None) -> tuple[Config, TuneSettings]:
    """The run configuration and the tuning settings: defaults < file < ``overrides``.

    The file holds flat config keys and optionally a ``[tune]`` table; a ``tuned.json``
    written by ``gpmpc tune`` is accepted too (its ``config`` and ``tune`` tables are used).
    Overrides named ``tune.NAME`` are tune settings, all others config keys.

    Raises:
        GpmpcError: unknown keys (nearest valid key named), bad values, unreadable file.
    """
    cfg_data: dict[str, Any] = {}
    tune_data: dict[str, Any] = {}
    if path is not None:
        data = read_mapping(path)
        tune_table = data.get("tune")
        cfg_data.update(data["config"] if isinstance(data.get("config"), dict)
                        else {k: v for k, v in data.items() if k != "tune"})
        if isinstance(tune_table, dict):
            tune_data.update(tune_table)
    for key, value in (overrides or {}).items():
        if key.startswith(TUNE_PREFIX):
            tune_data[key[len(TUNE_PREFIX):]] = value
        else:
            cfg_data[key] = value
    return from_mapping(cfg_data), TuneSettings.from_mapping(tune_data)


def load_config(path: str | Path | None = None, overrides: Mapping[str, Any] | None = None) -> Config:
    """The run configuration alone (:func:`load_settings` without the tune settings)."""
    return load_settings(path, overrides)[0]
