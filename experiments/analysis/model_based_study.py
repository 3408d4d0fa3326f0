"""Algorithm 2 planning on the model: training-state designs, budgets, seeds, true transitions (issue 10).

The runs are the sweep ``experiments/studies/model_based.toml`` (every design a ``[variants.NAME]``; M and S also at 4000
and 10000 iterations); this script only analyses them::

    mixedrl sweep experiments/studies/model_based.toml --out runs/model_based
    PYTHONPATH=. python experiments/analysis/model_based_study.py ship runs/model_based [--dest DIR]

``ship`` writes one JSON file per finished run of the sweep,

    experiments/results/model_based/per_run/<design>/<method>_s<seed>_n<iterations>.json

with the final course evaluation (the run's own evaluation seeds; the course is used for reporting only,
never to pick a checkpoint or a setting inside a run), the number of true-environment transitions, the
evaluations along the run (from its ``metrics.jsonl``), the policy's action and Jacobian at the origin (from
its checkpoint) and, for model-driven RL, the course driven in the world it plans in; then ``summary``
collects every file into ``summary.csv`` / ``summary.json`` (mean, std, worst seed per design, method and
budget) and the docs' tables. (Per-run files shipped before the move also hold per-evaluation batch
diagnostics that a sweep directory does not record.)

Other commands: ``summary`` (the tables from the per-run files), ``budgets`` (figure), ``reference``,
``objective``, ``origin``, ``own-model DIR`` (every run of a design of a sweep driven in the prior's world
too) and ``positions DIR`` (where the course copies are, from the observer's metrics of a sweep of
``experiments/studies/course_positions.toml``)::

    mixedrl sweep experiments/studies/course_positions.toml --out runs/course_positions --batch 1
    PYTHONPATH=. python experiments/analysis/model_based_study.py positions runs/course_positions [--dest DIR]
"""

from __future__ import annotations

import argparse
import io
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mixedrl.config import TrainConfig
from mixedrl.runs import RunDirectory, atomic_write_bytes, atomic_write_text, eval_seeds, load_checkpoint, make_trainer
from mixedrl.tables import csv_text
from mixedrl.tasks import task_from_config

OUT = Path("experiments/results/model_based")
#: Seeds from this one on are held out: run with the chosen design only, reported apart (``summary``).
HELD_OUT = 5

#: The study's spec: every design a variant (docs/model_based.rst).
SPEC = Path(__file__).resolve().parents[2] / "experiments" / "studies" / "model_based.toml"
#: The spec of ``positions``: designs M and S with the observer of :mod:`experiments.analysis.course_positions`.
POSITIONS_SPEC = SPEC.parent / "course_positions.toml"
#: One line per design, for the table of docs/model_based.rst (``designs.csv``).
DESIGN_NOTES = {
    "A": "50% course rollouts from iteration 0, box 4, no kicks",
    "C": "wide starts only (the former true-environment distribution, on the model)",
    "D": "75% course rollouts from iteration 500, box 3, no kicks",
    "E": "95% course rollouts from iteration 500, box 3, no kicks",
    "F": "90% course rollouts from iteration 500, box 3, kicks 0.01",
    "G": "75% course rollouts from iteration 500, box 3, kicks 0.01",
    "H": "G + learning-rate decay over a fixed 1500 iterations",
    "I": "H + actor learning rate 1e-3 (3.3x)",
    "J": "G + decay over 3000 iterations",
    "K": "H + batch of 1024 states",
    "M": "H + relative batch weighting in PEV and PIM (the defaults)",
    "M3": "M + decay over 3000 iterations",
    "N1": "M + 50% course rollouts (instead of 75%)",
    "N2": "M + batch_weight_offset 3 (instead of 1)",
    "N3": "M + decay over 2000 iterations",
    "P1": "M + batch_weight_offset 0.3 (instead of 1)",
    "Q1": "M + Polyak average of the actor (EMA, beta = 0.995) as the policy",
    "S": "M + course rollouts restart at a random point along the course, also at its end",
    "T": "M + course rollouts also restart at the course start when they pass its end (they loop)",
}


def policy_at_origin(actor: torch.nn.Module) -> dict[str, list[float]]:
    """The policy's action ``pi(0)`` and its Jacobian ``d pi / d obs`` at the origin (on the reference, 12 m/s)."""
    jac = torch.autograd.functional.jacobian(lambda o: actor(o[None])[0], torch.zeros(5))
    with torch.no_grad():
        u0 = actor(torch.zeros(1, 5))[0]
    return {"u0": u0.tolist(), "gain": jac.tolist()}


def _load_policy(run_dir: Path, cfg: TrainConfig) -> Any:
    trainer = make_trainer(cfg)
    trainer.load_state_dict(load_checkpoint(run_dir / "checkpoint.pt")["trainer"])
    return trainer


def per_run_record(sweep_dir: Path, row: dict[str, Any]) -> dict[str, Any]:
    """The per-run file of one finished run of the sweep (a row of its ``sweep.json``)."""
    run = RunDirectory(sweep_dir / row["run_dir"])
    cfg = run.read_config()
    res = run.read_results()
    design = row["point"]["variant"].split("_n")[0]
    evals = [{"iteration": int(r["iteration"]), "cost": r["eval/cost"], "lateral_mae": r["eval/lateral_mae"],
              "speed_mae": r["eval/speed_mae"], "terminated": r["eval/terminated"],
              "true_transitions": r["data/true_transitions"]}
             for r in run.read_metrics() if "eval/cost" in r]
    trainer = _load_policy(run.path, cfg)
    out = {"tag": design, "method": cfg.method, "seed": cfg.seed, "iterations": res["iterations"],
           "variant": row["point"]["variant"], "config_hash": row["config_hash"], "config": cfg.to_dict(),
           "wall_s": row["wall_seconds"], "train_seconds": res["train_seconds"],
           "lateral_mae": res["lateral_mae"], "speed_mae": res["speed_mae"], "cost": res["cost"],
           "terminated": res["final"]["terminated"], "true_transitions": res["true_transitions"],
           "final_ibe_mean_vx": res["final_ibe_mean"][2], "evals": evals, **policy_at_origin(trainer.policy)}
    if cfg.method == "model":
        # the course driven in the world model-driven RL plans in (own-model: a failure there is a failure
        # of training, not of the model's error)
        own = prior_world_task(cfg).evaluate(trainer.policy, eval_seeds(cfg))
        out["prior_world"] = {k: own[k] for k in ("lateral_mae", "speed_mae", "cost")}
    return out


def _finished_rows(sweep_dir: Path, spec: Path = SPEC) -> list[dict[str, Any]]:
    doc_path = sweep_dir / "sweep.json"
    if not doc_path.is_file():
        raise SystemExit(f"{doc_path} does not exist; run: mixedrl sweep {spec.relative_to(spec.parents[2])} "
                         f"--out {sweep_dir}")
    return [r for r in json.loads(doc_path.read_text())["runs"] if r["error"] is None and r["results"] is not None]


def ship(args: argparse.Namespace) -> None:
    """Write the per-run file of every finished run of the sweep ``args.sweep_dir``, then ``summary``."""
    global OUT
    OUT = args.dest
    torch.set_num_threads(1)
    for row in _finished_rows(args.sweep_dir):
        rec = per_run_record(args.sweep_dir, row)
        path = OUT / "per_run" / rec["tag"] / f"{rec['method']}_s{rec['seed']}_n{rec['iterations']}.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(path, json.dumps(rec, indent=1) + "\n")
        print(f"{path}: lateral {rec['lateral_mae']:.3f} m, speed {rec['speed_mae']:.4f} m/s, cost {rec['cost']:.1f}")
    summary(args)


def summary(_: argparse.Namespace) -> None:
    runs = [json.loads(p.read_text()) for p in sorted((OUT / "per_run").glob("*/*.json"))]
    groups: dict[tuple[str, str, int], list[dict[str, Any]]] = {}
    for r in runs:
        # seeds 0-4 are the study's; seeds >= 5 were run only to check the chosen design on seeds that took no
        # part in choosing it (reported apart); seeds 10-19 were added to count failures (never used to choose)
        group = "0-4" if r["seed"] < HELD_OUT else "held-out" if r["seed"] < 10 else "held-out 10-19"
        groups.setdefault((r["tag"], r["method"], r["iterations"], group), []).append(r)
    rows = []
    for (tag, method, n, group), rs in sorted(groups.items()):
        rs = sorted(rs, key=lambda r: r["seed"])
        lat = np.array([r["lateral_mae"] for r in rs])
        spd = np.array([r["speed_mae"] for r in rs])
        cost = np.array([r["cost"] for r in rs])
        ddof = 1 if len(rs) > 1 else 0  # sample standard deviation over seeds
        rows.append({"tag": tag, "method": method, "iterations": n, "seed_group": group,
                     "seeds": " ".join(str(r["seed"]) for r in rs),
                     "cost_mean": cost.mean(), "cost_max": cost.max(), "lateral_mean": lat.mean(),
                     "lateral_std": lat.std(ddof=ddof), "lateral_max": lat.max(), "speed_mean": spd.mean(),
                     "speed_std": spd.std(ddof=ddof), "speed_max": spd.max(),
                     "true_transitions": int(np.mean([r["true_transitions"] for r in rs])),
                     "per_seed_lateral": " ".join(f"{x:.3f}" for x in lat),
                     "per_seed_speed": " ".join(f"{x:.4f}" for x in spd),
                     "per_seed_cost": " ".join(f"{x:.1f}" for x in cost)})
    OUT.mkdir(parents=True, exist_ok=True)
    atomic_write_text(OUT / "summary.csv", csv_text(rows))
    atomic_write_text(OUT / "summary.json", json.dumps(rows, indent=1) + "\n")
    # the designs at 1500 iterations (J: 3000; mixed RL, seeds 0-4) and the chosen design at every budget
    designs = [{"tag": r["tag"], "design": DESIGN_NOTES.get(r["tag"], ""), "budget": r["iterations"],
                "seeds": r["seeds"],
                "lateral per seed [m]": r["per_seed_lateral"].replace(" ", " / "),
                "cost mean": f"{r['cost_mean']:.1f}", "speed mean [m/s]": f"{r['speed_mean']:.4f}"}
               for r in rows if r["method"] == "mixed" and r["seed_group"] == "0-4"
               and (r["iterations"] == 1500 or r["tag"] in ("J", "M3", "N3"))]  # these decay longer: their budget
    atomic_write_text(OUT / "designs.csv", csv_text(designs))
    for tag in BUDGET_TABLES:
        atomic_write_text(OUT / f"budgets_{tag}.csv", csv_text(_budget_rows(rows, tag)))
    # model-driven runs driven in the world they plan in too (the files written since run_job records it)
    own = [{"design": r["tag"], "budget": r["iterations"], "seed": r["seed"],
            "lateral true world [m]": f"{r['lateral_mae']:.3f}", "cost true world": f"{r['cost']:.1f}",
            "lateral prior world [m]": f"{r['prior_world']['lateral_mae']:.3f}",
            "cost prior world": f"{r['prior_world']['cost']:.1f}",
            "speed true / prior world [m/s]": f"{r['speed_mae']:.4f} / {r['prior_world']['speed_mae']:.4f}"}
           for r in sorted(runs, key=lambda r: (r["tag"], r["iterations"], r["seed"])) if "prior_world" in r]
    if own:
        atomic_write_text(OUT / "prior_world.csv", csv_text(own))
    for r in rows:
        print(f"{r['tag']:>14} {r['method']:>6} n={r['iterations']:>5} seeds[{r['seeds']}] cost {r['cost_mean']:6.1f} "
              f"(max {r['cost_max']:6.1f}) lat {r['lateral_mean']:.3f}±{r['lateral_std']:.3f} "
              f"spd {r['speed_mean']:.4f}±{r['speed_std']:.4f} true {r['true_transitions']} | {r['per_seed_lateral']}")


#: Designs whose every budget and seed group gets a table ``budgets_<tag>.csv`` (``summary``).
BUDGET_TABLES = ("M", "S")


def _budget_rows(rows: list[dict[str, Any]], tag: str) -> list[dict[str, Any]]:
    """The rows of ``budgets_<tag>.csv``: each method, budget and seed group of design ``tag``, with the
    change of the mean cost from the previous budget."""
    chosen: list[dict[str, Any]] = []
    for r in rows:
        if r["tag"] != tag:
            continue
        prev = [q for q in chosen if q["method"] == r["method"] and q["seeds"] == r["seeds"]]
        chosen.append({"method": r["method"], "iterations": r["iterations"], "seeds": r["seeds"],
                       "cost mean": f"{r['cost_mean']:.1f}",
                       "change": f"{100 * (r['cost_mean'] / prev[-1]['_cost'] - 1):+.1f}%" if prev else "",
                       "cost per seed": r["per_seed_cost"].replace(" ", " / "),
                       "lateral mean +- std [m]": f"{r['lateral_mean']:.3f} +- {r['lateral_std']:.3f}",
                       "lateral per seed": r["per_seed_lateral"].replace(" ", " / "),
                       "speed mean (max) [m/s]": f"{r['speed_mean']:.4f} ({r['speed_max']:.4f})",
                       "speed per seed": r["per_seed_speed"].replace(" ", " / "),
                       "true transitions": r["true_transitions"], "_cost": r["cost_mean"]})
    order = {"mixed": 0, "model": 1, "oracle": 2}
    chosen.sort(key=lambda q: (q["seeds"] != "0 1 2 3 4", order.get(q["method"], 9), q["iterations"]))
    return [{k: v for k, v in q.items() if k != "_cost"} for q in chosen]


def budgets(args: argparse.Namespace) -> None:
    """Figure ``budgets_<tag>.png``: course cost, lateral and speed error of every seed against the budget."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = [json.loads(p.read_text()) for p in sorted((OUT / "per_run" / args.tag).glob("*.json"))]
    runs = [r for r in runs if r["seed"] < HELD_OUT]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    for c, method in enumerate(("mixed", "model", "oracle")):
        mine = [r for r in runs if r["method"] == method]
        budgets_ = sorted({r["iterations"] for r in mine})
        if not mine:
            continue
        for ax, key in zip(axes, ("cost", "lateral_mae", "speed_mae")):
            for seed in sorted({r["seed"] for r in mine}):
                pts = sorted((r["iterations"], r[key]) for r in mine if r["seed"] == seed)
                ax.plot(*zip(*pts), color=f"C{c}", alpha=0.35, lw=0.8, marker=".")
            means = [np.mean([r[key] for r in mine if r["iterations"] == n]) for n in budgets_]
            ax.plot(budgets_, means, color=f"C{c}", lw=2.2, marker="o", label=f"{method} (mean of seeds 0-4)")
    for ax, label in zip(axes, ("course cost", "lateral error [m]", "speed error [m/s]")):
        ax.set_xscale("log")
        ax.set_xlabel("budget [iterations]")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[2].axhline(0.010, color="k", ls=":", lw=1)
    axes[1].axhline(0.151, color="k", ls=":", lw=1)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"design {args.tag}: every seed (thin) and the mean (thick) at each budget")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, dpi=110, metadata={"Software": None})
    plt.close(fig)
    atomic_write_bytes(OUT / f"budgets_{args.tag}.png", buf.getvalue())
    print(f"wrote {OUT / f'budgets_{args.tag}.png'}")


def reference(_: argparse.Namespace) -> None:
    """LQR of the linearised model (no preview, the policy class's linear member) for several discounts:
    gains and course errors on the evaluation seeds of seeds 0-4 (``mixedrl.runs.eval_seeds``)."""
    import sys

    from mixedrl.envs import DoubleLaneChangeModel, evaluate_tracking
    from mixedrl.runs import eval_seeds

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from vehicle_figures import lqr_gain

    model = DoubleLaneChangeModel()
    seeds = [s for seed in range(5) for s in eval_seeds(TrainConfig(seed=seed))]
    rows = []
    for gamma in (0.99, 0.995, 0.998, 0.999, 1.0):
        K = lqr_gain(model, gamma)
        res = [evaluate_tracking(lambda o: -K @ o[:5], seed=s) for s in seeds]
        rows.append({"gamma": gamma, "gain": (-K).tolist(),
                     "lateral_mae": float(np.mean([r.mean_abs_lateral_error for r in res])),
                     "speed_mae": float(np.mean([r.mean_abs_speed_error for r in res])),
                     "cost": float(np.mean([r.total_cost for r in res]))})
        print(f"gamma {gamma}: lateral {rows[-1]['lateral_mae']:.3f} m, speed {rows[-1]['speed_mae']:.4f} m/s, "
              f"cost {rows[-1]['cost']:.1f}, steering gains {np.round(-K[0], 3)}")
    OUT.mkdir(parents=True, exist_ok=True)
    atomic_write_text(OUT / "lqr_reference.json", json.dumps(rows, indent=1) + "\n")


def objective(_: argparse.Namespace) -> None:
    """Which linear feedback does Algorithm 2's objective prefer? The discounted cost (gamma = 0.99, 800
    steps, true noise) of the LQR gains of several discounts, from (a) the wide training distribution and
    (b) the states the car visits on the course (every 10th state of a course driven by the gamma = 1 LQR)."""
    import sys

    from mixedrl.envs import evaluate_tracking
    from mixedrl.tasks import DoubleLaneChangeTask

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from vehicle_figures import lqr_gain

    task = DoubleLaneChangeTask()
    bound = task.action_bound.double()
    ref = evaluate_tracking(lambda o: -lqr_gain(task.model, 1.0) @ o[:5], seed=7)
    course = torch.as_tensor(ref.states[::10], dtype=torch.float64)
    wide = task.sample_initial(1024, torch.Generator().manual_seed(12345))
    rows = []
    for gamma in (0.99, 0.995, 0.998, 1.0):
        K = torch.as_tensor(lqr_gain(task.model, gamma))
        row: dict[str, Any] = {"lqr_gamma": gamma}
        for name, starts in (("wide", wide), ("course", course)):
            gen = torch.Generator().manual_seed(999)
            s, total = starts.clone(), torch.zeros(starts.shape[0], dtype=torch.float64)
            for t in range(800):
                u = torch.maximum(torch.minimum(-task.observe(s) @ K.T, bound), -bound)
                s = task.true_step(s, u, gen)
                total += task.gamma**t * task.cost(s, u)
            row[f"J_{name}"] = float(total.mean())
        rows.append(row)
        print(f"LQR(gamma={gamma}): J_0.99 from wide starts {row['J_wide']:.4f}, from course states {row['J_course']:.4f}")
    OUT.mkdir(parents=True, exist_ok=True)
    atomic_write_text(OUT / "objective_of_lqr_gains.json", json.dumps(rows, indent=1) + "\n")


def origin(_: argparse.Namespace) -> None:
    """What sets the speed error? The policy's longitudinal action at the origin across every run.

    For each method, over the runs of design M and over every per-run file, those that stayed on the road (lateral error <= 0.2 m): the mean
    and standard deviation of ``a_x = pi(0)[1]`` (the acceleration on the reference at 12 m/s), the
    acceleration that cancels the true mean force (``-F_true / m``) and the prior's (``-F_prior / m``),
    and how much of the course speed error the offset ``|a_x + F_true / m|`` explains (correlation, and
    the steady-state prediction ``|a_x + F_true / m| / |d a_x / d v_x|``). Writes ``origin_action.csv``.
    """
    from mixedrl.tasks import DoubleLaneChangeTask

    task = DoubleLaneChangeTask()
    dt = float(task.model.config.dt)
    a_true = -float(task.true_mean[task.noise_index]) / dt
    a_prior = -float(task.prior_mean[task.noise_index]) / dt
    runs = [json.loads(p.read_text()) for p in sorted((OUT / "per_run").glob("*/*.json"))]
    rows = []
    for scope, method in [(scope, m) for scope in ("M", "every design") for m in ("mixed", "model", "oracle")]:
        mine = [r for r in runs if r["method"] == method and r["lateral_mae"] <= 0.2
                and (scope != "M" or r["tag"] == "M")]
        a0 = np.array([r["u0"][1] for r in mine])
        gain = np.array([r["gain"][1][2] for r in mine])
        speed = np.array([r["speed_mae"] for r in mine])
        offset = np.abs(a0 - a_true)
        rows.append({"design": scope, "method": method, "runs": len(mine), "a_x(0) mean [m/s^2]": f"{a0.mean():.3f}",
                     "a_x(0) std": f"{a0.std(ddof=1):.3f}", "cancels the true mean": f"{a_true:.3f}",
                     "cancels the prior mean": f"{a_prior:.3f}",
                     "da_x/dv_x mean": f"{gain.mean():.2f}",
                     "corr(speed error, abs(a_x(0) - a_true))": f"{np.corrcoef(speed, offset)[0, 1]:.2f}",
                     "corr(speed error, steady-state prediction)":
                         f"{np.corrcoef(speed, offset / np.abs(gain))[0, 1]:.2f}",
                     "speed error mean [m/s]": f"{speed.mean():.4f}"})
        print(rows[-1])
    atomic_write_text(OUT / "origin_action.csv", csv_text(rows))


def positions(args: argparse.Namespace) -> None:
    """Where along the course are the course copies of the batch? From the finished sweep
    ``args.sweep_dir`` of ``experiments/studies/course_positions.toml`` (one run per design, its observer
    :mod:`experiments.analysis.course_positions` records every 100 iterations the quantiles of ``X`` of the course
    copies and the fraction of them in each part of the course: straight 0-20 m, first lane change
    20-52 m, second 52-85 m, last straight 85-120 m). Writes ``course_positions.csv`` into ``--dest``."""
    from experiments.analysis.course_positions import PARTS, share_key

    rows = []
    for row in _finished_rows(args.sweep_dir, POSITIONS_SPEC):
        run = RunDirectory(args.sweep_dir / row["run_dir"])
        cfg = run.read_config()
        for r in run.read_metrics():
            if "positions/X_median" not in r:
                continue
            out = {"design": row["point"]["variant"], "seed": cfg.seed, "iteration": int(r["iteration"]),
                   "X q10 [m]": f"{r['positions/X_q10']:.1f}", "X median [m]": f"{r['positions/X_median']:.1f}",
                   "X q90 [m]": f"{r['positions/X_q90']:.1f}"}
            for a, b in PARTS:
                out[f"share {a:.0f}-{b:.0f} m"] = f"{r[share_key(a, b)]:.2f}"
            rows.append(out)
    if not rows:
        raise SystemExit(f"positions: no positions/ metrics in {args.sweep_dir} (a sweep of {POSITIONS_SPEC.name}?)")
    args.dest.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.dest / "course_positions.csv", csv_text(rows))
    print(f"{args.dest / 'course_positions.csv'}: {len(rows)} rows")


def prior_world_task(cfg: TrainConfig) -> Any:
    """The task whose true disturbance is the prior's ``N(prior_force_mean, prior_force_std^2)``: the world
    model-driven RL plans in (eq. 55)."""
    task = cfg.to_dict()["task"]
    return task_from_config({**task, "disturbance": {**task["disturbance"], "mean": task["prior_force_mean"],
                                                     "variance": task["prior_force_std"] ** 2}})


def own_model(args: argparse.Namespace) -> None:
    """Is a failing run wrong in the world it plans in, or only in the true one? Every finished run of design
    ``--tag`` (1500 iterations) of the sweep ``args.sweep_dir``, its final policy driven on the course twice:
    under the true disturbance (the run's own ``results.json``) and under the prior's
    ``N(prior_force_mean, prior_force_std^2)``, the world model-driven RL plans in. Writes ``own_model.csv``."""
    torch.set_num_threads(1)
    rows = []
    for row in _finished_rows(args.sweep_dir):
        if row["point"]["variant"] != args.tag:
            continue
        run = RunDirectory(args.sweep_dir / row["run_dir"])
        cfg, res = run.read_config(), run.read_results()
        own = prior_world_task(cfg).evaluate(_load_policy(run.path, cfg).policy, eval_seeds(cfg))
        rows.append({"design": args.tag, "method": cfg.method, "seed": cfg.seed,
                     "lateral true world [m]": f"{res['lateral_mae']:.3f}",
                     "speed true world [m/s]": f"{res['speed_mae']:.4f}", "cost true world": f"{res['cost']:.1f}",
                     "lateral prior world [m]": f"{own['lateral_mae']:.3f}",
                     "speed prior world [m/s]": f"{own['speed_mae']:.4f}", "cost prior world": f"{own['cost']:.1f}"})
        print(rows[-1], flush=True)
    atomic_write_text(OUT / "own_model.csv", csv_text(rows))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("ship", help="per-run files and tables from a sweep of experiments/studies/model_based.toml")
    p.add_argument("sweep_dir", type=Path)
    p.add_argument("--dest", type=Path, default=OUT)
    sub.add_parser("summary")
    p = sub.add_parser("budgets")
    p.add_argument("--tag", default="M")
    sub.add_parser("reference")
    sub.add_parser("objective")
    sub.add_parser("origin")
    p = sub.add_parser("positions", help="course_positions.csv from a sweep of experiments/studies/course_positions.toml")
    p.add_argument("sweep_dir", type=Path)
    p.add_argument("--dest", type=Path, default=OUT)
    p = sub.add_parser("own-model")
    p.add_argument("sweep_dir", type=Path)
    p.add_argument("--tag", default="S")
    args = parser.parse_args(argv)
    {"ship": ship, "summary": summary, "budgets": budgets, "reference": reference,
     "objective": objective, "origin": origin,
     "positions": positions, "own-model": own_model}[args.cmd](args)


if __name__ == "__main__":
    main()
