"""Griffe extension of the API reference: amigo's reST markup, read as Markdown.

amigo's docstrings are written for ``help()`` and Sphinx-minded readers: they name other
objects with reST roles (``:func:`~amigo.io.calvis.read_calvis```) and introduce literal
blocks with ``::``. mkdocstrings renders Markdown, where a role would show as
``:func:`` followed by code. While the site is built (the sources are not touched), each
role becomes a link to the object's entry in the reference, shown as code (``~``: its
last name only), or plain code where the reference has no entry for it (another
package's object, a private one); a ``::`` that ends a paragraph becomes ``:``, and a
reST simple table (columns under ``=====  =====`` rules) a Markdown table. Constants
documented by ``#:`` comments above them (Sphinx's convention, which griffe does not
read) get those comments as their docstrings, so that they appear in the reference.
"""

from __future__ import annotations

import re
from typing import Any

import griffe

#: ``:role:`target``` or ``:role:`title <target>```, with Sphinx's ``~``, ``!`` and ``.``.
ROLE = re.compile(
    r":(?:py:)?(?:func|class|mod|data|attr|meth|obj|exc|const|type):`(?P<body>[^`]+)`"
)
#: A paragraph's closing ``::`` (reST: the indented block that follows is literal).
LITERAL = re.compile(r"(?<=\S)::[ \t]*$", flags=re.MULTILINE)
BARE_LITERAL = re.compile(r"^[ \t]*::[ \t]*$", flags=re.MULTILINE)
#: A reST simple table with a header: three rules of ``=`` columns, the same each time.
TABLE = re.compile(
    r"^(?P<rule>=+(?: +=+)+)[ \t]*\n(?P<head>(?:.+\n)+?)(?P=rule)[ \t]*\n"
    r"(?P<body>(?:.+\n)+?)(?P=rule)[ \t]*$",
    flags=re.MULTILINE,
)


def _identifier(target: str, obj: griffe.Object) -> str:
    """Full path of ``target`` as seen from ``obj``'s docstring (Sphinx's search order:
    the object, its parents up to the module; else ``target`` as written)."""
    if target.startswith("amigo"):
        return target
    head, _, rest = target.partition(".")
    scope: Any = obj
    while scope is not None:
        if not scope.is_alias and head in scope.members:
            member = scope.members[head]
            path = member.target_path if member.is_alias else member.path
            return f"{path}.{rest}" if rest else path
        scope = scope.parent
    return target


def _link(match: re.Match[str], obj: griffe.Object) -> str:
    body = match["body"].strip()
    explicit = re.fullmatch(r"(?P<title>.+?)\s*<(?P<target>[^<>]+)>", body)
    target = (explicit["target"] if explicit else body).strip()
    plain = target.startswith("!")
    target = target.lstrip("!~.")
    if explicit:
        title = explicit["title"]
    elif body.lstrip("!").startswith("~"):
        title = target.split(".")[-1]
    else:
        title = target
    code = f"<code>{title}</code>"
    if plain:
        return code
    return f'<autoref identifier="{_identifier(target, obj)}" optional>{code}</autoref>'


def _table(match: re.Match[str]) -> str:
    """A reST simple table as a Markdown table (cells cut at the rules' column starts)."""
    starts = [m.start() for m in re.finditer(r"=+", match["rule"])]
    bounds = [*zip(starts, [*starts[1:], None], strict=True)]

    def row(line: str) -> str:
        return "| " + " | ".join(line[a:b].strip() for a, b in bounds) + " |"

    head = [row(line) for line in match["head"].splitlines()]
    body = [row(line) for line in match["body"].splitlines()]
    rule = "|" + "---|" * len(bounds)
    return "\n".join([*head[:1], rule, *body])


def markdown(text: str, obj: griffe.Object) -> str:
    """``text`` (a docstring of ``obj``) with roles and literal markers as Markdown."""
    text = ROLE.sub(lambda m: _link(m, obj), text)
    text = TABLE.sub(_table, text)
    text = BARE_LITERAL.sub("", text)
    return LITERAL.sub(":", text)


def _comment_docstring(obj: griffe.Object) -> str | None:
    """The ``#:`` comment lines right above an attribute's assignment, as text."""
    try:
        lines = obj.lines_collection[obj.filepath]
    except (KeyError, TypeError, ValueError):
        return None
    if not obj.lineno:
        return None
    found: list[str] = []
    index = obj.lineno - 2  # the line above the assignment (linenos start at 1)
    while index >= 0 and lines[index].lstrip().startswith("#:"):
        found.insert(0, lines[index].lstrip()[2:].strip())
        index -= 1
    return "\n".join(found) or None


def _objects(obj: griffe.Object):
    yield obj
    for member in obj.members.values():
        if not member.is_alias:
            yield from _objects(member)


class RstToMarkdown(griffe.Extension):
    """Rewrite the docstrings of a loaded package (see the module's notes)."""

    def on_package(self, *, pkg: griffe.Module, **kwargs: Any) -> None:
        for obj in _objects(pkg):
            if obj.docstring is None and obj.is_attribute:
                comment = _comment_docstring(obj)
                if comment:
                    obj.docstring = griffe.Docstring(comment, parent=obj)
            if obj.docstring is not None:
                obj.docstring.value = markdown(obj.docstring.value, obj)
