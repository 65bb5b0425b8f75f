"""The API reference's reading of the package's docstrings (a griffe extension that mkdocs.yml loads).

The docstrings write a parameter as ``name : what it is`` on one line, where numpy's style wants the type
there and the description below it; and they refer to names with Sphinx roles (``:class:`~a.b.C```),
which Markdown does not know. Before griffe parses a docstring, each such line becomes ``name`` with its
description indented under it (the type then comes from the signature's annotation), and each role the
name in code.
"""

from __future__ import annotations

import re
from typing import Any

import griffe

_SECTIONS = ("Parameters", "Attributes")
_ENTRY = re.compile(r"^(?P<names>[A-Za-z_][\w, ]*?) : (?P<what>.+)$")
_ROLE = re.compile(r":(?:class|func|data|attr|meth|mod|exc):`~?(?:[\w.]*\.)?(?P<name>\w+)`")


def rewrite(text: str) -> str:
    """``text`` with its entries under Parameters/Attributes split as numpy's style reads them, its roles as code."""
    out: list[str] = []
    section = None
    lines = text.splitlines()
    for i, line in enumerate(lines):
        underline = i + 1 < len(lines) and set(lines[i + 1].strip()) == {"-"}
        if underline:
            section = line.strip()
        elif not line.strip():
            pass
        elif section in _SECTIONS and not line.startswith(" "):
            entry = _ENTRY.match(line)
            if entry:
                out += [entry["names"], "    " + entry["what"]]
                continue
        out.append(line)
    return _ROLE.sub(lambda m: f"`{m['name']}`", "\n".join(out))


class LooseNumpy(griffe.Extension):
    """Rewrites every docstring as :func:`rewrite` says, before griffe parses it."""

    def on_instance(self, *, node: Any, obj: griffe.Object, agent: Any, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = rewrite(obj.docstring.value)
