"""Print the import graph of the project's packages, its cycles and its cross-module private imports.

Usage (from the repository root)::

    python scripts/import_graph.py            # edges, then cycles and private imports; exit 1 if any
    python scripts/import_graph.py --quiet    # only the problems

An *upward arrow* is an import that climbs the layers of :data:`LAYERS` (:func:`upward`): the generic
algorithm importing a task or the evaluation yardstick, or a task importing the algorithm.

Every ``import`` / ``from ... import`` statement of ``mixedrl/``, ``theory/`` and ``validation/`` counts,
wherever it stands (module level or inside a function: a lazy import still ties the two modules
together). An edge ``a -> b`` links two modules of these packages; ``from pkg import name`` is an edge to
``pkg.name`` when that is a module, else to ``pkg``. The implicit import of a parent package's
``__init__`` is not an edge. Cycles are the strongly connected components with more than one module
(or a self-import), among modules and among the three packages (``theory -> validation -> theory`` is a
cycle of packages even when no module imports itself back). A *private import* is ``from m import _name`` with ``m`` one of the project's modules,
in another module (names of modules, such as ``mixedrl.checks``, are not private names).

The same functions back ``tests/test_imports.py``.
"""

from __future__ import annotations

import argparse
import ast
import sys
from pathlib import Path

#: The project's packages scanned, relative to the repository root.
PACKAGES = ("mixedrl", "theory", "validation")
ROOT = Path(__file__).resolve().parents[1]


def modules(root: Path = ROOT) -> dict[str, Path]:
    """Dotted module name -> file, for every ``.py`` file of :data:`PACKAGES`."""
    out = {}
    for pkg in PACKAGES:
        for path in sorted((root / pkg).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    return out


def _resolve(module: str, is_package: bool, node: ast.ImportFrom) -> str:
    """The absolute module named by a (possibly relative) ``from ... import``."""
    if not node.level:
        return node.module or ""
    base = module.split(".")
    base = base if is_package else base[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def imports(root: Path = ROOT) -> tuple[dict[str, set[str]], list[tuple[str, str, str]]]:
    """The edges ``module -> imported project modules`` and the private imports ``(module, source, name)``."""
    mods = modules(root)
    edges: dict[str, set[str]] = {m: set() for m in mods}
    private: list[tuple[str, str, str]] = []

    def target(name: str) -> str | None:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    for mod, path in mods.items():
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for alias in node.names:
                    t = target(alias.name)
                    if t and t != mod:
                        edges[mod].add(t)
            elif isinstance(node, ast.ImportFrom):
                source = _resolve(mod, path.name == "__init__.py", node)
                if source == "__future__":
                    continue
                for alias in node.names:
                    full = f"{source}.{alias.name}"
                    t = full if full in mods else target(source)
                    if t and t != mod:
                        edges[mod].add(t)
                    private_name = alias.name.startswith("_") and not alias.name.startswith("__") and full not in mods
                    # a private module (a dotted component starting with "_") imported from another module
                    private_module = any(p.startswith("_") and not p.startswith("__") for p in full.split("."))
                    if ((private_name or private_module) and target(source) is not None
                            and target(source) != mod):
                        private.append((mod, source, alias.name))
    return edges, private


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), each sorted; sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    sys.setrecursionlimit(max(10_000, sys.getrecursionlimit()))
    for v in sorted(edges):
        if v not in index:
            visit(v)
    return sorted(out)


def package_edges(edges: dict[str, set[str]]) -> set[tuple[str, str]]:
    """Edges between top-level packages (``("mixedrl", "theory")`` means mixedrl imports theory)."""
    return {(a.split(".")[0], b.split(".")[0]) for a, bs in edges.items() for b in bs
            if a.split(".")[0] != b.split(".")[0]}


#: The layers of mixedrl that imports must not climb: a module of a layer imports only modules of its own or
#: a lower layer (listed lowest first; a module matches the first prefix that names it or a package above it).
#: ``configuration`` is the run's configuration (:mod:`mixedrl.config` and its parts), which a task registers
#: with and which must not know any task; ``generic`` is the paper's algorithm and its departures, which must
#: not know any task; ``tasks`` the built-in tasks, which must not know the algorithm that trains on them;
#: ``evaluation`` the yardsticks, which training must not import.
LAYERS: dict[str, tuple[str, ...]] = {
    "configuration": ("mixedrl.config", "mixedrl.config_tasks", "mixedrl.config_sections"),
    "generic": ("mixedrl.algorithms", "mixedrl.departures", "mixedrl.pev", "mixedrl.pim", "mixedrl.expectation",
                "mixedrl.noise", "mixedrl.schedule", "mixedrl.samplers", "mixedrl.ibe"),
    "tasks": ("mixedrl.envs", "mixedrl.linear_task", "mixedrl.tasks"),
    "evaluation": ("mixedrl.precision",),
}
#: Which layers may not import which: the configuration imports no task (a task registers its configuration
#: class and preset with it: :func:`mixedrl.config.register_builtin_task`, :func:`mixedrl.config.register_preset`);
#: ``generic`` imports no task and no yardstick; a task imports no algorithm.
FORBIDDEN: tuple[tuple[str, str], ...] = (("configuration", "tasks"), ("generic", "tasks"), ("generic", "evaluation"),
                                          ("tasks", "generic"))


def layer(module: str) -> str | None:
    """The layer of :data:`LAYERS` of ``module``, or ``None``."""
    for name, prefixes in LAYERS.items():
        if any(module == p or module.startswith(p + ".") for p in prefixes):
            return name
    return None


def upward(edges: dict[str, set[str]]) -> list[tuple[str, str]]:
    """The edges ``a -> b`` that climb: the layers of ``a`` and ``b`` are a pair of :data:`FORBIDDEN`; sorted.
    (A task's own sampler, :mod:`mixedrl.envs.dlc_sampler`, builds on the generic :mod:`mixedrl.samplers`,
    the extension point a task plugs into, and the configuration checks the laws of the task-independent
    disturbance model :mod:`mixedrl.envs.disturbance` (``DISTURBANCE_LAWS``, also the linear task's): those
    edges are the allowed ones.)"""
    allowed = {("mixedrl.envs.dlc_sampler", "mixedrl.samplers"), ("mixedrl.config_tasks", "mixedrl.envs.disturbance")}
    return sorted((a, b) for a, bs in edges.items() for b in bs
                  if (layer(a), layer(b)) in FORBIDDEN and (a, b) not in allowed)


def main(argv: list[str] | None = None) -> int:
    """Print the graph and the problems; exit status 1 if there is a cycle or a private import."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quiet", action="store_true", help="print only cycles and private imports")
    args = parser.parse_args(argv)
    edges, private = imports()
    if not args.quiet:
        for mod in sorted(edges):
            if edges[mod]:
                print(f"{mod} -> {', '.join(sorted(edges[mod]))}")
        print("package edges:", ", ".join(f"{a} -> {b}" for a, b in sorted(package_edges(edges))))
    pkg_graph: dict[str, set[str]] = {}
    for a, b in package_edges(edges):
        pkg_graph.setdefault(a, set()).add(b)
    found = cycles(edges) + cycles(pkg_graph)
    print(f"cycles (modules, then packages): {len(found)}")
    for comp in found:
        print("  " + " <-> ".join(comp))
    print(f"private imports across modules: {len(private)}")
    for mod, source, name in private:
        print(f"  {mod}: from {source} import {name}")
    up = upward(edges)
    print(f"upward arrows (configuration or generic -> task, generic -> yardstick, task -> generic): {len(up)}")
    for a, b in up:
        print(f"  {a} -> {b}")
    return 1 if found or private or up else 0


if __name__ == "__main__":
    raise SystemExit(main())
