"""The package's shape: no import cycles, module-level imports only (except the slow optional
libraries), nothing outside the library reaching into private modules or editing sys.path.
Pure static analysis of the source (ast): no JAX programs, milliseconds."""

from __future__ import annotations

import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
PKG = ROOT / "jaxvcm"
# libraries slow to import (or optional) that may be imported inside functions, so that
# `import jaxvcm` stays light (and a few standard-library modules used on rare paths)
LAZY_OK = {"colour", "matplotlib", "optimistix", "OpenEXR", "trimesh", "signal", "threading",
           "warnings", "time",
           "flatbuffers"}  # the optional extra `warm`: imported only to see whether it is there


def _modules() -> dict[str, pathlib.Path]:
    mods = {}
    for p in PKG.rglob("*.py"):
        parts = list(p.relative_to(ROOT).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        mods[".".join(parts)] = p
    return mods


def _imports(name: str, path: pathlib.Path, mods):
    """(module-level internal imports, function-local internal imports, function-local
    external top-level names) of one module."""
    tree = ast.parse(path.read_text())
    is_pkg = path.name == "__init__.py"
    top, local, external = set(), set(), set()
    top_nodes = set(map(id, tree.body))
    for node in ast.walk(tree):
        targets = []
        if isinstance(node, ast.ImportFrom) and node.level > 0:
            base = name.split(".") if is_pkg else name.split(".")[:-1]
            base = base[: len(base) - (node.level - 1)]
            mod = ".".join(base + ([node.module] if node.module else []))
            subs = [f"{mod}.{a.name}" for a in node.names if f"{mod}.{a.name}" in mods]
            named = [a.name for a in node.names if f"{mod}.{a.name}" not in mods]
            targets = subs + ([mod] if named and mod in mods else [])
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""])
            targets = [n for n in names if n in mods or n.startswith("jaxvcm.")]
            if id(node) not in top_nodes and not targets:
                external.update(n.split(".")[0] for n in names)
        else:
            continue
        (top if id(node) in top_nodes else local).update(t for t in targets if t != name)
    return top, local, external


def test_no_import_cycles_and_no_hidden_local_imports():
    mods = _modules()
    graph, problems = {}, []
    for name, path in mods.items():
        top, local, external = _imports(name, path, mods)
        graph[name] = top
        if local:
            problems.append(f"{name}: function-local imports of {sorted(local)}")
        if external - LAZY_OK:
            problems.append(f"{name}: function-local imports of {sorted(external - LAZY_OK)}")
    # `from . import _x` is an edge to the submodule _x, not to the package; importing
    # names from a package's __init__ is an edge to it (so `from . import __version__`
    # inside the package would be a cycle)
    state: dict[str, int] = {}

    def visit(n, stack):
        state[n] = 1
        for m in sorted(graph[n]):
            if state.get(m) == 1:
                problems.append("cycle: " + " -> ".join(stack[stack.index(m):] + [m]))
            elif m not in state:
                visit(m, stack + [m])
        state[n] = 2

    for n in sorted(graph):
        if n not in state:
            visit(n, [n])
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("where", ["fits", "docs", "benchmarks"])
def test_tools_use_the_public_api_only(where):
    bad = []
    for p in (ROOT / where).rglob("*.py"):
        text = p.read_text()
        tree = ast.parse(text)
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("jaxvcm._"):
                bad.append(f"{p.relative_to(ROOT)}: from {node.module} import ...")
            if isinstance(node, ast.ImportFrom) and node.module == "jaxvcm":
                bad += [f"{p.relative_to(ROOT)}: {a.name}" for a in node.names
                        if a.name.startswith("_") and a.name != "__version__"]
            if isinstance(node, ast.Import):
                bad += [f"{p.relative_to(ROOT)}: import {a.name}" for a in node.names
                        if a.name.startswith("jaxvcm._")]
            if isinstance(node, ast.Attribute) and node.attr == "path" and \
                    isinstance(node.value, ast.Name) and node.value.id == "sys":
                bad.append(f"{p.relative_to(ROOT)}: sys.path")
    assert not bad, "\n".join(bad)
