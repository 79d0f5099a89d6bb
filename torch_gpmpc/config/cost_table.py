"""The ``[cost]`` table of a run configuration: a stated quadratic tracking cost as plain numbers.

Given as ``cost = {Q = ..., R = ..., P = ..., u_ref = ...}`` (a ``[cost]`` table in a TOML file), each
weight a number (times I), a list (the diagonal) or a list of rows (the matrix). The sizes are
checked against the agent model when the controller is built
(:class:`~torch_gpmpc.control.cost.QuadraticCost`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from torch_gpmpc.config.fields import nearest_key
from torch_gpmpc.errors import GpmpcError

#: How a terminal weight is chosen when the cost gives no ``P``.
TERMINAL_COSTS = ("lqr", "stage")

Weight = float | tuple[float, ...] | tuple[tuple[float, ...], ...]


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _weight(value: Any, where: str) -> Weight:
    """A number, a list of numbers or a list of equal-length rows, as floats and tuples."""
    if _number(value):
        return float(value)
    if isinstance(value, (list, tuple)) and value and all(_number(v) for v in value):
        return tuple(float(v) for v in value)
    if isinstance(value, (list, tuple)) and value and all(
            isinstance(r, (list, tuple)) and len(r) == len(value) and all(_number(v) for v in r) for r in value):
        return tuple(tuple(float(v) for v in r) for r in value)
    raise GpmpcError(f"{where}: give a finite number (times I), a list (the diagonal) or a square list of rows; "
                     f"got {value!r}")


@dataclass(frozen=True)
class CostTable:
    """A stated cost's weights as plain numbers (see the module docstring); ``P`` and ``u_ref`` may be
    ``None`` (the terminal weight from ``terminal_cost``; no input reference).

    Examples:
        >>> CostTable.parse({"Q": [1, 1, 0.1, 0.1], "R": 0.01}).Q
        (1.0, 1.0, 0.1, 0.1)
    """

    Q: Weight
    R: Weight
    P: Weight | None = None
    u_ref: tuple[float, ...] | None = None

    @classmethod
    def parse(cls, value: Any, where: str = "cost") -> "CostTable":
        """Validate ``{"Q": ..., "R": ..., "P": ..., "u_ref": ...}`` (or a :class:`CostTable`)."""
        if isinstance(value, CostTable):
            return value
        allowed = ("Q", "R", "P", "u_ref")
        if not isinstance(value, dict):
            raise GpmpcError(f"{where}: give the cost as a table with Q and R (and optionally P, u_ref), e.g. "
                             f"[cost] Q = [1, 1, 0.1, 0.1] R = 0.01; got {value!r}")
        for key in value:
            if key not in allowed:
                raise GpmpcError(f"{where}: unknown entry {key!r} (did you mean {nearest_key(key, allowed)!r}?); "
                                 f"the entries are Q, R, P (terminal) and u_ref")
        missing = [key for key in ("Q", "R") if key not in value]
        if missing:
            raise GpmpcError(f"{where}: missing entry {' and '.join(missing)}; a cost needs Q and R")
        u_ref = value.get("u_ref")
        if u_ref is not None:
            u_ref = _weight(u_ref, f"{where}, entry u_ref")
            if not isinstance(u_ref, tuple) or isinstance(u_ref[0], tuple):
                raise GpmpcError(f"{where}, entry u_ref: give one number per input, e.g. [0, 0, 9.81]")
        return cls(Q=_weight(value["Q"], f"{where}, entry Q"), R=_weight(value["R"], f"{where}, entry R"),
                   P=None if value.get("P") is None else _weight(value["P"], f"{where}, entry P"), u_ref=u_ref)

    def to_table(self) -> dict[str, Any]:
        """The table (``parse(to_table())`` is equal)."""
        def plain(w):
            return [list(r) if isinstance(r, tuple) else r for r in w] if isinstance(w, tuple) else w

        table = {"Q": plain(self.Q), "R": plain(self.R)}
        if self.P is not None:
            table["P"] = plain(self.P)
        if self.u_ref is not None:
            table["u_ref"] = list(self.u_ref)
        return table
