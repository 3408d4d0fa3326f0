"""Mixed RL with path preview against the NMPC reference (issue 11, item 4).

Sub-commands:

``horizon``
    Evidence for the preview distances that does not use a learned policy: the NMPC of
    :mod:`validation.nmpc` (gamma = 0.99, true mean, seed 0) with shorter horizons. The horizon at which
    its course cost stops improving is the look-ahead the discounted problem needs.
    Writes ``docs/_static/preview/nmpc_horizon.json``.
``reach``
    The same evidence with the horizon kept at 2 s: the NMPC (gamma = 0.99, true mean, seed 0) that knows
    the path only up to ``D`` metres ahead of the car (:class:`LimitedPreviewNMPC`: beyond ``X + D`` it
    predicts on the path's tangent at ``X + D``; ``D = 0`` is the no-preview NMPC of
    :mod:`validation.nmpc`). Writes ``docs/_static/preview/nmpc_reach.json``.
``run``
    Trains one run per (candidate, method, seed) (``mixedrl.runs.make_trainer`` / ``train``,
    ``num_threads=1``, every training setting at the defaults of :class:`mixedrl.config.TrainConfig` but
    ``task.preview_distances`` and the batch design ``--design``: ``S``, today's default, or ``M``, the
    default when the study was first run, see :data:`DESIGNS`) and writes one JSON file
    ``docs/_static/preview/per_run/<design>/<candidate>/<method>_s<seed>.json`` with the final course
    evaluation (the run's own evaluation seeds), the true transitions and the actor's weights (for the
    figure and the benchmark). Existing files are skipped.
``ship``
    Collects every per-run file into ``summary.csv`` / ``summary.json`` (per design; seeds 0-4 and the
    held-out seeds >= 5 apart) and draws ``trajectory.png`` (the preview policy of seed 0 against the NMPC
    and the no-preview policy on the course of noise seed 0, design :data:`FIGURE_DESIGN`).

Usage::

    PYTHONPATH=. python scripts/preview_study.py horizon
    PYTHONPATH=. python scripts/preview_study.py run --candidate P12 --methods mixed --seeds 0-4 [--design S]
    PYTHONPATH=. python scripts/preview_study.py ship
"""

from __future__ import annotations

import argparse
import io
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mixedrl.config import TrainConfig, migrate
from mixedrl.runs import atomic_write_bytes, atomic_write_text, make_trainer, train
from mixedrl.tasks import task_from_config

sys.path.insert(0, str(Path(__file__).resolve().parent))
from model_based_study import _csv, seeds_of  # noqa: E402  (the same seed syntax and CSV writer)

OUT = Path("docs/_static/preview")
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
#: 2 m for every preview column.
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


class LimitedPreviewNMPC:
    """The 2 s NMPC of :class:`validation.nmpc.VehicleNMPC` that knows the path only ``reach`` metres ahead.

    At each solve, with the car at ``X_c`` and ``X_e = X_c + reach``, it charges eq. (54) against

    .. math:: Y_{lim}(X) = Y_{ref}(\\min(X, X_e)) + \\tan\\psi_{ref}(X_e)\\,\\max(X - X_e, 0),

    the true path up to ``X_e`` continued by its tangent there (``reach = 0``: the no-preview NMPC's
    tangent at the car). Everything else (model, mean, discount, horizon, warm start) is the NMPC's.

    Parameters
    ----------
    reach : float
        Preview distance ``D`` >= 0 [m].
    **kwargs
        Passed to :class:`validation.nmpc.VehicleNMPC` (``horizon``, ``gamma``, ``force``).

    Raises
    ------
    ValueError
        ``reach`` negative or not finite.
    """

    def __init__(self, reach: float, **kwargs: Any) -> None:
        import casadi as ca

        from validation import nmpc

        if not (isinstance(reach, (int, float)) and np.isfinite(reach) and reach >= 0):
            raise ValueError(f"reach: expected a finite distance >= 0 [m], got {reach!r}")
        self.reach = float(reach)
        self.inner = nmpc.VehicleNMPC(preview=False, **kwargs)
        model = self.inner.model
        cfg = model.config
        s, u, theta = ca.SX.sym("s", 6), ca.SX.sym("u", 2), ca.SX.sym("theta", 3)
        # theta = [X_e, Y_ref(X_e), slope(X_e)];  Y_lim(X) = Y_ref(min(X, X_e)) + slope_e max(X - X_e, 0)
        y_lim = model.lateral(ca.fmin(s[5], theta[0])) + theta[2] * ca.fmax(s[5] - theta[0], 0)
        e_y, dv = s[4] - y_lim, s[2] - cfg.v_des
        cost = ca.Function("l_limited", [s, u, theta],
                           [cfg.dt * (cfg.q_speed * dv * dv + cfg.q_lateral * e_y * e_y
                                      + cfg.r_steer * u[0] * u[0] + cfg.r_accel * u[1] * u[1])])
        bound = np.array([cfg.delta_max, cfg.ax_max])
        self.inner.core = nmpc.RecedingHorizon(nmpc._predict_step(ca, model, self.inner.force), cost,
                                               horizon_steps=self.inner.horizon_steps,
                                               gamma=self.inner.core.gamma, u_min=-bound, u_max=bound)
        self.config = cfg
        self.solve_ms = self.inner.solve_ms

    def reset(self) -> None:
        """Start a new episode."""
        self.inner.reset()
        self.solve_ms = self.inner.solve_ms

    def __call__(self, s: np.ndarray) -> np.ndarray:
        """The first input of the plan for tracking state ``s`` (shape (6,))."""
        from validation import nmpc

        inner, k = self.inner, self.inner._k
        s = np.asarray(s, dtype=np.float64)
        X_e = float(s[5]) + self.reach
        line = nmpc._tangent_line(self.config, X_e)
        guess = None
        if inner._plan is None:
            guess = nmpc._reference_guess(self.config, s, inner.horizon_steps)
        sol = inner.core.solve(s, step=k, guess=guess, theta=line)
        inner.solve_ms.append(sol.solve_ms)
        inner._plan, inner._plan_step = sol.u, k
        inner._k += 1
        return sol.u[0].copy()


def reach(args: argparse.Namespace) -> None:
    """NMPC (2 s, gamma = 0.99, true mean, seed 0) course cost against its preview distance."""
    from validation.nmpc import drive

    def drive_one(d: float) -> dict[str, Any]:
        res, timing = drive(LimitedPreviewNMPC(d, horizon=2.0, gamma=0.99, force="true"), seed=0)
        return {"horizon": 2.0, "gamma": 0.99, "seed": 0, "cost": res.total_cost,
                "lateral_mae": res.mean_abs_lateral_error, "speed_mae": res.mean_abs_speed_error,
                "terminated": res.terminated, "solve_ms_mean": timing["solve_ms_mean"]}

    _nmpc_sweep(OUT / "nmpc_reach.json", "reach_m", [float(x) for x in args.reaches.split(",")], drive_one)


class NumpyActor:
    """The forward pass of a :class:`mixedrl.networks.Actor` in plain NumPy (float64), for deployment.

    ``u = bound * tanh(W_L(... elu(W_1 (o / scale) + b_1) ...) + b_L)``: the same weights, no torch call.

    Parameters
    ----------
    state_dict : dict
        ``actor.state_dict()`` of an :class:`~mixedrl.networks.Actor` with ELU hidden layers (tensors or
        nested lists, as :func:`actor_weights` writes them).

    Raises
    ------
    ValueError
        ``state_dict`` lacks the actor's buffers or a layer's shapes do not chain.
    """

    def __init__(self, state_dict: dict[str, Any]) -> None:
        arrays = {k: np.asarray(v.detach().numpy() if isinstance(v, torch.Tensor) else v, dtype=np.float64)
                  for k, v in state_dict.items()}
        for key in ("action_bound", "net.input_scale"):
            if key not in arrays:
                raise ValueError(f"state_dict: expected the actor's {key!r}, got keys {sorted(arrays)}")
        self.bound, self.inv_scale = arrays["action_bound"], 1.0 / arrays["net.input_scale"]
        idx = sorted({int(k.split(".")[2]) for k in arrays if k.startswith("net.body.")})
        self.layers = [(arrays[f"net.body.{i}.weight"], arrays[f"net.body.{i}.bias"]) for i in idx]
        width = self.inv_scale.shape[0]
        for W, b in self.layers:
            if W.shape[1] != width or b.shape != (W.shape[0],):
                raise ValueError(f"state_dict: layer of shape {W.shape} does not follow a width of {width}")
            width = W.shape[0]
        self.obs_dim = self.inv_scale.shape[0]

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """The action for one observation (shape (obs_dim,)): shape (2,)."""
        z = obs * self.inv_scale
        for W, b in self.layers[:-1]:
            z = W @ z + b
            z = np.where(z > 0.0, z, np.expm1(np.minimum(z, 0.0)))  # ELU
        W, b = self.layers[-1]
        return self.bound * np.tanh(W @ z + b)


def actor_weights(actor: torch.nn.Module) -> dict[str, list[Any]]:
    """``actor.state_dict()`` as nested lists (exact float32 values), for the per-run JSON."""
    return {k: v.detach().double().tolist() for k, v in actor.state_dict().items()}


#: Batch designs (docs/model_based.rst) -> ``CourseSampler.course_starts``. The study first ran on
#: design M, the default then (its runs are kept, under ``per_run/M``, and reproduce); S is the default now.
DESIGNS: dict[str, str] = {"M": "start", "S": "along"}
#: The design of the figure's policies.
FIGURE_DESIGN = "S"


def _check_design(design: str) -> str:
    if design not in DESIGNS:
        raise ValueError(f"design: expected one of {sorted(DESIGNS)}, got {design!r}")
    return DESIGNS[design]


def job_path(candidate: str, method: str, seed: int, iterations: int | None = None, design: str = "S") -> Path:
    """``docs/_static/preview/per_run/<design>/<candidate>/<method>_s<seed>.json`` (``_n<iterations>``
    appended for a budget other than the default)."""
    _check_design(design)
    tail = "" if iterations in (None, TrainConfig().algorithm.iterations) else f"_n{iterations}"
    return OUT / "per_run" / design / candidate / f"{method}_s{seed}{tail}.json"


def design_of(config: dict[str, Any]) -> str:
    """The design (a key of :data:`DESIGNS`) of a run's saved config (a config saved before
    ``model_course_starts`` existed ran design M, the only one then)."""
    starts = migrate(config).get("sampler", {}).get("course_starts", DESIGNS["M"])  # old flat configs too
    return next(d for d, v in DESIGNS.items() if v == starts)


def config_of(candidate: str, method: str, seed: int, iterations: int | None = None,
              design: str = "S") -> TrainConfig:
    """The run's config: :class:`~mixedrl.config.TrainConfig`'s defaults with the design's course
    rollouts (:data:`DESIGNS`; ``S`` is the default's) plus the candidate's ``task.preview_distances``;
    evaluations every 300 iterations (reporting only, as in scripts/model_based_study.py), one checkpoint
    at the end. ``iterations`` (default: the default budget, 1500) is the budget, as the model-based study
    varies it."""
    if candidate not in CANDIDATES:
        raise ValueError(f"candidate: expected one of {sorted(CANDIDATES)}, got {candidate!r}")
    starts = _check_design(design)
    n = TrainConfig().algorithm.iterations if iterations is None else iterations
    return TrainConfig().replace(method=method, seed=seed, iterations=n, eval_every=max(100, n // 5),
                                 checkpoint_every=n,
                                 num_threads=1, model_course_starts=starts,
                                 **{"task.preview_distances": list(CANDIDATES[candidate])})


def preview_scale(task: Any) -> torch.Tensor:
    """``max_X |Y_ref(X + d_i) - Y_ref(X)|`` over the course (``X`` in [0, course_length], 1 cm grid) for
    each preview distance of the task: each preview column then lies in [-1, 1] on the path."""
    cfg = task.model.config
    X = np.linspace(0.0, cfg.course_length, int(round(cfg.course_length * 100)) + 1)
    return torch.tensor([float(np.abs(cfg.reference.lateral(X + d) - cfg.reference.lateral(X)).max())
                         for d in cfg.preview_distances], dtype=torch.float32)


def make_task(candidate: str, cfg: TrainConfig) -> Any:
    """The run's task: ``task_from_config(cfg.task)``, with :func:`preview_scale` on the preview columns of
    ``obs_scale`` for the candidates of :data:`PER_DISTANCE_SCALE` (the networks' input scaling and the
    model box follow ``task.obs_scale``)."""
    task = task_from_config(cfg.task)
    if candidate in PER_DISTANCE_SCALE:
        task.obs_scale = torch.cat([task.obs_scale[:5], preview_scale(task)])
    return task


def run_job(candidate: str, method: str, seed: int, iterations: int | None = None, design: str = "S") -> str:
    """Train one run and write its JSON (skipped if it exists); returns a one-line summary."""
    path = job_path(candidate, method, seed, iterations, design)
    if path.exists():
        return f"skip {path}"
    torch.set_num_threads(1)
    cfg = config_of(candidate, method, seed, iterations, design)
    trainer = make_trainer(cfg, make_task(candidate, cfg))
    evals: list[dict[str, float]] = []

    def callback(row: dict[str, Any]) -> None:
        if "eval/cost" in row:
            evals.append({"iteration": int(row["iteration"]), "cost": row["eval/cost"],
                          "lateral_mae": row["eval/lateral_mae"], "speed_mae": row["eval/speed_mae"],
                          "true_transitions": row["data/true_transitions"]})

    t0 = time.perf_counter()
    res = train(trainer, None, callback=callback)
    out = {"candidate": candidate, "design": design, "preview_distances": list(CANDIDATES[candidate]), "method": method,
           "seed": seed, "iterations": int(res["iterations"]), "config": cfg.to_dict(),
           "wall_s": time.perf_counter() - t0, "train_seconds": res["train_seconds"],
           "lateral_mae": res["lateral_mae"], "speed_mae": res["speed_mae"], "cost": res["cost"],
           "terminated": res["final"]["terminated"], "true_transitions": res["true_transitions"],
           "final_ibe_mean_vx": res["final_ibe_mean"][2], "evals": evals,
           "obs_scale": trainer.task.obs_scale.tolist(), "actor": actor_weights(trainer.actor)}
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(out) + "\n")
    return (f"{candidate} {design} {method} s{seed}: cost {out['cost']:.2f}, lateral {out['lateral_mae']:.4f} m, "
            f"speed {out['speed_mae']:.4f} m/s, true {out['true_transitions']}, {out['wall_s']:.0f} s")


def run(args: argparse.Namespace) -> None:
    """Train every (candidate, method, seed) of the arguments, one at a time."""
    for candidate in args.candidate.split(","):
        for seed in seeds_of(args.seeds):
            for method in args.methods.split(","):
                print(run_job(candidate, method, seed, args.iterations, args.design), flush=True)


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
    """Write ``summary.csv``, ``summary.json``, ``per_seed.csv`` and ``trajectory.png``."""
    runs = [json.loads(p.read_text()) for p in sorted((OUT / "per_run").glob("*/*/*.json"))]
    if not runs:
        raise SystemExit(f"no runs under {OUT / 'per_run'}: run `preview_study.py run` first")
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
    atomic_write_text(OUT / "summary.csv", _csv(table))
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
    atomic_write_text(OUT / "per_seed.csv", _csv(per_seed))
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
    p = sub.add_parser("run")
    p.add_argument("--candidate", required=True, help=f"comma-separated, of {sorted(CANDIDATES)}")
    p.add_argument("--methods", default="mixed")
    p.add_argument("--seeds", default="0-4")
    p.add_argument("--iterations", type=int, default=None, help="budget (default: TrainConfig's, 1500)")
    p.add_argument("--design", default="S", choices=sorted(DESIGNS), help="batch design (default S, the default's)")
    p = sub.add_parser("ship")
    p.add_argument("--chosen", default=CHOSEN)
    args = parser.parse_args(argv)
    {"horizon": horizon, "reach": reach, "run": run, "ship": ship}[args.cmd](args)


if __name__ == "__main__":
    main()
