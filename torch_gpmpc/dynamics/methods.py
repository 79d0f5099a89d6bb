"""The controller methods of the paper's Table 1: a dynamics model times a collision rule.

:class:`Method` is parsed once from the config string (``cfg.method``); everything
downstream asks it questions (``method.chance``, ``method.needs_gp``) instead of
parsing the string again.
"""

from __future__ import annotations

import enum

from torch_gpmpc.config.settings import METHOD_NAMES
from torch_gpmpc.errors import GpmpcError


class Dynamics(enum.Enum):
    """What an agent knows of its residual dynamics ``g``."""

    NOMINAL = "nominal"  # nothing: g = 0
    NONLINEAR = "nonlinear"  # the true wind, linearized along the plan like the GP mean
    GP = "gp"  # its learned residual GP's mean, linearized along the plan


class Method(enum.Enum):
    """A row of Table 1: dynamics x (deterministic | chance) collision constraint."""

    NOMINAL = "nominal"
    NOMINAL_CHANCE = "nominal-chance"
    NONLINEAR = "nonlinear"
    NONLINEAR_CHANCE = "nonlinear-chance"
    GP = "gp"
    GP_CHANCE = "gp-chance"

    @classmethod
    def parse(cls, name: "str | Method") -> "Method":
        """The method called ``name`` (a :class:`Method` passes through).

        Raises:
            GpmpcError: unknown name, listing the valid ones.
        """
        if isinstance(name, Method):
            return name
        try:
            return cls(name)
        except ValueError:
            raise GpmpcError(f"method: unknown method {name!r}; choose from {', '.join(METHOD_NAMES)}") from None

    @property
    def dynamics(self) -> Dynamics:
        """The dynamics model of this method."""
        return Dynamics(self.value.removesuffix("-chance"))

    @property
    def chance(self) -> bool:
        """Whether collision rows carry a chance margin (eq. 24)."""
        return self.value.endswith("-chance")

    @property
    def needs_gp(self) -> bool:
        """Whether the method uses a residual GP: for its dynamics or for its margins'
        variance (chance variants of ``nominal``/``nonlinear`` take sigma from the GP, as in
        the paper)."""
        return self.dynamics is Dynamics.GP or self.chance

    @property
    def needs_wind(self) -> bool:
        """Whether the method is given the true wind (the ``nonlinear`` baselines)."""
        return self.dynamics is Dynamics.NONLINEAR


# the configuration layer lists the names (it imports no later layer); the enum must agree
assert tuple(m.value for m in Method) == METHOD_NAMES, "Method and config.settings.METHOD_NAMES disagree"
