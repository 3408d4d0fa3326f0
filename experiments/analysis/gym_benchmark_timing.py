"""Short measurements for the gym benchmark (issue 41): training speed and what the disturbance costs.

Not the study: one seed of each run of ``experiments/studies/gym_benchmark.toml`` with the budget cut to
``--steps`` (SB3; published hyperparameters otherwise, TD3/DDPG's 10k-step warm-up on Pendulum-v1 kept
and followed by 1k learning steps) and, for Algorithm 2, the full default budget on Pendulum-v1 (model
against oracle: the prior-model against the true-model policy) and mixed RL on both envs. Writes one
JSON per run into ``--out`` (resumable, as the study) and prints seconds per 1k steps or iterations;
``--estimate`` turns those JSONs into the full study's time on one core (:func:`estimate`)::

    PYTHONPATH=. python experiments/analysis/gym_benchmark_timing.py --out runs/gym_benchmark_timing
    PYTHONPATH=. python experiments/analysis/gym_benchmark_timing.py --out runs/gym_benchmark_timing --estimate
"""

from __future__ import annotations

import argparse
import json
import sys
from copy import deepcopy
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import gym_benchmark as gb  # noqa: E402


def measurement_runs(spec: dict, steps: int) -> list[dict]:
    runs = []
    for run in gb.expand_runs(spec):
        if run["seed"] != 0:
            continue
        run = deepcopy(run)
        if run["kind"] == "sb3":
            hp = run["hyperparams"]
            warm = int(hp.get("learning_starts", 100))
            total = warm + 1000 if warm >= 1000 else steps
            run["reduced"] = {"n_timesteps": total, "learning_starts": warm,
                              "buffer_size": int(hp.get("buffer_size", 1_000_000))}
            run["evaluation"]["points"] = max(1, total // 1000)
        elif run["env"] != "Pendulum-v1" and run["method"] != "mixed":
            continue
        elif run["env"] != "Pendulum-v1":
            run["evaluation"]["points"] = 1
        run["id"] = gb.run_id(run) + "__timing"
        runs.append(run)
    return runs


def rates(results: list[dict]) -> dict[tuple[str, str], dict[str, float]]:
    """Per (env, method): seconds per 1k warm-up steps and per 1k learning steps (SB3) or iterations
    (Algorithm 2), and milliseconds per evaluation step, from the measurement JSONs."""
    out = {}
    for r in results:
        c = r["config"]
        rows = r["rows"]
        evals = sum(x["transitions"] for x in rows)
        rate = {"eval_ms": 1000 * (r["wall_seconds"] - r["train_seconds"]) / max(1, evals)}
        if c["kind"] == "sb3":
            warm = int(c["reduced"]["learning_starts"])
            before = [x for x in rows if 0 < x["true_transitions"] <= warm]
            last = before[-1] if before else None
            rate["warm_s_per_1k"] = 1000 * last["wall_seconds"] / last["true_transitions"] if last else 0.2
            spent_warm = rate["warm_s_per_1k"] * min(warm, r["steps"]) / 1000
            rate["learn_s_per_1k"] = 1000 * (r["train_seconds"] - spent_warm) / max(1, r["steps"] - warm)
        else:
            rate["learn_s_per_1k"] = 1000 * r["train_seconds"] / r["steps"]
        out[(c["env"], c["method"])] = rate
    return out


def estimate(spec: dict, measured: dict[tuple[str, str], dict[str, float]]) -> list[dict]:
    """Seconds of the full study per (env, method) on one core: training from the measured rates (a
    pair not measured borrows the same method's rate on the other env, or mixed RL's on the same env:
    ``borrowed``), evaluation as (points + 1) evaluations of every episode seed at the env's full episode
    length (an upper bound for the car, which can end early)."""
    from mixedrl.config import TrainConfig
    from mixedrl.schedule import resolve_budget

    episode = {"Pendulum-v1": 200, "MountainCarContinuous-v0": 999}
    groups: dict[tuple[str, str], list[dict]] = {}
    for run in gb.expand_runs(spec):
        groups.setdefault((run["env"], run["method"]), []).append(run)
    rows = []
    for (env, method), runs in groups.items():
        key, borrowed = (env, method), None
        if key not in measured:
            other = [k for k in measured if k[1] == method and runs[0]["kind"] == "sb3"]
            key = other[0] if other else (env, "mixed")
            borrowed = f"{key[1]} on {key[0]}"
        rate, run = measured[key], runs[0]
        if run["kind"] == "sb3":
            total = int(run["hyperparams"]["n_timesteps"])
            warm = min(total, int(run["hyperparams"].get("learning_starts", 100)))
            train = rate.get("warm_s_per_1k", 0.2) * warm / 1000 + rate["learn_s_per_1k"] * (total - warm) / 1000
        else:
            # the budget its trainer resolves (a task that declares its state region: region_budget x the iterations)
            config = resolve_budget(TrainConfig(method=run["mixedrl_method"]),
                                    gb.make_task(run["env_spec"], run["disturbance"]))[0]
            train = rate["learn_s_per_1k"] * config.algorithm.iterations / 1000
        ev = run["evaluation"]
        evals = (ev["points"] + 1) * len(ev["episode_seeds"]) * episode[env] * measured.get(
            (env, method), rate)["eval_ms"] / 1000
        rows.append({"env": env, "method": method, "runs": len(runs), "train_s_per_run": round(train),
                     "eval_s_per_run": round(evals), "total_s": round(len(runs) * (train + evals)),
                     "borrowed": borrowed})
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--spec", default=str(gb.SPEC))
    parser.add_argument("--out", default=str(gb.ROOT / "runs" / "gym_benchmark_timing"))
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--only", default=None)
    parser.add_argument("--estimate", action="store_true", help="only the estimate, from the JSONs in --out")
    args = parser.parse_args()
    if args.estimate:
        results = [json.loads(p.read_text()) for p in sorted(Path(args.out).glob("*__timing.json"))]
        rows = estimate(gb.load_spec(args.spec), rates(results))
        for row in rows:
            print(json.dumps(row))
        total = sum(r["total_s"] for r in rows)
        print(f"full study: {total} s = {total / 3600:.1f} h on one core; the longest run "
              f"{max(r['train_s_per_run'] + r['eval_s_per_run'] for r in rows) / 3600:.1f} h")
        return 0
    runs = measurement_runs(gb.load_spec(args.spec), args.steps)
    if args.only:
        runs = [r for r in runs if args.only in r["id"]]
    for run in runs:
        res, _ = gb.run_one(run, Path(args.out))
        rows = res["rows"]
        per = [(b["wall_seconds"] - a["wall_seconds"]) / max(1, b["true_transitions"] - a["true_transitions"]) * 1000
               for a, b in zip(rows, rows[1:])] if run["kind"] == "sb3" else []
        print(json.dumps({"id": run["id"], "train_seconds": round(res["train_seconds"], 2), "steps": res["steps"],
                          "s_per_1k": round(1000 * res["train_seconds"] / max(1, res["steps"]), 2),
                          "s_per_1k_by_segment": [round(p, 2) for p in per],
                          "true_transitions": res["true_transitions"],
                          "final_return": round(res["final_return"], 1),
                          "returns_along": [round(r["return"], 1) for r in rows]}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
