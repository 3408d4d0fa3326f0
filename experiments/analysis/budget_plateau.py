"""The budgets check of issue 21 over many seeds: does each method's course cost keep its plateau as the
iteration budget grows, and does any seed diverge?

Reads the sources of each budget -- a finished sweep directory of ``mixedrl sweep`` or a ``per_seed.csv`` of
``experiments/analysis/seed_statistics.py`` (:func:`seed_statistics.load_sources`) -- each holding the runs of one
iteration budget on the same seeds (for example the shipped rows ``feedforward_lq_train`` at 1500,
``..._n4000`` at 4000 and ``..._n10000`` at 10,000 iterations, whose option was retired at commit ee954d7;
several sources may give one budget, each its own rows), and writes into ``--dest``:

* ``budgets.json``: per row (method, or ``method[variant]``) and budget the mean course cost with its 95%
  bootstrap interval, the runs that left the road, the worst seed; per step from one budget to the next the
  ratio of mean costs with its paired 95% interval (seeds resampled with both values,
  :func:`mixedrl.tables.paired_interval`), the seeds whose cost rose by more than
  :data:`DIVERGED_RISE` (called diverged), and the target "mean cost rises at most 5%" met or not;
* ``budgets.txt``: the same as text.

A budget is the runs' ``iterations`` (every run of a source must have the same), and only seeds present at
every budget are compared. A row need not be present at every budget (``--partial``: an unfinished sweep gives
the rows of its finished runs): it is compared over the budgets where it was measured, and shown as "not run"
at the others.

Usage::

    python experiments/analysis/budget_plateau.py experiments/results/table1_seeds20/feedforward_lq_train/per_seed.csv \\
        experiments/results/table1_seeds20/feedforward_lq_train_n4000/per_seed.csv \
        experiments/results/table1_seeds20/feedforward_lq_train_n10000/per_seed.csv \\
        --dest experiments/results/table1_seeds20/budgets_lq_train
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from mixedrl.runs import atomic_write_text
from mixedrl.tables import bootstrap_interval, paired_interval
from seed_statistics import label, load_sources, ordered

#: The issue's plateau target: the mean course cost rises at most this fraction from one budget to the next.
MAX_MEAN_RISE = 0.05
#: A seed "diverges" from one budget to the next when its course cost grows by more than this fraction
#: (or when its runs leave the road).
DIVERGED_RISE = 0.5


def by_budget(sources: list[Path], partial: bool = False) -> dict[int, dict[str, list[dict[str, Any]]]]:
    """Per budget (iterations), the rows of its sources merged (``partial``: a sweep's finished runs only).

    Several sources may give one budget (for example the shipped ``per_seed.csv`` of two methods and the
    sweep directory of the third), as long as no row comes from two of them.

    Raises
    ------
    ValueError
        If a source's runs have different iteration counts, or two sources of one budget give the same row.
    """
    out: dict[int, dict[str, list[dict[str, Any]]]] = {}
    for src in sources:
        rows, _ = load_sources([src], partial=partial)
        its = {int(r["iterations"]) for runs in rows.values() for r in runs}
        if len(its) != 1:
            raise ValueError(f"{src}: runs of several budgets {sorted(its)}; give one budget per source")
        (n,) = its
        twice = sorted(set(rows) & set(out.get(n, {})))
        if twice:
            raise ValueError(f"{src}: rows {twice} of the budget of {n} iterations also come from an earlier "
                             f"source")
        out.setdefault(n, {}).update(rows)
    return dict(sorted(out.items()))


def plateau(budgets: dict[int, dict[str, list[dict[str, Any]]]]) -> dict[str, Any]:
    """The content of ``budgets.json`` (module docstring)."""
    out: dict[str, Any] = {"budgets": list(budgets), "max_mean_rise": MAX_MEAN_RISE, "diverged_rise": DIVERGED_RISE,
                           "rows": {}}
    for key in ordered(set().union(*(set(rows) for rows in budgets.values()))):
        # a row measured at two budgets or more; the steps join its consecutive measured budgets
        steps = [n for n, rows in budgets.items() if key in rows]
        if len(steps) < 2:
            continue
        seeds = sorted(set.intersection(*({r["seed"] for r in budgets[n][key]} for n in steps)))
        cost = {n: {r["seed"]: float(r["cost"]) for r in budgets[n][key]} for n in steps}
        left = {n: [r["seed"] for r in budgets[n][key] if r["seed"] in seeds and (r.get("left_road") or 0.0) > 0.0]
                for n in steps}
        entry: dict[str, Any] = {"seeds": seeds, "per_budget": {}, "steps": []}
        for n in steps:
            vals = [cost[n][s] for s in seeds]
            low, high = bootstrap_interval(vals)
            worst = int(seeds[int(np.argmax(vals))])
            entry["per_budget"][str(n)] = {"cost_mean": float(np.mean(vals)), "ci": [low, high],
                                           "worst_seed": worst, "worst_cost": cost[n][worst], "left_road": left[n]}
        for a, b in zip(steps, steps[1:]):
            xa = [cost[a][s] for s in seeds]
            xb = [cost[b][s] for s in seeds]
            ratio, lo, hi = paired_interval(xb, xa, statistic="ratio")
            diverged = sorted({s for s in seeds if cost[b][s] > (1.0 + DIVERGED_RISE) * cost[a][s]} | set(left[b]))
            entry["steps"].append({"from": a, "to": b, "mean_ratio": ratio, "ratio_ci": [lo, hi],
                                   "rose_on": int(sum(y > x for x, y in zip(xa, xb))), "n": len(seeds),
                                   "diverged_seeds": diverged,
                                   "plateau_met": ratio <= 1.0 + MAX_MEAN_RISE and not diverged})
        out["rows"][key] = entry
    return out


def format_table(doc: dict[str, Any]) -> str:
    """``budgets.txt``."""
    steps = doc["budgets"]
    lines = [f"Course cost per iteration budget: mean [95% bootstrap interval], worst seed (cost); a row's seeds "
             f"are the same at each of its budgets", ""]
    head = f"{'method':<22}" + "".join(f"{str(n) + ' it':>34}" for n in steps)
    lines += [head, "-" * len(head)]
    for key, e in doc["rows"].items():
        cells = ""
        for n in steps:
            b = e["per_budget"].get(str(n))
            cells += ("not run" if b is None else f"{b['cost_mean']:.2f} [{b['ci'][0]:.2f}, {b['ci'][1]:.2f}] "
                      f"s{b['worst_seed']} ({b['worst_cost']:.1f})").rjust(34)
        lines.append(f"{label(key):<22}{cells}")
    lines += ["", f"From one budget to the next: ratio of mean costs [paired 95% interval], seeds whose cost rose, "
                  f"seeds that diverged (cost up more than {doc['diverged_rise']:.0%} or off the road); the plateau "
                  f"target: ratio <= {1 + doc['max_mean_rise']:.2f} and no seed diverged"]
    for key, e in doc["rows"].items():
        for s in e["steps"]:
            lines.append(f"  {label(key):<22} {s['from']:>6} -> {s['to']:<6} {s['mean_ratio']:.3f} "
                         f"[{s['ratio_ci'][0]:.3f}, {s['ratio_ci'][1]:.3f}]   rose on {s['rose_on']} of {s['n']}   "
                         f"diverged {s['diverged_seeds'] or 'none'}   {'met' if s['plateau_met'] else 'MISSED'}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("sources", type=Path, nargs="+",
                        help="a finished sweep directory or a per_seed.csv of seed_statistics.py, each of one "
                             "budget (several may give one budget, not the same row)")
    parser.add_argument("--dest", type=Path, required=True, help="where to write budgets.json and budgets.txt")
    parser.add_argument("--partial", action="store_true",
                        help="read only the finished runs of an unfinished sweep (default: refuse it)")
    args = parser.parse_args(argv)
    if len(args.sources) < 2:
        parser.error("sources: give at least two budgets")
    try:
        budgets = by_budget(args.sources, args.partial)
    except ValueError as exc:
        parser.error(str(exc))
    doc = plateau(budgets)
    if not doc["rows"]:
        parser.error("sources: no method is present at two budgets or more")
    args.dest.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.dest / "budgets.json", json.dumps(doc, indent=2) + "\n")
    table = format_table(doc)
    atomic_write_text(args.dest / "budgets.txt", table + "\n")
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
