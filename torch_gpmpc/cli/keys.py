"""``gpmpc keys [WORD]``: the configuration keys with their defaults, allowed values, when each applies
and what it means (:func:`~torch_gpmpc.config.reference.config_keys`), in the terminal."""

from __future__ import annotations

import argparse
import sys
import textwrap

from torch_gpmpc.config.reference import ConfigKey, config_keys, strip_roles


def main(args: argparse.Namespace) -> int:
    """Print the key named ``args.word``, else every key whose name or meaning contains it (all keys
    without it); 2 if none does."""
    word = (args.word or "").lower()
    keys = [k for k in config_keys() if k.name == word] or \
        [k for k in config_keys() if word in k.name.lower() or word in k.meaning.lower()]
    if not keys:
        print(f"gpmpc keys: no config key mentions {args.word!r}; `gpmpc keys` lists them all", file=sys.stderr)
        return 2
    print("\n\n".join(describe(k) for k in keys))
    return 0


def describe(key: ConfigKey, width: int = 100) -> str:
    """A key as a few lines: ``name = default  (type)``, then what it means, its allowed values and when
    it applies, indented."""
    lines = [f"{key.name} = {key.default!r}  ({key.type})"]
    body = [plain(key.meaning)]
    if key.allowed:
        body.append(f"allowed: {key.allowed}")
    if key.applies != "always":
        body.append(f"applies: {key.applies}")
    for text in body:
        lines += textwrap.wrap(text, width, initial_indent="    ", subsequent_indent="    ")
    return "\n".join(lines)


def plain(text: str) -> str:
    """Docstring markup as plain text: double backquotes and Sphinx roles dropped."""
    return strip_roles(text).replace("``", "")
