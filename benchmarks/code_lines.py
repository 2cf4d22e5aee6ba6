"""Lines of code of a module or of one function or class in it (used by the dependency
benchmarks, benchmarks/solvers.py and benchmarks/dlux.py).

A line counts when it holds a Python token that is neither a comment nor part of a
docstring: blank lines, comment lines and docstrings are left out, so the count is of the
lines a reader must check.

    python benchmarks/code_lines.py src/amigo/companions/fit.py levenberg_marquardt
"""

from __future__ import annotations

import ast
import io
import sys
import tokenize
from pathlib import Path

_LAYOUT = {tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT}


def _docstring_lines(tree: ast.AST) -> set[int]:
    """Line numbers covered by the docstrings of the module, its classes and functions."""
    lines: set[int] = set()
    for node in ast.walk(tree):
        if not isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
            continue
        body = node.body
        if (
            body
            and isinstance(body[0], ast.Expr)
            and isinstance(body[0].value, ast.Constant)
            and isinstance(body[0].value.value, str)
        ):
            first = body[0]
            lines.update(range(first.lineno, (first.end_lineno or first.lineno) + 1))
    return lines


def code_lines(path: str | Path, name: str | None = None) -> int:
    """Code lines of the file at ``path``, or of its top-level function or class ``name``
    (decorators included)."""
    source = Path(path).read_text()
    tree = ast.parse(source)
    first, last = 1, len(source.splitlines())
    if name is not None:
        for node in tree.body:
            if getattr(node, "name", None) == name:
                decorators = getattr(node, "decorator_list", [])
                first = min([node.lineno, *(d.lineno for d in decorators)])
                last = node.end_lineno or node.lineno
                break
        else:
            raise LookupError(f"{name} is not defined at the top level of {path}")
    skip = _docstring_lines(tree)
    counted: set[int] = set()
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type in _LAYOUT or token.type == tokenize.ENDMARKER:
            continue
        for line in range(token.start[0], token.end[0] + 1):
            if first <= line <= last and line not in skip:
                counted.add(line)
    return len(counted)


if __name__ == "__main__":
    print(code_lines(sys.argv[1], sys.argv[2] if len(sys.argv) > 2 else None))
