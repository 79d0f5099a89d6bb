"""The configuration keys as data: name, type, default, allowed values, when each applies and what it
means, read from the schema (:class:`~torch_gpmpc.config.schema.Config`, whose docstrings and rules
are the one source). ``gpmpc keys`` prints them; the docs' configuration reference is built from them.
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass

from torch_gpmpc.config.schema import CONFIG_CONDITIONS, RULES, Config
from torch_gpmpc.config.settings import ControllerSettings


@dataclass(frozen=True)
class ConfigKey:
    """One configuration key.

    Attributes:
        name: the key. type: its annotation as text. default: its default value.
        allowed: its choices or range, as text ("" where any value of its type goes).
        applies: when it matters ("always", or the keys that decide and why).
        meaning: its docstring entry. controller: whether ``ControllerSettings`` has it too.
    """

    name: str
    type: str
    default: object
    allowed: str
    applies: str
    meaning: str
    controller: bool


def config_keys() -> list[ConfigKey]:
    """Every key of :class:`~torch_gpmpc.config.schema.Config`, in declaration order.

    Examples:
        >>> keys = {k.name: k for k in config_keys()}
        >>> keys["admm_coupling"].default, keys["admm_coupling"].allowed
        ('copies', 'copies, planes')
    """
    docs = {**attribute_docs(ControllerSettings), **attribute_docs(Config)}  # a key Config redefines: its text
    controller = set(ControllerSettings.__dataclass_fields__)
    return [ConfigKey(f.name, str(f.type).replace("typing.", "").replace("torch_gpmpc.config.", ""),
                      default_of(f), allowed(f.name), applies(f.name), docs.get(f.name, ""), f.name in controller)
            for f in dataclasses.fields(Config)]


def default_of(field: dataclasses.Field) -> object:
    """A dataclass field's default (its factory's value where it has one)."""
    if field.default is not dataclasses.MISSING:
        return field.default
    return field.default_factory() if field.default_factory is not dataclasses.MISSING else None


def attribute_docs(cls: type) -> dict[str, str]:
    """``name -> text`` of a class docstring's ``Attributes:`` entries (Google style), joined to one line."""
    doc = cls.__doc__ or ""
    block = doc.split("Attributes:", 1)[1].split("\n    Example", 1)[0] if "Attributes:" in doc else ""
    entries: dict[str, list[str]] = {}
    current = None
    for line in block.split("\n"):
        m = re.match(r"^        ([a-z_0-9]+): (.*)$", line)
        if m:
            current = m.group(1)
            entries[current] = [m.group(2)]
        elif current is not None and line.strip():
            entries[current].append(line.strip())
    return {k: " ".join(v) for k, v in entries.items()}


def strip_roles(text: str, quote: str = "") -> str:
    """``text`` with its Sphinx roles (``:class:`~a.b.C```) as their last name, between ``quote``s."""
    return re.sub(r":(?:class|meth|func|mod|data|attr):`~?([^`]*)`",
                  lambda m: f"{quote}{m.group(1).rsplit('.', 1)[-1]}{quote}", text)


def allowed(name: str) -> str:
    """The key's choices or range as text, or "" where the type alone decides."""
    if name in RULES.choices:
        return ", ".join(RULES.choices[name])
    if name in RULES.ranges:
        return RULES.ranges[name][1]
    return ""


def applies(name: str) -> str:
    """When the key matters: "always", or each key that decides and why."""
    rules = CONFIG_CONDITIONS.get(name, ())
    return "; ".join(f"depends on {r.by} (else ignored, with a warning: {r.why})" for r in rules) or "always"
