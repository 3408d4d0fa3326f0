"""Is the learner's seed-to-seed spread independent per-run error? A diagnostic on the tracking tuning system
``slalom_weak`` (:mod:`experiments.tuning_tracking`; issue 42's double-lane-change per-seed claim is decided by
that spread, and it is chosen on tuning systems only).

Mixed and model-driven RL are trained at the library defaults (``learner_tuning``'s variant ``default``) on
seeds ``100 .. 100 + K n - 1``; each run's actor is kept in ``--cache``. An *ensemble* ``e`` of size ``K`` is the
policy whose action is the mean of the actions of the actors of seeds ``100 + K e .. 100 + K e + K - 1``; the
ensembles of mixed and of model-driven RL take the same seeds, so ``e`` pairs them as a seed pairs two runs.
Every policy is evaluated as ``learner_tuning``'s tracking rows (:data:`learner_tuning.TRACKING_EVAL_SEEDS`).
If the runs' errors were independent, the paired spread of ``K``-ensembles would be about ``1 / sqrt(K)`` of the
single runs'. An ensemble trains ``K`` runs, so it also costs ``K`` times the true transitions and the wall time:
this measures the spread, it is not a learner.

``--iterations N`` trains every run with a budget of ``N`` iterations instead (results in
``ensemble_spread_n<N>``): ``K`` runs of ``800 / K`` iterations take the compute and, each with its own data, the true
transitions of one default run.

Usage (two processes; a run already in ``--cache`` is not trained again; about 35 minutes for ``--runs 40``)::

    PYTHONPATH=. python experiments/analysis/ensemble_spread.py --runs 40 --sizes 1 2 4 8 --cache /tmp/ensemble_actors
    PYTHONPATH=. python experiments/analysis/ensemble_spread.py --runs 40 --sizes 1 4 --iterations 200 \
        --cache /tmp/ensemble_actors

Writes ``experiments/results/ensemble_spread/{rows.json,summary.md}``.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
for p in (ROOT, ROOT / "experiments" / "analysis"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from learner_tuning import ONESTEP, TRACKING_EVAL_SEEDS, TRACKING_TUNING_SYSTEMS, VARIANTS, _trained  # noqa: E402
from mixedrl.runs import atomic_write_text  # noqa: E402

OUT = ROOT / "experiments" / "results" / "ensemble_spread"
SYSTEM, FIRST_SEED, METHODS = "slalom_weak", 100, ("mixed", "model")


class MeanPolicy(torch.nn.Module):
    """The mean of the actions of ``actors``."""

    def __init__(self, actors: list[torch.nn.Module]) -> None:
        super().__init__()
        self.actors = torch.nn.ModuleList(actors)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.stack([a(obs) for a in self.actors]).mean(dim=0)


def actor_file(method: str, seed: int, iterations: int | None) -> str:
    """The cache's file of a run (the budget in its name unless it is the default's)."""
    return f"{method}_{seed}.pt" if iterations is None else f"{method}_{seed}_n{iterations}.pt"


def train_one(args: tuple[str, int, str, int | None]) -> dict[str, Any]:
    """Train one default run (or load it from the cache) and return its row; the actor goes to the cache.
    ``iterations``: the run's budget, ``None`` for the default's."""
    method, seed, cache, iterations = args
    torch.set_num_threads(1)
    path = Path(cache) / actor_file(method, seed, iterations)
    if not path.exists():
        algorithm = {**ONESTEP, **VARIANTS["default"], **({} if iterations is None else {"iterations": iterations})}
        task, run, row = _trained(SYSTEM, method, seed, algorithm, TRACKING_TUNING_SYSTEMS)
        if run.feedforward != "learned":
            raise RuntimeError(f"{SYSTEM}: expected the learned policy to be deployed, got {run.feedforward!r}")
        row["course"] = task.evaluate(run.policy, TRACKING_EVAL_SEEDS)
        tmp = path.with_suffix(".tmp")
        torch.save({"actor": run.actor, "row": row}, tmp)
        tmp.replace(path)
    row = torch.load(path, weights_only=False)["row"]
    return {"method": method, "seed": seed, **row}


def paired(rows: list[dict[str, Any]], key: str) -> dict[str, Any]:
    """Model-driven minus mixed RL of ``key`` over the paired units of ``rows``: wins of mixed RL, mean, sd."""
    by = {(r["method"], r["unit"]): r["course"][key] for r in rows}
    units = sorted({u for _, u in by})
    d = np.array([by[("model", u)] - by[("mixed", u)] for u in units])
    mixed = np.array([by[("mixed", u)] for u in units])
    return {"units": len(units), "mixed_better": int((d > 0).sum()), "difference_mean": float(d.mean()),
            "difference_sd": float(d.std(ddof=1)), "mixed_mean": float(mixed.mean()),
            "mixed_sd": float(mixed.std(ddof=1))}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=40, help="runs per method (seeds 100 ..)")
    ap.add_argument("--sizes", type=int, nargs="+", default=[1, 2, 4], help="ensemble sizes K")
    ap.add_argument("--cache", required=True, help="directory of the trained actors")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--iterations", type=int, default=None,
                    help="each run's budget (default: the library's); results go to ensemble_spread_n<ITERATIONS>")
    args = ap.parse_args(argv)
    if args.runs < 2 or any(k < 1 or args.runs // k < 2 for k in args.sizes):
        raise SystemExit(f"--sizes: every K needs at least 2 ensembles of --runs {args.runs}")
    if args.iterations is not None and args.iterations < 1:
        raise SystemExit(f"--iterations: expected a positive budget, got {args.iterations}")
    out = OUT if args.iterations is None else OUT.with_name(f"{OUT.name}_n{args.iterations}")
    Path(args.cache).mkdir(parents=True, exist_ok=True)
    jobs = [(m, FIRST_SEED + i, args.cache, args.iterations) for i in range(args.runs) for m in METHODS]
    with multiprocessing.get_context("fork").Pool(args.jobs) as pool:
        runs = []
        for i, row in enumerate(pool.imap_unordered(train_one, jobs), 1):
            print(f"[{i}/{len(jobs)}] {row['method']} {row['seed']}: lateral MAE {row['course']['lateral_mae']:.4f}",
                  file=sys.stderr, flush=True)
            runs.append(row)
    task = TRACKING_TUNING_SYSTEMS[SYSTEM]()
    torch.set_num_threads(1)
    rows, summary = [], {}
    for k in args.sizes:
        for method in METHODS:
            for e in range(args.runs // k):
                seeds = list(range(FIRST_SEED + k * e, FIRST_SEED + k * (e + 1)))
                if k == 1:  # the run's own row: the same evaluation of the same policy
                    course = next(r["course"] for r in runs if r["method"] == method and r["seed"] == seeds[0])
                else:
                    actors = [torch.load(Path(args.cache) / actor_file(method, s, args.iterations),
                                         weights_only=False)["actor"]
                              for s in seeds]
                    course = task.evaluate(MeanPolicy(actors), TRACKING_EVAL_SEEDS)
                rows.append({"K": k, "method": method, "unit": e, "seeds": seeds, "course": course})
        summary[k] = {key: paired([r for r in rows if r["K"] == k], key)
                      for key in ("lateral_mae", "cost", "lateral_mean")}
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "rows.json", json.dumps({"runs": sorted(runs, key=lambda r: (r["method"], r["seed"])),
                                                     "ensembles": rows, "summary": summary}, indent=1) + "\n")
    budget = "" if args.iterations is None else f" of {args.iterations} iterations"
    lines = [f"Ensembles of K default runs{budget} on {SYSTEM} (experiments/analysis/ensemble_spread.py, {args.runs} runs per "
             "method, seeds 100 and up): model-driven minus mixed RL per pair of ensembles of the same seeds.", "",
             "| K | pairs | lateral MAE: mixed better | mean difference | paired sd | mixed mean (sd) | "
             "mixed signed lateral mean: sd | course cost: mixed better | mean difference | paired sd |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for k, s in summary.items():
        a, c, m = s["lateral_mae"], s["cost"], s["lateral_mean"]
        lines.append(f"| {k} | {a['units']} | {a['mixed_better']} | {a['difference_mean']:+.4f} | "
                     f"{a['difference_sd']:.4f} | {a['mixed_mean']:.4f} ({a['mixed_sd']:.4f}) | {m['mixed_sd']:.4f} | "
                     f"{c['mixed_better']} | {c['difference_mean']:+.3f} | {c['difference_sd']:.3f} |")
    atomic_write_text(out / "summary.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
