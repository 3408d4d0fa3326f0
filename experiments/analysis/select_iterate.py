"""Deploy the iterate of lowest model-predicted cost instead of the last one? Measured before it is built.

Why: on ``MountainCarContinuous-v0`` (issue 42's global target) every Algorithm-2 method reaches the goal on
9 of the 10 reported seeds; on seed 2 all three learn the swing, then collapse late (the last evaluations
give -34 to -39). On held-out seeds 100-127 (mixed RL, defaults) the last iterate reached the goal on all
28, and one run (seed 120) collapsed at one evaluation (-47.9) and recovered. A run that keeps snapshots of
its actor and deploys the one whose cost *in the planner's own model* is lowest would not deploy a
collapsed iterate, if the model sees the collapse; it uses no true transition.

**Pre-registered (stop 56, before any run of this script):** each run is trained once with the library
defaults; its actor is kept at every periodic evaluation point (``run.eval_every``) and at the end. Each
snapshot's *model cost* is :func:`model_cost` (the task's own evaluation loop, ``eval_starts`` starts from
``sample_initial``, ``eval_horizon`` steps, discounted, with the planner's step ``f(x, u) + E xi``, ``xi``
drawn from the run's final noise estimate: mixed RL's IBE, model-driven RL's prior, the oracle's true law;
the same draws for every snapshot), and each snapshot's true figure is the task's own evaluation (the same
for last and selected). The *selected* iterate is the snapshot of lowest model cost. It becomes the default
candidate (the next session builds it as a departure and re-measures every target) only if all hold:

1. the tuning systems (``cart_friction``, ``two_tank``, ``cart_noisy``, ``cart_drift_bias``, ``swing_up_eq``;
   seeds 100-102; mixed, model, oracle): the selected iterate's true cost is at most 1% above the last's
   on every run, and not above it on the mean;
2. ``MountainCarContinuous-v0`` held-out seeds 120-139 (mixed): the selected iterate's return is at least the
   last's minus 1 on every seed, and no selected iterate fails (return below 0);
3. the double lane change, held-out seeds 100 and 101 (mixed, model, oracle; the veto): the selected
   iterate's course cost is at most 1.02 times the last's on all six runs.

Otherwise its result goes to one line of the results page and nothing is built.

Usage::

    PYTHONPATH=. python experiments/analysis/select_iterate.py --part tuning --jobs 2
    PYTHONPATH=. python experiments/analysis/select_iterate.py --part car --jobs 2
    PYTHONPATH=. python experiments/analysis/select_iterate.py --part dlc --jobs 2
    PYTHONPATH=. python experiments/analysis/select_iterate.py --table-only

Each run writes ``experiments/results/select_iterate/per_run/<part>_<system>_<method>_<seed>.json`` (skipped
when it exists); ``--table-only`` (and every invocation at its end) writes ``table.md`` from them.
"""

from __future__ import annotations

import argparse
import copy
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

from experiments.tuning_systems import GLOBAL_TUNING_SYSTEMS, TUNING_SYSTEMS  # noqa: E402
from mixedrl.algorithms.agpi import AGPI  # noqa: E402
from mixedrl.config import TrainConfig  # noqa: E402
from mixedrl.gaussian import sample_gaussian  # noqa: E402
from mixedrl.runs import PeriodicObserver, atomic_write_text, eval_seeds, train  # noqa: E402
from mixedrl.tasks import task_from_config  # noqa: E402

OUT = ROOT / "experiments" / "results" / "select_iterate"
METHODS = ("mixed", "model", "oracle")
PARTS: dict[str, dict[str, Any]] = {
    "tuning": {"systems": ("cart_friction", "two_tank", "cart_noisy", "cart_drift_bias", "swing_up_eq"),
               "seeds": (100, 101, 102), "methods": METHODS},
    "car": {"systems": ("MountainCarContinuous-v0",), "seeds": tuple(range(120, 140)), "methods": ("mixed",)},
    "dlc": {"systems": ("dlc",), "seeds": (100, 101), "methods": METHODS},
}
#: The generator seeds of the model-cost rollouts (not the evaluation's seeds).
MODEL_SEEDS = (777001, 777002)
#: The pre-registered tolerances (module docstring).
TUNING_REL, CAR_ABS, DLC_REL = 0.01, 1.0, 1.02


class Snapshots(PeriodicObserver):
    """Keeps a copy of the actor's weights every ``every`` iterations (reads the trainer only)."""

    def __init__(self, every: int) -> None:
        super().__init__(every)
        self.kept: list[tuple[int, dict[str, torch.Tensor]]] = []

    def record(self, trainer: Any) -> dict[str, float]:
        self.kept.append((int(trainer.k), copy.deepcopy(trainer.actor.state_dict())))
        return {}


def model_cost(trainer: AGPI, policy: torch.nn.Module) -> float:
    """The task's evaluation loop (:meth:`mixedrl.task_base.Task.evaluate`) with the planner's step: discounted
    cost of ``eval_horizon`` steps from ``eval_starts`` starts, ``x' = f(x, u) + E xi``, ``xi ~ N(mu_hat, K_hat)``
    of the run's current noise estimate, per seed of :data:`MODEL_SEEDS`; the mean over seeds and starts."""
    task = trainer.task
    mean, cov = trainer.noise_moments()
    e = task.noise_matrix.double()
    n, costs = int(task.eval_starts), []
    with torch.no_grad():
        for seed in MODEL_SEEDS:
            gen = torch.Generator().manual_seed(seed)
            s = task.sample_initial(n, gen).to(torch.float64)
            alive = torch.ones(n, dtype=torch.bool)
            total = torch.zeros(n, dtype=torch.float64)
            for t in range(int(task.eval_horizon)):
                u = policy(task.observe(s.float())).double()
                xi = sample_gaussian(mean, cov, n, gen).to(torch.float64)
                s_next = task.f(s, u) + xi @ e.T
                total += torch.where(alive, task.gamma**t * task.cost(s_next, u).double(), torch.zeros_like(total))
                alive = alive & ~task.is_terminal(s_next)
                s = torch.where(alive[:, None], s_next, s)
            costs.append(float(total.mean()))
    return float(np.mean(costs))


def _build(part: str, system: str, method: str, seed: int, iterations: int | None) -> tuple[AGPI, Any, Any]:
    """The trainer (library defaults; ``iterations`` overrides the budget of a reduced run) and the true figure
    of a policy (``policy -> float``, lower is better)."""
    algorithm = {} if iterations is None else {"iterations": iterations}
    if part == "car":
        import gym_benchmark as gb
        from mixedrl.plant import GymnasiumPlant, attach_plant

        spec = gb.load_spec()
        env_spec = spec["envs"][system]
        dist = env_spec["disturbances"][0]
        task = gb.make_task(env_spec, dist)
        attach_plant(task, GymnasiumPlant(gb.make_env(system, dist)), evaluation="plant")
        probe = TrainConfig(method=method, task="linear", seed=seed, algorithm=algorithm)
        points = spec["evaluation"]["points"]
        config = TrainConfig(method=method, task="linear", seed=seed, algorithm=algorithm,
                             sampler={"name": "model_rollouts"},
                             run={"eval_every": max(1, probe.algorithm.iterations // points), "eval_seeds": 1,
                                  "num_threads": 1})
        episodes = spec["evaluation"]["episode_seeds"]

        def figure(policy: torch.nn.Module) -> float:  # the benchmark's return, as a cost
            return -gb.evaluate_policy(gb.task_actor(task, policy), system, dist, episodes)["return"]

        task.plant_evaluate = lambda policy, seeds, horizon=None: {"cost": figure(policy)}
        return AGPI(task, config), config, figure
    if part == "dlc":
        config = TrainConfig(method=method, seed=seed, algorithm=algorithm)
        task = task_from_config(config.task)
    else:
        config = TrainConfig(method=method, task="linear", seed=seed, algorithm=algorithm)
        task = {**TUNING_SYSTEMS, **GLOBAL_TUNING_SYSTEMS}[system]()
    seeds = eval_seeds(config)
    return AGPI(task, config), config, lambda policy: float(task.evaluate(policy, seeds)["cost"])


def one(part: str, system: str, method: str, seed: int, iterations: int | None = None) -> dict[str, Any]:
    path = _out(iterations) / "per_run" / f"{part}_{system}_{method}_{seed}.json"
    if path.exists():
        return json.loads(path.read_text())
    torch.set_num_threads(1)
    trainer, config, figure = _build(part, system, method, seed, iterations)
    snaps = Snapshots(config.run.eval_every)
    train(trainer, progress=False, observer=snaps)
    if not snaps.kept or snaps.kept[-1][0] != trainer.k:
        snaps.record(trainer)
    last = copy.deepcopy(trainer.actor.state_dict())
    rows = []
    for k, weights in snaps.kept:
        trainer.actor.load_state_dict(weights)
        rows.append({"iteration": k, "model_cost": model_cost(trainer, trainer.policy),
                     "true_cost": figure(trainer.policy)})
    trainer.actor.load_state_dict(last)
    best = min(range(len(rows)), key=lambda i: rows[i]["model_cost"])
    record = {"part": part, "system": system, "method": method, "seed": seed, "snapshots": rows,
              "selected": best, "last_true": rows[-1]["true_cost"], "selected_true": rows[best]["true_cost"],
              "config": config.to_dict()}
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(record, indent=1) + "\n")
    return record


def _out(iterations: int | None) -> Path:
    """The results' folder: :data:`OUT`, or ``OUT/reduced_<iterations>`` for a reduced run."""
    return OUT if iterations is None else OUT / f"reduced_{iterations}"


def _one(args: tuple[str, str, str, int, int | None]) -> dict[str, Any]:
    r = one(*args)
    print(f"{args}: last {r['last_true']:.5g}, selected {r['selected_true']:.5g} (snapshot {r['selected'] + 1}"
          f" of {len(r['snapshots'])})", file=sys.stderr, flush=True)
    return r


def table(out: Path = OUT) -> str:
    """``table.md`` from the per-run files: per run last vs selected, then each criterion's verdict."""
    records = [json.loads(p.read_text()) for p in sorted((out / "per_run").glob("*.json"))]
    lines = ["Last iterate against the iterate of lowest model-predicted cost (experiments/analysis/select_iterate.py;"
             " the criteria are its docstring's). True figure: cost (the car: minus the return).", "",
             "| part | system | method | seed | last | selected | selected snapshot | change |",
             "|---|---|---|---|---|---|---|---|"]
    verdicts: dict[str, list[bool]] = {}
    for r in records:
        last, sel = r["last_true"], r["selected_true"]
        change = sel - last if r["part"] == "car" else (sel / last - 1 if last else 0.0)
        if r["part"] == "tuning":
            ok = sel <= last + TUNING_REL * abs(last)
        elif r["part"] == "car":
            ok = -sel >= -last - CAR_ABS and -sel >= 0
        else:
            ok = sel <= DLC_REL * last
        verdicts.setdefault(r["part"], []).append(bool(ok))
        lines.append(f"| {r['part']} | {r['system']} | {r['method']} | {r['seed']} | {last:.5g} | {sel:.5g} | "
                     f"{r['selected'] + 1} of {len(r['snapshots'])} | "
                     f"{change:+.4g}{'' if r['part'] == 'car' else ' (rel)'} | ")
    lines.append("")
    for part, oks in verdicts.items():
        extra = ""
        if part == "tuning":
            rs = [r for r in records if r["part"] == part]
            mean_ok = np.mean([r["selected_true"] for r in rs]) <= np.mean([r["last_true"] for r in rs])
            extra = f"; mean not above the last's: {'yes' if mean_ok else 'NO'}"
        lines.append(f"- {part}: within the tolerance on {sum(oks)} of {len(oks)} runs{extra}")
    fails = [r for r in records if r["part"] == "car" and any(-x["true_cost"] < 0 for x in r["snapshots"])]
    for r in fails:
        lines.append(f"  - car seed {r['seed']}: snapshots' (model cost, return) "
                     + ", ".join(f"({x['model_cost']:.4g}, {-x['true_cost']:.1f})" for x in r["snapshots"]))
    text = "\n".join(lines) + "\n"
    atomic_write_text(out / "table.md", text)
    return text


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", choices=tuple(PARTS), action="append", default=[])
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--table-only", action="store_true")
    ap.add_argument("--iterations", type=int, default=None, help="a reduced budget (results in OUT/reduced_N)")
    args = ap.parse_args(argv)
    if not args.table_only:
        jobs = [(part, system, method, seed, args.iterations) for part in args.part for system in PARTS[part]["systems"]
                for seed in PARTS[part]["seeds"] for method in PARTS[part]["methods"]]
        if args.jobs > 1:
            with multiprocessing.get_context("spawn").Pool(args.jobs) as pool:
                list(pool.imap_unordered(_one, jobs))
        else:
            for job in jobs:
                _one(job)
    sys.stdout.write(table(_out(args.iterations)))


if __name__ == "__main__":
    main()
