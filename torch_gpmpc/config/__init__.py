"""Settings: the run configuration and the tuning settings in one schema machinery
(:mod:`.fields`), read from files by one reader (:mod:`.reader`)."""

from torch_gpmpc.config.load import load_config, load_settings, read_mapping
from torch_gpmpc.config.reader import parse_overrides, parse_value, read_table
from torch_gpmpc.config.schema import METHODS, REFERENCES, SCENARIOS, Config, from_mapping
from torch_gpmpc.config.settings import SOLVERS, UNCERTAINTY_MODES, ControllerSettings
from torch_gpmpc.config.tune_settings import TuneSettings

__all__ = ["METHODS", "REFERENCES", "SCENARIOS", "SOLVERS", "UNCERTAINTY_MODES", "Config", "ControllerSettings", "TuneSettings",
           "from_mapping", "load_config", "load_settings", "parse_overrides", "parse_value", "read_mapping", "read_table"]
