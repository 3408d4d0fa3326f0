"""Which component of the LQ feed-forward moves the course errors? Analysis of a finished sweep.

For every run of ``--method`` (default mixed RL) of a sweep of the double lane change (for example
``experiments/studies/table1_seeds20.toml``), its final actor is evaluated on the run's evaluation seeds with the
shift of the retired ``algorithm.feedforward = "lq"`` (to the LQ optimum's action at the equilibrium,
:func:`mixedrl.precision.feedforward_action`, by :class:`mixedrl.precision.FeedForwardPolicy`) applied to one
action component only: ``steer_only`` (the steering angle at the origin set to the LQ optimum's, the
acceleration left as learned) and ``ax_only`` (the other way round). Prints one line per seed and the
means (docs page ``precision.rst``)::

    PYTHONPATH=. python experiments/analysis/feedforward_components.py runs/table1_seeds20
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from mixedrl.precision import FeedForwardPolicy, equilibrium_observation, feedforward_action
from mixedrl.runs import RunDirectory, eval_seeds, load_checkpoint, make_trainer

COMPONENTS = {"steer_only": 0, "ax_only": 1}


def component_errors(run_dir: Path) -> dict[str, tuple[float, float]]:
    """``{name: (lateral_mae, speed_mae)}`` of the run's final actor with one component of the LQ shift."""
    run = RunDirectory(run_dir)
    cfg = run.read_config()
    trainer = make_trainer(cfg)
    trainer.load_state_dict(load_checkpoint(run.checkpoint_path)["trainer"])
    lin = trainer.task.linearisation()
    o_star = equilibrium_observation(trainer.task, lin)
    u_ff = feedforward_action(trainer, lin, trainer.learned_policy).float()
    bound = trainer.learned_policy.action_bound
    with torch.no_grad():
        learned = trainer.learned_policy(o_star[None])[0]
    out = {}
    for name, index in COMPONENTS.items():
        target = learned.clone()
        target[index] = u_ff[index]
        ev = trainer.task.evaluate(FeedForwardPolicy(trainer.learned_policy, o_star, target, bound), eval_seeds(cfg))
        out[name] = (float(ev["lateral_mae"]), float(ev["speed_mae"]))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("sweep", type=Path, help="a finished sweep directory (sweep.json)")
    parser.add_argument("--method", default="mixed", choices=("mixed", "model", "oracle"))
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    runs = [r for r in json.loads((args.sweep / "sweep.json").read_text())["runs"]
            if r["error"] is None and r["method"] == args.method]
    rows = []
    for rec in sorted(runs, key=lambda r: r["seed"]):
        res = component_errors(args.sweep / rec["run_dir"])
        rows.append([res["steer_only"][0], res["ax_only"][0], res["steer_only"][1], res["ax_only"][1]])
        print(f"seed {rec['seed']:>3}: lateral steer_only {rows[-1][0]:.4f} ax_only {rows[-1][1]:.4f} m; "
              f"speed steer_only {rows[-1][2]:.4f} ax_only {rows[-1][3]:.4f} m/s", flush=True)
    m = np.mean(rows, axis=0)
    print(f"mean over {len(rows)} seeds: lateral steer_only {m[0]:.4f} ax_only {m[1]:.4f} m; "
          f"speed steer_only {m[2]:.4f} ax_only {m[3]:.4f} m/s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
