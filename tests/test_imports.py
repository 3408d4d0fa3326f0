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


def test_no_upward_arrows() -> None:
    """Imports point one way (issue 40): the generic algorithm (algorithms, departures, PEV/PIM, samplers, ...)
    imports no task module and not the precision yardstick; a task module imports no part of the algorithm."""
    assert GRAPH.upward(EDGES) == []
    assert GRAPH.upward({"mixedrl.algorithms.agpi": {"mixedrl.envs.dlc_task"}}) == [
        ("mixedrl.algorithms.agpi", "mixedrl.envs.dlc_task")]  # the rule can fail
    assert GRAPH.layer("mixedrl.algorithms.algorithm2") == "generic" and GRAPH.layer("mixedrl.envs.vehicle") == "tasks"


def test_the_configuration_imports_no_task() -> None:
    """The generic configuration imports no task module (issue 40): the double lane change registers its
    configuration class with it (mixedrl.config.register_builtin_task), not the other way round."""
    for module in ("mixedrl.config", "mixedrl.config_tasks", "mixedrl.config_sections"):
        assert GRAPH.layer(module) == "configuration"
        assert not {b for b in EDGES[module] if GRAPH.layer(b) == "tasks"} - {"mixedrl.envs.disturbance"}, module
    assert "mixedrl.config" in EDGES["mixedrl.envs.dlc_task"]  # the task registers with the configuration
    assert GRAPH.upward({"mixedrl.config": {"mixedrl.envs.dlc_config"}}) == [
        ("mixedrl.config", "mixedrl.envs.dlc_config")]  # the arrow of before is refused
    assert GRAPH.upward({"mixedrl.config_tasks": {"mixedrl.envs.dlc_config"}}) == [
        ("mixedrl.config_tasks", "mixedrl.envs.dlc_config")]


def test_no_private_name_imported_across_modules() -> None:
    assert PRIVATE == [], "\n".join(f"{m}: from {s} import {n}" for m, s, n in PRIVATE)


#: The task interface and the two built-in tasks: :mod:`mixedrl.tasks` (the public face) imports them.
TASK_MODULES = ("mixedrl.task_base", "mixedrl.linear_task", "mixedrl.envs.dlc_task")


def _reachable(start: str) -> set[str]:
    """The modules ``start`` imports, directly or not (per :data:`EDGES`), ``start`` included."""
    seen, todo = {start}, [start]
    while todo:
        for b in EDGES.get(todo.pop(), ()):
            if b not in seen:
                seen.add(b)
                todo.append(b)
    return seen


def test_the_task_modules_do_not_import_the_public_face_back() -> None:
    """No cycle through mixedrl.tasks, not even a hidden one: the task modules (and all they import) import
    neither mixedrl.tasks nor importlib, and mixedrl.tasks imports them with plain statements."""
    mods = GRAPH.modules(ROOT)
    assert {"mixedrl.task_base", "mixedrl.linear_task", "mixedrl.envs.dlc_task"} <= EDGES["mixedrl.tasks"]
    assert "importlib" not in mods["mixedrl.tasks"].read_text()
    for start in TASK_MODULES:
        reached = _reachable(start)
        assert "mixedrl.tasks" not in reached, start
        for mod in sorted(reached):
            assert "importlib" not in mods[mod].read_text(), f"{start} -> ... -> {mod} uses importlib"


_SPY = r"""
import builtins, importlib, json, sys

edges = []
real_import, real_import_module = builtins.__import__, importlib.import_module

def spy_import(name, globals=None, locals=None, fromlist=(), level=0):
    importer = (globals or {}).get("__name__", "")
    if importer.startswith("mixedrl") and level == 0 and name.startswith("mixedrl"):
        edges.append((importer, name, list(fromlist or ())))
    return real_import(name, globals, locals, fromlist, level)

def spy_import_module(name, package=None):
    edges.append((sys._getframe(1).f_globals.get("__name__", ""), name, []))
    return real_import_module(name, package)

builtins.__import__, importlib.import_module = spy_import, spy_import_module
import mixedrl.tasks as tasks
tasks.make_task("linear"), tasks.make_task("dlc"), tasks.task_from_config("linear"), tasks.task_from_config("dlc")
for name in tasks.__all__:
    getattr(tasks, name)
builtins.__import__, importlib.import_module = real_import, real_import_module
out = set()
for importer, name, fromlist in edges:
    if not importer.startswith("mixedrl"):
        continue
    subs = [f"{name}.{item}" for item in fromlist if f"{name}.{item}" in sys.modules]
    for target in subs or [name]:
        if target != importer:
            out.add((importer, target))
print(json.dumps(sorted(out)))
"""


def test_no_import_cycle_at_run_time() -> None:
    """In a fresh interpreter, every import mixedrl's modules make while ``mixedrl.tasks`` is imported and
    its tasks are built -- import statements, lazy ones and ``importlib.import_module`` alike -- forms an
    acyclic graph (the static scan above cannot see ``importlib``)."""
    import json
    import os
    import subprocess

    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    done = subprocess.run([sys.executable, "-c", _SPY], capture_output=True, text=True, cwd=ROOT, env=env,
                          check=False)
    assert done.returncode == 0, done.stderr
    runtime: dict[str, set[str]] = {}
    for a, b in json.loads(done.stdout.strip().splitlines()[-1]):
        runtime.setdefault(a, set()).add(b)
    assert "mixedrl.task_base" in runtime["mixedrl.tasks"]  # the spy sees the imports
    assert GRAPH.cycles(runtime) == []


def test_import_mixedrl_leaves_control_unimported() -> None:
    """Issue 44: ``control`` (which pulls in scipy.signal and matplotlib.pyplot, about 1 s) is not imported by
    ``import mixedrl``, nor by building a trainer whose deployed policy needs the LQ optimum
    (:func:`mixedrl.lq.discounted_lq_optimum` calls scipy's DARE directly); ``torch._dynamo`` (the
    compiler, about 1.3 s) not by importing the package, its training modules or :mod:`mixedrl.compiled` (only a
    compiled step, ``algorithm.compile = "on"``, or torch's own optimisers import it)."""
    import os
    import subprocess

    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}

    def last_line(code: str) -> str:
        done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env=env,
                              check=False)
        assert done.returncode == 0, done.stderr
        return done.stdout.strip().splitlines()[-1]

    assert last_line("import sys, mixedrl, mixedrl.runs, mixedrl.lq, mixedrl.compiled; "
                     "heavy = ('control', 'matplotlib.pyplot', 'scipy.signal', 'torch._dynamo'); "
                     "print([m for m in heavy if m in sys.modules])") == "[]"
    assert last_line("import sys; from mixedrl.config import TrainConfig; from mixedrl.runs import make_trainer; "
                     "t = make_trainer(TrainConfig(task='linear')); heavy = ('control', 'matplotlib.pyplot', "
                     "'scipy.signal'); print(t.feedforward, [m for m in heavy if m in sys.modules])"
                     ) == "lq_handover []"
