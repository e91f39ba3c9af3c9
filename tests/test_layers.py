"""The import layers: data flows converters → store → method → jobs → outputs, never back; and
no module imports itself through others (no import circle).

Every import of every module (also those inside functions or under ``TYPE_CHECKING``) is read
from the source with `ast`, so a forbidden import fails here even where no test exercises it.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYERS = {
    # package: module prefixes it must not import
    "bgs_batch/render": ("bgs_batch.slam", "bgs_batch.cli", "bgs_batch.demo", "jobs", "outputs",
                         "converters"),  # fmt: skip
    "bgs_batch/slam": ("bgs_batch.cli", "bgs_batch.demo", "jobs", "outputs", "converters"),
    "converters": ("bgs_batch.slam", "bgs_batch.render", "jobs", "outputs"),
    "jobs": ("bgs_batch.cli", "bgs_batch.demo", "outputs"),
}
PACKAGES = ("bgs_batch", "converters", "jobs", "outputs")


def imported_modules(source: str, package: str) -> set[str]:
    """Absolute names of the modules a module of `package` imports (relative ones resolved)."""
    tree = ast.parse(source)
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                base = f"{parent}.{base}" if base else parent
            names.add(base)  # and each name, which may be a module: `from .. import slam`
            names.update(f"{base}.{alias.name}" for alias in node.names)
    return names


def _package_of(path: Path) -> str:
    return ".".join(path.relative_to(ROOT).parts[:-1])


def _within(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".")


@pytest.mark.parametrize("package", sorted(LAYERS))
def test_no_module_imports_a_later_layer(package):
    sources = sorted((ROOT / package).rglob("*.py"))
    assert sources, f"{package} holds no modules"
    offences = [
        f"{path.relative_to(ROOT)} imports {name}"
        for path in sources
        for name in sorted(imported_modules(path.read_text(), _package_of(path)))
        if any(_within(name, prefix) for prefix in LAYERS[package])
    ]
    assert offences == [], "\n".join(offences)


def module_graph(root: Path = ROOT) -> dict[str, set[str]]:
    """Each module of `PACKAGES` → the modules of `PACKAGES` it imports. An import of one of
    its own parent packages (``from bgs_batch.slam import losses``) adds no edge to that
    package: Python imports a module's parents before the module in any case."""
    imports = {}
    for top in PACKAGES:
        for path in sorted((root / top).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            imports[name] = imported_modules(path.read_text(), _package_of(path))
    return {name: {other for other in found if other in imports and other != name
                   and not _within(name, other)}
            for name, found in imports.items()}  # fmt: skip


def import_circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    circles = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for other in sorted(graph[node]):
            if other not in index:
                visit(other)
                low[node] = min(low[node], low[other])
            elif other in stack:
                low[node] = min(low[node], index[other])
        if low[node] == index[node]:
            component = []
            while not component or component[-1] != node:
                component.append(stack.pop())
            if len(component) > 1:
                circles.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return circles


def test_no_import_circle():
    graph = module_graph()
    assert "jobs.run" in graph and "bgs_batch.slam.pipeline" in graph
    assert import_circles(graph) == []


def test_a_circle_through_three_modules_is_found():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert import_circles(graph) == [["a", "b", "c"]]
    assert import_circles({"a": {"b"}, "b": set()}) == []


def test_the_reader_sees_relative_and_nested_imports():
    source = "from .project import project\nfrom .. import slam\ndef f():\n    import jobs.run\n"
    names = imported_modules(source, "bgs_batch.render")
    assert {"bgs_batch.render.project", "bgs_batch.slam", "jobs.run"} <= names
