"""The package's shape, checked from the source text (``ast``; nothing is imported).

- No import cycle between modules of hdmap_core and hdmap_ros. Every import counts: one inside a
  function still ties the two modules together, and one under ``if TYPE_CHECKING:`` still says a
  type sits in the wrong module (each of the five cycles issue 27 found was hidden one of these
  two ways, so a test that skipped them would pass on that tree).
- No ``from x import _private`` across modules: a name with a leading underscore belongs to its
  module. A private *module* imported from its own package (``nodes._common``) is fine.
- hdmap_core imports neither rclpy, nor a message package, nor hdmap_ros.
"""

from __future__ import annotations

import ast
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {
    "hdmap_core": ROOT / "src" / "hdmap_core" / "hdmap_core",
    "hdmap_ros": ROOT / "src" / "hdmap_ros" / "hdmap_ros",
}

# A cycle being removed on another branch right now (issue 27): helper `config` moves
# ConnectionConfig out of graph/connection.py. Each entry is the exact set of modules of one
# strongly connected component. Empty this list once that has landed; any other cycle fails.
_KNOWN_CYCLES: list[frozenset[str]] = []

# Top-level imports hdmap_core must not make: ROS client library, message packages, the ROS side.
_ROS_ONLY = re.compile(r"^(rclpy|rosidl\w*|builtin_interfaces|\w+_msgs|\w+_interfaces|hdmap_ros)$")


@dataclass(frozen=True)
class Import:
    """One imported name: ``module`` is the dotted target, ``name`` the imported name (or None)."""

    source: str  # the importing module
    module: str
    name: str | None
    line: int


def _module_files() -> dict[str, Path]:
    """Dotted module name -> file, for both packages (``__init__`` files named by their package)."""
    modules = {}
    for package, folder in PACKAGES.items():
        for path in sorted(folder.rglob("*.py")):
            parts = (package, *path.relative_to(folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            modules[".".join(parts)] = path
    return modules


MODULES = _module_files()


def _imports(module: str, path: Path) -> list[Import]:
    tree = ast.parse(path.read_text(), filename=str(path))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.extend(Import(module, alias.name, None, node.lineno) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            found.extend(Import(module, target, alias.name, node.lineno) for alias in node.names)
    return found


IMPORTS = {module: _imports(module, path) for module, path in MODULES.items()}


def _target(imp: Import) -> str | None:
    """The module of ours an import loads: ``from pkg import mod`` names the submodule."""
    if imp.name is not None and f"{imp.module}.{imp.name}" in MODULES:
        return f"{imp.module}.{imp.name}"
    return imp.module if imp.module in MODULES else None


def _import_edges() -> dict[str, dict[str, int]]:
    """Importing module -> {imported module: first line}, between modules of ours only."""
    edges: dict[str, dict[str, int]] = {m: {} for m in MODULES}
    for module, imports in IMPORTS.items():
        for imp in imports:
            target = _target(imp)
            if target is not None and target != module:
                edges[module].setdefault(target, imp.line)
    return edges


def _cycles(edges: dict[str, dict[str, int]]) -> list[frozenset[str]]:
    """The strongly connected components of more than one module (each holds at least one cycle)."""
    names = sorted(edges)
    index = {name: i for i, name in enumerate(names)}
    rows = [index[a] for a in names for b in edges[a]]
    cols = [index[b] for a in names for b in edges[a]]
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(names), len(names)))
    _, labels = connected_components(graph, directed=True, connection="strong")
    groups: dict[int, set[str]] = {}
    for name, label in zip(names, labels):
        groups.setdefault(int(label), set()).add(name)
    return [frozenset(g) for g in groups.values() if len(g) > 1]


def _describe(component: frozenset[str], edges: dict[str, dict[str, int]]) -> str:
    lines = [f"cycle among {sorted(component)}:"]
    for a in sorted(component):
        for b, line in sorted(edges[a].items()):
            if b in component:
                lines.append(f"    {MODULES[a].relative_to(ROOT)}:{line} imports {b}")
    return "\n".join(lines)


def test_the_scan_sees_the_packages() -> None:
    # Guards the checks below against passing on an empty scan (a moved folder, a changed root).
    assert "hdmap_core.pipeline.driver" in MODULES
    assert "hdmap_ros.nodes.segment_mapper" in MODULES
    edges = _import_edges()
    assert "hdmap_core.model" in edges["hdmap_core.pipeline.driver"]


def test_no_import_cycles() -> None:
    edges = _import_edges()
    cycles = _cycles(edges)
    new = [c for c in cycles if c not in _KNOWN_CYCLES]
    assert not new, "import cycles (cut each by moving the shared type to its own module):\n" + "\n".join(
        _describe(c, edges) for c in sorted(new, key=sorted)
    )


def test_known_cycles_still_exist() -> None:
    # Once a listed cycle is gone, its entry must go too, so the list cannot hide a new cycle later.
    cycles = _cycles(_import_edges())
    stale = [sorted(c) for c in _KNOWN_CYCLES if c not in cycles]
    assert not stale, f"these cycles are gone: remove them from _KNOWN_CYCLES: {stale}"


def _private_imports() -> list[Import]:
    """Imports of a name with one leading underscore from another module of ours (a private module
    imported by a sibling in its own package, like ``nodes._common``, is fine)."""
    found = []
    for module, imports in IMPORTS.items():
        for imp in imports:
            if imp.name is None or not imp.name.startswith("_") or imp.name.startswith("__"):
                continue
            if _target(imp) is None:
                continue  # a third-party name, not ours to judge
            submodule = f"{imp.module}.{imp.name}"
            if submodule in MODULES and submodule.rpartition(".")[0] == module.rpartition(".")[0]:
                continue
            found.append(imp)
    return found


def test_no_private_names_across_modules() -> None:
    offences = [
        f"{MODULES[imp.source].relative_to(ROOT)}:{imp.line}: from {imp.module} import {imp.name}"
        for imp in _private_imports()
    ]
    assert not offences, "private names imported across modules (make them public or move them):\n" + "\n".join(
        offences
    )


def test_core_imports_no_ros() -> None:
    offences = [
        f"{MODULES[module].relative_to(ROOT)}:{imp.line}: {imp.module}"
        for module, imports in IMPORTS.items()
        if module.startswith("hdmap_core")
        for imp in imports
        if _ROS_ONLY.match(imp.module.split(".")[0])
    ]
    assert not offences, "hdmap_core must not import rclpy, messages or hdmap_ros:\n" + "\n".join(offences)
