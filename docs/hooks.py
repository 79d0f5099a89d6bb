"""MkDocs hook: the docstrings cross-reference in Sphinx roles (``:class:`~a.b.C```), which mkdocstrings
shows as written; render them as plain code names."""

from __future__ import annotations

import re

_ROLE = re.compile(r":(?:class|meth|func|mod|data|attr|obj|exc):<code>(~?)([^<]*)</code>")


def _name(match: re.Match) -> str:
    tilde, target = match.group(1), match.group(2)
    if " &lt;" in target:  # :meth:`shown text <full.target>`: the shown text
        return f"<code>{target.split(' &lt;', 1)[0]}</code>"
    return f"<code>{target.rsplit('.', 1)[-1] if tilde else target}</code>"


def on_page_content(html: str, **kwargs) -> str:  # noqa: D103 - the MkDocs hook
    return _ROLE.sub(_name, html)
