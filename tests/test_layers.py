"""The import layers: data flows converters → store → method → jobs → outputs, never back.

Every import of every module (also those inside functions) is read from the source with `ast`,
so a forbidden import fails here even where no test exercises it.
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
}


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


def test_the_reader_sees_relative_and_nested_imports():
    source = "from .project import project\nfrom .. import slam\ndef f():\n    import jobs.run\n"
    names = imported_modules(source, "bgs_batch.render")
    assert {"bgs_batch.render.project", "bgs_batch.slam", "jobs.run"} <= names
