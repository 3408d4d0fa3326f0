"""The import graph of mixedrl / theory / validation (scripts/import_graph.py): no cycles, the core imports
neither theory nor validation, no private name imported across modules."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _graph_module() -> ModuleType:
    spec = importlib.util.spec_from_file_location("import_graph", ROOT / "scripts" / "import_graph.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("import_graph", module)
    spec.loader.exec_module(module)
    return module


GRAPH = _graph_module()
EDGES, PRIVATE = GRAPH.imports(ROOT)


def test_the_graph_is_read() -> None:
    """The scan sees the edges it must (so that the assertions below could fail)."""
    assert "mixedrl.config" in EDGES["mixedrl.runs"] and "theory" in EDGES["validation.reproduce"]
    assert GRAPH.cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_import_cycles() -> None:
    assert GRAPH.cycles(EDGES) == []
    packages: dict[str, set[str]] = {}
    for a, b in GRAPH.package_edges(EDGES):
        packages.setdefault(a, set()).add(b)
    assert GRAPH.cycles(packages) == []


def test_core_imports_neither_theory_nor_validation() -> None:
    edges = GRAPH.package_edges(EDGES)
    assert ("mixedrl", "theory") not in edges and ("mixedrl", "validation") not in edges
    assert ("theory", "validation") not in edges  # theory imports only mixedrl


def test_no_private_name_imported_across_modules() -> None:
    assert PRIVATE == [], "\n".join(f"{m}: from {s} import {n}" for m, s, n in PRIVATE)
