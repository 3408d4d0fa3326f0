"""What happens when Algorithm 2 trains longer than the reproduction's budget (docs/reproduction.rst):
the analysis of the sweep ``experiments/studies/long_training.toml``.

The sweep trains mixed RL and the oracle (seed 0, the reproduction's config except ``iterations``; the
learning rates decay over ``lr_decay_iterations`` = 1500 iterations and then stay at 1%); its observer
(:mod:`experiments.analysis.long_training_observer`) records, every 500 iterations, the Table I errors and the course cost,
``J_train`` (the discounted cost from 1024 fixed wide start states) and the policy's action and Jacobian
at the origin of the observation. This script reads those records from the runs' ``metrics.jsonl``, adds
the discounted LQR of the linearised model (python-control ``dlqr``, :func:`vehicle_figures.lqr_gain`) and
its course errors, and writes ``long_training.csv``, ``long_training.json`` and ``long_training.png``.

Usage::

    PYTHONPATH=. mixedrl sweep experiments/studies/long_training.toml --out runs/long_training      # about 8 minutes on 2 cores
    PYTHONPATH=. python experiments/analysis/long_training.py runs/long_training [--dest experiments/results/long_training]
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import sys
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from mixedrl.envs import DoubleLaneChangeModel, evaluate_tracking  # noqa: E402
from mixedrl.runs import RunDirectory, atomic_write_bytes, atomic_write_text  # noqa: E402
from experiments.analysis.long_training_observer import EVAL_SEEDS  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from vehicle_figures import lqr_gain  # noqa: E402


def records(sweep: Path) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """The observer's records of every run of the sweep (``long/`` stripped), and the sweep's ``sweep.json``."""
    doc = json.loads((sweep / "sweep.json").read_text())
    rows: list[dict[str, Any]] = []
    for rec in doc["runs"]:
        if rec["error"] is not None:
            raise SystemExit(f"{sweep}: run {rec['name']} failed: {rec['error']}")
        for row in RunDirectory(sweep / rec["run_dir"]).read_metrics():
            if "long/J_train" in row:
                rows.append({"method": rec["method"], "iteration": row["iteration"],
                             **{k[5:]: v for k, v in row.items() if k.startswith("long/")}})
    return rows, doc


def lqr_reference() -> dict[str, Any]:
    model = DoubleLaneChangeModel()
    K = lqr_gain(model)
    res = [evaluate_tracking(lambda o: -K @ o[:5], seed=s) for s in EVAL_SEEDS]
    return {"gain": (-K).tolist(), "lateral_mae": float(np.mean([r.mean_abs_lateral_error for r in res])),
            "speed_mae": float(np.mean([r.mean_abs_speed_error for r in res])),
            "course_cost": float(np.mean([r.total_cost for r in res]))}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("sweep", type=Path, help="the finished sweep of experiments/studies/long_training.toml")
    parser.add_argument("--dest", type=Path, default=Path("experiments/results/long_training"))
    args = parser.parse_args(argv)
    out = args.dest
    out.mkdir(parents=True, exist_ok=True)
    rows, doc = records(args.sweep)
    if not rows:
        raise SystemExit(f"{args.sweep}: no records of experiments.analysis.long_training_observer's observer")
    iterations = max(r["iteration"] for r in rows)
    every = min(r["iteration"] for r in rows)
    lqr = lqr_reference()
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_text(out / "long_training.csv", buf.getvalue())
    atomic_write_text(out / "long_training.json", json.dumps({"rows": rows, "lqr": lqr, "iterations": iterations,
                                                              "every": every,
                                                              "batch_size_runs": [r["metrics"].get("batch_size_runs", 1)
                                                                                  for r in doc["runs"]]}, indent=1))

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
