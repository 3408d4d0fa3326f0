"""What happens when Algorithm 2 trains longer than the reproduction's budget (docs/reproduction.rst).

Trains mixed RL and the oracle (seed 0, the reproduction's config except ``iterations``; the learning rates
decay over ``lr_decay_iterations`` = 1500 iterations and then stay at 1%) and, every ``--every`` iterations,
records

* the Table I errors and the total cost of the course (:meth:`DoubleLaneChangeTask.evaluate`);
* ``J_train``: the discounted cost (gamma = 0.99, 400 steps, true noise) of the current policy from a
  fixed set of 1024 start states drawn from the *wide* training distribution (``sample_initial``; the
  whole batch of the earlier design, a quarter of the model batch now);
* the policy at the origin of the observation (on the reference, at 12 m/s): its action ``pi(0)`` and
  its Jacobian ``d pi / d obs`` (the linear feedback gains), beside the gains of the discounted LQR of the
  linearised model (python-control ``dlqr``, :func:`vehicle_figures.lqr_gain`) and that LQR's course
  errors.

Writes ``long_training.csv``, ``long_training.json`` and ``long_training.png`` to the output directory.

Usage: ``PYTHONPATH=. python scripts/long_training.py [--iterations 10000] [--every 500] [outdir]``
(default ``docs/_static/reproduction``); about 5 minutes on 2 cores for 10000 iterations (the two runs in
parallel, on a quiet machine).
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import sys
from multiprocessing import Pool
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from mixedrl.config import TrainConfig  # noqa: E402
from mixedrl.envs import DoubleLaneChangeModel, evaluate_tracking  # noqa: E402
from mixedrl.runs import atomic_write_bytes, atomic_write_text, make_trainer, train  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from vehicle_figures import lqr_gain  # noqa: E402

OBS_NAMES = ["v_y", "r", "v_x-12", "e_phi", "e_y"]
EVAL_SEEDS = [1, 2]


def discounted_cost(task: Any, actor: torch.nn.Module, starts: torch.Tensor, steps: int = 400,
                    seed: int = 999) -> float:
    """Mean over ``starts`` of sum_t gamma^t l(s_{t+1}, u_t) under the true noise (frozen after leaving)."""
    gen = torch.Generator().manual_seed(seed)
    s = starts.clone()
    total = torch.zeros(s.shape[0], dtype=torch.float64)
    alive = torch.ones(s.shape[0], dtype=torch.bool)
    with torch.no_grad():
        for t in range(steps):
            u = actor(task.observe(s.float())).double()
            s_next = task.true_step(s, u, gen)
            total += torch.where(alive, task.gamma**t * task.cost(s_next, u), torch.zeros_like(total))
            alive &= ~task.is_terminal(s_next)
            s = torch.where(alive[:, None], s_next, s)
    return float(total.mean())


def policy_at_origin(actor: torch.nn.Module) -> tuple[np.ndarray, np.ndarray]:
    """``pi(0)`` (2,) and ``d pi / d obs`` at 0 (2, 5)."""
    jac = torch.autograd.functional.jacobian(lambda o: actor(o[None])[0], torch.zeros(5))
    with torch.no_grad():
        u0 = actor(torch.zeros(1, 5))[0]
    return u0.numpy().astype(float), jac.numpy().astype(float)


def run(job: dict[str, Any]) -> list[dict[str, float]]:
    torch.set_num_threads(1)
    cfg = TrainConfig(method=job["method"], seed=0, iterations=job["iterations"], eval_every=job["iterations"])
    trainer = make_trainer(cfg)
    task = trainer.task
    starts = task.sample_initial(1024, torch.Generator().manual_seed(12345))
    rows: list[dict[str, float]] = []

    def record(k: int) -> None:
        ev = task.evaluate(trainer.policy, EVAL_SEEDS)
        u0, jac = policy_at_origin(trainer.policy)
        row = {"method": job["method"], "iteration": k, "lateral_mae": ev["lateral_mae"],
               "speed_mae": ev["speed_mae"], "course_cost": ev["cost"],
               "J_train": discounted_cost(task, trainer.policy, starts),
               "delta0": u0[0], "ax0": u0[1]}
        row.update({f"ddelta_d{n}": jac[0, i] for i, n in enumerate(OBS_NAMES)})
        row.update({f"dax_d{n}": jac[1, i] for i, n in enumerate(OBS_NAMES)})
        rows.append(row)
        # progress: one line per checkpoint (the two runs are in separate processes)
        print(f"{job['method']:>6} {k:>5}/{job['iterations']}: lateral {row['lateral_mae']:.3f} m, "
              f"speed {row['speed_mae']:.4f} m/s, J_train {row['J_train']:.3f}", flush=True)

    def callback(metrics: dict[str, Any]) -> None:
        if metrics["iteration"] % job["every"] == 0:
            record(int(metrics["iteration"]))

    train(trainer, None, callback=callback)
    return rows


def lqr_reference() -> dict[str, Any]:
    model = DoubleLaneChangeModel()
    K = lqr_gain(model)
    res = [evaluate_tracking(lambda o: -K @ o[:5], seed=s) for s in EVAL_SEEDS]
    return {"gain": (-K).tolist(), "lateral_mae": float(np.mean([r.mean_abs_lateral_error for r in res])),
            "speed_mae": float(np.mean([r.mean_abs_speed_error for r in res])),
            "course_cost": float(np.mean([r.total_cost for r in res]))}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("outdir", nargs="?", default="docs/_static/reproduction")
    parser.add_argument("--iterations", type=int, default=10000)
    parser.add_argument("--every", type=int, default=500)
    args = parser.parse_args(argv)
    out = Path(args.outdir)
    out.mkdir(parents=True, exist_ok=True)
    jobs = [{"method": m, "iterations": args.iterations, "every": args.every} for m in ("mixed", "oracle")]
    with Pool(2) as pool:
        results = pool.map(run, jobs, chunksize=1)
    rows = [r for res in results for r in res]
    lqr = lqr_reference()
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_text(out / "long_training.csv", buf.getvalue())
    atomic_write_text(out / "long_training.json", json.dumps({"rows": rows, "lqr": lqr, "iterations": args.iterations,
                                                              "every": args.every}, indent=1))

    fig, ax = plt.subplots(1, 4, figsize=(16, 3.6))
    for method, color in (("mixed", "C0"), ("oracle", "C2")):
        r = [x for x in rows if x["method"] == method]
        k = [x["iteration"] for x in r]
        ax[0].plot(k, [x["course_cost"] for x in r], color, label=f"{method}: course cost")
        ax[0].plot(k, [100 * x["J_train"] / r[1]["J_train"] for x in r], color, ls=":",
                   label=f"{method}: J_train (% of it. {r[1]['iteration']})")
        ax[1].plot(k, [x["lateral_mae"] for x in r], color, label=method)
        ax[2].plot(k, [-x["ddelta_de_y"] for x in r], color, label=f"{method}: $-\\partial\\delta/\\partial e_y$")
        ax[2].plot(k, [-x["ddelta_de_phi"] / 5 for x in r], color, ls="--",
                   label=f"{method}: $-\\partial\\delta/\\partial e_\\varphi$ / 5")
        ax[3].plot(k, [x["speed_mae"] for x in r], color, label=f"{method}: speed MAE [m/s]")
        ax[3].plot(k, [-x["ax0"] / 10 for x in r], color, ls="--", label=f"{method}: $-a_x(0)$ / 10 [m/s$^2$]")
    ax[0].axhline(lqr["course_cost"], color="k", lw=0.8, label="LQR course cost")
    ax[1].axhline(lqr["lateral_mae"], color="k", lw=0.8, label="LQR")
    ax[1].axhline(0.151, color="r", lw=0.8, ls=":", label="paper (mixed)")
    ax[2].axhline(-lqr["gain"][0][4], color="k", lw=0.8, label="LQR")
    ax[2].axhline(-lqr["gain"][0][3] / 5, color="k", lw=0.8, ls="--")
    ax[0].set_ylim(0, 200)
    ax[0].set_title("course cost vs training objective", fontsize=9)
    ax[1].set_title("lateral MAE on the course [m]", fontsize=9)
    ax[2].set_title("steering gains at the origin", fontsize=9)
    ax[3].axhline(0.010, color="r", lw=0.8, ls=":", label="0.010 m/s")
    ax[3].axhline(0.0174, color="k", lw=0.8, ls="--", label="full compensation of 261 N / 10")
    ax[3].set_title("speed error and longitudinal action at the origin", fontsize=9)
    for a in ax:
        a.set_xlabel("iteration")
        a.grid(alpha=0.3)
        a.legend(fontsize=7)
    fig.tight_layout()
    png = io.BytesIO()
    fig.savefig(png, dpi=110, metadata={"Software": None})
    plt.close(fig)
    atomic_write_bytes(out / "long_training.png", png.getvalue())


if __name__ == "__main__":
    main()
