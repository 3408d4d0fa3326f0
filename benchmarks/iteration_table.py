"""Per-iteration cost of Algorithm 2 and where one default run's wall time goes (issue 44).

    python benchmarks/iteration_table.py [--sizes 1 5 15] [--blocks 6] [--block 5] [--run-iterations N]
                                         [--cache-ab | --compile-ab [--cache-dir DIR]]
                                         [--table-only | --split-only] [--out FILE.json] [--algorithm JSON]

**Table**: for each ``R`` (``--sizes``; seeds x mixed / model / oracle at the double lane change's
defaults, one :class:`mixedrl.algorithms.batched.BatchedAGPI`; ``R = 1`` is a run alone, as
:meth:`AGPI.iteration <mixedrl.algorithms.agpi.AGPI.iteration>` runs it) the engine is built and warmed up
(3 iterations), then all sizes are timed in this one process (one torch thread) in alternating blocks
(``--blocks`` blocks of ``--block`` iterations, the order of the sizes reversed every other block), each
iteration timed on its own: the table gives the min and the median ms per batch iteration and the median
per run-iteration. Alternating blocks give every size the same load from other jobs on a shared machine.
``--cache-ab`` times every size twice, the same runs with the quadrature cache of issue 44 and without it
(``run.node_cache = None``: the nodes computed at every call, as before), side by side in the same blocks.
``--compile-ab`` times every size twice, the same runs with ``algorithm.compile = "off"`` (the eager step)
and ``"on"`` (PEV and PIM each one compiled graph, :mod:`mixedrl.compiled`), side by side in the same
blocks; the compiled engines' warm-up gives the **cold** compile (its wall time less three steady compiled
iterations) in a fresh, empty compile cache (a temporary ``MIXEDRL_CACHE_DIR``, unless ``--cache-dir``
names one), and after the timing ``torch._dynamo.reset()`` and a new compiled engine per size give the
**warm** compile (the graphs loaded from that on-disk cache; the same process, so Python modules and
inductor's in-memory caches are warm too, a fresh process pays some more).

``--algorithm '{"rollout_horizon": 16, ...}'`` times the table's engines with these ``algorithm.*`` settings over the
double lane change's defaults (e.g. the rollout learner of :mod:`mixedrl.departures.rollout`, eager against
compiled).

**Split**: one default run (``TrainConfig(method="mixed", seed=0, task="dlc")``, its budget or ``--run-iterations``,
trained by :func:`mixedrl.runs.train` in memory) in a fresh subprocess, its wall time split into
interpreter start, imports (``mixedrl``, :mod:`mixedrl.runs`), construction (:func:`mixedrl.runs.make_trainer`),
the first iteration (which pays the lazy imports of the first optimiser step, ``torch._dynamo``), the other
iterations, the evaluations (periodic and final, :func:`mixedrl.runs.evaluate_together`) and the rest of
:func:`~mixedrl.runs.train` (metrics, summary).

The code measured is the ``mixedrl`` on ``PYTHONPATH`` (run it from another tree to time that tree's
code: ``cd OLD && PYTHONPATH=OLD python NEW/benchmarks/iteration_table.py``). Timings only: nothing is
asserted. The header names the machine, torch and the date.
"""

from __future__ import annotations

import time

STARTED = time.time()  # the wall clock when this script began to run (the split's interpreter start ends here)

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

METHODS = ("mixed", "model", "oracle")


def machine() -> dict[str, Any]:
    """Machine, torch and date of the measurement."""
    import torch

    cpu = platform.processor() or "?"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"date_utc": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M"), "cpu": cpu,
            "cores": os.cpu_count(), "python": platform.python_version(), "torch": torch.__version__,
            "mixedrl": str(Path(sys.modules["mixedrl"].__file__).parent.parent) if "mixedrl" in sys.modules else "",
            "load_avg_1min": os.getloadavg()[0]}


#: ``algorithm.*`` settings over the double lane change's defaults for every engine timed (``--algorithm``).
SETTINGS: dict[str, Any] = {}


def _engine(size: int, first_seed: int, compile: str = "off") -> Any:
    from mixedrl.algorithms.batched import BatchedAGPI
    from mixedrl.config import TrainConfig
    from mixedrl.runs import make_trainer

    trainers = [make_trainer(TrainConfig(method=METHODS[i % 3], seed=first_seed + i // 3, task="dlc",
                                         algorithm={**SETTINGS, "compile": compile})) for i in range(size)]
    return trainers[0] if size == 1 else BatchedAGPI(trainers)


def _warm_up(engine: Any, iterations: int = 3) -> float:
    """Seconds of the engine's first ``iterations`` (a compiled engine compiles its graphs in them)."""
    t0 = time.perf_counter()
    for _ in range(iterations):
        engine.iteration()
    return time.perf_counter() - t0


def table(sizes: list[int], blocks: int, block: int, cache_ab: bool = False,
          compile_ab: bool = False) -> list[dict[str, Any]]:
    """Per-iteration wall times of ``R`` runs, all sizes in alternating blocks (see the module docstring).
    ``cache_ab``: every size twice, the same runs with and without the quadrature cache (``run.node_cache``,
    issue 44; ``None`` computes the nodes every call, as before), side by side in the same blocks.
    ``compile_ab``: every size twice, ``algorithm.compile`` off and on, side by side, with the cold and the
    warm compile seconds of the compiled engines."""
    import torch

    torch.set_num_threads(1)
    variants: tuple[Any, ...] = (True, False) if cache_ab else ("off", "on") if compile_ab else (None,)
    cases = [(size, v) for size in sizes for v in variants]
    engines = [_engine(size, 100 * sizes.index(size), v if compile_ab else "off") for size, v in cases]
    for engine, (_, cached) in zip(engines, cases):
        if cached is False:
            for m in getattr(engine, "members", [engine]):
                m.node_cache = None
    warm_ups = [_warm_up(engine) for engine in engines]
    times: list[list[float]] = [[] for _ in cases]
    for b in range(blocks):
        order = list(range(len(cases))) if b % 2 == 0 else list(reversed(range(len(cases))))
        for j in order:
            for _ in range(block):
                t0 = time.perf_counter()
                engines[j].iteration()
                times[j].append(time.perf_counter() - t0)
    rows = [{"runs": size, "node_cache": v if cache_ab else None, "compile": v if compile_ab else "off",
             "iterations": len(t), "min_ms": 1e3 * min(t), "median_ms": 1e3 * statistics.median(t),
             "median_ms_per_run": 1e3 * statistics.median(t) / size} for (size, v), t in zip(cases, times)]
    if compile_ab:
        torch._dynamo.reset()  # the compiled code in memory forgotten: the next compile loads the on-disk cache
        for row, warm_up in zip(rows, warm_ups):
            if row["compile"] == "on":
                steady = 3 * row["median_ms"] / 1e3
                row["compile_cold_s"] = warm_up - steady
                row["compile_warm_s"] = _warm_up(_engine(row["runs"], 100 * sizes.index(row["runs"]), "on")) - steady
    return rows


def split_child(iterations: int | None) -> dict[str, float]:
    """One default run in this (fresh) process, timed by phase."""
    t0 = time.perf_counter()
    import torch

    import mixedrl  # noqa: F401
    import mixedrl.runs as runs
    from mixedrl.config import TrainConfig

    t_imports = time.perf_counter() - t0
    torch.set_num_threads(1)
    config = TrainConfig(method="mixed", seed=0, task="dlc", algorithm=dict(SETTINGS))
    if iterations is not None:
        config = config.replace(**{"algorithm.iterations": iterations})
    t1 = time.perf_counter()
    trainer = runs.make_trainer(config)
    t_construct = time.perf_counter() - t1
    spent = {"evaluation": 0.0}
    evaluate_together = runs.evaluate_together

    def timed(*args: Any, **kwargs: Any) -> Any:
        t = time.perf_counter()
        try:
            return evaluate_together(*args, **kwargs)
        finally:
            spent["evaluation"] += time.perf_counter() - t

    runs.evaluate_together = timed  # type: ignore[assignment]  (this process only)
    its: list[float] = []

    def callback(row: dict[str, Any]) -> None:
        its.append(row["time/elapsed_s"])

    t2 = time.perf_counter()
    result = runs.train(trainer, None, progress=False, callback=callback)
    t_train = time.perf_counter() - t2
    first = its[0]
    iterations_s = result["train_seconds"]
    return {"imports_s": t_imports, "construction_s": t_construct, "first_iteration_s": first,
            "other_iterations_s": iterations_s - first, "iterations": len(its),
            "evaluation_s": spent["evaluation"], "train_rest_s": t_train - iterations_s - spent["evaluation"],
            "started": STARTED, "in_process_s": time.perf_counter() - t0, "cost": result.get("cost")}


def split(iterations: int | None) -> dict[str, float]:
    """:func:`split_child` in a fresh interpreter; the interpreter's start (to the script's first line) and its
    exit (after the last phase, the teardown of torch included) from the wall clock."""
    t0, spawned = time.perf_counter(), time.time()
    args = [sys.executable, __file__, "--split-child", "--algorithm", json.dumps(SETTINGS)] + \
        ([] if iterations is None else ["--run-iterations", str(iterations)])
    out = subprocess.run(args, capture_output=True, text=True, check=True, env=dict(os.environ, OMP_NUM_THREADS="1"))
    wall = time.perf_counter() - t0
    res = json.loads(out.stdout.strip().splitlines()[-1])
    res["wall_s"] = wall
    res["interpreter_s"] = res.pop("started") - spawned
    res["exit_s"] = wall - res["interpreter_s"] - res.pop("in_process_s")
    return res


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[1, 5, 15])
    p.add_argument("--blocks", type=int, default=6)
    p.add_argument("--block", type=int, default=5)
    p.add_argument("--run-iterations", type=int, default=None, help="budget of the split's run (default: its config's)")
    p.add_argument("--cache-ab", action="store_true",
                   help="each size with and without the quadrature cache (run.node_cache), side by side")
    p.add_argument("--compile-ab", action="store_true",
                   help="each size with algorithm.compile off and on, side by side; cold and warm compile seconds")
    p.add_argument("--cache-dir", type=Path, default=None,
                   help="with --compile-ab: the compile cache (MIXEDRL_CACHE_DIR; default a fresh temporary one: cold)")
    p.add_argument("--table-only", action="store_true")
    p.add_argument("--split-only", action="store_true")
    p.add_argument("--split-child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--algorithm", type=json.loads, default={}, metavar="JSON",
                   help='algorithm.* settings over the defaults for the table\'s engines, e.g. \'{"rollout_horizon": 16}\'')
    args = p.parse_args(argv)
    SETTINGS.update(args.algorithm)
    if args.split_child:
        print(json.dumps(split_child(args.run_iterations)))
        return 0
    import mixedrl  # noqa: F401  (for the header)

    if args.cache_dir is not None:
        os.environ["MIXEDRL_CACHE_DIR"] = str(args.cache_dir)  # the split's run (algorithm.compile) and the table's
    doc: dict[str, Any] = {"machine": machine(), "algorithm": dict(SETTINGS)}
    print("  ".join(f"{k}={v}" for k, v in doc["machine"].items()))
    if not args.split_only:
        if args.compile_ab:
            import tempfile

            cache = args.cache_dir or Path(tempfile.mkdtemp(prefix="mixedrl-cold-cache-"))
            os.environ["MIXEDRL_CACHE_DIR"] = str(cache)
            doc["machine"]["compile_cache"] = str(cache)
        doc["table"] = table(args.sizes, args.blocks, args.block, args.cache_ab, args.compile_ab)
        print(f"{'R':>4} {'nodes':>8} {'step':>5} {'its':>5} {'min ms':>9} {'median ms':>10} {'median ms / run':>16} "
              f"{'cold s':>7} {'warm s':>7}")
        for r in doc["table"]:
            nodes = {None: "", True: "cached", False: "every"}[r["node_cache"]]
            cold, warm = (f"{r[k]:>7.1f}" if k in r else f"{'':>7}" for k in ("compile_cold_s", "compile_warm_s"))
            print(f"{r['runs']:>4} {nodes:>8} {r['compile']:>5} {r['iterations']:>5} {r['min_ms']:>9.1f} "
                  f"{r['median_ms']:>10.1f} {r['median_ms_per_run']:>16.2f} {cold} {warm}")
    if not args.table_only:
        s = doc["split"] = split(args.run_iterations)
        print(f"one default run (mixed, seed 0, {s['iterations']} iterations): wall {s['wall_s']:.2f} s")
        for key in ("interpreter_s", "imports_s", "construction_s", "first_iteration_s", "other_iterations_s",
                    "evaluation_s", "train_rest_s", "exit_s"):
            print(f"  {key[:-2]:<18} {s[key]:8.2f} s  {100 * s[key] / s['wall_s']:5.1f}%")
        print(f"  (cost {s['cost']})")
    if args.out is not None:
        args.out.write_text(json.dumps(doc, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
