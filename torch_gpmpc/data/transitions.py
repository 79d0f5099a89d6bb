"""Logged transitions ``(x, u, x')`` of the agents and the residuals the GP learns.

A :class:`Transitions` holds N transitions of one or several agents:

* ``x``      (N, D)  states,
* ``u``      (N, Du) inputs,
* ``x_next`` (N, D)  next states,
* ``agent``  (N,)    integer agent ids, or ``None``.

Files: ``.npz`` with arrays ``x``, ``u``, ``x_next`` and optional
integer ``agent`` (loaded with ``allow_pickle=False``), or ``.csv`` with the header
``x0..x{D-1}, u0..u{Du-1}, x_next0..x_next{D-1}[, agent]``. Every problem with a
file raises :class:`~torch_gpmpc.errors.GpmpcError` with one message naming the file,
the field and the fix. Exact duplicate rows are dropped with a logged warning; the
same ``x`` with a different ``x_next`` is kept (that is noise, not a duplicate).

The residual targets (paper eq. 2) are ``y = x' - f(x, u)`` for the nominal model f.
:mod:`~torch_gpmpc.data.formats` reads and writes the files; :mod:`~torch_gpmpc.data.collect`
implements the paper's data recipe.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torch_gpmpc.data.formats import ARRAYS, check_suffix, read_arrays, source_error, write_arrays
from torch_gpmpc.dynamics.systems import NominalModel
from torch_gpmpc.errors import GpmpcError

log = logging.getLogger(__name__)

#: Largest accepted absolute value in a transitions file (larger values are almost
#: always wrong units or a corrupt file, and would wreck the GP's standardization).
MAX_ABS_VALUE = 1e6
#: Fewest transitions a GP can be fitted to.
MIN_SAMPLES = 2


#: How ``Transitions.split`` holds rows out.
SPLIT_MODES = ("random", "blocks")
#: Contiguous blocks of the ``blocks`` split.
SPLIT_BLOCKS = 20


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

    Examples:
        >>> import torch
        >>> from torch_gpmpc import NominalModel, Transitions
        >>> x = torch.tensor([[0.0, 0.0], [1.0, 0.5]], dtype=torch.float64)
        >>> u = torch.ones(2, 2, dtype=torch.float64)
        >>> data = Transitions(x, u, x + 0.1 * u + 0.01)
        >>> inputs, y = data.residuals(NominalModel(2))       # y = x' - (A x + B u)
        >>> tuple(inputs.shape), [round(v, 3) for v in y[0].tolist()]
        ((2, 2), [0.01, 0.01])
    """

    x: Tensor
    u: Tensor
    x_next: Tensor
    agent: Tensor | None = None
    source: str = "transitions"

    def __post_init__(self) -> None:
        src = self.source
        for name in ARRAYS:
            object.__setattr__(self, name, _as_float_matrix(getattr(self, name), name, src))
        if self.agent is not None:
            object.__setattr__(self, "agent", _as_agent_ids(self.agent, src))
        _check_shapes(self.x, self.u, self.x_next, self.agent, src)
        for name in ARRAYS:
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
            raise source_error(self.source, f"agent {k} requested but the data has no 'agent' column; "
                        "drop the agent selection (e.g. --agent) or add the column")
        mask = self.agent == int(k)
        if not bool(mask.any()):
            raise source_error(self.source, f"agent {k} not found; available agent ids: {self.agent_ids}")
        out = self._rows(mask, source=f"{self.source} (agent {k})")
        _check_count(out.num_samples, out.source)
        return out

    def split(self, holdout_fraction: float, seed: int = 0, mode: str = "random"
              ) -> tuple["Transitions", "Transitions"]:
        """Split into training and held-out parts.

        Args:
            holdout_fraction: share of rows held out, in (0, 1).
            seed: seed of the permutation (``random``) or of the choice of blocks (``blocks``).
            mode: ``random`` (rows drawn uniformly) or ``blocks``: the rows, in log order, cut
                into :data:`SPLIT_BLOCKS` contiguous blocks of equal size and
                ``round(fraction * blocks)`` (at least 1) of them held out. Logged transitions
                are autocorrelated, so a random split puts near-copies of every held-out row in
                the training set and flatters a model; held-out time blocks do not.

        Returns:
            ``(train, holdout)``; ``holdout`` has about ``fraction * N`` rows (at least 1)
            and ``train`` keeps at least 2.

        Raises:
            GpmpcError: if the fraction is outside (0, 1), the mode is unknown, or the split
                leaves too few rows.
        """
        f = float(holdout_fraction)
        if not 0.0 < f < 1.0:
            raise GpmpcError(f"holdout fraction must be in (0, 1), got {holdout_fraction}; "
                             "e.g. --holdout 0.2")
        if mode not in SPLIT_MODES:
            raise GpmpcError(f"holdout split must be one of {SPLIT_MODES}, got {mode!r}")
        gen = torch.Generator().manual_seed(int(seed))
        n = self.num_samples
        if mode == "random":
            held = torch.randperm(n, generator=gen)[:max(1, int(round(f * n)))].sort().values
        else:
            blocks = min(SPLIT_BLOCKS, n)
            bounds = torch.linspace(0, n, blocks + 1).round().long()
            chosen = torch.randperm(blocks, generator=gen)[:max(1, int(round(f * blocks)))].sort().values
            held = torch.cat([torch.arange(int(bounds[b]), int(bounds[b + 1])) for b in chosen.tolist()])
        keep = torch.ones(n, dtype=torch.bool)
        keep[held] = False
        if int(keep.sum()) < MIN_SAMPLES:
            raise source_error(self.source, f"holdout fraction {f} leaves {int(keep.sum())} "
                               f"training rows of {n}; use a smaller fraction or more data")
        return (self._rows(keep.nonzero().flatten(), f"{self.source} (train)"),
                self._rows(held, f"{self.source} (holdout)"))

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
            raise source_error(self.source, f"only {keep.numel()} transition(s) left after dropping {dropped} "
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
            raise source_error(self.source, f"state dimension D={self.state_dim} (columns of x) does not "
                        f"match the model's D={dim}; fit with the --model the data was collected with "
                        "(gpmpc collect --model ...), or collect data with this model")
        if input_dim is not None and self.input_dim != int(input_dim):
            raise source_error(self.source, f"input dimension Du={self.input_dim} (columns of u) does not "
                        f"match the model's Du={input_dim}")

    def residuals(self, nominal: NominalModel, gp_inputs: str | None = None) -> tuple[Tensor, Tensor]:
        """GP training data: inputs and residual targets ``y = [x_next - f(x, u)]_residual`` (eq. 2).

        Args:
            nominal: the known model f (its state and input dimensions must match the data);
                its ``residual`` rows are the targets.
            gp_inputs: ``None`` (the model's ``gp_inputs`` columns), ``"state"`` (all of x, the
                paper) or ``"state_input"`` (x and u).

        Returns:
            ``(inputs, y)``: inputs of shape (N, Din), y of shape (N, R).

        Raises:
            GpmpcError: on a dimension mismatch or an unknown ``gp_inputs``.
        """
        self.check_dim(nominal.dim, nominal.input_dim)
        y = (self.x_next - nominal(self.x, self.u))[:, nominal.residual]
        if gp_inputs is None:
            return nominal.gp_input(self.x, self.u), y
        if gp_inputs == "state":
            return self.x, y
        if gp_inputs == "state_input":
            return torch.cat([self.x, self.u], dim=1), y
        raise GpmpcError(f"gp_inputs must be 'state' or 'state_input', got {gp_inputs!r}")

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
            raise source_error(src, "file not found; check the path (create one with `gpmpc collect --out FILE`)")
        x, u, x_next, agent = read_arrays(path, suffix, src)
        return cls(x, u, x_next, agent, source=src).deduplicated()

    def save(self, path: str | Path) -> None:
        """Write atomically as ``.npz`` or ``.csv`` (chosen by the suffix).

        Raises:
            GpmpcError: for any other suffix (before anything is written).
        """
        write_arrays(path, self.x, self.u, self.x_next, self.agent)


# ---------------------------------------------------------------------- validation
def _as_float_matrix(value, name: str, src: str) -> Tensor:
    arr = value.detach().cpu().numpy() if isinstance(value, Tensor) else np.asarray(value)
    if arr.dtype.kind not in "fiu":
        raise source_error(src, f"array {name!r} must be numeric (float), got dtype {arr.dtype}")
    if arr.ndim != 2:
        raise source_error(src, f"array {name!r} must be 2-D with shape (N, D), got shape {tuple(arr.shape)}")
    return torch.as_tensor(np.ascontiguousarray(arr, dtype=np.float64))


def _as_agent_ids(value, src: str) -> Tensor:
    arr = value.detach().cpu().numpy() if isinstance(value, Tensor) else np.asarray(value)
    if arr.ndim != 1:
        raise source_error(src, f"array 'agent' must be 1-D with shape (N,), got shape {tuple(arr.shape)}")
    if arr.dtype.kind not in "iu":
        raise source_error(src, f"array 'agent' must hold integer ids, got dtype {arr.dtype}")
    if arr.size and arr.min() < 0:
        raise source_error(src, f"array 'agent' has negative id {int(arr.min())}; ids are 0..K-1")
    return torch.as_tensor(arr.astype(np.int64))


def _check_count(n: int, src: str) -> None:
    if n < MIN_SAMPLES:
        raise source_error(src, f"only {n} transition(s); need at least {MIN_SAMPLES} to fit a GP "
                    "(collect more with `gpmpc collect --samples N`)")


def _check_shapes(x: Tensor, u: Tensor, x_next: Tensor, agent: Tensor | None, src: str) -> None:
    n = x.shape[0]
    for name, arr in (("u", u), ("x_next", x_next)) + ((("agent", agent),) if agent is not None else ()):
        if arr.shape[0] != n:
            raise source_error(src, f"shape mismatch: 'x' has {n} rows but {name!r} has {arr.shape[0]}; "
                        "every array needs one row per transition")
    if x_next.shape[1] != x.shape[1]:
        raise source_error(src, f"shape mismatch: 'x' has D={x.shape[1]} columns but 'x_next' has "
                    f"{x_next.shape[1]}; both are states of the same dimension")
    if x.shape[1] == 0 or u.shape[1] == 0:
        raise source_error(src, "'x' and 'u' need at least one column each")
    _check_count(n, src)


def _check_values(arr: Tensor, name: str, src: str) -> None:
    bad = ~torch.isfinite(arr)
    if bool(bad.any()):
        row = int(bad.any(dim=1).nonzero()[0])
        raise source_error(src, f"array {name!r} has {int(bad.sum())} non-finite value(s) (NaN/inf), "
                    f"first in row {row}; remove or fix those rows")
    big = arr.abs() > MAX_ABS_VALUE
    if bool(big.any()):
        row = int(big.any(dim=1).nonzero()[0])
        raise source_error(src, f"array {name!r} has extreme value {float(arr.abs().max()):.3g} "
                    f"(|value| > {MAX_ABS_VALUE:g}) in row {row}; check the units or the file")


# ---------------------------------------------------------------------- readers
