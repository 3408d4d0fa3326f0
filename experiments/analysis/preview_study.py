"""Mixed RL with path preview against the NMPC reference (issue 11, item 4).

Sub-commands:

``horizon``
    Evidence for the preview distances that does not use a learned policy: the NMPC of
    :mod:`validation.nmpc` (gamma = 0.99, true mean, seed 0) with shorter horizons. The horizon at which
    its course cost stops improving is the look-ahead the discounted problem needs.
    Writes ``experiments/results/preview/nmpc_horizon.json``.
``reach``
    The same evidence with the horizon kept at 2 s: the NMPC (gamma = 0.99, true mean, seed 0) that knows
    the path only up to ``D`` metres ahead of the car (:class:`LimitedPreviewNMPC`: beyond ``X + D`` it
    predicts on the path's tangent at ``X + D``; ``D = 0`` is the no-preview NMPC of
    :mod:`validation.nmpc`). Writes ``experiments/results/preview/nmpc_reach.json``.
``ship [SWEEP_DIR ...]``
    The runs are the sweep ``experiments/studies/preview.toml`` (``mixedrl sweep experiments/studies/preview.toml --out DIR``:
    variant ``<design>_<candidate>``, every training setting at the defaults of
    :class:`mixedrl.config.TrainConfig` but ``task.preview_distances`` and the batch design: ``S``, today's
    default, or ``M``, the default when the study was first run, see :data:`DESIGNS`). For each sweep
    directory given, ``ship`` first writes one JSON file per finished run,
    ``experiments/results/preview/per_run/<design>/<candidate>/<method>_s<seed>.json``, with the final course
    evaluation (the run's own evaluation seeds), the true transitions, the evaluations along the run and the
    actor's weights (for the figure and the benchmark). Then it collects every per-run file into ``summary.csv`` / ``summary.json`` (per design; seeds 0-4 and the
    held-out seeds >= 5 apart) and draws ``trajectory.png`` (the preview policy of seed 0 against the NMPC
    and the no-preview policy on the course of noise seed 0, design :data:`FIGURE_DESIGN`).

Usage::

    PYTHONPATH=. python experiments/analysis/preview_study.py horizon
    mixedrl sweep experiments/studies/preview.toml --out runs/preview
    PYTHONPATH=. python experiments/analysis/preview_study.py ship runs/preview
"""

from __future__ import annotations

import argparse
import io
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mixedrl.config import TrainConfig
from mixedrl.runs import RunDirectory, atomic_write_bytes, atomic_write_text, load_checkpoint, make_trainer

from mixedrl.tables import csv_text
from validation.preview import LimitedPreviewNMPC, NumpyActor, actor_weights

OUT = Path("experiments/results/preview")
#: Seeds from this one on are held out: run with the chosen candidate only, reported apart.
HELD_OUT = 5

#: Candidate preview distances [m] (see docs/references.rst, "Mixed RL with path preview").
CANDIDATES: dict[str, tuple[float, ...]] = {
    "none": (),
    "P12": (2.0, 4.0, 6.0, 8.0, 10.0, 12.0),
    "P24": (3.0, 6.0, 9.0, 12.0, 15.0, 18.0, 21.0, 24.0),
    "P6": (1.5, 3.0, 4.5, 6.0),
    "P12s": (2.0, 4.0, 6.0, 8.0, 10.0, 12.0),
}
#: Candidates whose preview columns are scaled per distance (:func:`preview_scale`) instead of the task's
#: 2 m for every preview column (in the spec: ``task.obs_scale``, variant ``M_P12s``).
PER_DISTANCE_SCALE = {"P12s"}
#: The chosen candidate (docs/references.rst: chosen from the NMPC's evidence, before any training).
CHOSEN = "P12"


def _nmpc_sweep(path: Path, key: str, values: list[float], drive_one: Any) -> None:
    """Run ``drive_one(value) -> row`` for each value not yet in the JSON list at ``path`` (keyed by
    ``key``); the file is rewritten (atomically) after each row."""
    rows = json.loads(path.read_text()) if path.exists() else []
    done = {r[key] for r in rows}
    for value in values:
        if value in done:
            print(f"skip {key} {value}")
            continue
        t0 = time.perf_counter()
        row = {key: value, **drive_one(value), "wall_s": 0.0}
        row["wall_s"] = time.perf_counter() - t0
        rows.append(row)
        rows.sort(key=lambda r: r[key])
        OUT.mkdir(parents=True, exist_ok=True)
        atomic_write_text(path, json.dumps(rows, indent=1) + "\n")
        print(f"{key} {value}: cost {row['cost']:.2f}, lateral {row['lateral_mae']:.4f} m, "
              f"speed {row['speed_mae']:.4f} m/s, {row['wall_s']:.0f} s", flush=True)


def horizon(args: argparse.Namespace) -> None:
    """NMPC (gamma = 0.99, true mean, seed 0) course cost against its horizon."""
    from validation.nmpc import run_reference

    def drive_one(h: float) -> dict[str, Any]:
        res = run_reference("nmpc", gamma=0.99, horizon=h, disturbance_mean="true", seeds=(0,))
        return {"preview_m": 12.0 * h, "cost": res["cost"], "lateral_mae": res["lateral_mae"],
                "speed_mae": res["speed_mae"], "solve_ms_mean": res["solve_ms_mean"]}

    _nmpc_sweep(OUT / "nmpc_horizon.json", "horizon", [float(x) for x in args.horizons.split(",")], drive_one)


def reach(args: argparse.Namespace) -> None:
    """NMPC (2 s, gamma = 0.99, true mean, seed 0) course cost against its preview distance."""
    from validation.nmpc import drive

    def drive_one(d: float) -> dict[str, Any]:
        res, timing = drive(LimitedPreviewNMPC(d, horizon=2.0, gamma=0.99, force="true"), seed=0)
        return {"horizon": 2.0, "gamma": 0.99, "seed": 0, "cost": res.total_cost,
                "lateral_mae": res.mean_abs_lateral_error, "speed_mae": res.mean_abs_speed_error,
                "terminated": res.terminated, "solve_ms_mean": timing["solve_ms_mean"]}

    _nmpc_sweep(OUT / "nmpc_reach.json", "reach_m", [float(x) for x in args.reaches.split(",")], drive_one)


#: Batch designs (docs/model_based.rst) -> ``CourseSampler.course_starts``. The study first ran on
#: design M, the default then (its runs are kept, under ``per_run/M``, and reproduce); S is the default now.
DESIGNS: dict[str, str] = {"M": "start", "S": "along"}
#: The design of the figure's policies.
FIGURE_DESIGN = "S"


def design_of(config: dict[str, Any]) -> str:
    """The design (a key of :data:`DESIGNS`) of a run's saved config: ``sampler.course_starts``, or in the
    flat form of the shipped runs of mixedrl 0.1.0 ``model_course_starts`` (a config saved before it
    existed ran design M, the only one then)."""
    starts = config.get("sampler", {}).get("course_starts", config.get("model_course_starts", DESIGNS["M"]))
    return next(d for d, v in DESIGNS.items() if v == starts)


def per_run_record(sweep_dir: Path, row: dict[str, Any]) -> tuple[Path, dict[str, Any]]:
    """The per-run file (its path and content) of one finished run of a sweep of ``experiments/studies/preview.toml``
    (a row of its ``sweep.json``: variant ``<design>_<candidate>``, ``_n<iterations>`` for a larger budget)."""
    run = RunDirectory(sweep_dir / row["run_dir"])
    cfg, res = run.read_config(), run.read_results()
    design, candidate = row["point"]["variant"].split("_", 1)
    candidate = candidate.split("_n")[0]  # <design>_<candidate>_n<budget> for the larger budgets
    trainer = make_trainer(cfg)
    trainer.load_state_dict(load_checkpoint(run.checkpoint_path)["trainer"])
    evals = [{"iteration": int(r["iteration"]), "cost": r["eval/cost"], "lateral_mae": r["eval/lateral_mae"],
              "speed_mae": r["eval/speed_mae"], "true_transitions": r["data/true_transitions"]}
             for r in run.read_metrics() if "eval/cost" in r]
    out = {"candidate": candidate, "design": design, "preview_distances": list(cfg.task.preview_distances),
           "method": cfg.method, "seed": cfg.seed, "iterations": int(res["iterations"]), "config": cfg.to_dict(),
           "config_hash": row["config_hash"], "wall_s": row["wall_seconds"], "train_seconds": res["train_seconds"],
           "lateral_mae": res["lateral_mae"], "speed_mae": res["speed_mae"], "cost": res["cost"],
           "terminated": res["final"]["terminated"], "true_transitions": res["true_transitions"],
           "final_ibe_mean_vx": res["final_ibe_mean"][2], "evals": evals,
           "obs_scale": trainer.task.obs_scale.tolist(), "actor": actor_weights(trainer.actor)}
    tail = "" if out["iterations"] == TrainConfig().algorithm.iterations else f"_n{out['iterations']}"
    return OUT / "per_run" / design / candidate / f"{cfg.method}_s{cfg.seed}{tail}.json", out


def write_per_run(sweep_dir: Path) -> None:
    """Write the per-run file of every finished run of the sweep ``sweep_dir``."""
    doc_path = sweep_dir / "sweep.json"
    if not doc_path.is_file():
        raise SystemExit(f"ship: {doc_path} does not exist; run: mixedrl sweep experiments/studies/preview.toml --out {sweep_dir}")
    torch.set_num_threads(1)
    for row in json.loads(doc_path.read_text())["runs"]:
        if row["error"] is None and row["results"] is not None:
            path, rec = per_run_record(sweep_dir, row)
            path.parent.mkdir(parents=True, exist_ok=True)
            atomic_write_text(path, json.dumps(rec) + "\n")
            print(f"{path}: cost {rec['cost']:.2f}, lateral {rec['lateral_mae']:.4f} m", flush=True)


def summarize(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Mean and sample standard deviation per (design, candidate, method, budget, seed group); seeds >=
    :data:`HELD_OUT` form the ``held-out`` group."""
    groups: dict[tuple[str, str, str, int, str], list[dict[str, Any]]] = {}
    for r in runs:
        group = "0-4" if r["seed"] < HELD_OUT else "held-out"
        groups.setdefault((design_of(r["config"]), r["candidate"], r["method"], r["iterations"], group),
                          []).append(r)
    rows = []
    for (design, candidate, method, iterations, group), rs in sorted(groups.items()):
        rs = sorted(rs, key=lambda r: r["seed"])
        ddof = 1 if len(rs) > 1 else 0
        row: dict[str, Any] = {"design": design, "candidate": candidate,
                               "preview_distances": " ".join(f"{d:g}" for d in rs[0]["preview_distances"]),
                               "method": method, "iterations": iterations, "seed_group": group,
                               "seeds": " ".join(str(r["seed"]) for r in rs)}
        for key in ("cost", "lateral_mae", "speed_mae"):
            x = np.array([r[key] for r in rs])
            row[f"{key}_mean"], row[f"{key}_std"], row[f"{key}_max"] = x.mean(), x.std(ddof=ddof), x.max()
        row["terminated"] = float(np.mean([r["terminated"] for r in rs]))
        row["true_transitions"] = int(np.mean([r["true_transitions"] for r in rs]))
        row["per_seed_cost"] = " ".join(f"{r['cost']:.2f}" for r in rs)
        row["per_seed_lateral"] = " ".join(f"{r['lateral_mae']:.4f}" for r in rs)
        row["per_seed_speed"] = " ".join(f"{r['speed_mae']:.4f}" for r in rs)
        rows.append(row)
    return rows


def steer_gains(run_row: dict[str, Any]) -> np.ndarray:
    """``d delta / d o`` of a run's actor at the origin (on the path, 12 m/s, straight road ahead), by
    central differences (step 1e-4) of :class:`NumpyActor`: shape (obs_dim,) [rad per unit of o]."""
    actor = NumpyActor(run_row["actor"])
    eye = 1e-4 * np.eye(actor.obs_dim)
    return np.array([(actor(e)[0] - actor(-e)[0]) / 2e-4 for e in eye])


def ship(args: argparse.Namespace) -> None:
    """Write the per-run files of the sweep directories ``args.sweep_dirs``, then ``summary.csv``,
    ``summary.json``, ``per_seed.csv`` and ``trajectory.png`` from every per-run file."""
    global OUT
    OUT = args.dest
    for sweep_dir in args.sweep_dirs:
        write_per_run(sweep_dir)
    runs = [json.loads(p.read_text()) for p in sorted((OUT / "per_run").glob("*/*/*.json"))]
    if not runs:
        raise SystemExit(f"no runs under {OUT / 'per_run'}: ship a sweep of experiments/studies/preview.toml first")
    rows = summarize(runs)
    atomic_write_text(OUT / "summary.json", json.dumps(rows, indent=1) + "\n")
    table = [{"design": r["design"], "candidate": r["candidate"], "preview [m]": r["preview_distances"] or "none",
              "preview scale": "per distance" if r["candidate"] in PER_DISTANCE_SCALE
              else ("2 m" if r["preview_distances"] else ""),
              "method": r["method"], "iterations": r["iterations"], "seeds": r["seeds"] if r["seed_group"] == "0-4" else r["seeds"] + " (held out)",
              "course cost": f"{r['cost_mean']:.2f} +- {r['cost_std']:.2f}",
              "lateral [m]": f"{r['lateral_mae_mean']:.4f} +- {r['lateral_mae_std']:.4f}",
              "speed [m/s]": f"{r['speed_mae_mean']:.4f} +- {r['speed_mae_std']:.4f}",
              "worst cost": f"{r['cost_max']:.2f}", "true transitions": r["true_transitions"]} for r in rows]
    atomic_write_text(OUT / "summary.csv", csv_text(table))
    per_seed = [{"design": design_of(r["config"]), "candidate": r["candidate"], "method": r["method"], "iterations": r["iterations"],
                 "seed": r["seed"],
                 "course cost": f"{r['cost']:.2f}", "lateral [m]": f"{r['lateral_mae']:.4f}",
                 "speed [m/s]": f"{r['speed_mae']:.4f}", "true transitions": r["true_transitions"],
                 "steer gain e_y [rad/m]": f"{steer_gains(r)[4]:.3f}",
                 "max steer gain preview [rad/m]": f"{np.abs(steer_gains(r)[5:]).max():.3f}"
                 if r["preview_distances"] else "",
                 "wall [s]": f"{r['wall_s']:.0f}"}
                for r in sorted(runs, key=lambda r: (design_of(r["config"]), r["candidate"], r["method"],
                                                     r["iterations"], r["seed"]))]
    atomic_write_text(OUT / "per_seed.csv", csv_text(per_seed))
    for r in rows:
        print(f"{r['design']} {r['candidate']:>5} {r['method']:>6} n={r['iterations']} [{r['seeds']}] cost {r['cost_mean']:.2f}+-{r['cost_std']:.2f} "
              f"lat {r['lateral_mae_mean']:.4f}+-{r['lateral_mae_std']:.4f} "
              f"spd {r['speed_mae_mean']:.4f}+-{r['speed_mae_std']:.4f} true {r['true_transitions']}")
    figure(runs, args.chosen)


def figure(runs: list[dict[str, Any]], chosen: str) -> None:
    """``trajectory.png``: lateral error and speed error along the course (noise seed 0) of the seed-0
    policy with the chosen preview (at the default budget and at the largest budget run), the seed-0
    policy without preview (all of design :data:`FIGURE_DESIGN`) and the NMPC (2 s, gamma = 0.99, true mean, from
    docs/_static/references/trajectories.npz)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mixedrl.envs import DoubleLaneChangeConfig, evaluate_tracking

    curves = []
    default = TrainConfig().algorithm.iterations
    seed0 = [r for r in runs if r["method"] == "mixed" and r["seed"] == 0 and design_of(r["config"]) == FIGURE_DESIGN]
    longest = max((r["iterations"] for r in seed0 if r["candidate"] == chosen), default=default)
    drawn = [(chosen, default, "C0")] + ([(chosen, longest, "C2")] if longest != default else []) + [("none", default, "C3")]
    for candidate, iterations, color in drawn:
        mine = [r for r in seed0 if r["candidate"] == candidate and r["iterations"] == iterations]
        if not mine:
            continue
        label = f"mixed RL, preview {chosen}" if candidate == chosen else "mixed RL, no preview"
        cfg = DoubleLaneChangeConfig(preview_distances=tuple(mine[0]["preview_distances"]))
        res = evaluate_tracking(NumpyActor(mine[0]["actor"]), cfg, seed=0)
        curves.append((f"{label}, {iterations} iterations (design {FIGURE_DESIGN}, seed 0): cost {res.total_cost:.1f}",
                       color, res.states[:, 5], res.lateral_error, res.speed_error))
    ref = Path("docs/_static/references/trajectories.npz")
    if ref.exists():
        from validation.nmpc import REFERENCE_SETTINGS

        data = np.load(ref)
        i = [label for label, _ in REFERENCE_SETTINGS].index("NMPC 2 s, gamma=0.99, true mean")
        curves.append(("NMPC 2 s, gamma = 0.99, true mean (noise seed 0)", "k", data[f"X_{i}"],
                       data[f"ey_{i}"], data[f"ev_{i}"]))
    fig, axes = plt.subplots(2, 1, figsize=(9, 5.5), sharex=True)
    for label, color, X, lat, spd in curves:
        axes[0].plot(X, lat, color=color, lw=1.2, label=label)
        axes[1].plot(X, spd, color=color, lw=1.2)
    axes[0].set_ylabel("lateral error e_y [m]")
    axes[1].set_ylabel("speed error v_x - 12 [m/s]")
    axes[1].set_xlabel("X [m]")
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, dpi=110, metadata={"Software": None})
    plt.close(fig)
    atomic_write_bytes(OUT / "trajectory.png", buf.getvalue())
    print(f"wrote {OUT / 'trajectory.png'}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("horizon")
    p.add_argument("--horizons", default="0.25,0.5,1.0,1.5,2.0")
    p = sub.add_parser("reach")
    p.add_argument("--reaches", default="0,3,6,9,12,18,24,36")
    p = sub.add_parser("ship")
    p.add_argument("sweep_dirs", type=Path, nargs="*", help="sweep directories of experiments/studies/preview.toml")
    p.add_argument("--dest", type=Path, default=OUT)
    p.add_argument("--chosen", default=CHOSEN)
    args = parser.parse_args(argv)
    {"horizon": horizon, "reach": reach, "ship": ship}[args.cmd](args)


if __name__ == "__main__":
    main()
