"""Run configuration: the schema (:mod:`.schema`) and the strict file reader."""

from torch_gpmpc.config.schema import *  # noqa: F401,F403
from torch_gpmpc.config.schema import Config, load_config

__all__ = ["Config", "load_config"]
