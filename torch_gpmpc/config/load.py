"""Loading settings: defaults, then a file, then ``--set`` overrides, parsed once for every command."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from torch_gpmpc.config.reader import read_table
from torch_gpmpc.config.schema import Config, from_mapping
from torch_gpmpc.config.tune_settings import TuneSettings

#: How a tune setting is written on the command line (``--set tune.lr=0.1``).
TUNE_PREFIX = "tune."
#: Config keys whose values may name files (model files), and the suffixes that mark a file name.
FILE_KEYS, FILE_SUFFIXES = ("model", "models"), (".toml", ".json")


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
        cfg_data = files_beside(path, cfg_data)
        if isinstance(tune_table, dict):
            tune_data.update(tune_table)
    for key, value in (overrides or {}).items():
        if key.startswith(TUNE_PREFIX):
            tune_data[key[len(TUNE_PREFIX):]] = value
        else:
            cfg_data[key] = value
    return from_mapping(cfg_data), TuneSettings.from_mapping(tune_data)


def files_beside(config_path: str | Path, data: dict[str, Any]) -> dict[str, Any]:
    """``data`` (a config file's keys) with each relative file name of :data:`FILE_KEYS` that does not
    exist from the working directory replaced by the path beside the config file, where it does.

    So ``model = "crazyflie.toml"`` in ``examples/rotorpy/swap.toml`` is found from any directory,
    while names written from the working directory (``examples/rotorpy/crazyflie.toml`` run from the
    repository root) keep their meaning, and their value, unchanged."""
    base = Path(config_path).parent

    def beside(value: Any) -> Any:
        if not isinstance(value, str) or Path(value).suffix.lower() not in FILE_SUFFIXES:
            return value
        name = Path(value)
        if name.is_absolute() or name.exists() or not (base / name).is_file():
            return value
        return str(base / name)

    out = dict(data)
    for key in FILE_KEYS:
        if isinstance(out.get(key), str):
            out[key] = beside(out[key])
        elif isinstance(out.get(key), list):
            out[key] = [beside(v) for v in out[key]]
    return out


def load_config(path: str | Path | None = None, overrides: Mapping[str, Any] | None = None) -> Config:
    """The run configuration alone (:func:`load_settings` without the tune settings)."""
    return load_settings(path, overrides)[0]
