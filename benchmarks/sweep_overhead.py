"""Runs per minute of one set of runs through local Ray (``mixedrl sweep``) and through the process pool of
``mixedrl reproduce`` (docs/sweeps.rst, issue 12 item 2).

The same ``--runs`` short double-lane-change runs (``methods = ["mixed", "model"]``, seeds ``0 ..``, the
reproduction's config with ``iterations`` cut) are trained twice into fresh directories:

1. **process pool**: what :func:`validation.reproduce.reproduce` does with ``workers`` > 1 -- a
   ``multiprocessing`` pool of ``--workers`` processes (``spawn`` context), ``imap_unordered`` over the
   runs -- with the sweep's run function :func:`mixedrl.sweep.run_point` (``make_trainer`` + ``train``;
   ``reproduce``'s own job also adds theory probes and a trajectory, which would be measured as work, not
   as engine overhead);
2. **Ray**: :func:`mixedrl.sweep.run_sweep` on a local cluster of ``--workers`` CPUs, one task per run.
   ``ray.init`` (starting the local cluster) is timed separately: it is paid once per sweep.

With ``--repeats R`` the two run R times each in the order pool, Ray, Ray, pool, pool, Ray, ... (so a steady
drift of the machine's load hits both alike) and the walls are summed.

Both walls include starting the workers (process spawn and imports). The script prints runs per minute of
each; the time outside the runs (wall minus the summed time inside the runs over the workers: the
engines' start-up and hand-over, robust to a change of load that slows the runs themselves); the overhead
ratio ``wall_ray / wall_pool - 1`` (with and without ``ray.init``); the load average before and after; and
checks that both engines gave bit-identical results (same final evaluation).

Usage: ``python benchmarks/sweep_overhead.py [--runs 8] [--iterations 150] [--workers 2] [--repeats 1] [--out DIR]``
(needs the extra ``sweep``; about 2 x (runs / workers) x the time of one run).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

from mixedrl.runs import RunDirectory
from mixedrl.sweep import expand, parse_spec, run_point, run_sweep


def spec_text(runs: int, iterations: int) -> str:
    """A spec of ``runs`` short DLC runs: mixed and model, seeds ``0 .. runs/2 - 1``."""
    seeds = list(range((runs + 1) // 2))
    return (f'methods = ["mixed", "model"]\nseeds = {seeds}\n\n[base]\n"algorithm.iterations" = {iterations}\n'
            f'"run.eval_every" = {iterations}\n"run.checkpoint_every" = {iterations}\n"run.eval_seeds" = 1\n')


def pool_job(job: tuple[dict[str, Any], str]) -> dict[str, Any]:
    """One run in a pool worker (the same function as a sweep's Ray task)."""
    config, path = job
    return run_point(config, path, resume=False)


def time_pool(spec_toml: str, out: Path, workers: int) -> float:
    """Wall time of the runs through a ``spawn`` pool of ``workers`` processes (as in ``reproduce``)."""
    jobs = [(r.config.to_dict(), str(out / "runs" / r.name)) for r in expand(parse_spec(spec_toml))]
    t0 = time.perf_counter()
    ctx = mp.get_context("spawn")
    with ctx.Pool(workers) as pool:
        for _ in pool.imap_unordered(pool_job, jobs):
            pass
    return time.perf_counter() - t0


def time_ray(spec_toml: str, out: Path, workers: int) -> tuple[float, float]:
    """``(ray.init seconds, sweep seconds)`` of the runs on a local Ray cluster of ``workers`` CPUs."""
    import ray

    t0 = time.perf_counter()
    ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
    t_init = time.perf_counter() - t0
    try:
        t0 = time.perf_counter()
        run_sweep(parse_spec(spec_toml), out, address="local", progress=False)
        t_sweep = time.perf_counter() - t0
    finally:
        ray.shutdown()
    return t_init, t_sweep


def run_seconds(out: Path) -> float:
    """Sum over the runs in ``out/runs`` of the time inside the run (``config.json`` written at its start,
    ``results.json`` at its end): the work, without the engine's start-up and hand-over."""
    return sum(os.stat(d / "results.json").st_mtime - os.stat(d / "config.json").st_mtime
               for d in sorted((out / "runs").iterdir()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--runs", type=int, default=8)
    parser.add_argument("--iterations", type=int, default=150)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--repeats", type=int, default=1, help="alternate pool and Ray this many times")
    parser.add_argument("--out", type=Path, default=None, help="where the runs go (default: a temporary dir)")
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="sweep_overhead_"))
    text = spec_text(args.runs, args.iterations)
    names = [r.name for r in expand(parse_spec(text))]
    n = len(names)
    load0 = os.getloadavg()
    pool_s, init_s, ray_s, outside = [], [], [], {"pool": 0.0, "ray": 0.0}
    for rep in range(args.repeats):
        # pool, Ray, then Ray, pool, ...: a steady drift of the machine's load hits both engines alike
        for engine in ("pool", "ray") if rep % 2 == 0 else ("ray", "pool"):
            if engine == "pool":
                pool_s.append(time_pool(text, out / f"pool{rep}", args.workers))
                outside["pool"] += pool_s[-1] - run_seconds(out / f"pool{rep}") / args.workers
            else:
                t_init, t_ray = time_ray(text, out / f"ray{rep}", args.workers)
                init_s.append(t_init)
                ray_s.append(t_ray)
                outside["ray"] += ray_s[-1] - run_seconds(out / f"ray{rep}") / args.workers
    load1 = os.getloadavg()
    same = all(RunDirectory(out / "pool0" / "runs" / m).read_results()["final"]
               == RunDirectory(out / f"ray{rep}" / "runs" / m).read_results()["final"]
               for m in names for rep in range(args.repeats))
    wall_pool, wall_ray, t_init = sum(pool_s), sum(ray_s), sum(init_s)
    total = n * args.repeats
    report = {
        "runs": n, "repeats": args.repeats, "iterations": args.iterations, "workers": args.workers,
        "cpu_count": os.cpu_count(), "load_before": [round(x, 2) for x in load0],
        "load_after": [round(x, 2) for x in load1],
        "pool_seconds": [round(x, 2) for x in pool_s], "ray_seconds": [round(x, 2) for x in ray_s],
        "ray_init_seconds": [round(x, 2) for x in init_s],
        "pool_runs_per_minute": round(60 * total / wall_pool, 3),
        "ray_runs_per_minute": round(60 * total / wall_ray, 3),
        "ray_runs_per_minute_with_init": round(60 * total / (wall_ray + t_init), 3),
        "overhead_ratio": round(wall_ray / wall_pool - 1, 4),
        "overhead_ratio_with_init": round((wall_ray + t_init) / wall_pool - 1, 4),
        "outside_runs_seconds": {k: round(v, 2) for k, v in outside.items()},
        "identical_results": same,
    }
    print(f"{n} runs x {args.repeats} of {args.iterations} iterations, {args.workers} workers, "
          f"load {load0[0]:.2f} -> {load1[0]:.2f}")
    print(f"{'engine':<26}{'wall [s]':>10}{'runs/min':>10}")
    for label, wall in (("process pool (reproduce)", wall_pool), ("Ray (sweep)", wall_ray),
                        ("Ray incl. ray.init", wall_ray + t_init)):
        print(f"{label:<26}{wall:>10.1f}{60 * total / wall:>10.2f}")
    print(f"time outside the runs (wall - run time / workers): pool {outside['pool']:.1f} s, "
          f"Ray {outside['ray']:.1f} s (+ ray.init {t_init:.1f} s)")
    print(f"overhead of Ray: {100 * report['overhead_ratio']:+.1f}% "
          f"({100 * report['overhead_ratio_with_init']:+.1f}% with ray.init); identical results: {same}")
    print(json.dumps(report))
    if args.out is None:
        shutil.rmtree(out)


if __name__ == "__main__":
    main()
