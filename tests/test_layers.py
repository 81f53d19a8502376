"""The package's layers: every import points down a layer (or stays in its folder), and no module imports
itself round a circle. Imports are read with ``ast``, lazy ones and ``TYPE_CHECKING`` ones included."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "elicit_diffrender"

# Each layer and the layers it may import, bottom to top (a module may always import from its own folder).
# ``kernels/`` and ``scenes/`` (top-level folders installed as elicit_diffrender.kernels and .scenes) sit
# outside the ladder: only ``model`` calls the kernels, and the shipped rigs are data files.
OUTSIDE = {"kernels": ROOT / "kernels", "scenes": ROOT / "scenes"}
MAY_IMPORT: dict[str, set[str]] = {
    "kernels": set(),
    "scenes": set(),
    "core": set(),
    "body": {"core"},
    "data": {"body", "core"},
    "model": {"data", "body", "core", "kernels"},
    "inputs": {"model", "data", "body", "core"},
    "fit": {"model", "data", "body", "core"},
    "outputs": {"model", "data", "body", "core"},
    "apps": {"inputs", "fit", "outputs", "model", "data", "body", "core"},
}
MAX_TOP_LEVEL_MODULES = 10


def package_modules(root: Path, package: str, extra: dict[str, Path]) -> dict[str, Path]:
    """Dotted module name -> file, for the package under ``root`` and the extra folders installed inside it."""
    modules = {}
    folders = {package: root / package, **{f"{package}.{name}": path for name, path in extra.items()}}
    for prefix, folder in folders.items():
        for path in sorted(folder.rglob("*.py")):
            parts = path.relative_to(folder).with_suffix("").parts
            name = ".".join((prefix, *parts))
            modules[name.removesuffix(".__init__")] = path
    return modules


def imports_of(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The package's modules that ``name`` imports anywhere in its file (a package counts as its ``__init__``)."""
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            targets = [f"{target}.{alias.name}" for alias in node.names] + [target]
        elif isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        else:
            continue
        for target in targets:
            while target and target not in modules:
                target = target.rpartition(".")[0]
            if target and target != name:
                found.add(target)
    return found


def layer_of(name: str, package: str) -> str:
    """The layer folder of a module (``""`` for the package's own ``__init__``)."""
    parts = name.split(".")
    return parts[1] if len(parts) > 1 and name != package else ""


def layer_violations(graph: dict[str, set[str]], package: str, rules: dict[str, set[str]]) -> list[str]:
    """Each import that leaves its folder for a layer it may not import, and each module outside every layer."""
    out = []
    for name, targets in sorted(graph.items()):
        layer = layer_of(name, package)
        if layer not in rules:
            if layer:
                out.append(f"{name} lies in no layer ({layer}/ is not in MAY_IMPORT)")
            continue
        for target in sorted(targets):
            other = layer_of(target, package)
            if other and other != layer and other not in rules[layer]:
                out.append(f"{name} imports {target}: {layer}/ may not import {other}/")
    return out


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected groups of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    groups = []

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
            group = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                groups.append(sorted(group))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return groups


def import_graph(root: Path, package: str, extra: dict[str, Path]) -> dict[str, set[str]]:
    modules = package_modules(root, package, extra)
    return {name: imports_of(name, path, modules) for name, path in modules.items()}


def project_graph() -> dict[str, set[str]]:
    return import_graph(ROOT, PACKAGE, OUTSIDE)


def test_every_import_points_down_a_layer():
    assert layer_violations(project_graph(), PACKAGE, MAY_IMPORT) == []


def test_no_import_circle():
    assert circles(project_graph()) == []


def test_few_modules_at_the_top_and_every_folder_says_its_layer():
    top = [p.name for p in (ROOT / PACKAGE).glob("*.py")]
    assert len(top) <= MAX_TOP_LEVEL_MODULES, top
    for layer in MAY_IMPORT:
        folder = OUTSIDE.get(layer, ROOT / PACKAGE / layer)
        doc = ast.get_docstring(ast.parse((folder / "__init__.py").read_text()))
        assert doc, f"{folder}/__init__.py has no docstring"
        if layer not in OUTSIDE:
            assert "May import:" in doc, f"{folder}/__init__.py does not say which layers it may import"


def test_the_checks_catch_an_upward_import_and_a_circle(tmp_path):
    """The checker itself, on a small package with one upward import and one circle."""
    pkg = tmp_path / "pkg"
    for folder, files in {
        "core": {
            "a.py": "from ..apps import tool\n",
            "b.py": "from . import c\n",
            "c.py": "def f():\n    from .b import x\n",
        },
        "apps": {"tool.py": "from ..core.a import y\n"},
        "odd": {"z.py": ""},
    }.items():
        (pkg / folder).mkdir(parents=True)
        (pkg / folder / "__init__.py").write_text("")
        for name, text in files.items():
            (pkg / folder / name).write_text(text)
    (pkg / "__init__.py").write_text("")
    graph = import_graph(tmp_path, "pkg", {})
    assert layer_violations(graph, "pkg", {"core": set(), "apps": {"core"}}) == [
        "pkg.core.a imports pkg.apps: core/ may not import apps/",
        "pkg.core.a imports pkg.apps.tool: core/ may not import apps/",
        "pkg.odd lies in no layer (odd/ is not in MAY_IMPORT)",
        "pkg.odd.z lies in no layer (odd/ is not in MAY_IMPORT)",
    ]
    assert sorted(circles(graph)) == [["pkg.apps.tool", "pkg.core.a"], ["pkg.core.b", "pkg.core.c"]]
