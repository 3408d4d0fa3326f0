"""The library defaults of a task without a preset (issue 19), measured: analysis of ``experiments/studies/custom_defaults.toml``.

A task that registers no preset (the pendulum of docs/pendulum.rst, the linear test bed, a user's own system)
trains with the library defaults of :class:`mixedrl.config.TrainConfig`. Two of them decide whether such a run
is stable: ``algorithm.batch_weighting`` (``"uniform"``, the paper's plain batch mean, or ``"relative"``) and
``sampler.box`` (a model rollout restarts when its observation leaves ``box * obs_scale``). The spec trains
the four combinations on both tasks, mixed and model-driven RL, five seeds; this script only analyses it::

    mixedrl sweep experiments/studies/custom_defaults.toml --out runs/custom_defaults
    PYTHONPATH=. python experiments/analysis/custom_defaults.py runs/custom_defaults --dest experiments/results/custom_defaults

Per variant and method it reports the final course cost (``results.json``'s ``cost``: the discounted cost of
the task's own evaluation, :meth:`mixedrl.tasks.Task.evaluate`) as mean, median and worst over the seeds, the
number of runs that failed (the cost not finite, or above :data:`FAILED_FACTOR` times the median of the
variant that has the lowest median on that task and method), the action error at the equilibrium
(``policy_gap``), and per seed the paired difference against the paper's combination (``uniform_inf``) with its
95% bootstrap interval. It writes ``rows.json`` (one object per run) and ``table.md`` to ``--dest``.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from mixedrl.runs import atomic_write_text
from mixedrl.tables import paired_interval

#: A run "fails" when its cost exceeds this factor times the best variant's median on its task and method.
FAILED_FACTOR = 2.0
#: The paper's combination, the reference of the paired differences.
PAPER = "uniform_inf"


def load(sweep_dir: Path) -> list[dict[str, Any]]:
    """One row per finished run: task, variant (without the task prefix), method, seed, cost, action error."""
    doc = json.loads((sweep_dir / "sweep.json").read_text())
    rows = []
    for r in doc["runs"]:
        if r.get("error") or not r.get("metrics"):
            continue
        task, _, variant = r["point"]["variant"].partition("_")
        results = json.loads((sweep_dir / r["run_dir"] / "results.json").read_text())
        gap = results.get("policy_gap") or {}
        err = gap.get("action_error")
        rows.append({"task": task, "variant": variant, "method": r["method"], "seed": r["seed"],
                     "cost": float(r["metrics"]["cost"]),
                     "action_error": None if err is None else float(np.max(np.abs(err)))})
    return rows


def table(rows: list[dict[str, Any]]) -> str:
    """The markdown table of the module docstring."""
    out = ["| task | method | variant | cost mean | median | worst | failed | max abs action error at eq. (mean) "
           "| paired cost diff vs uniform_inf [95%] | cheaper seeds |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    for task in sorted({r["task"] for r in rows}):
        for method in sorted({r["method"] for r in rows if r["task"] == task}):
            sub = [r for r in rows if r["task"] == task and r["method"] == method]
            variants = sorted({r["variant"] for r in sub})
            by = {v: sorted((r for r in sub if r["variant"] == v), key=lambda r: r["seed"]) for v in variants}
            medians = {v: float(np.median([r["cost"] for r in by[v]])) for v in variants}
            limit = FAILED_FACTOR * min(m for m in medians.values() if math.isfinite(m))
            for v in variants:
                cost = np.array([r["cost"] for r in by[v]])
                failed = int(np.sum(~np.isfinite(cost) | (cost > limit)))
                errs = [r["action_error"] for r in by[v] if r["action_error"] is not None]
                err = f"{np.mean(errs):.3g}" if errs else "-"
                paired, wins = "-", "-"
                if v != PAPER and PAPER in by and [r["seed"] for r in by[PAPER]] == [r["seed"] for r in by[v]] \
                        and np.all(np.isfinite(cost)):
                    ref = np.array([r["cost"] for r in by[PAPER]])
                    if np.all(np.isfinite(ref)):
                        d, lo, hi = paired_interval(cost, ref)
                        paired = f"{d:+.3g}" + ("" if lo is None else f" [{lo:+.3g}, {hi:+.3g}]")
                        wins = f"{int(np.sum(cost < ref))}/{len(cost)}"
                out.append(f"| {task} | {method} | {v} | {np.mean(cost):.4g} | {np.median(cost):.4g} | "
                           f"{np.max(cost):.4g} | {failed}/{len(cost)} | {err} | {paired} | {wins} |")
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sweep_dir", type=Path, help="the sweep directory of experiments/studies/custom_defaults.toml")
    parser.add_argument("--dest", type=Path, default=None, help="write rows.json and table.md here")
    args = parser.parse_args(argv)
    if not (args.sweep_dir / "sweep.json").is_file():
        parser.error(f"sweep_dir: {args.sweep_dir} holds no sweep.json")
    rows = load(args.sweep_dir)
    text = table(rows)
    print(text, end="")
    if args.dest is not None:
        args.dest.mkdir(parents=True, exist_ok=True)
        atomic_write_text(args.dest / "rows.json", json.dumps(rows, indent=1) + "\n")
        atomic_write_text(args.dest / "table.md", text)


if __name__ == "__main__":
    main()
