"""The workspace: a box on the agents' positions, ``min <= p <= max`` (a soft state constraint).

Given as ``workspace = {"min": [...], "max": [...]}`` (one entry per position coordinate) in a
scenario file or as the run configuration's ``workspace`` key.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from torch_gpmpc.errors import GpmpcError


@dataclass(frozen=True)
class Workspace:
    """A box ``lower <= p <= upper`` on the position coordinates (length P each).

    Examples:
        >>> from torch_gpmpc.config.workspace import Workspace
        >>> Workspace.parse({"min": [-5, -5, 0], "max": [5, 5, 3]}).upper
        (5.0, 5.0, 3.0)
    """

    lower: tuple[float, ...]
    upper: tuple[float, ...]

    @classmethod
    def parse(cls, value: Any, where: str = "workspace") -> "Workspace":
        """Validate ``{"min": [...], "max": [...]}`` (or a :class:`Workspace`)."""
        if isinstance(value, Workspace):
            return value
        if not isinstance(value, dict) or set(value) != {"min", "max"}:
            raise GpmpcError(f"{where}: give the workspace as {{\"min\": [...], \"max\": [...]}} (one number per "
                             f"position coordinate), got {value!r}")
        bounds = []
        for key in ("min", "max"):
            row = value[key]
            if not isinstance(row, list) or not row or not all(
                    isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in row):
                raise GpmpcError(f"{where}: workspace {key} must be a non-empty list of finite numbers, got {row!r}")
            bounds.append(tuple(float(v) for v in row))
        lower, upper = bounds
        if len(lower) != len(upper):
            raise GpmpcError(f"{where}: workspace min and max have lengths {len(lower)} and {len(upper)}; "
                             "give one number per position coordinate in each")
        if any(lo >= hi for lo, hi in zip(lower, upper)):
            raise GpmpcError(f"{where}: workspace min must be < max in every coordinate, got {lower} and {upper}")
        return cls(lower, upper)

    def to_table(self) -> dict[str, list[float]]:
        """``{"min": [...], "max": [...]}`` (``parse(to_table())`` is equal)."""
        return {"min": list(self.lower), "max": list(self.upper)}

    def check_dim(self, position_dim: int, where: str = "workspace") -> None:
        """Refuse a box whose length is not the model's position dimension P."""
        if len(self.lower) != position_dim:
            raise GpmpcError(f"{where}: the workspace has {len(self.lower)} coordinates but positions have "
                             f"{position_dim}; give {position_dim} numbers in min and max")
