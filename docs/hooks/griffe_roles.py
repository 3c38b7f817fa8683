"""Griffe extension for the Python API pages: oga's numpydoc docstrings use Sphinx's roles
(``:func:`oga.optimize```) and literal blocks (a paragraph ending ``::``), which Markdown
does not know. Shown as code spans and code blocks instead. Loaded by mkdocstrings
(``mkdocs.yml``); the docstrings themselves are left as they are.
"""

from __future__ import annotations

import re

import griffe

ROLE = re.compile(r":(?:py:)?(?:func|meth|class|mod|data|attr|obj|exc|const|ref|term)"
                  r":`~?([^`]+)`")
LITERAL = re.compile(r"(\S)::[ \t]*$", re.MULTILINE)


def plain(text: str) -> str:
    """A docstring's text with its Sphinx roles as code spans and ``::`` as ``:``."""
    return LITERAL.sub(r"\1:", ROLE.sub(r"`\1`", text))


class SphinxRoles(griffe.Extension):
    """Rewrite each docstring as :func:`plain` says, when its object is loaded."""

    def on_instance(self, *, obj: griffe.Object, **kwargs) -> None:
        if obj.docstring is not None:
            obj.docstring.value = plain(obj.docstring.value)
