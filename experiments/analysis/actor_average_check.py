"""The averaged actor (:mod:`mixedrl.departures.actor_average`) against the last one, on the tuning systems only.

The departure leaves training unchanged, so one run gives both policies: a run is trained at the library default
(``learner_tuning``'s variant ``default``) with ``algorithm.actor_average_window = --window`` and evaluated twice, with its
averaged actor (``average``) and with the averaged actor removed (``last``: exactly the run without the departure).
Per system, mixed and model-driven RL on the same seeds:

* ``slalom_weak`` (tracking, :mod:`experiments.tuning_tracking`): course cost and lateral MAE over the course
  (``learner_tuning.TRACKING_EVAL_SEEDS``); the paired model-driven minus mixed difference per seed and its spread;
* ``cart_friction``, ``two_tank`` (near an equilibrium, :mod:`experiments.tuning_systems`): cost over the discounted
  LQR with the true feed-forward and the controlled state's steady offset (``tuning_baseline``'s measures);
* ``swing_up`` (global): the return of 20 episodes (IQM), as ``learner_tuning``'s global rows.

Seeds 100 and up (0-9 belong to the targets). Each run writes ``runs/<system>_<method>_<seed>.json`` (its config and
both evaluations) atomically and is skipped when present with the same config; ``summary.md`` and ``rows.json`` are
written from every run present, a table per system and block of consecutive seeds.

Usage (two processes; the screen, its confirmation on fresh seeds, the other tuning systems; about 15, 25 and 35
minutes)::

    PYTHONPATH=. python experiments/analysis/actor_average_check.py --systems slalom_weak --seeds $(seq 100 109)
    PYTHONPATH=. python experiments/analysis/actor_average_check.py --systems slalom_weak --seeds $(seq 140 159)
    PYTHONPATH=. python experiments/analysis/actor_average_check.py --systems cart_friction two_tank swing_up \
        --seeds $(seq 100 109)
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
for p in (ROOT, ROOT / "experiments" / "analysis"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from experiments.tuning_systems import GLOBAL_TUNING_SYSTEMS, TUNING_SYSTEMS, LQRPolicy  # noqa: E402
from experiments.tuning_tracking import TRACKING_TUNING_SYSTEMS  # noqa: E402
from learner_tuning import ONESTEP, TRACKING_EVAL_SEEDS, VARIANTS  # noqa: E402
from tuning_baseline import CONTROLLED, OFFSET_ABS, OFFSET_REL  # noqa: E402
from mixedrl.algorithms.agpi import AGPI  # noqa: E402
from mixedrl.config import TrainConfig  # noqa: E402
from mixedrl.run_results import eval_seeds  # noqa: E402
from mixedrl.runs import atomic_write_text, train  # noqa: E402
from mixedrl.tasks import Task  # noqa: E402

OUT = ROOT / "experiments" / "results" / "actor_average"
SYSTEMS: dict[str, Any] = {"slalom_weak": TRACKING_TUNING_SYSTEMS["slalom_weak"],
                           "cart_friction": TUNING_SYSTEMS["cart_friction"], "two_tank": TUNING_SYSTEMS["two_tank"],
                           "swing_up": GLOBAL_TUNING_SYSTEMS["swing_up"]}
METHODS = ("mixed", "model")
POLICIES = ("last", "average")


def measure(system: str, task: Any, trainer: AGPI, seeds: list[int]) -> dict[str, Any]:
    """The system's measures of ``trainer.policy`` (what the run deploys)."""
    if system in TRACKING_TUNING_SYSTEMS:
        c = task.evaluate(trainer.policy, TRACKING_EVAL_SEEDS)
        return {"cost": c["cost"], "lateral_mae": c["lateral_mae"], "lateral_mean": c["lateral_mean"]}
    if system in GLOBAL_TUNING_SYSTEMS:
        return {"returns": task.evaluate_return(trainer.policy, episodes=20)}
    out = task.evaluate(trainer.policy, seeds)
    if "mean_state_0" not in out:
        out.update({k: v for k, v in Task.evaluate(task, trainer.policy, seeds).items() if k.startswith("mean_state_")})
    return {"cost": out["cost"], "offset": out[f"mean_state_{CONTROLLED[system]}"]}


def run_one(args: tuple[str, str, int, float]) -> dict[str, Any]:
    """Train one run and evaluate it with its last and its averaged actor (module docstring)."""
    system, method, seed, window = args
    torch.set_num_threads(1)
    config = TrainConfig(method=method, task="linear", seed=seed,
                         algorithm={**ONESTEP, **VARIANTS["default"], "actor_average_window": window})
    saved_config = json.loads(json.dumps(config.to_dict()))
    path = OUT / "runs" / f"{system}_{method}_{seed}.json"
    if path.exists():
        row = json.loads(path.read_text())
        if row["config"] == saved_config:
            return row
    task = SYSTEMS[system]()
    t0 = time.time()
    trainer = AGPI(task, config)
    train(trainer, progress=False)
    wall = time.time() - t0
    seeds = eval_seeds(config)
    row: dict[str, Any] = {"system": system, "method": method, "seed": seed, "config": saved_config,
                           "wall_seconds": wall, "averaged_iterations": int(trainer.actor_average.n_averaged),
                           "feedforward": trainer.feedforward}
    row["average"] = measure(system, task, trainer, seeds)
    average, trainer.actor_average = trainer.actor_average, None  # the same run deploying its last actor
    row["last"] = measure(system, task, trainer, seeds)
    trainer.actor_average = average
    if system in TUNING_SYSTEMS:
        lqr = task.evaluate(LQRPolicy(task, np.asarray(task.true_mean, dtype=np.float64)), seeds)
        if "mean_state_0" not in lqr:
            lqr.update(Task.evaluate(task, LQRPolicy(task, np.asarray(task.true_mean, dtype=np.float64)), seeds))
        row["lqr_true"] = {"cost": lqr["cost"], "offset": lqr[f"mean_state_{CONTROLLED[system]}"],
                           "offset_tolerance": OFFSET_REL * abs(lqr[f"mean_state_{CONTROLLED[system]}"])
                           + OFFSET_ABS * float(task.obs_scale[CONTROLLED[system]])}
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(row, indent=1) + "\n")
    return row


def iqm(values: list[float]) -> float:
    """Interquartile mean (the middle half of the sorted values)."""
    v = np.sort(np.asarray(values, dtype=np.float64))
    q = len(v) // 4
    return float(v[q:len(v) - q].mean())


def lines_for(system: str, rows: list[dict[str, Any]]) -> list[str]:
    """The summary lines of one system."""
    by = {(r["method"], r["seed"]): r for r in rows}
    seeds = sorted({s for m, s in by if all((x, s) in by for x in METHODS)})
    out = [f"### {system} (seeds {seeds[0]}-{seeds[-1]}, {len(seeds)} per method)", ""]
    if system in TRACKING_TUNING_SYSTEMS:
        out += ["| policy | lateral MAE: mixed better | mean diff (model - mixed) | paired sd | mixed MAE (sd) | "
                "model MAE (sd) | course cost: mixed better | mixed cost |", "|---|---|---|---|---|---|---|---|"]
        for p in POLICIES:
            d = np.array([by["model", s][p]["lateral_mae"] - by["mixed", s][p]["lateral_mae"] for s in seeds])
            c = np.array([by["model", s][p]["cost"] - by["mixed", s][p]["cost"] for s in seeds])
            mx = np.array([by["mixed", s][p]["lateral_mae"] for s in seeds])
            mo = np.array([by["model", s][p]["lateral_mae"] for s in seeds])
            out.append(f"| {p} | {int((d > 0).sum())}/{len(d)} | {d.mean():+.4f} | {d.std(ddof=1):.4f} | "
                       f"{mx.mean():.4f} ({mx.std(ddof=1):.4f}) | {mo.mean():.4f} ({mo.std(ddof=1):.4f}) | "
                       f"{int((c > 0).sum())}/{len(c)} | "
                       f"{np.mean([by['mixed', s][p]['cost'] for s in seeds]):.3f} |")
    elif system in GLOBAL_TUNING_SYSTEMS:
        out += ["| policy | method | return IQM over seeds (of each run's 20-episode IQM) | worst run | "
                "runs better than the other policy |", "|---|---|---|---|---|"]
        for p in POLICIES:
            other = POLICIES[1 - POLICIES.index(p)]
            for m in METHODS:
                v = [by[m, s][p]["returns"]["iqm"] for s in seeds]
                better = sum(by[m, s][p]["returns"]["iqm"] > by[m, s][other]["returns"]["iqm"] for s in seeds)
                out.append(f"| {p} | {m} | {iqm(v):.1f} | {min(v):.1f} | {better}/{len(seeds)} |")
    else:
        out += ["| policy | method | cost / LQR(true) mean (worst) | offset within target | mean abs(offset - LQR's) |",
                "|---|---|---|---|---|"]
        for p in POLICIES:
            for m in METHODS:
                rs = [by[m, s] for s in seeds]
                ratio = [r[p]["cost"] / r["lqr_true"]["cost"] for r in rs]
                dev = [abs(r[p]["offset"] - r["lqr_true"]["offset"]) for r in rs]
                within = sum(d <= r["lqr_true"]["offset_tolerance"] for d, r in zip(dev, rs))
                out.append(f"| {p} | {m} | {np.mean(ratio):.4f} ({max(ratio):.4f}) | {within}/{len(rs)} | "
                           f"{np.mean(dev):.5f} |")
    walls = [r["wall_seconds"] for r in rows]
    out += ["", f"Wall time {np.mean(walls):.0f} s per run (two runs side by side); averaged iterations per run: "
            f"{sorted({r['averaged_iterations'] for r in rows})}.", ""]
    return out


def write_summary() -> list[str]:
    """``summary.md`` and ``rows.json`` from every run present."""
    rows = [json.loads(p.read_text()) for p in sorted((OUT / "runs").glob("*.json"))]
    windows = sorted({r["config"]["algorithm"]["actor_average_window"] for r in rows})
    lines = ["# The averaged actor against the last one (experiments/analysis/actor_average_check.py)", "",
             f"One run per system, method and seed at the library default with `algorithm.actor_average_window` "
             f"{windows}, evaluated with its last actor (`last`: the run without the departure) and its averaged "
             "actor (`average`). Tuning systems and seeds only.", ""]
    for system in SYSTEMS:
        seeds = sorted({r["seed"] for r in rows if r["system"] == system})
        blocks = [[s] for s in seeds[:1]]
        for s in seeds[1:]:  # consecutive seeds form one block (a screen, a confirmation), each its own table
            if s == blocks[-1][-1] + 1:
                blocks[-1].append(s)
            else:
                blocks.append([s])
        for block in blocks:
            lines += lines_for(system, [r for r in rows if r["system"] == system and r["seed"] in block])
    atomic_write_text(OUT / "summary.md", "\n".join(lines))
    atomic_write_text(OUT / "rows.json", json.dumps([{k: v for k, v in r.items() if k != "config"} for r in rows],
                                                    indent=1) + "\n")
    return lines


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--systems", nargs="+", choices=sorted(SYSTEMS), default=sorted(SYSTEMS))
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(100, 110)))
    ap.add_argument("--window", type=float, default=0.5, help="algorithm.actor_average_window, in (0, 1]")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--summary-only", action="store_true")
    args = ap.parse_args(argv)
    if any(s < 100 for s in args.seeds):
        raise SystemExit("--seeds: the tuning seeds are 100 and up (0-9 belong to the targets)")
    if not 0 < args.window <= 1:
        raise SystemExit(f"--window: expected a fraction in (0, 1], got {args.window}")
    jobs = [] if args.summary_only else [(s, m, seed, args.window) for s in args.systems for seed in args.seeds
                                         for m in METHODS]
    with multiprocessing.get_context("fork").Pool(args.jobs) as pool:
        for i, row in enumerate(pool.imap_unordered(run_one, jobs), 1):
            print(f"[{i}/{len(jobs)}] {row['system']} {row['method']} {row['seed']}: last {row['last']} "
                  f"average {row['average']} ({row['wall_seconds']:.0f} s)", file=sys.stderr, flush=True)
    print("\n".join(write_summary()))


if __name__ == "__main__":
    main()
