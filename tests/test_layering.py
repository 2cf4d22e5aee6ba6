"""The package's layering: every import points down the paper's flow, and nothing loops.

The layers, lowest first (docs/design.md, "Layout"): a module may import its own layer
(within its own package) and the layers below; ``io`` imports only the foundation; the
command line only the pipeline (and what the pipeline's own callers need: io, foundation).
The graph is read from the source with :mod:`ast`: every import counts, module level, in
functions, and under ``TYPE_CHECKING``.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"

#: Layers, lowest first; each is a list of packages or modules (prefixes of dotted names).
LAYERS: tuple[tuple[str, ...], ...] = (
    (
        "amigo._version",
        "amigo.errors",
        "amigo.progress",
        "amigo.cachedir",
        "amigo.runtime",
        "amigo.heap",
        "amigo.niriss",
    ),
    ("amigo.orientation", "amigo.programs"),
    ("amigo.io",),
    ("amigo.processing",),
    ("amigo.model",),
    ("amigo.simulation",),
    ("amigo.likelihood",),
    ("amigo.solvers",),
    ("amigo.fitting", "amigo.training"),
    ("amigo.observables",),
    ("amigo.companions",),
    ("amigo.plots",),
    ("amigo.pipeline",),
    ("amigo.cli",),
    # The package's face (the lazy API) and ``python -m amigo``.
    ("amigo", "amigo.__main__"),
)

#: What some layers may import besides their own package, beyond "anything below".
ONLY: dict[str, tuple[str, ...]] = {
    # Readers and writers know the file formats and the instrument's facts, nothing else.
    "amigo.io": LAYERS[0] + LAYERS[1],
    # Solvers see vectors and matrices, never the instrument.
    "amigo.solvers": LAYERS[0],
    # The command line parses options and calls the pipeline.
    "amigo.cli": (*LAYERS[0], *LAYERS[1], "amigo.io", "amigo.pipeline"),
}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def read_graph(src: Path = SRC) -> dict[str, set[str]]:
    """``{module: modules of amigo it imports}`` for every module under ``src/amigo``."""
    files = {module_name(p): p for p in (src / "amigo").rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for name, path in files.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        targets: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                targets.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")[: len(package.split(".")) - node.level + 1]
                    source = ".".join(base + ([node.module] if node.module else []))
                else:
                    source = node.module or ""
                for alias in node.names:
                    # `from amigo.x import y`: y is the module amigo.x.y if there is one.
                    sub = f"{source}.{alias.name}"
                    targets.add(sub if sub in files else source)
        graph[name] = {t for t in targets if t in files and t != name}
    return graph


def _within(module: str, prefix: str) -> bool:
    """Whether ``module`` is ``prefix`` or inside it (``amigo`` itself holds only itself)."""
    return module == prefix or (prefix != "amigo" and module.startswith(prefix + "."))


def layer_of(module: str) -> int:
    best, rank = -1, -1
    for index, layer in enumerate(LAYERS):
        for prefix in layer:
            if _within(module, prefix) and len(prefix) > best:
                best, rank = len(prefix), index
    if rank < 0:
        raise KeyError(f"{module} is in no layer: add it to LAYERS")
    return rank


def home(module: str) -> str:
    """The layer entry (package or module) that ``module`` belongs to."""
    layer = LAYERS[layer_of(module)]
    return max((p for p in layer if _within(module, p)), key=len)


def violations(graph: dict[str, set[str]]) -> list[str]:
    """Every import that points up the layers or sideways into a peer, and every import
    a restricted layer (:data:`ONLY`) may not make."""
    found = []
    for module, targets in sorted(graph.items()):
        mine = layer_of(module)
        for target in sorted(targets):
            theirs = layer_of(target)
            if theirs > mine or (theirs == mine and home(target) != home(module)):
                found.append(f"{module} -> {target} (up or sideways)")
            allowed = ONLY.get(home(module))
            if allowed is not None and home(target) != home(module):
                if not any(_within(target, a) for a in allowed):
                    found.append(f"{module} -> {target} (not allowed for {home(module)})")
    return found


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    return read_graph()


def test_every_module_has_a_layer(graph):
    homeless = []
    for module in graph:
        try:
            layer_of(module)
        except KeyError:
            homeless.append(module)
    assert len(graph) > 50 and homeless == []


def test_imports_point_down_the_layers(graph):
    assert violations(graph) == []


def test_no_import_cycles(graph):
    assert cycles(graph) == []


def test_an_upward_import_is_caught(graph):
    """The checks above can fail: a reader importing the fitting, a solver importing the
    instrument model, a command reaching past the pipeline, and a loop, each named."""
    bad = {k: set(v) for k, v in graph.items()}
    bad["amigo.io.jwst"].add("amigo.fitting.filter_fit")
    bad["amigo.solvers.levenberg_marquardt"].add("amigo.model.image")
    bad["amigo.cli.fit"].add("amigo.model.base")
    assert violations(bad) == [
        "amigo.cli.fit -> amigo.model.base (not allowed for amigo.cli)",
        "amigo.io.jwst -> amigo.fitting.filter_fit (up or sideways)",
        "amigo.io.jwst -> amigo.fitting.filter_fit (not allowed for amigo.io)",
        "amigo.solvers.levenberg_marquardt -> amigo.model.image (not allowed for amigo.solvers)",
    ]
    bad["amigo.niriss"].add("amigo.errors")
    bad["amigo.errors"].add("amigo.niriss")
    assert ["amigo.errors", "amigo.niriss"] in cycles(bad)


def test_peers_do_not_import_each_other(graph):
    bad = {k: set(v) for k, v in graph.items()}
    bad["amigo.training.trainer"].add("amigo.fitting.filter_fit")
    assert violations(bad) == [
        "amigo.training.trainer -> amigo.fitting.filter_fit (up or sideways)"
    ]
