"""Agent dynamics: the nominal model f, the vortex wind g and the true system.

True system (paper eq. 1): ``x' = f(x, u) + g(x) + w`` with ``f(x, u) = A x + B u``,
``A = I``, ``B = 0.1 I`` and ``w ~ N(0, s^2 I)``. Other linear models (the double
integrator, a model file) keep ``f`` general and put ``g`` and ``w`` on their residual rows.

The wind (paper eq. 32) in 2D is ``g(x) = scale * [sin(x_2), cos(x_1)]``. In 3D we
extend it by a vertical component ``scale * sin(x_1) cos(x_2)`` (an updraft pattern
over the same vortex cells); the horizontal components are unchanged.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from torch import Tensor

from torch_gpmpc.config.model_spec import ModelSpec, single_integrator
from torch_gpmpc.errors import GpmpcError


class SpecSizes:
    """Sizes and position of a model read from its ``spec`` (a :class:`ModelSpec`): shared by
    :class:`NominalModel` and a mixed team's :class:`~torch_gpmpc.dynamics.team.TeamNominal`."""

    spec: ModelSpec

    @property
    def dim(self) -> int:
        """State dimension n."""
        return self.spec.state_dim

    @property
    def input_dim(self) -> int:
        """Input dimension m."""
        return self.spec.input_dim

    @property
    def position(self) -> list[int]:
        """State indices of the position (P of them)."""
        return list(self.spec.position)

    def positions(self, x: Tensor) -> Tensor:
        """Positions of states: (..., n) -> (..., P)."""
        return x[..., self.position]

    @property
    def input_memory_rows(self) -> list[int]:
        """State rows that hold the last applied input (:attr:`ModelSpec.input_memory`)."""
        return [row for row, _ in self.spec.input_memory]


class NominalModel(SpecSizes):
    """The known linear model ``f(x, u) = A x + B u`` of one agent, from a :class:`ModelSpec`.

    Besides A and B it knows which states are the position (collision rows, references,
    arrival), which rows have a residual (one GP each) and which state and input columns
    the GPs read. ``NominalModel(2)`` is the paper's single integrator in 2D.

    Args:
        spec: the model description, or an int ``dim`` for the paper's model in ``dim`` dimensions.
        dim, a, b: the single integrator ``A = a I``, ``B = b I`` in ``dim`` dimensions (when
            ``spec`` is not given; the paper: a = 1, b = 0.1).

    Examples:
        >>> import torch
        >>> from torch_gpmpc import ModelSpec, NominalModel
        >>> f = NominalModel(ModelSpec.double_integrator(dim=2, dt=0.1))
        >>> x = torch.tensor([0.0, 0.0, 1.0, 0.0], dtype=torch.float64)   # at the origin, moving along x
        >>> f(x, torch.zeros(2, dtype=torch.float64)).tolist()
        [0.1, 0.0, 1.0, 0.0]
        >>> f.position, f.residual
        ([0, 1], [2, 3])
    """

    def __init__(self, spec: ModelSpec | int | None = None, dim: int | None = None, a: float = 1.0,
                 b: float = 0.1) -> None:
        if spec is None or isinstance(spec, int):
            si = single_integrator(dim or spec or 2, u_max=2.0, b=b)
            spec = dataclasses.replace(si, A=tuple(tuple(a * v for v in r) for r in si.A))
        self.spec = spec
        self._A = torch.tensor(self.spec.A, dtype=torch.float64)
        self._B = torch.tensor(self.spec.B, dtype=torch.float64)

    def __repr__(self) -> str:
        return f"NominalModel({self.spec.name!r}, n={self.dim}, m={self.input_dim})"

    def __eq__(self, other: object) -> bool:  # by value: solvers are cached per model
        return isinstance(other, NominalModel) and other.spec == self.spec

    def __hash__(self) -> int:
        return hash(self.spec)

    @property
    def residual(self) -> list[int]:
        """State indices with a residual (R of them, one GP each)."""
        return list(self.spec.residual)

    def A(self, dtype: torch.dtype = torch.float64, device=None) -> Tensor:
        """State matrix, shape (n, n)."""
        return self._A.to(dtype=dtype, device=device)

    def B(self, dtype: torch.dtype = torch.float64, device=None) -> Tensor:
        """Input matrix, shape (n, m)."""
        return self._B.to(dtype=dtype, device=device)

    def residual_embedding(self, dtype: torch.dtype = torch.float64, device=None) -> Tensor:
        """E, shape (n, R): ``E r`` puts a residual vector onto its state rows."""
        E = torch.zeros(self.dim, len(self.spec.residual), dtype=dtype, device=device)
        E[self.residual, torch.arange(len(self.spec.residual))] = 1.0
        return E

    def gp_selectors(self, dtype: torch.dtype = torch.float64, device=None) -> tuple[Tensor, Tensor]:
        """``(S_x (Din, n), S_u (Din, m))``: the GP input is ``S_x x + S_u u``."""
        Sx = torch.zeros(len(self.spec.gp_inputs), self.dim, dtype=dtype, device=device)
        Su = torch.zeros(len(self.spec.gp_inputs), self.input_dim, dtype=dtype, device=device)
        for i, col in enumerate(self.spec.gp_inputs):
            (Sx if col[0] == "x" else Su)[i, int(col[1:])] = 1.0
        return Sx, Su

    @property
    def gp_uses_input(self) -> bool:
        """Whether some GP input column is an input ``u_j``."""
        return any(col.startswith("u") for col in self.spec.gp_inputs)

    def gp_input(self, x: Tensor, u: Tensor | None) -> Tensor:
        """GP inputs, shape (..., Din), from states (..., n) and inputs (..., m) (``u`` may be
        ``None`` when no GP input column is an input)."""
        cols = []
        for col in self.spec.gp_inputs:
            src = x if col[0] == "x" else u
            cols.append(src[..., int(col[1:])])
        return torch.stack(cols, dim=-1)

    def states_at(self, positions: Tensor) -> Tensor:
        """States at rest at ``positions`` (..., P): the position set, every other state 0; (..., n).

        Raises:
            GpmpcError: when the last dimension of ``positions`` is not P.
        """
        if positions.ndim < 1 or positions.shape[-1] != len(self.position):
            raise GpmpcError(f"states_at: positions must have shape (..., {len(self.position)}) (the model's position "
                             f"states {list(self.position)}), got {tuple(positions.shape)}")
        x = positions.new_zeros(*positions.shape[:-1], self.dim)
        x[..., self.position] = positions
        return x

    def rate_states(self) -> list[tuple[int, int, float]]:
        """``(p, v, a)`` for each state ``v`` (not a position) that drives a position ``p`` through
        ``A[p, v] = a != 0``: a velocity of the double integrator (``a = dt``)."""
        pos = set(self.position)
        out = []
        for p in self.position:
            for v in range(self.dim):
                a = self.spec.A[p][v]
                if v not in pos and a != 0.0:
                    out.append((p, v, a))
        return out

    def momentum(self, num_agents: int) -> Tensor:
        """(K,) bool: whether each of K agents of this model has momentum (a state that drives its
        position, :meth:`rate_states`), so that it cannot stop at once."""
        return torch.full((num_agents,), bool(self.rate_states()), dtype=torch.bool)

    def reference_states(self, path: Tensor) -> Tensor:
        """State references from position references (..., S, P) -> (..., S, n).

        Positions follow the path. A state that drives a position (a velocity, see
        :meth:`rate_states`) follows the path's finite difference ``(p_{s+1} - p_s) / a``
        (the last point holds the previous one's); every other state is referenced at 0.
        """
        ref = self.states_at(path)
        if path.shape[-2] < 2:
            return ref
        step = torch.diff(path, dim=-2)
        step = torch.cat([step, step[..., -1:, :]], dim=-2)
        for p, v, a in self.rate_states():
            ref[..., v] = step[..., self.position.index(p)] / a
        return ref

    def project(self, u: Tensor) -> Tensor:
        """Inputs (..., m) projected onto the model's input bounds (:func:`project_input`)."""
        return project_input(u, self.spec)

    def gp_targets(self, x: Tensor, u: Tensor, x_next: Tensor) -> tuple[Tensor, Tensor]:
        """GP inputs (..., Din) and residual targets ``[x' - A x - B u]_R`` (..., R) of transitions
        x -> x_next (..., n) under inputs u (..., m)."""
        return self.gp_input(x, u), (x_next - self(x, u))[..., self.residual]

    def __call__(self, x: Tensor, u: Tensor) -> Tensor:
        """Nominal next state ``A x + B u``: x (..., n), u (..., m) -> (..., n)."""
        return x @ self.A(x.dtype, x.device).T + u @ self.B(x.dtype, x.device).T


@dataclass(frozen=True)
class VortexWind:
    """The unknown residual ``g`` of the paper (eq. 32), optionally in 3D.

    Attributes:
        scale: amplitude (paper: 0.1).

    Examples:
        >>> import torch
        >>> from torch_gpmpc import VortexWind
        >>> VortexWind(0.1)(torch.zeros(1, 2, dtype=torch.float64)).tolist()   # [0.1 sin(0), 0.1 cos(0)]
        [[0.0, 0.1]]
    """

    scale: float = 0.1

    def __call__(self, x: Tensor) -> Tensor:
        """Wind at states ``x``.

        Args:
            x: states, shape (..., D) with D in {2, 3}.

        Returns:
            g(x), shape (..., D).
        """
        parts = [self.scale * torch.sin(x[..., 1]), self.scale * torch.cos(x[..., 0])]
        if x.shape[-1] == 3:
            parts.append(self.scale * torch.sin(x[..., 0]) * torch.cos(x[..., 1]))
        elif x.shape[-1] != 2:
            raise ValueError(f"VortexWind is defined for D = 2 or 3, got D = {x.shape[-1]}")
        return torch.stack(parts, dim=-1)

    def jacobian(self, x: Tensor) -> Tensor:
        """Closed-form Jacobian dg/dx.

        Args:
            x: states, shape (n, D).

        Returns:
            Jacobians, shape (n, D, D); entry [i, d, e] = d g_d / d x_e at x[i].
        """
        n, dim = x.shape
        jac = x.new_zeros(n, dim, dim)
        jac[:, 0, 1] = self.scale * torch.cos(x[:, 1])
        jac[:, 1, 0] = -self.scale * torch.sin(x[:, 0])
        if dim == 3:
            jac[:, 2, 0] = self.scale * torch.cos(x[:, 0]) * torch.cos(x[:, 1])
            jac[:, 2, 1] = -self.scale * torch.sin(x[:, 0]) * torch.sin(x[:, 1])
        return jac


#: The paper's sampling time; the wind's effect on the residual rows scales with dt / PAPER_DT.
PAPER_DT = 0.1


@dataclass(frozen=True)
class TrueSystem:
    """``x' = f(x, u) + E (dt / 0.1) g(p) + E w``, ``w ~ N(0, noise_std^2 I_R)``.

    The wind ``g`` depends on the position ``p`` and acts on the residual rows ``E`` (R of them,
    R = P). For the paper's single integrator this is eq. 1 exactly. For the double integrator
    it is an acceleration ``(g(p) / 0.1)`` on the velocity rows, so a velocity change of
    ``dt g(p) / 0.1`` per step: at dt = 0.1 the same share of the input authority as the paper's.

    Attributes:
        nominal: the known model f.
        wind: the unknown residual g.
        noise_std: standard deviation of each noise component (on the residual rows).
        turned: the wind turned 90 degrees about the vertical axis, ``(g_1, g_2, g_3) ->
            (-g_2, g_1, g_3)`` (``wind_change_step``; :class:`~torch_gpmpc.dynamics.plants.ModelPlant`).

    Examples:
        >>> import torch
        >>> from torch_gpmpc import NominalModel, TrueSystem, VortexWind
        >>> plant = TrueSystem(NominalModel(2), VortexWind(0.1), noise_std=0.0)
        >>> x = torch.zeros(1, 2, dtype=torch.float64)
        >>> plant.step(x, torch.ones(1, 2, dtype=torch.float64)).tolist()   # x + 0.1 u + g(x)
        [[0.1, 0.2]]
    """

    nominal: NominalModel
    wind: VortexWind
    noise_std: float = 0.1
    turned: bool = False

    @property
    def wind_gain(self) -> float:
        """How the wind enters the residual rows: ``dt / PAPER_DT``."""
        return self.nominal.spec.dt / PAPER_DT

    def residual(self, x: Tensor) -> Tensor:
        """The true (noise-free) residual on the residual rows: states (..., n) -> (..., R)."""
        if self.wind.scale == 0.0:
            return x.new_zeros(*x.shape[:-1], len(self.nominal.residual))
        g = self.wind_gain * self.wind(self.nominal.positions(x))
        if self.turned:
            g = torch.cat([-g[..., 1:2], g[..., 0:1], g[..., 2:]], dim=-1)
        return g

    def step(self, x: Tensor, u: Tensor, noise: Tensor | None = None,
             generator: torch.Generator | None = None) -> Tensor:
        """One step of the true system.

        Args:
            x: states, shape (..., n).
            u: inputs, shape (..., m).
            noise: standard-normal draws, shape (..., R), scaled by ``noise_std`` here;
                drawn from ``generator`` when ``None``.
            generator: source of the noise (seeded by the caller for reproducibility).

        Returns:
            next states, shape (..., n).
        """
        R = len(self.nominal.residual)
        if noise is None:
            noise = torch.randn((*x.shape[:-1], R), generator=generator, dtype=x.dtype, device=x.device)
        E = self.nominal.residual_embedding(x.dtype, x.device)
        return self.nominal(x, u) + (self.residual(x) + self.noise_std * noise) @ E.T


def make_system(dim: int | ModelSpec = 2, noise_std: float = 0.1, wind_scale: float = 0.1) -> TrueSystem:
    """The true system of a model (default: the paper's, A = I, B = 0.1 I, in ``dim`` dimensions).

    Raises:
        GpmpcError: when the wind is on but the model has no R = P residual rows in 2D or 3D.
    """
    nominal = NominalModel(dim)
    P, R = len(nominal.position), len(nominal.residual)
    if wind_scale > 0 and (P != R or P not in (2, 3)):
        raise GpmpcError(f"model {nominal.spec.name!r}: the vortex wind acts on the residual rows from a 2D or 3D "
                         f"position, so it needs len(residual) == len(position) in (2, 3) (got {R} and {P}); "
                         "set wind_scale=0 or change the model")
    return TrueSystem(nominal, VortexWind(scale=wind_scale), noise_std=noise_std)


def system_from_config(cfg) -> TrueSystem:
    """The true system of a run configuration (its ``model``, ``noise_std`` and ``wind_scale``) of
    one model (a mixed team's: :func:`~torch_gpmpc.dynamics.team.team_system_from_config`).

    With ``plant = rotorpy`` the model's own world is not flown (only its nominal part plans), so
    the vortex wind is left out and any residual rows are allowed.
    """
    wind_scale = 0.0 if getattr(cfg, "plant", "model") == "rotorpy" else cfg.wind_scale
    if getattr(cfg, "models", None) is not None and cfg.team().is_mixed:
        raise GpmpcError("config key 'models': a mixed team has one system per model; build it with "
                         "torch_gpmpc.dynamics.team.team_system_from_config")
    return make_system(cfg.model_spec(), cfg.noise_std, wind_scale)


def project_input(u: Tensor, spec: ModelSpec) -> Tensor:
    """Inputs (..., m) projected onto the model's bounds (box, then norm ball: scaling towards 0 keeps
    a symmetric box) before they are applied."""
    if spec.input_box is not None:
        box = torch.tensor(spec.input_box, dtype=u.dtype, device=u.device)
        u = torch.maximum(torch.minimum(u, box), -box)
    return u if spec.input_norm is None else clip_norm(u, spec.input_norm)


def clip_norm(u: Tensor, u_max: float) -> Tensor:
    """Project inputs (..., Du) onto the ball ``||u|| <= u_max`` (guards solver tolerance and
    fallback plans before an input is applied to the system)."""
    norm = u.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    return u * torch.clamp(u_max / norm, max=1.0)
