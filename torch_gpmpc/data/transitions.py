"""Logged transitions ``(x, u, x')`` of the agents and the residuals the GP learns.

A :class:`Transitions` holds N transitions of one or several agents:

* ``x``      (N, D)  states,
* ``u``      (N, Du) inputs,
* ``x_next`` (N, D)  next states,
* ``agent``  (N,)    integer agent ids, or ``None``.

Files (design.md §2): ``.npz`` with arrays ``x``, ``u``, ``x_next`` and optional
integer ``agent`` (loaded with ``allow_pickle=False``), or ``.csv`` with the header
``x0..x{D-1}, u0..u{Du-1}, x_next0..x_next{D-1}[, agent]``. Every problem with a
file raises :class:`~torch_gpmpc.errors.GpmpcError` with one message naming the file,
the field and the fix. Exact duplicate rows are dropped with a logged warning; the
same ``x`` with a different ``x_next`` is kept (that is noise, not a duplicate).

The residual targets (paper eq. 2) are ``y = x' - f(x, u)`` for the nominal model f.
:func:`collect_transitions` implements the paper's data recipe (design.md §3).
"""

from __future__ import annotations

import csv
import io
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.fileio import atomic_path
from torch_gpmpc.dynamics.systems import NominalModel, TrueSystem

log = logging.getLogger(__name__)

#: Largest accepted absolute value in a transitions file (larger values are almost
#: always wrong units or a corrupt file, and would wreck the GP's standardization).
MAX_ABS_VALUE = 1e6
#: Fewest transitions a GP can be fitted to.
MIN_SAMPLES = 2
#: Most transitions :func:`collect_transitions` writes in one call (K x N); more is
#: almost always a typo and would exhaust memory before anything is written.
MAX_COLLECT_ROWS = 1_000_000
SUFFIXES = (".npz", ".csv")
_ARRAYS = ("x", "u", "x_next")


def _fail(source: str, message: str) -> GpmpcError:
    """A :class:`GpmpcError` prefixed with the data source."""
    return GpmpcError(f"{source}: {message}")


@dataclass(frozen=True, eq=False)
class Transitions:
    """N logged transitions ``x -> x_next`` under inputs ``u``.

    Construction validates shapes, finiteness and magnitudes and converts the arrays
    to float64 tensors (``agent`` to int64); it does not drop duplicates (see
    :meth:`deduplicated`, which :meth:`load` applies).

    Attributes:
        x: states, shape (N, D), float64.
        u: inputs, shape (N, Du), float64.
        x_next: next states, shape (N, D), float64.
        agent: agent ids, shape (N,), int64, or ``None``.
        source: where the data came from (used in error messages).
    """

    x: Tensor
    u: Tensor
    x_next: Tensor
    agent: Tensor | None = None
    source: str = "transitions"

    def __post_init__(self) -> None:
        src = self.source
        for name in _ARRAYS:
            object.__setattr__(self, name, _as_float_matrix(getattr(self, name), name, src))
        if self.agent is not None:
            object.__setattr__(self, "agent", _as_agent_ids(self.agent, src))
        _check_shapes(self.x, self.u, self.x_next, self.agent, src)
        for name in _ARRAYS:
            _check_values(getattr(self, name), name, src)

    # ------------------------------------------------------------------ shape info
    @property
    def num_samples(self) -> int:
        """N."""
        return int(self.x.shape[0])

    @property
    def state_dim(self) -> int:
        """D."""
        return int(self.x.shape[1])

    @property
    def input_dim(self) -> int:
        """Du."""
        return int(self.u.shape[1])

    @property
    def agent_ids(self) -> list[int]:
        """Sorted distinct agent ids (``[]`` without an agent column)."""
        return [] if self.agent is None else sorted(int(a) for a in torch.unique(self.agent))

    def __len__(self) -> int:
        return self.num_samples

    # ------------------------------------------------------------------ selection
    def _rows(self, index: Tensor, source: str | None = None) -> "Transitions":
        return Transitions(self.x[index], self.u[index], self.x_next[index],
                           None if self.agent is None else self.agent[index],
                           source=source or self.source)

    def for_agent(self, k: int) -> "Transitions":
        """The transitions of agent ``k``.

        Raises:
            GpmpcError: without an ``agent`` column, if ``k`` is absent, or if agent
                ``k`` has fewer than 2 transitions.
        """
        if self.agent is None:
            raise _fail(self.source, f"agent {k} requested but the data has no 'agent' column; "
                        "drop the agent selection (e.g. --agent) or add the column")
        mask = self.agent == int(k)
        if not bool(mask.any()):
            raise _fail(self.source, f"agent {k} not found; available agent ids: {self.agent_ids}")
        out = self._rows(mask, source=f"{self.source} (agent {k})")
        _check_count(out.num_samples, out.source)
        return out

    def split(self, holdout_fraction: float, seed: int = 0) -> tuple["Transitions", "Transitions"]:
        """Random split into training and held-out parts.

        Args:
            holdout_fraction: share of rows held out, in (0, 1).
            seed: seed of the permutation.

        Returns:
            ``(train, holdout)``; ``holdout`` has ``round(fraction * N)`` rows (at least 1)
            and ``train`` keeps at least 2.

        Raises:
            GpmpcError: if the fraction is outside (0, 1) or leaves too few rows.
        """
        f = float(holdout_fraction)
        if not 0.0 < f < 1.0:
            raise GpmpcError(f"holdout fraction must be in (0, 1), got {holdout_fraction}; "
                             "e.g. --holdout 0.2")
        n_test = max(1, int(round(f * self.num_samples)))
        if self.num_samples - n_test < MIN_SAMPLES:
            raise _fail(self.source, f"holdout fraction {f} leaves {self.num_samples - n_test} "
                        f"training rows of {self.num_samples}; use a smaller fraction or more data")
        gen = torch.Generator().manual_seed(int(seed))
        perm = torch.randperm(self.num_samples, generator=gen)
        return (self._rows(perm[n_test:], f"{self.source} (train)"),
                self._rows(perm[:n_test], f"{self.source} (holdout)"))

    def deduplicated(self) -> "Transitions":
        """Drop exact duplicate rows ``(x, u, x_next, agent)``, keeping the first.

        The same state with a different next state is kept (that is noise). A warning
        is logged with the number of dropped rows.
        """
        cols = [self.x, self.u, self.x_next]
        if self.agent is not None:
            cols.append(self.agent.to(torch.float64)[:, None])
        table = torch.cat(cols, dim=1).numpy()
        _, first = np.unique(table, axis=0, return_index=True)
        if first.size == self.num_samples:
            return self
        keep = torch.from_numpy(np.sort(first))
        dropped = self.num_samples - keep.numel()
        if keep.numel() < MIN_SAMPLES:
            raise _fail(self.source, f"only {keep.numel()} transition(s) left after dropping {dropped} "
                        f"exact duplicate row(s); need at least {MIN_SAMPLES} distinct rows to fit a GP "
                        "(collect more with `gpmpc collect --samples N`)")
        log.warning("%s: dropped %d exact duplicate transition row(s), %d remain",
                    self.source, dropped, keep.numel())
        return self._rows(keep)

    # ------------------------------------------------------------------ model checks
    def check_dim(self, dim: int, input_dim: int | None = None) -> None:
        """Check the state (and optionally input) dimension against a model's.

        Raises:
            GpmpcError: naming both dimensions.
        """
        if self.state_dim != int(dim):
            raise _fail(self.source, f"state dimension D={self.state_dim} (columns of x) does not "
                        f"match the model's D={dim}; use data collected with --dim {dim} "
                        "or a model of the data's dimension")
        if input_dim is not None and self.input_dim != int(input_dim):
            raise _fail(self.source, f"input dimension Du={self.input_dim} (columns of u) does not "
                        f"match the model's Du={input_dim}")

    def residuals(self, nominal: NominalModel, inputs: str = "state") -> tuple[Tensor, Tensor]:
        """GP training data: inputs and residual targets ``y = x_next - f(x, u)`` (eq. 2).

        Args:
            nominal: the known model f (its ``dim`` must match D and Du).
            inputs: ``"state"`` (paper: GP inputs are x) or ``"state_input"`` (x and u).

        Returns:
            ``(inputs, y)``: inputs of shape (N, D) (or (N, D + Du)), y of shape (N, D).

        Raises:
            GpmpcError: on a dimension mismatch or an unknown ``inputs``.
        """
        self.check_dim(nominal.dim, nominal.dim)
        y = self.x_next - nominal(self.x, self.u)
        if inputs == "state":
            return self.x, y
        if inputs == "state_input":
            return torch.cat([self.x, self.u], dim=1), y
        raise GpmpcError(f"inputs must be 'state' or 'state_input', got {inputs!r}")

    # ------------------------------------------------------------------ files
    @classmethod
    def load(cls, path: str | Path) -> "Transitions":
        """Read and validate a ``.npz`` or ``.csv`` transitions file.

        Exact duplicate rows are dropped with a logged warning.

        Raises:
            GpmpcError: one clear message per problem (missing file, unknown suffix,
                missing arrays/columns, bad header, unparsable or corrupt file, shape
                mismatch, non-finite or extreme values, fewer than 2 samples).
        """
        path = Path(path)
        src = f"transitions file {str(path)!r}"
        suffix = check_suffix(path)
        if not path.is_file():
            raise _fail(src, "file not found; check the path (create one with `gpmpc collect --out FILE`)")
        reader = _read_npz if suffix == ".npz" else _read_csv
        x, u, x_next, agent = reader(path, src)
        return cls(x, u, x_next, agent, source=src).deduplicated()

    def save(self, path: str | Path) -> None:
        """Write atomically as ``.npz`` or ``.csv`` (chosen by the suffix).

        Raises:
            GpmpcError: for any other suffix (before anything is written).
        """
        path = Path(path)
        suffix = check_suffix(path)
        with atomic_path(path) as tmp:
            if suffix == ".npz":
                arrays = {"x": self.x.numpy(), "u": self.u.numpy(), "x_next": self.x_next.numpy()}
                if self.agent is not None:
                    arrays["agent"] = self.agent.numpy()
                with open(tmp, "wb") as fh:
                    np.savez(fh, **arrays)
            else:
                tmp.write_text(self._to_csv())

    def _to_csv(self) -> str:
        header = csv_header(self.state_dim, self.input_dim, self.agent is not None)
        buf = io.StringIO()
        buf.write(",".join(header) + "\n")
        table = torch.cat([self.x, self.u, self.x_next], dim=1).numpy()
        agent = None if self.agent is None else self.agent.numpy()
        for i, row in enumerate(table):
            cells = [repr(float(v)) for v in row]
            if agent is not None:
                cells.append(str(int(agent[i])))
            buf.write(",".join(cells) + "\n")
        return buf.getvalue()


# ---------------------------------------------------------------------- validation
def check_suffix(path: str | Path) -> str:
    """Return the lower-case suffix of a transitions file, or raise if unsupported."""
    suffix = Path(path).suffix.lower()
    if suffix not in SUFFIXES:
        raise GpmpcError(f"transitions file {str(path)!r}: unknown suffix {suffix or '(none)'!r}; "
                         "use .npz or .csv")
    return suffix


def _as_float_matrix(value, name: str, src: str) -> Tensor:
    arr = value.detach().cpu().numpy() if isinstance(value, Tensor) else np.asarray(value)
    if arr.dtype.kind not in "fiu":
        raise _fail(src, f"array {name!r} must be numeric (float), got dtype {arr.dtype}")
    if arr.ndim != 2:
        raise _fail(src, f"array {name!r} must be 2-D with shape (N, D), got shape {tuple(arr.shape)}")
    return torch.as_tensor(np.ascontiguousarray(arr, dtype=np.float64))


def _as_agent_ids(value, src: str) -> Tensor:
    arr = value.detach().cpu().numpy() if isinstance(value, Tensor) else np.asarray(value)
    if arr.ndim != 1:
        raise _fail(src, f"array 'agent' must be 1-D with shape (N,), got shape {tuple(arr.shape)}")
    if arr.dtype.kind not in "iu":
        raise _fail(src, f"array 'agent' must hold integer ids, got dtype {arr.dtype}")
    if arr.size and arr.min() < 0:
        raise _fail(src, f"array 'agent' has negative id {int(arr.min())}; ids are 0..K-1")
    return torch.as_tensor(arr.astype(np.int64))


def _check_count(n: int, src: str) -> None:
    if n < MIN_SAMPLES:
        raise _fail(src, f"only {n} transition(s); need at least {MIN_SAMPLES} to fit a GP "
                    "(collect more with `gpmpc collect --samples N`)")


def _check_shapes(x: Tensor, u: Tensor, x_next: Tensor, agent: Tensor | None, src: str) -> None:
    n = x.shape[0]
    for name, arr in (("u", u), ("x_next", x_next)) + ((("agent", agent),) if agent is not None else ()):
        if arr.shape[0] != n:
            raise _fail(src, f"shape mismatch: 'x' has {n} rows but {name!r} has {arr.shape[0]}; "
                        "every array needs one row per transition")
    if x_next.shape[1] != x.shape[1]:
        raise _fail(src, f"shape mismatch: 'x' has D={x.shape[1]} columns but 'x_next' has "
                    f"{x_next.shape[1]}; both are states of the same dimension")
    if x.shape[1] == 0 or u.shape[1] == 0:
        raise _fail(src, "'x' and 'u' need at least one column each")
    _check_count(n, src)


def _check_values(arr: Tensor, name: str, src: str) -> None:
    bad = ~torch.isfinite(arr)
    if bool(bad.any()):
        row = int(bad.any(dim=1).nonzero()[0])
        raise _fail(src, f"array {name!r} has {int(bad.sum())} non-finite value(s) (NaN/inf), "
                    f"first in row {row}; remove or fix those rows")
    big = arr.abs() > MAX_ABS_VALUE
    if bool(big.any()):
        row = int(big.any(dim=1).nonzero()[0])
        raise _fail(src, f"array {name!r} has extreme value {float(arr.abs().max()):.3g} "
                    f"(|value| > {MAX_ABS_VALUE:g}) in row {row}; check the units or the file")


# ---------------------------------------------------------------------- readers
def _read_npz(path: Path, src: str):
    with open(path, "rb") as fh:
        magic = fh.read(4)
    if magic not in (b"PK\x03\x04", b"PK\x05\x06"):
        raise _fail(src, "cannot be read as .npz (corrupt or truncated?): not a zip archive; "
                    "write it with numpy.savez")
    try:
        with np.load(path, allow_pickle=False) as data:
            names = set(data.files)
            missing = [k for k in _ARRAYS if k not in names]
            if missing:
                raise _fail(src, f"missing array(s) {', '.join(map(repr, missing))}; an .npz needs "
                            "arrays x (N,D), u (N,Du), x_next (N,D) and optional int agent (N,) "
                            f"(found: {sorted(names) or 'none'})")
            arrays = {k: data[k] for k in (*_ARRAYS, "agent") if k in names}
    except GpmpcError:
        raise
    except ValueError as exc:
        if "allow_pickle" in str(exc) or "Object arrays" in str(exc):
            raise _fail(src, "contains a pickled (object) array, which is refused; "
                        "store plain numeric arrays") from exc
        raise _fail(src, f"cannot be read as .npz (corrupt or truncated?): {exc}") from exc
    except Exception as exc:  # noqa: BLE001 - a damaged zip/npy header fails in many ways
        # (BadZipFile, OSError, EOFError, KeyError, NotImplementedError, MemoryError, ...)
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise _fail(src, f"cannot be read as .npz (corrupt or truncated?): {first}") from exc
    return arrays["x"], arrays["u"], arrays["x_next"], arrays.get("agent")


def csv_header(dim: int, input_dim: int, with_agent: bool) -> list[str]:
    """Column names ``x0..x{D-1}, u0..u{Du-1}, x_next0..x_next{D-1}[, agent]``."""
    cols = ([f"x{i}" for i in range(dim)] + [f"u{i}" for i in range(input_dim)]
            + [f"x_next{i}" for i in range(dim)])
    return cols + (["agent"] if with_agent else [])


def _parse_header(header: list[str], src: str) -> tuple[int, int, bool]:
    """Return (D, Du, has_agent) from a CSV header, or raise a 'bad header' error."""
    names = [h.strip() for h in header]
    dim = sum(1 for h in names if h.startswith("x") and h[1:].isdigit())
    input_dim = sum(1 for h in names if h.startswith("u") and h[1:].isdigit())
    has_agent = "agent" in names
    expected = csv_header(dim, input_dim, has_agent)
    if dim == 0 or input_dim == 0 or names != expected:
        missing = [c for c in ("x0", "u0", "x_next0") if c not in names]
        hint = f"missing column(s) {', '.join(missing)}; " if missing else ""
        generic = "x0..x{D-1},u0..u{Du-1},x_next0..x_next{D-1}[,agent]"
        wanted = ",".join(expected) if dim and input_dim else generic
        raise _fail(src, f"bad header {','.join(names)!r}: {hint}expected columns {wanted} in this order")
    return dim, input_dim, has_agent


def _read_csv(path: Path, src: str):
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise _fail(src, "is not a UTF-8 text file (corrupt, or not a CSV?)") from exc
    try:
        rows = [r for r in csv.reader(io.StringIO(text)) if r and any(c.strip() for c in r)]
    except csv.Error as exc:  # NUL bytes, oversized fields, ...
        raise _fail(src, f"cannot be parsed as CSV (corrupt file?): {exc}") from exc
    if not rows:
        raise _fail(src, "is empty; expected a header line x0..,u0..,x_next0..[,agent] and data rows")
    dim, input_dim, has_agent = _parse_header(rows[0], src)
    names = [h.strip() for h in rows[0]]
    width = len(names)
    n_float = 2 * dim + input_dim
    table = np.empty((len(rows) - 1, n_float))
    agent = np.empty(len(rows) - 1, dtype=np.int64) if has_agent else None
    for i, row in enumerate(rows[1:]):
        line = i + 2
        if len(row) != width:
            raise _fail(src, f"line {line} has {len(row)} fields but the header has {width} "
                        "(truncated or corrupt file?)")
        for j in range(n_float):
            table[i, j] = _parse_float(row[j], line, names[j], src)
        if agent is not None:
            agent[i] = _parse_int(row[-1], line, src)
    x, u, x_next = np.split(table, [dim, dim + input_dim], axis=1)
    return x, u, x_next, agent


def _parse_float(cell: str, line: int, column: str, src: str) -> float:
    try:
        return float(cell)
    except ValueError:
        raise _fail(src, f"line {line}, column {column!r}: {cell.strip()!r} is not a number") from None


def _parse_int(cell: str, line: int, src: str) -> int:
    try:
        return int(cell.strip())
    except ValueError:
        raise _fail(src, f"line {line}, column 'agent': {cell.strip()!r} is not an integer id") from None


# ---------------------------------------------------------------------- data recipe
def sample_disc(n: int, dim: int, radius: float, generator: torch.Generator) -> Tensor:
    """Uniform samples from the ball ``||v|| < radius`` in ``dim`` dimensions.

    The direction is a normalized Gaussian and the radius ``radius * U^(1/dim)``
    (in 2D: ``radius * sqrt(U)``, area-uniform in the disc).

    Returns:
        samples, shape (n, dim), float64.
    """
    direction = torch.randn(n, dim, generator=generator, dtype=torch.float64)
    direction = direction / direction.norm(dim=1, keepdim=True).clamp_min(1e-300)
    r = radius * torch.rand(n, 1, generator=generator, dtype=torch.float64) ** (1.0 / dim)
    return r * direction


def collect_transitions(system: TrueSystem, num_agents: int = 3, samples: int = 100, seed: int = 0,
                        u_max: float = 2.0, box: float = 4.0) -> Transitions:
    """The paper's data recipe (design.md §3), ``samples`` transitions per agent.

    States are uniform in ``[-box, box]^D``, inputs uniform in the disc (ball)
    ``||v|| < u_max`` and ``x_next = system.step(x, v)`` with one seeded
    ``torch.Generator`` for states, inputs and noise.

    Args:
        system: the true system (nominal + wind + noise).
        num_agents: K; rows are tagged with agent ids 0..K-1.
        samples: N per agent.
        seed: seed of the generator.
        u_max: input norm bound.
        box: half-width of the state box.

    Returns:
        Transitions with K*N rows (agent 0's rows first).

    Raises:
        GpmpcError: for non-positive counts or sizes.
    """
    if int(num_agents) < 1:
        raise GpmpcError(f"agents must be >= 1, got {num_agents}; e.g. --agents 3")
    if int(samples) < MIN_SAMPLES:
        raise GpmpcError(f"samples must be >= {MIN_SAMPLES} per agent, got {samples}; e.g. --samples 100")
    if int(num_agents) * int(samples) > MAX_COLLECT_ROWS:
        raise GpmpcError(f"agents x samples = {int(num_agents) * int(samples)} transitions is more than "
                         f"{MAX_COLLECT_ROWS}; lower --agents or --samples (the paper uses 100 per agent)")
    for name, value in (("u-max", u_max), ("box", box)):
        if not (math.isfinite(value) and value > 0):
            raise GpmpcError(f"{name} must be a positive number, got {value}")
    dim = system.nominal.dim
    gen = torch.Generator().manual_seed(int(seed))
    xs, us, xns, ids = [], [], [], []
    for k in range(int(num_agents)):
        x = (2.0 * torch.rand(int(samples), dim, generator=gen, dtype=torch.float64) - 1.0) * box
        u = sample_disc(int(samples), dim, u_max, gen)
        xs.append(x)
        us.append(u)
        xns.append(system.step(x, u, generator=gen))
        ids.append(torch.full((int(samples),), k, dtype=torch.int64))
    return Transitions(torch.cat(xs), torch.cat(us), torch.cat(xns), torch.cat(ids),
                       source=f"collected (seed {seed})")
