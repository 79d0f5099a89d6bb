"""The transitions file formats: ``.npz`` (arrays ``x``, ``u``, ``x_next``[, ``agent``]) and
``.csv`` (header ``x0..x{D-1}, u0.., x_next0..``[, ``agent``]).

Readers return raw arrays and refuse anything they cannot read safely (pickled object
arrays, corrupt archives, bad headers) with one message naming the file and the problem;
validation of the values is :class:`~torch_gpmpc.data.transitions.Transitions`'.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np
from torch import Tensor

from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.fileio import atomic_path

SUFFIXES = (".npz", ".csv")
#: The float arrays of a transitions file (``agent`` is optional).
ARRAYS = ("x", "u", "x_next")


def source_error(source: str, message: str) -> GpmpcError:
    """A :class:`GpmpcError` prefixed with the data source."""
    return GpmpcError(f"{source}: {message}")


def read_arrays(path: Path, suffix: str, src: str):
    """``(x, u, x_next, agent or None)`` as read from a ``.npz`` or ``.csv`` file (unvalidated)."""
    return (_read_npz if suffix == ".npz" else _read_csv)(path, src)


def write_arrays(path: str | Path, x: Tensor, u: Tensor, x_next: Tensor, agent: Tensor | None) -> None:
    """Write transitions atomically as ``.npz`` or ``.csv`` (chosen by the suffix).

    Args:
        x: (N, D) states. u: (N, Du) inputs. x_next: (N, D) next states. agent: (N,) ids or ``None``.

    Raises:
        GpmpcError: for any other suffix (before anything is written).
    """
    suffix = check_suffix(path)
    with atomic_path(path) as tmp:
        if suffix == ".npz":
            arrays = {"x": x.numpy(), "u": u.numpy(), "x_next": x_next.numpy()}
            if agent is not None:
                arrays["agent"] = agent.numpy()
            with open(tmp, "wb") as fh:
                np.savez(fh, **arrays)
        else:
            tmp.write_text(_to_csv(x, u, x_next, agent))


def check_suffix(path: str | Path) -> str:
    """Return the lower-case suffix of a transitions file, or raise if unsupported."""
    suffix = Path(path).suffix.lower()
    if suffix not in SUFFIXES:
        raise GpmpcError(f"transitions file {str(path)!r}: unknown suffix {suffix or '(none)'!r}; "
                         "use .npz or .csv")
    return suffix


def _read_npz(path: Path, src: str):
    with open(path, "rb") as fh:
        magic = fh.read(4)
    if magic not in (b"PK\x03\x04", b"PK\x05\x06"):
        raise source_error(src, "cannot be read as .npz (corrupt or truncated?): not a zip archive; "
                    "write it with numpy.savez")
    try:
        # the file opened here, so that it is closed when numpy cannot read it (np.load leaks its own
        # handle when the archive is corrupt)
        with open(path, "rb") as handle, np.load(handle, allow_pickle=False) as data:
            names = set(data.files)
            missing = [k for k in ARRAYS if k not in names]
            if missing:
                raise source_error(src, f"missing array(s) {', '.join(map(repr, missing))}; an .npz needs "
                            "arrays x (N,D), u (N,Du), x_next (N,D) and optional int agent (N,) "
                            f"(found: {sorted(names) or 'none'})")
            arrays = {k: data[k] for k in (*ARRAYS, "agent") if k in names}
    except GpmpcError:
        raise
    except ValueError as exc:
        if "allow_pickle" in str(exc) or "Object arrays" in str(exc):
            raise source_error(src, "contains a pickled (object) array, which is refused; "
                        "store plain numeric arrays") from exc
        raise source_error(src, f"cannot be read as .npz (corrupt or truncated?): {exc}") from exc
    except Exception as exc:  # noqa: BLE001 - a damaged zip/npy header fails in many ways
        # (BadZipFile, OSError, EOFError, KeyError, NotImplementedError, MemoryError, ...)
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise source_error(src, f"cannot be read as .npz (corrupt or truncated?): {first}") from exc
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
        raise source_error(src, f"bad header {','.join(names)!r}: {hint}expected columns {wanted} in this order")
    return dim, input_dim, has_agent


def _read_csv(path: Path, src: str):
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise source_error(src, "is not a UTF-8 text file (corrupt, or not a CSV?)") from exc
    try:
        rows = [r for r in csv.reader(io.StringIO(text)) if r and any(c.strip() for c in r)]
    except csv.Error as exc:  # NUL bytes, oversized fields, ...
        raise source_error(src, f"cannot be parsed as CSV (corrupt file?): {exc}") from exc
    if not rows:
        raise source_error(src, "is empty; expected a header line x0..,u0..,x_next0..[,agent] and data rows")
    dim, input_dim, has_agent = _parse_header(rows[0], src)
    names = [h.strip() for h in rows[0]]
    width = len(names)
    n_float = 2 * dim + input_dim
    table = np.empty((len(rows) - 1, n_float))
    agent = np.empty(len(rows) - 1, dtype=np.int64) if has_agent else None
    for i, row in enumerate(rows[1:]):
        line = i + 2
        if len(row) != width:
            raise source_error(src, f"line {line} has {len(row)} fields but the header has {width} "
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
        raise source_error(src, f"line {line}, column {column!r}: {cell.strip()!r} is not a number") from None


def _parse_int(cell: str, line: int, src: str) -> int:
    try:
        return int(cell.strip())
    except ValueError:
        raise source_error(src, f"line {line}, column 'agent': {cell.strip()!r} is not an integer id") from None


# ---------------------------------------------------------------------- data recipe


def _to_csv(x: Tensor, u: Tensor, x_next: Tensor, agent: Tensor | None) -> str:
    header = csv_header(x.shape[1], u.shape[1], agent is not None)
    buf = io.StringIO()
    buf.write(",".join(header) + "\n")
    table = np.concatenate([x.numpy(), u.numpy(), x_next.numpy()], axis=1)
    ids = None if agent is None else agent.numpy()
    for i, row in enumerate(table):
        cells = [repr(float(v)) for v in row]
        if ids is not None:
            cells.append(str(int(ids[i])))
        buf.write(",".join(cells) + "\n")
    return buf.getvalue()
