"""How the package's modules import each other: no cycles (an import inside a function counts,
so a cycle cannot hide there), and each layer imports only the layers to its left
(docs/architecture.md: ndem → scenarios → fields → learn → reduce → adaptive → report, the shared modules
below them all, the command line on top)."""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"
#: The layers in their order; every module of the package belongs to one of them.
LAYERS = ("shared", "ndem", "scenarios", "fields", "learn", "reduce", "adaptive", "report", "cli")
SHARED = {
    "__init__",
    "sweep",
    "terrain",
    "config",
    "runtime",
    "tracking",
    "spool",
    "cluster",
    "cliargs",
    "headline",
    "console",
    "integrity",
}


def _modules(src: Path) -> dict[str, Path]:
    """Dotted module name → file, for every module of the ``dozerlab`` package under ``src``."""
    out = {}
    for path in (src / "dozerlab").rglob("*.py"):
        parts = path.relative_to(src).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def import_graph(src: Path) -> dict[str, set[str]]:
    """Module → the package's modules it imports anywhere in its code (``from pkg import sub``
    counts as importing ``pkg.sub``)."""
    modules = _modules(src)
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for module, path in modules.items():
        package = module if path.name == "__init__.py" else module.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join([*up, base] if base else up)
                targets = [f"{base}.{a.name}" for a in node.names]
                targets = [t if t in modules else base for t in targets]
            else:
                continue
            for target in targets:
                while target and target not in modules:
                    target = target.rpartition(".")[0]
                if target and target != module:
                    graph[module].add(target)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (each a cycle or several)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def layer(module: str) -> int:
    """The place of ``module``'s layer in :data:`LAYERS`."""
    parts = module.split(".")
    if len(parts) == 1 or parts[1] in SHARED:
        return LAYERS.index("shared")
    return LAYERS.index("cli" if parts[1] in ("__main__", "verify") else parts[1])


def test_the_package_has_no_import_cycle():
    graph = import_graph(SRC)
    assert len(graph) > 50, "too few modules found: the scan is broken"
    assert cycles(graph) == []


def test_a_layer_imports_only_the_layers_to_its_left():
    graph = import_graph(SRC)
    upward = sorted(
        f"{m} -> {t}" for m, targets in graph.items() for t in targets if layer(t) > layer(m)
    )
    assert upward == []


def test_the_scan_finds_a_cycle_hidden_inside_a_function(tmp_path):
    package = tmp_path / "dozerlab"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "a.py").write_text("from dozerlab.b import f\n")
    (package / "b.py").write_text("def f():\n    from dozerlab import a\n")
    (package / "c.py").write_text("from . import a\n")
    assert cycles(import_graph(tmp_path)) == [["dozerlab.a", "dozerlab.b"]]
