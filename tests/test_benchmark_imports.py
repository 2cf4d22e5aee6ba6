"""The benchmark scripts still name what the package provides.

Benchmarks run by hand, rarely, and import the package inside their functions; a rename in
``src/amigo`` breaks them silently (``benchmarks/peers.py``, ``simulate.py`` and
``fidelity.py`` imported the simulator's ``PointSource`` for months after it became
``DetectorSource``). Every ``from amigo... import name`` in ``benchmarks/``, at module
level or in a function, is resolved here against the installed package.
"""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def amigo_imports(path: Path) -> list[tuple[int, str, str]]:
    """(line, module, name) of every ``from amigo... import name`` in a script."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if node.module == "amigo" or node.module.startswith("amigo."):
                found += [(node.lineno, node.module, alias.name) for alias in node.names]
    return found


SCRIPTS = sorted(BENCHMARKS.glob("*.py"))


def test_the_benchmarks_are_found() -> None:
    assert len(SCRIPTS) >= 10
    assert sum(len(amigo_imports(p)) for p in SCRIPTS) >= 50


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.name)
def test_benchmark_imports_resolve(script: Path) -> None:
    missing = []
    for line, module_name, name in amigo_imports(script):
        module = importlib.import_module(module_name)
        if not hasattr(module, name):
            try:  # a submodule: ``from amigo.model import bandpass``
                importlib.import_module(f"{module_name}.{name}")
            except ModuleNotFoundError:
                missing.append(f"{script.name}:{line}: {module_name} has no {name!r}")
    assert not missing, "\n".join(missing)
