"""The agent model description: built-in names and model files (TOML or JSON).

A :class:`ModelSpec` is plain, validated data (lists of floats and indices); the dynamics
layer turns it into tensors (:class:`~torch_gpmpc.dynamics.systems.NominalModel`). A model
file looks like::

    name = "my-quadrotor"
    dt = 0.02
    A = [[...]]                 # n x n
    B = [[...]]                 # n x m
    position = [0, 1, 2]        # state indices of the position (collision rows, references, arrival)
    residual = [3, 4, 5]        # state indices the GPs learn (one GP each); other rows: zero residual
    gp_inputs = ["x3", "x4", "x5", "u0", "u1", "u2"]   # default: all states
    [input_bound]
    norm = 2.0                  # ||u|| <= norm; and/or box = [b0, b1, ...], |u_i| <= b_i (both: both hold)
    [state_bound]               # optional, e.g. a speed limit ||x[indices]|| <= norm (soft)
    indices = [3, 4, 5]
    norm = 1.5
    [state_box]                 # optional, lower <= x[indices] <= upper (soft; +-inf for one side)
    indices = [3, 4, 5]
    lower = [-1.0, -1.0, -0.5]
    upper = [1.0, 1.0, 0.5]
    [state_rows]                # optional, general rows G x <= h (soft), G is r x n
    G = [[0.0, 0.0, 1.0, 0.0, 0.0, 0.0]]
    h = [3.0]
    [control]                   # optional: what this vehicle needs from its controller
    input_rate_weight = 2.0     # the defaults of the config keys of these names (CONTROL_KEYS)

State constraints hold at the planned steps tau = 1..T and are soft (an exact penalty on a
slack, as the collision rows), so a measured state outside them never makes a plan fail.

Built-ins: ``single-integrator`` (the paper: ``A = I``, ``B = 0.1 I``, state = position of
dimension ``dim``) and ``double-integrator`` (state ``[p, v]``, input acceleration,
``p' = p + dt v + dt^2/2 u``, ``v' = v + dt u``; the GPs learn the velocity rows from the
position, where the wind acts). Both bound the input by ``||u|| <= u_max`` of the config.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from torch_gpmpc.config.fields import nearest_key
from torch_gpmpc.config.reader import read_table
from torch_gpmpc.errors import GpmpcError

BUILTIN_MODELS = ("single-integrator", "double-integrator")
MODEL_SUFFIXES = (".toml", ".json")
_KEYS = ("name", "dt", "A", "B", "position", "residual", "gp_inputs", "input_bound", "state_bound", "state_box",
         "state_rows", "control")
#: Config keys a model file's ``[control]`` table may give defaults for: what a vehicle needs from its
#: controller (a quadrotor that realizes its commands with a lag needs smooth inputs, learns online
#: only from steady ones, and estimates the wind it hovers in), and their package defaults.
CONTROL_KEYS = {"input_rate_weight": 0.0, "disturbance_drift": 0.0, "gp_online_max_input_change": None}
_REQUIRED = ("A", "B", "position", "residual")


@dataclass(frozen=True)
class ModelSpec:
    """A linear agent model ``x' = A x + B u`` (+ residual on some rows), validated.

    Attributes:
        name: a label.
        dt: the sampling time (s), used to scale the wind of the built-in double integrator.
        A: (n, n) rows. B: (n, m) rows.
        position: state indices of the position (length P, 2 or 3 for the built-in wind).
        residual: state indices with a residual, one GP each (length R).
        gp_inputs: GP input columns, ``x<i>`` (state i) or ``u<j>`` (input j), length Din.
        input_norm: ``||u|| <= input_norm``, or ``None``.
        input_box: ``|u_j| <= input_box[j]`` (length m), or ``None`` (at least one of the two is set).
        state_bound_indices: state indices of an optional bound ``||x[idx]|| <= state_bound_norm``.
        state_bound_norm: that bound, or ``None``.
        state_box_indices, state_box_lower, state_box_upper: an optional box
            ``lower <= x[idx] <= upper`` (entries may be infinite: one-sided), or ``None``.
        state_rows_G, state_rows_h: optional general rows ``G x <= h`` ((r, n) and (r,)), or ``None``.
        control: ``(key, value)`` pairs of the ``[control]`` table: defaults of those config keys
            (:data:`CONTROL_KEYS`) for runs with this model; a value set in the configuration wins.

    Examples:
        >>> from torch_gpmpc import ModelSpec
        >>> m = ModelSpec.from_table({"A": [[1.0, 0.1], [0.0, 1.0]], "B": [[0.005], [0.1]],
        ...                           "position": [0], "residual": [1], "input_bound": {"box": [2.0]}})
        >>> m.state_dim, m.input_dim, m.input_box, m.gp_inputs
        (2, 1, (2.0,), ('x0', 'x1'))
    """

    name: str
    dt: float
    A: tuple[tuple[float, ...], ...]
    B: tuple[tuple[float, ...], ...]
    position: tuple[int, ...]
    residual: tuple[int, ...]
    gp_inputs: tuple[str, ...]
    input_norm: float | None = None
    input_box: tuple[float, ...] | None = None
    state_bound_indices: tuple[int, ...] | None = None
    state_bound_norm: float | None = None
    state_box_indices: tuple[int, ...] | None = None
    state_box_lower: tuple[float, ...] | None = None
    state_box_upper: tuple[float, ...] | None = None
    state_rows_G: tuple[tuple[float, ...], ...] | None = None
    state_rows_h: tuple[float, ...] | None = None
    control: tuple[tuple[str, float], ...] = ()

    @property
    def state_dim(self) -> int:
        """n."""
        return len(self.A)

    @property
    def input_dim(self) -> int:
        """m."""
        return len(self.B[0])

    @property
    def position_dim(self) -> int:
        """P."""
        return len(self.position)

    @property
    def input_memory(self) -> tuple[tuple[int, int], ...]:
        """The state rows that hold the last applied input, as ``(row, input index)`` pairs: rows with
        ``A[row] = 0`` and ``B[row]`` the unit vector of one input, that no state reads (``A[:, row] = 0``)
        and that are not a position or residual row. (A state that does drive others, such as a
        velocity set by the command, ``v' = u``, ``p' = p + dt v``, is the robot's and keeps its weight.)

        Such a row (``w' = u_j``) lets a model, and its GPs through ``gp_inputs``, see the command
        before the current one: what a vehicle that realizes its commands with a lag still responds to
        (``examples/rotorpy/crazyflie_lag.toml``). The default cost does not weigh these rows (the
        input cost already does), plants set them to the command they applied, and the plan-tracking
        metric leaves them out (a plan predicts them exactly).

        Examples:
            >>> m = ModelSpec.from_table({"A": [[1.0, 0.0], [0.0, 0.0]], "B": [[0.1], [1.0]], "position": [0],
            ...                           "residual": [0], "input_bound": {"box": [1.0]}})
            >>> m.input_memory
            ((1, 0),)
        """
        skip = set(self.position) | set(self.residual)
        out = []
        for i, (a_row, b_row) in enumerate(zip(self.A, self.B)):
            ones = [j for j, b in enumerate(b_row) if b == 1.0]
            if (i not in skip and not any(a_row) and not any(r[i] for r in self.A) and len(ones) == 1
                    and all(b == 0.0 for j, b in enumerate(b_row) if j != ones[0])):
                out.append((i, ones[0]))
        return tuple(out)

    @classmethod
    def single_integrator(cls, dim: int = 2, u_max: float = 2.0) -> "ModelSpec":
        """The paper's model: ``A = I``, ``B = 0.1 I``, ``||u|| <= u_max`` in ``dim`` dimensions."""
        return single_integrator(dim, u_max)

    @classmethod
    def double_integrator(cls, dim: int = 2, dt: float = 0.1, u_max: float = 2.0) -> "ModelSpec":
        """State ``[p, v]`` (2 dim), input acceleration (dim), ``||u|| <= u_max``.

        Examples:
            >>> from torch_gpmpc import ModelSpec
            >>> m = ModelSpec.double_integrator(dim=3, dt=0.1, u_max=2.0)
            >>> m.state_dim, m.input_dim, m.position, m.residual
            (6, 3, (0, 1, 2), (3, 4, 5))
        """
        return double_integrator(dim, dt, u_max)

    @classmethod
    def load(cls, path: str | Path) -> "ModelSpec":
        """Read and validate a model file (TOML or JSON); see :func:`load_model_file`."""
        return load_model_file(path)

    @classmethod
    def from_table(cls, table: dict[str, Any], where: str = "model") -> "ModelSpec":
        """Validate a mapping with the model file's keys (see :func:`parse_model`)."""
        return parse_model(table, where)

    def __post_init__(self) -> None:
        # whatever the constructor was given (tuples, lists, tensors, arrays): validated as a model table
        # is, and kept as plain tuples (torch would otherwise copy-construct from a tensor and warn)
        if _VALIDATING:  # parse_model's own construction, of values it has just checked
            return
        values = {f: _as_plain(getattr(self, f)) for f in self.__dataclass_fields__}
        spec = parse_model(_table(values), "ModelSpec")
        for f in self.__dataclass_fields__:
            object.__setattr__(self, f, getattr(spec, f))

    def to_table(self) -> dict[str, Any]:
        """The model file's table (plain lists and numbers): ``from_table(to_table())`` is equal."""
        return _table({f: getattr(self, f) for f in self.__dataclass_fields__})


#: Set while :func:`parse_model` builds a ModelSpec from values it validated.
_VALIDATING: list = []


def _as_plain(value: Any) -> Any:
    """Tensors and arrays (anything with ``tolist``), tuples and dicts as plain lists, dicts and numbers."""
    if hasattr(value, "tolist"):
        return value.tolist()
    if isinstance(value, (list, tuple)):
        return [_as_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _as_plain(v) for k, v in value.items()}
    return value


def _table(v: dict[str, Any]) -> dict[str, Any]:
    """The model file's table of ModelSpec field values ``v`` (by field name)."""
    table: dict[str, Any] = {key: v[key] for key in ("name", "dt", "A", "B", "position", "residual", "gp_inputs")
                             if v[key] is not None}  # parse_model names what is missing or malformed
    table["input_bound"] = {**({} if v["input_norm"] is None else {"norm": v["input_norm"]}),
                            **({} if v["input_box"] is None else {"box": v["input_box"]})}
    if v["state_bound_norm"] is not None:
        table["state_bound"] = {"indices": v["state_bound_indices"], "norm": v["state_bound_norm"]}
    if v["state_box_indices"] is not None:
        table["state_box"] = {"indices": v["state_box_indices"], "lower": v["state_box_lower"],
                              "upper": v["state_box_upper"]}
    if v["state_rows_G"] is not None:
        table["state_rows"] = {"G": v["state_rows_G"], "h": v["state_rows_h"]}
    if v["control"]:
        table["control"] = dict(v["control"])
    return _as_plain(table)


def single_integrator(dim: int, u_max: float, b: float = 0.1) -> ModelSpec:
    """The paper's model in ``dim`` dimensions: ``A = I``, ``B = b I``, ``||u|| <= u_max``."""
    eye = [[1.0 if i == j else 0.0 for j in range(dim)] for i in range(dim)]
    return ModelSpec(name="single-integrator", dt=0.1, A=_rows(eye), B=_rows([[b * v for v in r] for r in eye]),
                     position=tuple(range(dim)), residual=tuple(range(dim)),
                     gp_inputs=tuple(f"x{i}" for i in range(dim)), input_norm=u_max)


def double_integrator(dim: int, dt: float, u_max: float) -> ModelSpec:
    """State ``[p (dim), v (dim)]``, input acceleration: ``p' = p + dt v + dt^2/2 u``,
    ``v' = v + dt u``, ``||u|| <= u_max``. The GPs learn the velocity rows from the position."""
    n = 2 * dim
    A = [[0.0] * n for _ in range(n)]
    B = [[0.0] * dim for _ in range(n)]
    for i in range(dim):
        A[i][i] = A[dim + i][dim + i] = 1.0
        A[i][dim + i] = dt
        B[i][i] = 0.5 * dt * dt
        B[dim + i][i] = dt
    return ModelSpec(name="double-integrator", dt=dt, A=_rows(A), B=_rows(B), position=tuple(range(dim)),
                     residual=tuple(range(dim, n)), gp_inputs=tuple(f"x{i}" for i in range(dim)), input_norm=u_max)


#: Model files already read: path -> ((mtime_ns, size), spec); a changed file is read again.
_READ: dict[str, tuple[tuple[int, int], ModelSpec]] = {}


def resolve_model(model: str, dim: int, dt: float, u_max: float) -> ModelSpec:
    """The model named by the config key ``model``: a built-in name or a model file path
    (read again whenever the file's modification time or size changes)."""
    if model == "single-integrator":
        return single_integrator(dim, u_max)
    if model == "double-integrator":
        return double_integrator(dim, dt, u_max)
    path = str(Path(model).resolve())
    try:
        st = Path(path).stat()
        stamp = (st.st_mtime_ns, st.st_size)
    except OSError:
        return load_model_file(model)  # names the missing file
    cached = _READ.get(path)
    if cached is None or cached[0] != stamp:
        cached = (stamp, load_model_file(model))
        _READ[path] = cached
    return cached[1]


def check_model_name(model: str, key: str = "model") -> None:
    """Refuse a ``model`` value (of config key ``key``) that is neither a built-in nor an existing model file."""
    if model in BUILTIN_MODELS:
        return
    path = Path(model)
    if path.suffix.lower() not in MODEL_SUFFIXES:
        raise GpmpcError(f"config key {key!r}: {model!r} is neither {' nor '.join(BUILTIN_MODELS)} nor a "
                         "model file (.toml or .json)")
    if not path.is_file():
        raise GpmpcError(f"config key {key!r}: model file {model!r} does not exist; check the path")


def load_model_file(path: str | Path) -> ModelSpec:
    """Read and validate a model file (TOML or JSON).

    Raises:
        GpmpcError: one line naming the file and the first problem (unknown keys with the
            nearest valid one, shapes, indices out of range, non-finite numbers, unknown
            ``gp_inputs`` columns, a missing or ambiguous input bound).
    """
    where = f"model file {str(path)!r}"
    data = read_table(path, "model file", suffixes=MODEL_SUFFIXES, expect="a table with A, B, position, residual")
    return parse_model(data, where)


def parse_model(data: dict[str, Any], where: str = "model") -> ModelSpec:
    """Validate a model mapping (see :func:`load_model_file`); tensors and arrays count as their lists."""
    data = _as_plain(dict(data))
    for key in data:
        if key not in _KEYS:
            raise GpmpcError(f"{where}: unknown key {key!r} (did you mean {nearest_key(key, _KEYS)!r}?)")
    missing = [k for k in _REQUIRED if k not in data]
    if missing:
        raise GpmpcError(f"{where}: missing key(s) {', '.join(missing)}")
    A = _matrix(data["A"], "A", where)
    B = _matrix(data["B"], "B", where)
    n, m = len(A), len(B[0])
    if any(len(r) != n for r in A):
        raise GpmpcError(f"{where}: A must be square (n x n), got {len(A)} rows of lengths "
                         f"{sorted({len(r) for r in A})}")
    if len(B) != n:
        raise GpmpcError(f"{where}: A is {n} x {n} (n = {n} states) but B has {len(B)} rows; give A and B one "
                         "row per state (A n x n, B n x m)")
    dt = _positive(data.get("dt", 0.1), "dt", where)
    position = _indices(data["position"], "position", n, where)
    residual = _indices(data["residual"], "residual", n, where)
    if not 1 <= len(position) <= 3:
        raise GpmpcError(f"{where}: position must list 1 to 3 state indices, got {len(position)}")
    gp_inputs = tuple(_gp_inputs(data.get("gp_inputs", [f"x{i}" for i in range(n)]), n, m, where))
    norm, box = _input_bound(data.get("input_bound"), m, where)
    sb_idx, sb_norm = _state_bound(data.get("state_bound"), n, where)
    box_idx, box_lo, box_hi = _state_box(data.get("state_box"), n, where)
    rows_G, rows_h = _state_rows(data.get("state_rows"), n, where)
    control = _control(data.get("control"), where)
    _VALIDATING.append(True)
    try:
        return ModelSpec(name=str(data.get("name", Path(where).stem)), dt=dt, A=A, B=B, position=position,
                         residual=residual, gp_inputs=gp_inputs, input_norm=norm, input_box=box,
                         state_bound_indices=sb_idx, state_bound_norm=sb_norm, state_box_indices=box_idx,
                         state_box_lower=box_lo, state_box_upper=box_hi, state_rows_G=rows_G, state_rows_h=rows_h,
                         control=control)
    finally:
        _VALIDATING.pop()


def _rows(m: list[list[float]]) -> tuple[tuple[float, ...], ...]:
    return tuple(tuple(float(v) for v in r) for r in m)


def _number(value: Any, field: str, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise GpmpcError(f"{where}: {field} must be a number, got {value!r}")
    if not math.isfinite(value):
        raise GpmpcError(f"{where}: {field} must be finite, got {value!r}")
    return float(value)


def _positive(value: Any, field: str, where: str) -> float:
    v = _number(value, field, where)
    if v <= 0:
        raise GpmpcError(f"{where}: {field} must be > 0, got {v}")
    return v


def _matrix(value: Any, field: str, where: str) -> tuple[tuple[float, ...], ...]:
    if not isinstance(value, list) or not value or not all(isinstance(r, list) and r for r in value):
        raise GpmpcError(f"{where}: {field} must be a non-empty list of non-empty rows (a matrix)")
    if len({len(r) for r in value}) != 1:
        raise GpmpcError(f"{where}: {field} rows have different lengths {sorted({len(r) for r in value})}")
    return tuple(tuple(_number(v, f"{field}[{i}][{j}]", where) for j, v in enumerate(r)) for i, r in enumerate(value))


def _indices(value: Any, field: str, n: int, where: str) -> tuple[int, ...]:
    if not isinstance(value, list) or not value:
        raise GpmpcError(f"{where}: {field} must be a non-empty list of state indices")
    out = []
    for v in value:
        if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v < n:
            raise GpmpcError(f"{where}: {field} index {v!r} is not a state index in 0..{n - 1}")
        out.append(v)
    if len(set(out)) != len(out):
        raise GpmpcError(f"{where}: {field} lists an index twice: {out}")
    return tuple(out)


def _gp_inputs(value: Any, n: int, m: int, where: str) -> list[str]:
    if not isinstance(value, list) or not value:
        raise GpmpcError(f"{where}: gp_inputs must be a non-empty list of columns such as \"x0\" or \"u1\"")
    valid = [f"x{i}" for i in range(n)] + [f"u{j}" for j in range(m)]
    for col in value:
        if col not in valid:
            raise GpmpcError(f"{where}: gp_inputs column {col!r} does not exist (states x0..x{n - 1}, inputs "
                             f"u0..u{m - 1}; nearest: {nearest_key(str(col), valid)!r})")
    if len(set(value)) != len(value):
        raise GpmpcError(f"{where}: gp_inputs lists a column twice: {value}")
    return list(value)


def _input_bound(value: Any, m: int, where: str) -> tuple[float | None, tuple[float, ...] | None]:
    if value is None:
        raise GpmpcError(f"{where}: missing [input_bound] with norm = <max ||u||> or box = [<max |u_j|>, ...]")
    if not isinstance(value, dict):
        raise GpmpcError(f"{where}: input_bound must be a table with norm or box")
    for key in value:
        if key not in ("norm", "box"):
            raise GpmpcError(f"{where}: unknown key input_bound.{key} (did you mean "
                             f"{nearest_key(key, ('norm', 'box'))!r}?)")
    if "norm" not in value and "box" not in value:
        raise GpmpcError(f"{where}: input_bound needs norm, box or both")
    norm = _positive(value["norm"], "input_bound.norm", where) if "norm" in value else None
    if "box" not in value:
        return norm, None
    box = value["box"]
    if not isinstance(box, list) or len(box) != m:
        raise GpmpcError(f"{where}: input_bound.box must list m = {m} bounds, got {box!r}")
    return norm, tuple(_positive(b, f"input_bound.box[{j}]", where) for j, b in enumerate(box))


def _state_bound(value: Any, n: int, where: str) -> tuple[tuple[int, ...] | None, float | None]:
    if value is None:
        return None, None
    if not isinstance(value, dict):
        raise GpmpcError(f"{where}: state_bound must be a table with indices and norm")
    for key in value:
        if key not in ("indices", "norm"):
            raise GpmpcError(f"{where}: unknown key state_bound.{key} (did you mean "
                             f"{nearest_key(key, ('indices', 'norm'))!r}?)")
    if "indices" not in value or "norm" not in value:
        raise GpmpcError(f"{where}: state_bound needs indices and norm")
    indices = _indices(value["indices"], "state_bound.indices", n, where)
    return indices, _positive(value["norm"], "state_bound.norm", where)


def _bound_list(value: Any, field: str, length: int, where: str) -> tuple[float, ...]:
    """A list of ``length`` numbers that are not NaN (infinite allowed: a one-sided bound)."""
    if not isinstance(value, list) or len(value) != length:
        raise GpmpcError(f"{where}: {field} must list {length} numbers (one per index), got {value!r}")
    out = []
    for j, v in enumerate(value):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or v != v:
            raise GpmpcError(f"{where}: {field}[{j}] must be a number (inf allowed), got {v!r}")
        out.append(float(v))
    return tuple(out)


def _state_box(value: Any, n: int, where: str) -> tuple[tuple[int, ...] | None, tuple[float, ...] | None,
                                                        tuple[float, ...] | None]:
    keys = ("indices", "lower", "upper")
    if value is None:
        return None, None, None
    if not isinstance(value, dict):
        raise GpmpcError(f"{where}: state_box must be a table with indices, lower and upper")
    for key in value:
        if key not in keys:
            raise GpmpcError(f"{where}: unknown key state_box.{key} (did you mean {nearest_key(key, keys)!r}?)")
    if any(k not in value for k in keys):
        raise GpmpcError(f"{where}: state_box needs indices, lower and upper (lists of the same length)")
    indices = _indices(value["indices"], "state_box.indices", n, where)
    lower = _bound_list(value["lower"], "state_box.lower", len(indices), where)
    upper = _bound_list(value["upper"], "state_box.upper", len(indices), where)
    for j, (lo, hi) in enumerate(zip(lower, upper)):
        if not lo < hi or lo == math.inf or hi == -math.inf:
            raise GpmpcError(f"{where}: state_box.lower[{j}] = {lo} must be < state_box.upper[{j}] = {hi}")
    return indices, lower, upper


def _state_rows(value: Any, n: int, where: str) -> tuple[tuple[tuple[float, ...], ...] | None,
                                                         tuple[float, ...] | None]:
    if value is None:
        return None, None
    if not isinstance(value, dict) or set(value) != {"G", "h"}:
        raise GpmpcError(f"{where}: state_rows must be a table with G (r x n) and h (r numbers): G x <= h")
    G = _matrix(value["G"], "state_rows.G", where)
    if len(G[0]) != n:
        raise GpmpcError(f"{where}: state_rows.G must have n = {n} columns, got {len(G[0])}")
    h = value["h"]
    if not isinstance(h, list) or len(h) != len(G):
        raise GpmpcError(f"{where}: state_rows.h must list one number per row of G ({len(G)}), got {h!r}")
    return G, tuple(_number(v, f"state_rows.h[{j}]", where) for j, v in enumerate(h))


def _control(value: Any, where: str) -> tuple[tuple[str, float], ...]:
    """The ``[control]`` table: known keys (:data:`CONTROL_KEYS`), finite numbers >= 0 (> 0 for
    ``gp_online_max_input_change``), in a fixed order."""
    if value is None:
        return ()
    if not isinstance(value, dict):
        raise GpmpcError(f"{where}: control must be a table of config defaults ({', '.join(CONTROL_KEYS)})")
    for key in value:
        if key not in CONTROL_KEYS:
            raise GpmpcError(f"{where}: control: unknown key {key!r} (did you mean "
                             f"{nearest_key(key, tuple(CONTROL_KEYS))!r}?); a model file may set "
                             f"{', '.join(CONTROL_KEYS)}")
    out = []
    for key in CONTROL_KEYS:
        if key in value:
            v = _number(value[key], f"control.{key}", where)
            if v < 0 or (key == "gp_online_max_input_change" and v == 0):
                raise GpmpcError(f"{where}: control.{key} must be "
                                 f"{'> 0' if key == 'gp_online_max_input_change' else '>= 0'}, got {v}")
            out.append((key, v))
    return tuple(out)
