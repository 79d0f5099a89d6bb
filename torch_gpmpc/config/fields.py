"""The one validation machinery of the settings dataclasses (:class:`~.schema.Config`,
:class:`~.tune_settings.TuneSettings`): types, finiteness, choices and ranges, and
building from a flat mapping in which an unknown key is named with the nearest valid one.
"""

from __future__ import annotations

import difflib
import math
import typing
import warnings
from dataclasses import dataclass, field, fields
from typing import Any, Callable, Iterable, Mapping

from torch_gpmpc.errors import GpmpcError

#: (predicate, description of the allowed values).
Range = tuple[Callable[[Any], bool], str]


@dataclass(frozen=True)
class Rules:
    """How the fields of one settings class are checked and named in errors.

    Attributes:
        what: the name of one field in messages (``config key``, ``tune setting``).
        prefix: how the user writes a key (``tune.`` for ``--set tune.NAME=VALUE``).
        choices: field -> its allowed values.
        ranges: field -> (predicate, description).
    """

    what: str
    prefix: str = ""
    choices: Mapping[str, tuple] = field(default_factory=dict)
    ranges: Mapping[str, Range] = field(default_factory=dict)


def nearest_key(name: str, keys: Iterable[str], cutoff: float = 0.0) -> str | None:
    """The key in ``keys`` closest to ``name`` (for "did you mean" messages); ``None`` when no key
    is at least ``cutoff`` alike (``difflib``'s ratio; with the default 0 every key is, so a
    non-empty ``keys`` always gives one)."""
    match = difflib.get_close_matches(str(name), list(keys), n=1, cutoff=cutoff)
    return match[0] if match else None


#: Keys that were removed, with why and what to do instead (CHANGELOG.md has the measurements).
REMOVED_KEYS = {
    "admm_acceleration": "Anderson acceleration was removed: it gained nothing in a crowd and lost on the "
                         "random transitions, and the default plane coupling needs no convergence within a step; "
                         "delete the key",
    "admm_anderson_memory": "Anderson acceleration was removed; delete the key",
}


def check_keys(data: Mapping[str, Any], keys: Iterable[str], what: str, prefix: str = "") -> None:
    """Raise on the first key of ``data`` not in ``keys``: a removed key (:data:`REMOVED_KEYS`) with
    what to do, else naming the nearest valid key.

    Raises:
        GpmpcError: ``<what> 'key': <why>; delete the key``, ``unknown <what> 'key'; did you mean
        '<prefix>near'?`` or, with no key alike, ``unknown <what> 'key'; `gpmpc keys` lists them``.
    """
    keys = list(keys)
    for key in data:
        if key in REMOVED_KEYS and key not in keys:
            raise GpmpcError(f"{what} '{prefix}{key}': {REMOVED_KEYS[key]}")
        if key not in keys:
            alike = nearest_key(key, keys, cutoff=0.6)  # difflib's own default: an unrelated key is no hint
            hint = f"did you mean '{prefix}{alike}'?" if alike else "`gpmpc keys` lists them"
            raise GpmpcError(f"unknown {what} '{key}'; {hint}")


def field_types(cls: type) -> dict[str, Any]:
    """Field name -> resolved type annotation of a dataclass."""
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in fields(cls)}


def build(cls: type, data: Mapping[str, Any], rules: Rules):
    """``cls(**data)`` after checking the keys and accepting ints for float fields.

    Raises:
        GpmpcError: unknown key (with the nearest valid key), or what ``validate`` finds.
    """
    types = field_types(cls)
    check_keys(data, types, rules.what, rules.prefix)
    return cls(**{key: _coerce(types[key], value) for key, value in data.items()})


def validate(obj: Any, rules: Rules) -> None:
    """Check every field of ``obj`` against its type, finiteness, choices and ranges.

    Raises:
        GpmpcError: ``<what> '<name>': ...`` naming the field and the allowed values.
    """
    for name, typ in field_types(type(obj)).items():
        value = getattr(obj, name)
        _check_type(rules.what, name, value, typ)
        if isinstance(value, float) and not math.isfinite(value):
            raise GpmpcError(f"{rules.what} '{name}': {value!r} is not finite; give a finite number")
    for name, choices in rules.choices.items():
        if getattr(obj, name) not in choices:
            raise GpmpcError(f"{rules.what} '{name}': {getattr(obj, name)!r} is not one of {', '.join(choices)}")
    for name, (ok, allowed) in rules.ranges.items():
        if not ok(getattr(obj, name)):
            raise GpmpcError(f"{rules.what} '{name}': {getattr(obj, name)!r} is out of range; use {allowed}")


def _coerce(typ: Any, value: Any) -> Any:
    """Accept ints for float fields; leave everything else for the type check."""
    tuple_type = _tuple_type(typ)
    if tuple_type is not None and isinstance(value, (list, tuple)):  # a TOML/JSON/Python list
        item = typing.get_args(tuple_type)[0]
        return tuple(_coerce(item, v) for v in value)
    allowed = typing.get_args(typ) or (typ,)
    if float in allowed and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    return value


def coerce_lists(obj: Any) -> None:
    """Turn every list given for a ``tuple[...]`` (or ``tuple[...] | None``) field of the frozen
    dataclass ``obj`` into a tuple (ints as floats for float items), as ``build`` does for flat
    mappings; call before :func:`validate`."""
    for name, typ in field_types(type(obj)).items():
        if _tuple_type(typ) is not None:
            object.__setattr__(obj, name, _coerce(typ, getattr(obj, name)))


def _tuple_type(typ: Any) -> Any:
    """The ``tuple[X, ...]`` of a field typed ``tuple[X, ...]`` or ``tuple[X, ...] | None``, else ``None``."""
    if typing.get_origin(typ) is tuple:
        return typ
    return next((t for t in typing.get_args(typ) if typing.get_origin(t) is tuple), None)


def _is(base: Any, value: Any) -> bool:
    if base is bool:
        return isinstance(value, bool)
    if base is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if base is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    return isinstance(value, base)


def _check_type(what: str, name: str, value: Any, typ: Any) -> None:
    tuple_type = _tuple_type(typ)
    if tuple_type is not None:  # tuple[int, ...], possibly | None
        item = typing.get_args(tuple_type)[0]
        if (value is None and tuple_type is not typ) or (
                isinstance(value, tuple) and all(_is(item, v) for v in value)):
            return
        none = " or null" if tuple_type is not typ else ""
        raise GpmpcError(f"{what} '{name}': expected a list of {item.__name__}{none}, got {value!r}")
    allowed = typing.get_args(typ) or (typ,)
    if value is None and type(None) in allowed:
        return
    bases = [t for t in allowed if t is not type(None)]
    if not any(_is(base, value) for base in bases):
        expected = " or ".join(base.__name__ for base in bases)
        word = value.strip().lower().lstrip("+-") if isinstance(value, str) else ""
        hint = ("; numbers must be finite, give a large finite one (e.g. 1e9)" if word in ("inf", "infinity")
                else "; numbers must be finite, give a number" if word == "nan" else "")
        raise GpmpcError(f"{what} '{name}': expected {expected}, got {type(value).__name__} {value!r}{hint}")


@dataclass(frozen=True)
class Applies:
    """When a key takes effect: while ``when(settings)`` holds; else it is ignored under the key ``by``
    (``why`` says why). Every key whose effect depends on another key's value declares one."""

    by: str
    when: Callable[[Any], bool]
    why: str


def warn_ignored(obj: Any, conditions: Mapping[str, tuple[Applies, ...]], what: str,
                 defaults: Mapping[str, Any] | None = None) -> None:
    """Warn, naming the key that overrides it, about every key of the frozen dataclass ``obj`` that is
    set to a non-default value its ``conditions`` say does not apply: ``<what> '<key>' is ignored under
    <by>=<value>: <why>``. ``defaults`` replaces the fields' defaults of the keys it names (where a
    null default is filled in at construction)."""
    defaults = {**{f.name: f.default for f in fields(obj)}, **(defaults or {})}
    for key, rules in conditions.items():
        if getattr(obj, key) == defaults[key]:
            continue
        rule = next((r for r in rules if not r.when(obj)), None)
        if rule is not None:
            by = getattr(obj, rule.by)
            shown = getattr(by, "name", by) if by is None or isinstance(by, (str, int, float, bool)) \
                or hasattr(by, "name") else "(a table)"
            warnings.warn(f"{what} '{key}' is ignored under {rule.by}={shown}: {rule.why}", UserWarning,
                          stacklevel=4)
