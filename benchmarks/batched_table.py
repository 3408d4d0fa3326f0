"""Side-by-side table of the batched engine (mixedrl.algorithms.batched): one run alone against R runs in one batch.

    python benchmarks/batched_table.py [--iterations N] [--sizes 1 5 15 50] [--ddpg] [--interleave] [--out FILE.json]
    python benchmarks/batched_table.py --evaluation [--sizes 1 15] [--run RUN_DIR] [--repeats K]

For each size ``R`` (seeds x mixed / model / oracle at the double lane change's defaults) it builds the
runs, times ``N`` iterations of the batch after 3 warm-up iterations, and reports the wall time per
batch iteration (wall and CPU time of the process: the CPU time is less disturbed by other jobs on a
shared machine), the iterations per second of all runs together (``R / time``), the ratio to one run
alone, and the peak resident memory of a fresh process (each size runs in its own subprocess, so the
peaks do not mix). Evaluation and start-up are not in the per-iteration times.

``--evaluation`` instead times the course evaluations of ``R`` runs x their 2 seeds (``--sizes``, default
1 and 15), side by side in this invocation: sequential (:func:`mixedrl.envs.evaluate_tracking` per course,
the evaluation before it was batched), in lock step with exact per-course policy calls (the final
evaluation, bit-identical) and in lock step with batched policy calls (the periodic evaluations of
training, :func:`mixedrl.runs.evaluate_together`). ``--run DIR`` loads that run's checkpoint into every
policy (a trained policy drives the whole course; fresh ones leave the road after about 1200 steps).

``--ddpg`` does the same for DDPG runs (seeds 0 .. R-1 at the double lane change's defaults, one
:class:`mixedrl.algorithms.batched_ddpg.BatchedDDPG`; ``R = 1`` is :meth:`DDPG.iteration`, a run alone).
The warm-up iterations include the first, which fills the replay buffer to ``ddpg.warmup``.

``--interleave`` times all sizes in one process instead, in alternating blocks of 10 iterations, so that
each sees the same load from other jobs on a shared machine (the peak memory is then of all together).

``--reproduction`` instead times ``mixedrl reproduce --quick`` (2 seeds at the paper's budget, 2 workers)
twice, side by side in this invocation: batched (``--batch 16``, the default) and every run alone
(``--batch 1``), each in a fresh directory, and prints both wall times and their ratio.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

METHODS = ("mixed", "model", "oracle")


def measure(size: int, iterations: int, threads: int, ddpg: bool = False) -> dict[str, float]:
    """Time ``iterations`` batch iterations of ``size`` runs in this process (``ddpg``: DDPG runs)."""
    import torch

    torch.set_num_threads(threads)
    t0 = time.perf_counter()
    engine = _engine(size, ddpg)
    build = time.perf_counter() - t0
    for _ in range(3):
        engine.iteration()
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(iterations):
        engine.iteration()
    per_iteration = (time.perf_counter() - t0) / iterations
    cpu = (time.process_time() - c0) / iterations  # less sensitive than the wall time to other jobs' load
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2  # KiB -> GiB
    return {"runs": size, "build_s": build, "s_per_iteration": per_iteration, "cpu_s_per_iteration": cpu,
            "run_iterations_per_s": size / per_iteration, "peak_gib": peak}


def evaluation(sizes: list[int], run: Path | None, repeats: int, threads: int, out: Path | None) -> int:
    """Seconds per evaluation of ``R`` runs x their seeds: sequential, lock step exact, lock step batched."""
    import numpy as np
    import torch

    from mixedrl.config import TrainConfig
    from mixedrl.envs import evaluate_tracking
    from mixedrl.runs import RunDirectory, eval_seeds, evaluate_together, load_checkpoint, make_trainer

    torch.set_num_threads(threads)
    state = None if run is None else load_checkpoint(RunDirectory(run).checkpoint_path)["trainer"]
    rows = []
    for size in sizes:
        trainers = [make_trainer(TrainConfig(method=METHODS[i % 3], seed=i // 3, task="dlc")) for i in range(size)]
        if state is not None:
            for t in trainers:
                t.actor.load_state_dict(state["actor"])
        seeds = [eval_seeds(t.config) for t in trainers]
        task = trainers[0].task
        config = task.model.config

        def sequential() -> list[float]:
            return [float(np.mean([evaluate_tracking(t.policy, config, seed=s).total_cost for s in ss]))
                    for t, ss in zip(trainers, seeds)]

        def exact() -> list[float]:
            return [e["cost"] for e in task.evaluate_many([t.policy for t in trainers], seeds, exact=True)]

        def batched() -> list[float]:
            return [e["cost"] for e in evaluate_together(trainers, seeds)]

        times, costs = {}, {}
        for name, fn in (("sequential", sequential), ("lock step exact", exact), ("lock step batched", batched)):
            best = float("inf")
            for _ in range(repeats):
                t0 = time.perf_counter()
                costs[name] = fn()
                best = min(best, time.perf_counter() - t0)
            times[name] = best
        rel = max(abs(a - b) / abs(a) for a, b in zip(costs["sequential"], costs["lock step batched"]))
        rows.append({"runs": size, "courses": sum(len(s) for s in seeds), **{f"{k} s": v for k, v in times.items()},
                     "exact bit-identical": costs["sequential"] == costs["lock step exact"],
                     "batched max rel cost diff": rel})
    print(f"{'R x seeds':>10} {'sequential s':>13} {'exact s':>9} {'x':>6} {'batched s':>10} {'x':>6} "
          f"{'exact bits':>11} {'batched rel':>12}")
    for r in rows:
        seq = r["sequential s"]
        print(f"{r['runs']:>5} x {r['courses'] // r['runs']:<2} {seq:>13.2f} {r['lock step exact s']:>9.2f} "
              f"{seq / r['lock step exact s']:>6.2f} {r['lock step batched s']:>10.2f} "
              f"{seq / r['lock step batched s']:>6.2f} {str(r['exact bit-identical']):>11} "
              f"{r['batched max rel cost diff']:>12.1e}")
    if out is not None:
        out.write_text(json.dumps({"evaluation": rows, "threads": threads, "run": str(run)}, indent=2) + "\n")
    return 0


def _engine(size: int, ddpg: bool, first_seed: int = 0) -> Any:
    """The engine of ``size`` runs at the double lane change's defaults (seeds from ``first_seed``)."""
    from mixedrl.algorithms.batched import BatchedAGPI
    from mixedrl.algorithms.batched_ddpg import BatchedDDPG
    from mixedrl.config import TrainConfig
    from mixedrl.runs import make_trainer

    if ddpg:
        return BatchedDDPG([make_trainer(TrainConfig(method="ddpg", seed=first_seed + i, task="dlc")) for i in range(size)])
    return BatchedAGPI([make_trainer(TrainConfig(method=METHODS[i % 3], seed=first_seed + i // 3, task="dlc"))
                        for i in range(size)])


def interleaved(sizes: list[int], iterations: int, threads: int, ddpg: bool) -> list[dict[str, float]]:
    """Time the sizes in one process, in alternating blocks of 10 iterations (``iterations`` per size in all),
    so that every size sees the same load from other jobs on a shared machine."""
    import torch

    torch.set_num_threads(threads)
    engines = [_engine(size, ddpg, first_seed=100 * j) for j, size in enumerate(sizes)]
    for engine in engines:
        for _ in range(3):
            engine.iteration()
    wall, cpu = [0.0] * len(sizes), [0.0] * len(sizes)
    for block in range(max(1, iterations // 10)):
        order = range(len(sizes)) if block % 2 == 0 else reversed(range(len(sizes)))
        for j in order:
            t0, c0 = time.perf_counter(), time.process_time()
            for _ in range(10):
                engines[j].iteration()
            wall[j] += time.perf_counter() - t0
            cpu[j] += time.process_time() - c0
    n = 10 * max(1, iterations // 10)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2  # of all sizes together
    return [{"runs": size, "build_s": float("nan"), "s_per_iteration": wall[j] / n, "cpu_s_per_iteration": cpu[j] / n,
             "run_iterations_per_s": size * n / wall[j], "peak_gib": peak} for j, size in enumerate(sizes)]


def reproduction(out: Path | None) -> int:
    """``mixedrl reproduce --quick`` with ``--batch 16`` and ``--batch 1``, one after the other."""
    import tempfile

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for batch in (16, 1):
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-m", "mixedrl.cli", "reproduce", "--quick", "--out",
                            str(Path(tmp) / f"batch{batch}"), "--batch", str(batch), "--no-progress"],
                           check=True, capture_output=True, text=True)
            wall = time.perf_counter() - t0
            res = json.loads((Path(tmp) / f"batch{batch}" / "results.json").read_text())
            rows.append({"batch": batch, "wall_s": wall, "batches": res["sweep"]["batches"],
                         "mixed_train_s": res["mixed"]["train_seconds_mean"]})
    print(f"{'--batch':>8} {'wall s':>8} {'tasks':>6} {'mixed train s':>14}")
    for r in rows:
        print(f"{r['batch']:>8} {r['wall_s']:>8.1f} {r['batches']:>6} {r['mixed_train_s']:>14.1f}")
    print(f"batched / alone: {rows[0]['wall_s'] / rows[1]['wall_s']:.2f}")
    if out is not None:
        out.write_text(json.dumps({"reproduction_quick": rows}, indent=2) + "\n")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--iterations", type=int, default=20)
    p.add_argument("--sizes", type=int, nargs="+", default=None, help="R (default 1 5 15 50; --evaluation: 1 15)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--one", type=int, default=None, help=argparse.SUPPRESS)
    p.add_argument("--ddpg", action="store_true", help="DDPG runs (BatchedDDPG) instead of Algorithm 2")
    p.add_argument("--interleave", action="store_true",
                   help="time all sizes in one process, alternating blocks (the same load for each; peak memory "
                        "of all together)")
    p.add_argument("--reproduction", action="store_true", help="time mixedrl reproduce --quick, batched and not")
    p.add_argument("--evaluation", action="store_true",
                   help="time the course evaluations of R runs: sequential, lock step exact and batched")
    p.add_argument("--run", type=Path, default=None, help="with --evaluation: load this run's policy into every run")
    p.add_argument("--repeats", type=int, default=1, help="with --evaluation: best of this many timings")
    args = p.parse_args(argv)
    if args.evaluation:
        return evaluation(args.sizes or [1, 15], args.run, args.repeats, args.threads, args.out)
    if args.reproduction:
        return reproduction(args.out)
    if args.one is not None:
        print(json.dumps(measure(args.one, args.iterations, args.threads, args.ddpg)))
        return 0
    sizes = args.sizes or [1, 5, 15, 50]
    rows = interleaved(sizes, args.iterations, args.threads, args.ddpg) if args.interleave else []
    for size in [] if args.interleave else sizes:
        out = subprocess.run([sys.executable, __file__, "--one", str(size), "--iterations", str(args.iterations),
                              "--threads", str(args.threads)] + (["--ddpg"] if args.ddpg else []),
                             capture_output=True, text=True, check=True)
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
    base = next((r for r in rows if r["runs"] == 1), rows[0])
    print(f"{'R':>4} {'s / batch it':>13} {'x one run':>10} {'run-its / s':>12} {'vs R x alone':>13} "
          f"{'cpu s / it':>11} {'cpu vs alone':>13} {'peak GiB':>9}")
    for r in rows:
        ratio = r["s_per_iteration"] / base["s_per_iteration"]
        cpu_ratio = r["cpu_s_per_iteration"] / base["cpu_s_per_iteration"]
        print(f"{r['runs']:>4} {r['s_per_iteration']:>13.4f} {ratio:>10.2f} {r['run_iterations_per_s']:>12.1f} "
              f"{r['runs'] / ratio:>12.2f}x {r['cpu_s_per_iteration']:>11.4f} {r['runs'] / cpu_ratio:>12.2f}x "
              f"{r['peak_gib']:>9.2f}")
        r["ratio_to_one_run"] = ratio
    if args.out is not None:
        args.out.write_text(json.dumps({"method": "ddpg" if args.ddpg else "algorithm2", "threads": args.threads,
                                        "iterations": args.iterations, "rows": rows}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
