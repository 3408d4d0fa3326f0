"""The calibrated shift (``algorithm.feedforward_calibration``, :func:`mixedrl.departures.calibration.calibrate_shift`)
against the shift alone, on the tuning systems near an equilibrium only.

The departure changes only the deployed policy, so one run gives both: a run is trained at the library defaults
of commit 68e4d9a, where this study ran (``TrainConfig(method=..., task="linear", seed=...)`` with the tuning task
object given to the trainer; ``feedforward_calibration`` 0, its default there, pinned since) and its final actor
evaluated with ``feedforward_calibration`` 0 (``shift``: that commit's default deployed policy, ``"lq_handover"``)
and 1 (``calibrated``: the default since, chosen by the criterion below). Per run, on
:func:`mixedrl.run_results.eval_seeds`: the cost over the discounted LQR with the true feed-forward on the same seeds,
and every state component's steady offset against the LQR's (issue 42's tolerance ``0.1 |LQR's| + 1e-3
obs_scale``, ``tuning_baseline``'s measures).

Why: on the linear test bed the default misses the offset target on 4 of 10 seeds for mixed RL and 5 of 10 for the
oracle, always above the LQR's, while its cost is the LQR's to 0.2%: a bias of the deployed actor, not of the IBE.
On ``cart_noisy`` (a tuning system) a screen with a scratch version of the calibration (three Newton steps on
the evaluator's own rollouts run in the model; seeds 103-107, mixed and oracle) found the same bias (position
offsets 0.027-0.034 m against the LQR's 0.032-0.035 m, the oracle's below the LQR's on 5 of 5 seeds) and brought
the oracle's to within 0.0003 m of the LQR's (mixed RL's to 0.031-0.041 m), at +0.06% to +0.08% of cost; on
``cart_friction`` and ``two_tank`` (103-104) the shift alone already rests at the LQR's offset and the
calibration moved nothing.

Criterion, fixed before the confirmation runs (fresh seeds 110-119; ``feedforward_calibration = 1``); the default
becomes 1 only if all hold:

(a) offsets within target, mixed RL and the oracle summed over the four systems: ``calibrated`` at least
    ``shift`` + 4 (of 80), and no system-method cell loses more than one seed;
(b) cost: on every system and method (model-driven RL included) the mean over seeds of ``calibrated / shift``
    at most 1.001;
(c) wall time: one calibration at most 2% of a default run's wall time (``calibration_seconds`` below).

Seeds 100 and up (0-9 belong to the targets). Each run writes ``runs/<system>_<method>_<seed>.json`` atomically and
is skipped when present with the same config; ``summary.md`` and ``rows.json`` are written from every run present.

Usage (two processes, about 40 minutes)::

    PYTHONPATH=. python experiments/analysis/offset_calibration.py --seeds $(seq 110 119)
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

from experiments.tuning_systems import TUNING_SYSTEMS, LQRPolicy  # noqa: E402
from tuning_baseline import OFFSET_ABS, OFFSET_REL  # noqa: E402
from mixedrl.algorithms.agpi import AGPI  # noqa: E402
from mixedrl.config import TrainConfig  # noqa: E402
from mixedrl.run_results import eval_seeds  # noqa: E402
from mixedrl.runs import atomic_write_text, train  # noqa: E402
from mixedrl.tasks import Task  # noqa: E402

OUT = ROOT / "experiments" / "results" / "offset_calibration"
SYSTEMS = ("cart_noisy", "cart_friction", "two_tank", "cart_drift")
METHODS = ("mixed", "model", "oracle")
POLICIES = {"shift": 0, "calibrated": 1}


def measure(task: Any, policy: torch.nn.Module, seeds: list[int]) -> dict[str, Any]:
    """Cost and every component's steady offset of ``policy`` on the true system."""
    out = task.evaluate(policy, seeds)
    if "mean_state_0" not in out:
        out.update({k: v for k, v in Task.evaluate(task, policy, seeds).items() if k.startswith("mean_state_")})
    return {"cost": out["cost"], "offsets": [out[f"mean_state_{i}"] for i in range(task.state_dim)]}


def run_one(args: tuple[str, str, int]) -> dict[str, Any]:
    """Train one run and evaluate its final actor with each calibration (module docstring)."""
    system, method, seed = args
    torch.set_num_threads(1)
    # the library defaults of commit 68e4d9a, where the study ran (training does not read the calibration)
    config = TrainConfig(method=method, task="linear", seed=seed, algorithm={"feedforward_calibration": 0})
    saved_config = json.loads(json.dumps(config.to_dict()))
    path = OUT / "runs" / f"{system}_{method}_{seed}.json"
    if path.exists():
        row = json.loads(path.read_text())
        if row["config"] == saved_config:
            return row
    task = TUNING_SYSTEMS[system]()
    t0 = time.time()
    trainer = AGPI(task, config)
    train(trainer, progress=False)
    wall = time.time() - t0
    seeds = eval_seeds(config)
    row: dict[str, Any] = {"system": system, "method": method, "seed": seed, "config": saved_config,
                           "wall_seconds": wall, "feedforward": trainer.feedforward}
    for name, steps in POLICIES.items():
        trainer.config.algorithm.feedforward_calibration = steps
        t1 = time.time()
        policy = trainer.policy
        row[name] = {"build_seconds": time.time() - t1, **measure(task, policy, seeds)}
        if steps:
            row[name]["delta"] = np.asarray(trainer._calibration[1]).tolist()
    lqr = measure(task, LQRPolicy(task, np.asarray(task.true_mean, dtype=np.float64)), seeds)
    scale = task.obs_scale.double().numpy()
    row["lqr_true"] = {**lqr, "tolerance": [OFFSET_REL * abs(o) + OFFSET_ABS * float(scale[i])
                                            for i, o in enumerate(lqr["offsets"])]}
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(row, indent=1) + "\n")
    return row


def within(row: dict[str, Any], policy: str) -> bool:
    """Every component's offset within the tolerance of the LQR's."""
    lqr = row["lqr_true"]
    return all(abs(o - lo) <= t for o, lo, t in zip(row[policy]["offsets"], lqr["offsets"], lqr["tolerance"]))


def write_summary() -> list[str]:
    """``summary.md`` and ``rows.json`` from every run present."""
    rows = [json.loads(p.read_text()) for p in sorted((OUT / "runs").glob("*.json"))]
    lines = ["# The calibrated shift against the shift alone (experiments/analysis/offset_calibration.py)", "",
             "One run per system, method and seed at the library default, its final actor deployed with "
             "`algorithm.feedforward_calibration` 0 (`shift`, the default's policy) and 1 (`calibrated`). "
             "Tuning systems and seeds only. Offset: the controlled component's (cart: position, two-tank: the lower "
             "level); within target: every component within 0.1 |LQR's| + 1e-3 obs_scale of the LQR's.", "",
             "| system | method | seeds | within target: shift | calibrated | cost ratio calibrated / shift: mean "
             "(largest) | mean abs(offset - LQR's): shift | calibrated | cost / LQR: shift | calibrated |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    controlled = {"two_tank": 1}
    totals = {p: 0 for p in POLICIES}
    for system in SYSTEMS:
        for method in METHODS:
            rs = sorted((r for r in rows if r["system"] == system and r["method"] == method), key=lambda r: r["seed"])
            if not rs:
                continue
            c = controlled.get(system, 0)
            ratio = [r["calibrated"]["cost"] / r["shift"]["cost"] for r in rs]
            dev = {p: np.mean([abs(r[p]["offsets"][c] - r["lqr_true"]["offsets"][c]) for r in rs]) for p in POLICIES}
            n_in = {p: sum(within(r, p) for r in rs) for p in POLICIES}
            if method != "model":
                for p in POLICIES:
                    totals[p] += n_in[p]
            lqr = {p: np.mean([r[p]["cost"] / r["lqr_true"]["cost"] for r in rs]) for p in POLICIES}
            seeds = [r["seed"] for r in rs]
            lines.append(f"| {system} | {method} | {seeds[0]}-{seeds[-1]} ({len(rs)}) | {n_in['shift']}/{len(rs)} | "
                         f"{n_in['calibrated']}/{len(rs)} | {np.mean(ratio):.5f} ({max(ratio):.5f}) | "
                         f"{dev['shift']:.5f} | {dev['calibrated']:.5f} | {lqr['shift']:.4f} | {lqr['calibrated']:.4f} |")
    walls = [r["wall_seconds"] for r in rows]
    builds = [r["calibrated"]["build_seconds"] for r in rows]
    lines += ["", f"Within target, mixed RL and the oracle over the systems: shift {totals['shift']}, calibrated "
              f"{totals['calibrated']}.", "",
              f"Wall time {np.mean(walls):.0f} s per run (two runs side by side); one calibration "
              f"(`calibration_seconds`: building the calibrated policy) {np.mean(builds):.2f} s on average, largest "
              f"{max(builds):.2f} s ({100 * np.mean(builds) / np.mean(walls):.1f}% of a run).", ""]
    atomic_write_text(OUT / "summary.md", "\n".join(lines))
    atomic_write_text(OUT / "rows.json", json.dumps([{k: v for k, v in r.items() if k != "config"} for r in rows],
                                                    indent=1) + "\n")
    return lines


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--systems", nargs="+", choices=SYSTEMS, default=list(SYSTEMS))
    ap.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS))
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(110, 120)))
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--summary-only", action="store_true")
    args = ap.parse_args(argv)
    if any(s < 100 for s in args.seeds):
        raise SystemExit("--seeds: the tuning seeds are 100 and up (0-9 belong to the targets)")
    jobs = [] if args.summary_only else [(s, m, seed) for seed in args.seeds for s in args.systems
                                         for m in args.methods]
    with multiprocessing.get_context("fork").Pool(args.jobs) as pool:
        for i, row in enumerate(pool.imap_unordered(run_one, jobs), 1):
            print(f"[{i}/{len(jobs)}] {row['system']} {row['method']} {row['seed']}: shift {row['shift']['offsets']} "
                  f"calibrated {row['calibrated']['offsets']} lqr {row['lqr_true']['offsets']} "
                  f"({row['wall_seconds']:.0f} s)", file=sys.stderr, flush=True)
    print("\n".join(write_summary()))


if __name__ == "__main__":
    main()
