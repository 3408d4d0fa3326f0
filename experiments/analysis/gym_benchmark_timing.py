"""Short measurements for the gym benchmark (issue 41): training speed and what the disturbance costs.

Not the study: one seed of each run of ``experiments/studies/gym_benchmark.toml`` with the budget cut to
``--steps`` (SB3; published hyperparameters otherwise, TD3/DDPG's 10k-step warm-up on Pendulum-v1 kept
and followed by 1k learning steps) and, for Algorithm 2, the full default budget on Pendulum-v1 (model
against oracle: the prior-model against the true-model policy) and mixed RL on both envs. Writes one
JSON per run into ``--out`` (resumable, as the study) and prints seconds per 1k steps or iterations::

    PYTHONPATH=. python experiments/analysis/gym_benchmark_timing.py --out runs/gym_benchmark_timing
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


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--spec", default=str(gb.SPEC))
    parser.add_argument("--out", default=str(gb.ROOT / "runs" / "gym_benchmark_timing"))
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--only", default=None)
    args = parser.parse_args()
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
