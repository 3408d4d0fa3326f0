"""Reproduction of the paper's Table I and Figs. 3-7 (Section VI's experiment, the double lane change; Fig. 3,
the effect of the IBE, belongs to Section IV) as one readable script.

Run it as ``mixedrl reproduce --seeds 5 --out DIR`` or ``python -m validation.reproduce --seeds 5 --out DIR``.
The ``mixedrl reproduce`` command is a plug-in of :mod:`mixedrl.cli` (entry point ``reproduce`` of the group
``mixedrl.commands``, :func:`register`): the core package does not import this script.

What it does, top to bottom:

1. For every method -- mixed RL (Algorithm 2 with the IBE), model-driven RL (Algorithm 2 on the prior,
   eq. 55), DDPG (data only) and the oracle (Algorithm 2 with the true noise) -- and every seed, train
   one run with **the same** :class:`mixedrl.config.TrainConfig` (networks, optimiser, learning rates,
   batch, iteration budget); only ``method`` and ``seed`` differ. The runs are the sweep
   :func:`reproduction_spec` (``experiments/studies/reproduction.toml`` for 5 seeds), trained by ``mixedrl sweep``'s
   engine into ``DIR/sweep/runs/<name>/``: the Algorithm-2 runs in batches
   (:mod:`mixedrl.algorithms.batched`), DDPG alone (batching DDPG does not pay on 2 cores:
   :func:`mixedrl.sweep.plan_batches`), on ``workers`` processes (one torch thread each).
   ``--resume`` reuses finished runs and resumes interrupted ones from their checkpoints. Mixed and
   model-driven RL train once more with the ``paper`` preset (the paper's literal Algorithm 2:
   ``TrainConfig.preset("paper")``; rows ``mixed_paper``, ``model_paper``, the sweep variant
   ``paper_preset``; the first seed only with ``--quick``), so the table shows the library defaults and the
   paper's algorithm side by side, each with mixed against model-driven RL seed by seed
   (:func:`compare_seeds`: wins, ratio, paired bootstrap interval).
2. During the Algorithm-2 runs, every 250th iteration (50th with ``--quick``) a :class:`TheoryObserver`
   (the spec's ``observer``) applies the ``theory`` checks to the iteration just made, on its batch of
   states: value decrease (eqs. 29/42), the pointwise MVC (eq. 38, with ``e_k >= 0`` of eq. 39),
   Lyapunov decrease (eq. 41) and the IBE shift (eq. 45).
3. Each final policy drives the full course (:func:`mixedrl.envs.evaluate_tracking`) with the run's
   evaluation seeds; Table I reports the mean absolute lateral and speed errors, mean ± std over seeds,
   beside the paper's numbers. Each method's first seed drives the course once more for Figs. 5-7
   (``DIR/trajectories/``, from its final checkpoint).
4. ``DIR/results.json`` (per method a list of runs ``{"seed", "lateral_mae", "speed_mae",
   "iterations_to_converge", "train_seconds"}`` and the means; the paper's values under ``"paper"``; the
   theory summary; the targets and whether each was met; the task configuration under ``"task"``) and
   ``DIR/figures/``, numbered as the paper's figures: ``fig3_ibe_effect``, ``fig4_convergence``,
   ``fig5_trajectory``, ``fig6_speed_error``, ``fig7_lateral_error`` (PNG).

The experiment's constants (true disturbance, prior, the component ``v_x`` it acts on, the force scale
``T / m``) are read from the task configuration (:class:`mixedrl.config.DoubleLaneChangeTaskConfig`) and
the task built from it, never repeated here.

Convergence is measured the same way for every method: :func:`mixedrl.runs.iterations_to_converge`
(the first evaluated iteration after which the evaluation cost stays within 10% of the run's final
level). One iteration is one PEV + PIM step (Algorithm 2) or one critic + actor update (DDPG).
"""

from __future__ import annotations

import argparse
import copy
import io
import json
import logging
import math
import os
import sys
import time
from pathlib import Path
from collections.abc import Callable
from typing import Any, Sequence

import numpy as np
import torch

import theory
from mixedrl.checks import check_positive_int
from mixedrl.config import DoubleLaneChangeTaskConfig, TrainConfig, task_config
from mixedrl.gaussian import sample_gaussian
from mixedrl.ibe import UnknownCovarianceIBE
from mixedrl.tables import mean_std, paired_interval
from mixedrl.runs import RunDirectory, atomic_write_bytes, atomic_write_text, eval_seeds, load_checkpoint, make_trainer
from mixedrl.sweep import DEFAULT_BATCH, SweepSpec, expand, parse_spec, run_sweep
from validation.nmpc import REFERENCE_SETTINGS
from mixedrl.tasks import DoubleLaneChangeTask, task_from_config

__all__ = ["PAPER", "METHODS", "EXTRA", "PRESET_ROWS", "compare_seeds", "reproduce", "reproduction_spec", "format_table", "format_references", "run_config",
           "TheoryObserver", "TheoryProbe", "theory_observer", "quick_theory_observer", "make_figures", "main",
           "register", "add_arguments", "run_command"]

logger = logging.getLogger(__name__)

#: Table I of the paper (and Section VI's iteration counts). The oracle is ours (no paper value).
PAPER: dict[str, dict[str, float]] = {
    "mixed": {"lateral_mae": 0.151, "speed_mae": 0.021, "iterations_to_converge": 1e4},
    "model": {"lateral_mae": 0.179, "speed_mae": 0.051, "iterations_to_converge": 1e4},
    "ddpg": {"lateral_mae": 0.228, "speed_mae": 0.093, "iterations_to_converge": 4e4},
}
#: Order of the table rows.
METHODS = ("mixed", "model", "ddpg", "oracle")
#: Extra rows: DDPG with :data:`DDPG_LONG_ITERATIONS` iterations, to measure where it converges; mixed
#: and model-driven RL with the paper's literal Algorithm 2 (``TrainConfig.preset("paper")``, :data:`PRESET_ROWS`).
EXTRA = ("ddpg_long", "mixed_paper", "model_paper")
#: The rows of the ``paper`` preset: label -> method. Their sweep variant is ``paper_preset``; in quick mode
#: they train the first seed only.
PRESET_ROWS = {"mixed_paper": "mixed", "model_paper": "model"}
#: The paired per-seed comparisons of mixed against model-driven RL: (setting, mixed's label, model's label).
COMPARISONS = (("library defaults", "mixed", "model"), ("paper preset", "mixed_paper", "model_paper"))
#: The longer DDPG budget: 16 times the one-step learner's 1500 iterations (the budget of
#: experiments/studies/table1_seeds20_ddpg.toml's ``ddpg_long`` rows), evaluated every 400 iterations.
DDPG_LONG_ITERATIONS = 24_000
#: Quick mode: DDPG with this many times the common budget, evaluated every ``factor / 4`` times as rarely.
QUICK_DDPG_LONG_FACTOR = 2
LABELS = {"mixed": "Mixed RL", "model": "Model-driven RL", "ddpg": "Data-driven RL (DDPG)",
          "oracle": "Oracle (true noise)", "ddpg_long": "DDPG, longer budget",
          "mixed_paper": "Mixed RL, paper preset", "model_paper": "Model-driven, paper preset"}
#: Quick mode (the test suite): 400 iterations for every row (half the default budget; measured on seeds 0-1:
#: mixed RL on the road at 0.097 m, its IBE mean within 0.2% of the truth), one evaluation course every 100
#: iterations, DDPG's longer budget 2x the common one instead of 24,000 iterations and on the first seed only
#: (as the paper preset's rows); at most this many seeds.
QUICK = {"algorithm.iterations": 400, "run.eval_every": 100, "run.eval_seeds": 1, "ddpg.warmup": 500}
QUICK_MAX_SEEDS = 2
#: The spec of the reproduction's runs (``mixedrl sweep experiments/studies/reproduction.toml`` trains the same).
SPEC_PATH = Path(__file__).resolve().parent.parent / "experiments" / "studies" / "reproduction.toml"


def run_config(label: str, seed: int, quick: bool = False) -> TrainConfig:
    """The config of one run: the shared defaults, with only ``method`` and ``seed`` changed.

    ``label="ddpg_long"`` is DDPG with :data:`DDPG_LONG_ITERATIONS` iterations, evaluated every 400 and
    checkpointed every 8000 (quick mode: :data:`QUICK_DDPG_LONG_FACTOR` times the budget, evaluated every
    ``factor / 4`` times as rarely); same everything else.
    ``"mixed_paper"`` / ``"model_paper"`` (:data:`PRESET_ROWS`) are mixed / model-driven RL with the
    ``paper`` preset (the paper's literal Algorithm 2) applied to those defaults.
    """
    method = "ddpg" if label == "ddpg_long" else PRESET_ROWS.get(label, label)
    config = TrainConfig(method=method, seed=seed, task="dlc")
    if label in PRESET_ROWS:
        config = config.with_preset("paper")
    if quick:
        config = config.replace(**QUICK)
    if label == "ddpg_long":
        # DDPG keeps its schedule: the learning rates decay over its whole (longer) budget
        if quick:
            factor = QUICK_DDPG_LONG_FACTOR
            longer = {"algorithm.iterations": factor * config.algorithm.iterations,
                      "run.checkpoint_every": factor * config.run.checkpoint_every,
                      "run.eval_every": max(1, factor // 4) * config.run.eval_every}
        else:
            longer = {"algorithm.iterations": DDPG_LONG_ITERATIONS, "run.checkpoint_every": 8000, "run.eval_every": 400}
        config = config.replace(**longer, **{"algorithm.lr_decay_iterations": 0})
    return config


# ----------------------------------------------------------------------------------------------------
# theory checks on the runs
# ----------------------------------------------------------------------------------------------------
class _StateNoise:
    """A noise source lifted to the simulator state: mean ``E mu``, covariance ``E K E^T``."""

    def __init__(self, mean: np.ndarray, cov: np.ndarray, E: np.ndarray) -> None:
        self.mean = E @ mean
        self.cov = E @ cov @ E.T


class TheoryObserver:
    """Every ``every`` iterations of an :class:`~mixedrl.algorithms.agpi.AGPI` run, checks the iteration just
    made with the ``theory`` package on its batch of states (an :class:`mixedrl.runs.IterationObserver`:
    it works on a run alone and inside a batch).

    Metrics added to that iteration's row: ``theory/value_decrease`` (fraction of states with
    ``V^{k+1}(x) <= V^k(x)``, eq. 29/42), ``theory/mvc_pointwise`` (fraction with eq. 38 pointwise),
    ``theory/mvc_batch_mean`` (eq. 38 on the batch mean), ``theory/e_nonnegative`` (eq. 39),
    ``theory/lyapunov`` (fraction with ``E V^k(x') <= V^k(x)`` under ``pi^{k+1}``, ``xi_hat_{k+1}``,
    eq. 41), ``theory/ibe_kl`` (eq. 45).

    Expectations use the ``theory`` package's default rule (sigma points), in float64 on the same
    ``f``, ``l`` and networks. The observer only reads the run (copies of its networks and moments).
    """

    def __init__(self, every: int) -> None:
        self.every = check_positive_int(every, "every")

    def before(self, tr: Any) -> Any:
        if tr.k % self.every != 0:
            return None
        return copy.deepcopy(tr.critic), copy.deepcopy(tr.actor), tr.noise_moments()

    def after(self, tr: Any, token: Any, row: dict[str, float]) -> dict[str, float] | None:
        if token is None:
            return None
        critic_k, actor_k, (mean_k, cov_k) = token
        task = tr.task
        E = task.noise_matrix.double().numpy()
        noise_k = _StateNoise(mean_k, cov_k, E)
        noise_k1 = _StateNoise(*tr.noise_moments(), E)
        states = tr.last_batch.double().numpy()

        def on_states(net: torch.nn.Module) -> Any:
            """A network on observations as a numpy function of simulator states (value or policy)."""
            def fn(x: np.ndarray) -> np.ndarray:
                with torch.no_grad():
                    return net(task.observe(torch.as_tensor(x)).float()).double().numpy()
            return fn

        def f(x: np.ndarray, u: np.ndarray) -> np.ndarray:
            return task.f(torch.as_tensor(x), torch.as_tensor(u)).numpy()

        def utility(x: np.ndarray, u: np.ndarray) -> np.ndarray:
            return task.cost(torch.as_tensor(x), torch.as_tensor(u)).numpy()

        # V^k is the critic after this iteration's PEV step (the value Algorithm 2 improves against)
        vk = on_states(tr.critic)
        vd = theory.value_decrease(on_states(critic_k), vk, states)
        mv = theory.mvc(vk, on_states(actor_k), on_states(tr.actor), f, utility, task.gamma, noise_k, noise_k1,
                        states)
        ly = theory.lyapunov_decrease(vk, on_states(tr.actor), f, noise_k1, states)
        kl = theory.ibe_shift(noise_k, noise_k1)
        return {
            "theory/value_decrease": vd.held_fraction,
            "theory/mvc_pointwise": mv.held_fraction,
            "theory/mvc_batch_mean": float(mv.extra["held_on_batch_mean"]),
            "theory/e_nonnegative": float(mv.extra["e_nonnegative_fraction"]),
            "theory/lyapunov": ly.held_fraction,
            "theory/ibe_kl": float(kl.kl),
        }


def theory_observer(config: TrainConfig, every: int = 250) -> TheoryObserver | None:
    """The observer of a reproduction run: :class:`TheoryObserver` for Algorithm 2, none for DDPG (the
    ``observer`` of ``experiments/studies/reproduction.toml``)."""
    return None if config.method == "ddpg" else TheoryObserver(every)


def quick_theory_observer(config: TrainConfig) -> TheoryObserver | None:
    """:func:`theory_observer` every 50 iterations (``--quick``)."""
    return theory_observer(config, 50)


class TheoryProbe:
    """A trainer whose :meth:`iteration` is the trainer's with the :class:`TheoryObserver` checks added
    (for use outside :func:`mixedrl.runs.train`)."""

    def __init__(self, trainer: Any, every: int) -> None:
        self.trainer = trainer
        self.observer = TheoryObserver(every)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.trainer, name)

    def iteration(self) -> dict[str, float]:
        token = self.observer.before(self.trainer)
        row = self.trainer.iteration()
        row.update(self.observer.after(self.trainer, token, row) or {})
        return row


# ----------------------------------------------------------------------------------------------------
# one run
# ----------------------------------------------------------------------------------------------------
def _trajectory(trainer: Any, seed: int) -> dict[str, np.ndarray]:
    task = trainer.task
    ev = task.evaluate(trainer.policy, [seed], keep_trajectory=True)
    r = ev["trajectories"][0]
    X = r.states[:, 5]
    return {"time": r.time, "X": X, "Y": r.states[:, 4], "Y_ref": np.asarray(task.model.reference.lateral(X)),
            "lateral_error": r.lateral_error, "speed_error": r.speed_error, "actions": r.actions}


def reproduction_spec(seeds: int = 5, quick: bool = False) -> SweepSpec:
    """The sweep of the reproduction: every label of :data:`METHODS` and :data:`EXTRA` over seeds
    ``0 .. seeds-1``, each run's config :func:`run_config`, with the theory checks as its observer.

    For ``seeds=5`` (not quick) it expands to the runs of ``experiments/studies/reproduction.toml`` (tested).
    """
    base = run_config("mixed", 0, quick).to_dict()
    default = TrainConfig(task="dlc").to_dict()
    long_cfg = run_config("ddpg_long", 0, quick)

    def dotted(cfg: dict[str, Any], ref: dict[str, Any]) -> dict[str, Any]:
        return {f"{sec}.{k}": v for sec in ("algorithm", "run", "ddpg", "sampler") for k, v in cfg[sec].items()
                if v != ref[sec][k]}

    lines = [f"# mixedrl reproduce{' --quick' if quick else ''} --seeds {seeds} (validation.reproduce.reproduction_spec)",
             f"methods = {json.dumps(list(METHODS))}", f"seeds = {json.dumps(list(range(seeds)))}",
             f'observer = "validation.reproduce:{"quick_theory_observer" if quick else "theory_observer"}"', "",
             "[base]"]
    lines += [f'"{k}" = {json.dumps(v)}' for k, v in dotted(base, default).items()]
    lines += ["", "[variants.paper]", "", "[variants.ddpg_long]", 'methods = ["ddpg"]']
    lines += ["seeds = [0]"] if quick else []
    lines += [f'"{k}" = {json.dumps(v)}' for k, v in dotted(long_cfg.to_dict(), base).items()]
    lines += ["", "[variants.paper_preset]", f"methods = {json.dumps(list(PRESET_ROWS.values()))}"]
    lines += ["seeds = [0]"] if quick else []
    lines += [f'"{k}" = {json.dumps(v)}' for k, v in dotted(run_config("mixed_paper", 0, quick).to_dict(), base).items()]
    return parse_spec("\n".join(lines) + "\n", "reproduction_spec")


def _label(record: dict[str, Any]) -> str:
    """The table row of a sweep row: ``ddpg_long`` for that variant, ``<method>_paper`` for the
    ``paper_preset`` variant, else the method."""
    variant = record["point"].get("variant")
    if variant == "paper_preset":
        return f"{record['method']}_paper"
    return "ddpg_long" if variant == "ddpg_long" else record["method"]


def _trajectory_path(out: Path, label: str, seed: int) -> Path:
    return out / "trajectories" / f"{label}_seed{seed}.npz"


def _save_trajectory(out: Path, run: RunDirectory, label: str) -> None:
    """The course of a finished run's final policy with its first evaluation seed (Figs. 5-7), from its
    checkpoint (evaluation only)."""
    config = run.read_config()
    path = _trajectory_path(out, label, config.seed)
    if path.is_file():
        return
    trainer = make_trainer(config)
    trainer.load_state_dict(load_checkpoint(run.checkpoint_path)["trainer"])
    buffer = io.BytesIO()
    np.savez(buffer, **_trajectory(trainer, eval_seeds(config)[0]))
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, buffer.getvalue())


def _summary_of_run(res: dict[str, Any]) -> dict[str, Any]:
    return {"seed": res["seed"], "run_dir": res.get("run_dir"), "lateral_mae": res["lateral_mae"], "speed_mae": res["speed_mae"],
            "iterations_to_converge": res["iterations_to_converge"], "train_seconds": res["train_seconds"],
            "cost": res.get("cost"), "left_road": res.get("final", {}).get("terminated"),
            "true_transitions": res.get("true_transitions"),
            "policy_gap_action_error": (res.get("policy_gap") or {}).get("action_error")}


def _theory_summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    keys = ("theory/value_decrease", "theory/mvc_pointwise", "theory/mvc_batch_mean", "theory/e_nonnegative",
            "theory/lyapunov", "theory/ibe_kl")
    for key in keys:
        vals = [r[key] for r in rows if key in r and math.isfinite(r[key])]
        if vals:
            out[key.split("/", 1)[1]] = float(np.mean(vals))
    n_inf = sum(1 for r in rows if "theory/ibe_kl" in r and not math.isfinite(r["theory/ibe_kl"]))
    if n_inf:
        # KL(p_k || p_{k+1}) is infinite when the support of p_{k+1} is smaller than p_k's: the prior's
        # 1e-20 variances on the four noise-free components collapse to 0 after the first data
        out["ibe_kl_infinite_count"] = n_inf
    held = [r["mvc/held"] for r in rows if "mvc/held" in r]
    if held:
        out["mvc_held_after_inner_loop"] = float(np.mean(held))
        out["mean_inner_steps"] = float(np.mean([r["mvc/inner_steps"] for r in rows]))
    kls = [r["theory/ibe_kl"] for r in rows if "theory/ibe_kl" in r]
    if kls:
        out["ibe_kl_first"], out["ibe_kl_last"] = _finite_or_str(kls[0]), _finite_or_str(kls[-1])
    return out


def _finite_or_str(x: float) -> float | str:
    return float(x) if math.isfinite(x) else str(x)


def reproduce(out: str | Path, seeds: int = 5, quick: bool = False, resume: bool = False, workers: int | None = None,
              progress: bool = True, references: str | Path | None = None,
              batch: int = DEFAULT_BATCH) -> dict[str, Any]:
    """Train every method over ``seeds`` seeds, write ``results.json`` and the figures; return the results.

    The runs are the sweep :func:`reproduction_spec`, trained by :func:`mixedrl.sweep.run_sweep` into
    ``out/sweep`` (the Algorithm-2 runs batched, :mod:`mixedrl.algorithms.batched`); then the course of
    each label's first seed is driven for Figs. 5-7 (``out/trajectories``), and the table and figures
    are written.

    Parameters
    ----------
    out : str or pathlib.Path
        Output directory.
    seeds : int
        Number of seeds ``0 .. seeds-1`` per method (quick mode: at most 2).
    quick : bool
        Reduced run (:data:`QUICK`) for the test suite.
    resume : bool
        Reuse finished runs, resume interrupted ones.
    workers : int, optional
        Parallel processes (default ``min(2, cpu_count)``).
    progress : bool
        tqdm progress bar over runs.
    references : str or pathlib.Path, optional
        A directory written by ``scripts/references.py`` (``references.json`` and ``trajectories.npz``,
        shipped in ``docs/_static/references``): the trajectory and error figures overlay the reference
        controllers' seed-0 courses (measured, not re-run here).
    batch : int
        Most runs trained as one computation (``mixedrl sweep --batch``; 1: every run alone).

    Returns
    -------
    dict
        The content of ``results.json``.

    Raises
    ------
    ValueError
        ``seeds``, ``workers`` or ``batch`` not a positive integer; ``out`` holds a reproduction and
        ``resume`` is false.
    RuntimeError
        A run failed (its error is in ``out/sweep/sweep.json``).
    """
    seeds = check_positive_int(seeds, "seeds")
    if quick:
        seeds = min(seeds, QUICK_MAX_SEEDS)
    workers = check_positive_int(workers if workers is not None else min(2, os.cpu_count() or 1), "workers")
    out = Path(out)
    spec = reproduction_spec(seeds, quick)
    t0 = time.perf_counter()
    doc = run_sweep(spec, out / "sweep", resume=resume, progress=progress, workers=workers, batch=batch)
    if doc["failed"]:
        errors = "; ".join(f"{r['name']}: {r['error']}" for r in doc["runs"] if r["error"])
        raise RuntimeError(f"{doc['failed']} run(s) of the reproduction failed: {errors}")
    finished: list[dict[str, Any]] = []
    for rec in sorted(doc["runs"], key=lambda r: r["seed"]):
        label = _label(rec)
        run = RunDirectory(out / "sweep" / rec["run_dir"])
        if label not in PRESET_ROWS and all(r["label"] != label for r in finished):  # first seed: Figs. 5-7
            _save_trajectory(out, run, label)
        finished.append({**run.read_results(), "label": label, "run_dir": str(Path("sweep") / rec["run_dir"])})
    wall = time.perf_counter() - t0
    previous = out / "results.json"
    if resume and previous.is_file():
        # the wall time of a resumed reproduction includes the interrupted invocation's
        wall += float(json.loads(previous.read_text()).get("wall_seconds", 0.0))
    results = aggregate(out, finished, wall, quick, task=expand(spec)[0].config.to_dict()["task"])
    results["sweep"] = {k: doc.get(k) for k in ("engine", "workers", "batch", "batches", "wall_seconds")}
    atomic_write_text(out / "results.json", json.dumps(results, indent=2, sort_keys=True) + "\n")
    try:
        make_figures(out, results, references=references)
    except ImportError:  # pragma: no cover - matplotlib is an optional extra
        logger.warning("matplotlib not installed: no figures")
    return results


def aggregate(out: Path, finished: list[dict[str, Any]], wall: float, quick: bool,
              task: dict[str, Any] | None = None) -> dict[str, Any]:
    """Group the runs by method, add means, the paper's values, the theory summary and the targets.

    ``task`` is the runs' task configuration as a dict (default: the double lane change's defaults).
    """
    task = task_config(task if task is not None else "dlc")
    results: dict[str, Any] = {"paper": PAPER, "quick": quick, "wall_seconds": wall,
                               "task": TrainConfig(task=task).to_dict()["task"],
                               "convergence_criterion": finished[0]["convergence_criterion"] if finished else None}
    for method in METHODS + EXTRA:
        runs = sorted((r for r in finished if r["label"] == method), key=lambda r: r["seed"])
        if not runs:
            continue
        entry: dict[str, Any] = {"runs": [_summary_of_run(r) for r in runs]}
        for key in ("lateral_mae", "speed_mae", "iterations_to_converge", "train_seconds"):
            entry[f"{key}_mean"], entry[f"{key}_std"] = mean_std([r[key] for r in runs])
        if all(r.get("cost") is not None for r in runs):
            entry["cost_mean"], entry["cost_std"] = mean_std([r["cost"] for r in runs])
        if all(r.get("true_transitions") is not None for r in runs):
            entry["true_transitions_mean"] = float(np.mean([r["true_transitions"] for r in runs]))
        if method != "ddpg":
            rows = []
            for r in runs:
                rows += _run_dir(out, method, r).read_metrics()
            entry["theory"] = _theory_summary(rows)
        if method == "mixed":
            entry["final_ibe_mean"] = [r["final_ibe_mean"] for r in runs]
        gaps = [(r.get("policy_gap") or {}).get("action_error") for r in runs]
        if all(g is not None for g in gaps):  # mixedrl.precision: action - LQ optimum at the origin, own mean
            entry["policy_gap_abs_mean"], entry["policy_gap_abs_std"] = (
                np.abs(np.asarray(gaps, dtype=float)).mean(axis=0).tolist(),
                np.abs(np.asarray(gaps, dtype=float)).std(axis=0, ddof=1 if len(gaps) > 1 else 0).tolist())
        results[method] = entry
    results["comparisons"] = compare_seeds(results)
    results["targets"] = check_targets(results)
    return results


def compare_seeds(results: dict[str, Any]) -> list[dict[str, Any]]:
    """Mixed against model-driven RL seed by seed, per setting of :data:`COMPARISONS` (the library defaults,
    the paper preset) and per error (``speed_mae``, ``lateral_mae``): on how many common seeds mixed RL's
    error is smaller, the ratio of the means (model / mixed) and the mean paired difference (model - mixed)
    with its percentile-bootstrap 95% interval (:func:`mixedrl.tables.paired_interval`; none with one seed)."""
    out = []
    for setting, a, b in COMPARISONS:
        if a not in results or b not in results:
            continue
        mixed = {r["seed"]: r for r in results[a]["runs"]}
        model = {r["seed"]: r for r in results[b]["runs"]}
        seeds = sorted(set(mixed) & set(model))
        for key in ("speed_mae", "lateral_mae"):
            x, y = [model[s][key] for s in seeds], [mixed[s][key] for s in seeds]
            diff, lo, hi = paired_interval(x, y)
            out.append({"setting": setting, "error": key, "seeds": seeds,
                        "mixed_wins": int(sum(u > v for u, v in zip(x, y))),
                        "ratio_model_over_mixed": float(np.mean(x) / np.mean(y)),
                        "difference_model_minus_mixed": diff, "interval": [lo, hi]})
    return out


def _run_dir(out: Path, label: str, run: dict[str, Any]) -> RunDirectory:
    """A run of the results: its ``run_dir`` (under ``out``), or ``runs/<label>_seed<S>`` (reproductions
    written before the runs went through ``mixedrl sweep``)."""
    rel = run.get("run_dir")
    return RunDirectory(out / rel if rel else out / "runs" / f"{label}_seed{run['seed']}")


def _dlc_task(results: dict[str, Any]) -> tuple[DoubleLaneChangeTaskConfig, DoubleLaneChangeTask]:
    """The task configuration of the results (``results["task"]``, default the paper's) and its task."""
    config = task_config(results.get("task", "dlc"))
    if not isinstance(config, DoubleLaneChangeTaskConfig):
        raise ValueError(f"task: the reproduction is on the double lane change, got {config.name!r}")
    task = task_from_config(config)
    assert isinstance(task, DoubleLaneChangeTask)
    return config, task


def check_targets(results: dict[str, Any]) -> dict[str, Any]:
    """Evaluate the issue's targets on the aggregated results (booleans and the measured figures)."""
    t: dict[str, Any] = {}
    mixed, model, ddpg, oracle = (results.get(m) for m in METHODS)
    if not (mixed and model and ddpg and oracle):
        return t
    lm, sm = mixed["lateral_mae_mean"], mixed["speed_mae_mean"]
    t["mixed_lateral_le_0.151"] = lm <= 0.151
    t["mixed_speed_le_0.021"] = sm <= 0.021
    t["mixed_within_10pct_of_oracle"] = (lm <= 1.1 * oracle["lateral_mae_mean"]
                                         and sm <= 1.1 * oracle["speed_mae_mean"])
    t["order_lateral_mixed_lt_model_lt_ddpg"] = lm < model["lateral_mae_mean"] < ddpg["lateral_mae_mean"]
    t["order_speed_mixed_lt_model_lt_ddpg"] = sm < model["speed_mae_mean"] < ddpg["speed_mae_mean"]
    t["speed_gap_vs_model"] = 1.0 - sm / model["speed_mae_mean"]
    t["speed_gap_vs_ddpg"] = 1.0 - sm / ddpg["speed_mae_mean"]
    t["speed_gap_vs_model_ge_0.58"] = t["speed_gap_vs_model"] >= 0.58
    t["speed_gap_vs_ddpg_ge_0.77"] = t["speed_gap_vs_ddpg"] >= 0.77
    t["mixed_converges_within_1e4"] = mixed["iterations_to_converge_mean"] <= 1e4
    long = results.get("ddpg_long", ddpg)
    t["ddpg_needs_2x_mixed"] = long["iterations_to_converge_mean"] >= 2 * mixed["iterations_to_converge_mean"]
    _, task = _dlc_task(results)
    vx = task.noise_index
    true_mean = float(task.true_mean[vx])  # F_dis mean T / m
    errs = [abs(m[vx] - true_mean) / true_mean for m in mixed.get("final_ibe_mean", [])]
    t["ibe_mean_rel_error_max"] = float(max(errs)) if errs else None
    t["ibe_mean_within_2pct"] = bool(errs) and max(errs) <= 0.02
    t["mixed_train_seconds_mean"] = mixed["train_seconds_mean"]
    t["mixed_run_le_180s"] = mixed["train_seconds_mean"] <= 180.0
    t["reproduce_wall_le_1800s"] = results["wall_seconds"] <= 1800.0
    # the model-based Algorithm 2 (docs/model_based.rst): every seed, the oracle's cost, the data used
    t["mixed_every_seed_lateral_le_0.151"] = all(r["lateral_mae"] <= 0.151 for r in mixed["runs"])
    t["mixed_every_seed_speed_le_0.010"] = all(r["speed_mae"] <= 0.010 for r in mixed["runs"])
    t["model_over_mixed_speed"] = model["speed_mae_mean"] / sm
    t["model_over_mixed_speed_ge_1.5"] = t["model_over_mixed_speed"] >= 1.5
    if "cost_mean" in mixed and "cost_mean" in oracle:
        t["mixed_cost_over_oracle"] = mixed["cost_mean"] / oracle["cost_mean"]
        t["mixed_cost_within_5pct_of_oracle"] = t["mixed_cost_over_oracle"] <= 1.05
    if "true_transitions_mean" in mixed:
        t["mixed_true_transitions_le_5e4"] = mixed["true_transitions_mean"] <= 5e4
    t["mixed_run_le_60s"] = mixed["train_seconds_mean"] <= 60.0
    t["reproduce_wall_le_900s"] = results["wall_seconds"] <= 900.0
    return t


def format_table(results: dict[str, Any]) -> str:
    """Table I with the paper's numbers beside ours (mean ± std over seeds) as plain text."""
    n = len(results["mixed"]["runs"]) if "mixed" in results else 0
    lines = [f"Table I -- mean absolute tracking errors on the double lane change ({n} seeds, mean ± std)"
             + ("  [QUICK: at most 2 seeds, 1 evaluation course, DDPG's longer budget 2x on the first seed]" if results.get("quick") else ""), ""]
    head = f"{'method':<24}{'lateral [m] ours':>20}{'paper':>8}{'speed [m/s] ours':>22}{'paper':>8}" \
           f"{'iters to converge':>20}{'paper':>8}{'train s':>9}{'course cost':>17}{'true trans.':>13}"
    lines += [head, "-" * len(head)]
    for method in METHODS + EXTRA:
        if method not in results:
            continue
        e, p = results[method], PAPER.get(method, {})

        def paper(key: str, fmt: str) -> str:
            return format(p[key], fmt) if key in p else "--"
        lines.append(
            f"{LABELS[method]:<24}"
            f"{e['lateral_mae_mean']:>12.3f} ± {e['lateral_mae_std']:<5.3f}{paper('lateral_mae', '.3f'):>8}"
            f"{e['speed_mae_mean']:>14.4f} ± {e['speed_mae_std']:<5.4f}{paper('speed_mae', '.3f'):>8}"
            f"{e['iterations_to_converge_mean']:>12.0f} ± {e['iterations_to_converge_std']:<5.0f}"
            f"{paper('iterations_to_converge', '.0e'):>8}{e['train_seconds_mean']:>9.1f}"
            + (f"{e['cost_mean']:>9.1f} ± {e['cost_std']:<5.1f}" if "cost_mean" in e else f"{'--':>17}")
            + (f"{e['true_transitions_mean']:>13,.0f}" if "true_transitions_mean" in e else f"{'--':>13}"))
    lines.append("")
    for c in results.get("comparisons", []):
        lo, hi = c["interval"]
        ci = "no interval (one seed)" if lo is None else f"95% paired bootstrap [{lo:+.4f}, {hi:+.4f}]"
        lines.append(f"{c['setting']}, {c['error']}: mixed better than model-driven on {c['mixed_wins']} of "
                     f"{len(c['seeds'])} seeds; model / mixed {c['ratio_model_over_mixed']:.2f}; model - mixed "
                     f"{c['difference_model_minus_mixed']:+.4f}, {ci}")
    lines.append(f"convergence: {results.get('convergence_criterion')}")
    lines.append(f"wall time: {results['wall_seconds']:.1f} s")
    if results.get("targets"):
        lines.append("targets: " + ", ".join(f"{k}={_fmt(v)}" for k, v in results["targets"].items()))
    for method in METHODS + EXTRA:
        gap = results.get(method, {}).get("policy_gap_abs_mean")
        if gap is not None:
            std = results[method]["policy_gap_abs_std"]
            lines.append(f"policy_gap ({method}): |action - LQ optimum| at the origin, own mean: "
                         + ", ".join(f"{g:.4f} ± {s:.4f}" for g, s in zip(gap, std)))
    for method in ("mixed", "model", "oracle"):
        th = results.get(method, {}).get("theory")
        if th:
            lines.append(f"theory ({method}): " + ", ".join(f"{k}={_fmt(v)}" for k, v in th.items()))
    return "\n".join(lines)


def format_references(rows: Sequence[dict[str, Any]]) -> str:
    """The block "references, not learned" of Table I, from the rows of :func:`validation.nmpc.reference_rows`.

    Parameters
    ----------
    rows : sequence of dict
        Each with ``method``, ``lateral_mae``, ``speed_mae``, ``cost``, ``solve_ms_mean``, ``solve_ms_max``
        and ``seeds`` (as written by ``scripts/references.py`` into ``references.json``).

    Returns
    -------
    str
        The block as plain text: lateral and speed error, undiscounted course cost and the online time per
        control step (mean and max over the course, mean over seeds).

    Raises
    ------
    ValueError
        A row lacks one of the keys above.
    """
    keys = ("method", "lateral_mae", "speed_mae", "cost", "solve_ms_mean", "solve_ms_max", "seeds")
    for i, row in enumerate(rows):
        missing = [k for k in keys if k not in row]
        if missing:
            raise ValueError(f"rows: row {i} lacks {missing}")
    width = max([34] + [len(str(row["method"])) + 2 for row in rows])
    head = f"{'reference (not learned)':<{width}}{'lateral [m]':>12}{'speed [m/s]':>13}{'course cost':>13}" \
           f"{'online ms mean':>16}{'max':>9}{'seeds':>7}"
    lines = [head, "-" * len(head)]
    for row in rows:
        lines.append(f"{str(row['method']):<{width}}{row['lateral_mae']:>12.3f}{row['speed_mae']:>13.4f}"
                     f"{row['cost']:>13.2f}{row['solve_ms_mean']:>16.3g}{row['solve_ms_max']:>9.3g}"
                     f"{len(row['seeds']):>7d}")
    return "\n".join(lines)


def _fmt(v: Any) -> str:
    if isinstance(v, bool):
        return "yes" if v else "NO"
    if isinstance(v, float):
        return f"{v:.3g}"
    return str(v)


# ----------------------------------------------------------------------------------------------------
# figures
# ----------------------------------------------------------------------------------------------------
#: The reference controllers overlaid on Figs. 5-7 (``method`` of ``references.json``) and their line styles.
REFERENCE_OVERLAY = {"whole-course optimum": ":", "NMPC 2 s, gamma=0.99, true mean": "-.", "LQR, gamma=0.99, true mean": "--"}


def _reference_courses(references: str | Path | None) -> list[tuple[str, str, dict[str, np.ndarray]]]:
    """``(label, line style, {"X", "ey", "ev"})`` of the overlaid references' seed-0 courses (none if no dir)."""
    if references is None:
        return []
    ref_dir = Path(references)
    rows = json.loads((ref_dir / "references.json").read_text())
    courses = np.load(ref_dir / "trajectories.npz")
    # the arrays are keyed by the index of the setting in validation.nmpc.REFERENCE_SETTINGS
    index = {label: i for i, (label, _) in enumerate(REFERENCE_SETTINGS)}
    out = []
    for row in rows:
        i = index.get(row["method"])
        if row["method"] in REFERENCE_OVERLAY and i is not None and f"X_{i}" in courses:
            out.append((row["method"], REFERENCE_OVERLAY[row["method"]],
                        {k: courses[f"{k}_{i}"] for k in ("X", "ey", "ev")}))
    return out


def make_figures(out: str | Path, results: dict[str, Any], references: str | Path | None = None) -> list[Path]:
    """Write Figs. 3-7 of the paper (numbered as there) as PNG files under ``out/figures``; returns their paths.

    With ``references`` (see :func:`reproduce`), Figs. 5-7 overlay the reference controllers of
    :data:`REFERENCE_OVERLAY` in grey ("references, not learned").
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    fig_dir = out / "figures"
    fig_dir.mkdir(parents=True, exist_ok=True)
    colors = {"mixed": "C0", "model": "C1", "ddpg": "C3", "oracle": "k"}
    paths = []
    methods = [m for m in METHODS if m in results]

    def metrics(method: str, run: dict[str, Any]) -> list[dict[str, Any]]:
        return _run_dir(out, method, run).read_metrics()

    # Fig. 4: convergence (evaluation cost of the course against iterations, mean and range over seeds)
    fig, ax = plt.subplots(figsize=(6, 4))
    colors["ddpg_long"] = "C3"
    colors.update({label: colors[method] for label, method in PRESET_ROWS.items()})
    for m in methods + [e for e in EXTRA if e in results]:
        curves = []
        for r in results[m]["runs"]:
            rows = [row for row in metrics(m, r) if "eval/cost" in row]
            curves.append(([row["iteration"] for row in rows], [row["eval/cost"] for row in rows]))
        its = curves[0][0]
        vals = np.array([c[1] for c in curves if len(c[1]) == len(its)])
        style = ":" if m in PRESET_ROWS else "--" if m in EXTRA else "-"
        ax.plot(its, vals.mean(axis=0), style, color=colors[m], label=LABELS[m])
        ax.fill_between(its, vals.min(axis=0), vals.max(axis=0), color=colors[m], alpha=0.1)
    ax.set_yscale("log")
    ax.set_xscale("log")
    ax.set_xlabel("iteration")
    ax.set_ylabel("evaluation cost of the course (eq. 54)")
    ax.set_title("Fig. 4: convergence")
    ax.legend()
    paths.append(_save(fig, fig_dir / "fig4_convergence.png"))

    def trajectory(m: str) -> Any:
        seed = results[m]["runs"][0]["seed"]
        path = _trajectory_path(out, m, seed)
        return np.load(path if path.is_file() else out / "runs" / f"{m}_seed{seed}" / "trajectory.npz")

    trajs = {m: trajectory(m) for m in methods}
    # Fig. 5: trajectory
    fig, ax = plt.subplots(figsize=(7, 3))
    first = trajs[methods[0]]
    ax.plot(first["X"], first["Y_ref"], "k--", lw=1, label="reference")
    for m in methods:
        ax.plot(trajs[m]["X"], trajs[m]["Y"], color=colors[m], lw=1, label=LABELS[m])
    ax.set_xlabel("X [m]")
    ax.set_ylabel("Y [m]")
    refs = _reference_courses(references)
    dt = float(np.median(np.diff(first["time"])))
    for label, style, c in refs:
        ax.plot(c["X"], np.interp(c["X"], first["X"], first["Y_ref"]) + c["ey"], style, color="grey", lw=1,
                label=f"{label} (reference)")
    ax.set_title("Fig. 5: tracking (seed 0)")
    ax.legend(fontsize=7)
    paths.append(_save(fig, fig_dir / "fig5_trajectory.png"))
    # Figs. 6 and 7: speed and lateral error
    for key, name, ylabel in (("speed_error", "fig6_speed_error", "v_x - 12 [m/s]"),
                              ("lateral_error", "fig7_lateral_error", "lateral error [m]")):
        fig, ax = plt.subplots(figsize=(7, 3))
        for m in methods:
            ax.plot(trajs[m]["time"], trajs[m][key], color=colors[m], lw=1, label=LABELS[m])
        for label, style, c in refs:
            ax.plot(dt * np.arange(len(c["X"])), c["ev" if key == "speed_error" else "ey"], style, color="grey",
                    lw=1, label=f"{label} (reference)")
        ax.axhline(0.0, color="grey", lw=0.5)
        ax.set_xlabel("t [s]")
        ax.set_ylabel(ylabel)
        ax.set_title(("Fig. 6: " if key == "speed_error" else "Fig. 7: ") + ylabel.split(" [")[0])
        ax.legend(fontsize=7)
        paths.append(_save(fig, fig_dir / f"{name}.png"))
    # Fig. 3: IBE effect. Left: one residual at a time (seeded draws of the true noise), the posterior
    # mean against the running sample mean and the single residuals -- the prior damps the first, noisy
    # samples. Right: the posterior mean in the mixed runs (one batch of residuals per iteration).
    if "mixed" in results:
        task_cfg, task = _dlc_task(results)
        vx, force = task.noise_index, task.xi_to_force  # xi [m/s] -> F_dis [N] (m / T)
        true_force, prior_force = task_cfg.disturbance.mean, task_cfg.prior_force_mean
        xi = sample_gaussian(task.true_mean, task.true_cov, 400, np.random.default_rng(0))
        ibe = UnknownCovarianceIBE(task.prior_mean, task.prior_cov)
        post = [force(ibe.update(x).mean[vx]) for x in xi]
        n = np.arange(1, len(xi) + 1)
        fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
        ax1.plot(n, force(xi[:, vx]), ".", color="C2", ms=3, label="single residual")
        ax1.plot(n, force(np.cumsum(xi[:, vx]) / n), color="C1", label="running sample mean")
        ax1.plot(n, post, color="C0", label="IBE posterior mean (eq. 17)")
        ax1.axhline(true_force, color="k", ls="--", lw=1, label=f"true mean {true_force:g} N")
        ax1.axhline(prior_force, color="C1", ls=":", lw=1, label=f"prior mean {prior_force:g} N")
        ax1.set_xscale("log")
        ax1.set_xlabel("number of residuals")
        ax1.set_ylabel("F_dis [N]")
        ax1.legend(fontsize=7)
        for r in results["mixed"]["runs"]:
            rows = [row for row in metrics("mixed", r) if f"ibe/mean_{vx}" in row]
            ax2.plot([0] + [row["iteration"] for row in rows],
                     [prior_force] + [force(row[f"ibe/mean_{vx}"]) for row in rows],
                     color="C0", lw=1)
        ax2.axhline(true_force, color="k", ls="--", lw=1)
        ax2.set_xscale("symlog", linthresh=1.0)
        ax2.set_xlim(left=0.0)
        ax2.set_xlabel("iteration (mixed RL runs, one batch of residuals each)")
        ax2.set_ylabel("IBE posterior mean of F_dis [N]")
        fig.suptitle("Fig. 3: effect of the IBE")
        paths.append(_save(fig, fig_dir / "fig3_ibe_effect.png"))
    plt.close("all")
    return paths


def _save(fig: Any, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    return path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of the reproduction (shared by ``mixedrl reproduce`` and ``python -m validation.reproduce``)."""
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path("runs/reproduce"))
    parser.add_argument("--quick", action="store_true",
                        help="reduced run (2 seeds at the paper's budget, about 2-3 minutes), for the test suite")
    parser.add_argument("--resume", action="store_true", help="reuse finished runs and resume interrupted ones")
    parser.add_argument("--workers", type=int, default=None, help="parallel training processes (default: 2)")
    parser.add_argument("--batch", type=int, default=DEFAULT_BATCH,
                        help=f"most runs trained as one computation (default {DEFAULT_BATCH}; 1: every run alone)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    parser.add_argument("--references", type=Path, default=None,
                        help="directory of measured references (docs/_static/references) to overlay on Figs. 5-7")


def run_command(args: argparse.Namespace) -> int:
    """Handler of the command: run :func:`reproduce`, print Table I and where the files are; exit status 0."""
    results = reproduce(args.out, seeds=args.seeds, quick=args.quick, resume=args.resume, workers=args.workers,
                        progress=not args.no_progress, references=args.references, batch=args.batch)
    print(format_table(results))
    print(f"\nresults: {Path(args.out) / 'results.json'}   figures: {Path(args.out) / 'figures'}")
    return 0


def register(subparsers: Any) -> Callable[[argparse.Namespace], int]:
    """Plug-in hook of ``mixedrl reproduce`` (entry point group ``mixedrl.commands``, see :mod:`mixedrl.cli`):
    add the ``reproduce`` sub-parser to ``subparsers`` and return its handler, :func:`run_command`."""
    add_arguments(subparsers.add_parser("reproduce", help="reproduce Table I and the figures of the paper"))
    return run_command


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m validation.reproduce``: same options as ``mixedrl reproduce``.

    Errors in the user's input (``ValueError``) are reported in one line with exit status 2.
    """
    parser = argparse.ArgumentParser(prog="python -m validation.reproduce", description=__doc__.split("\n")[0])
    add_arguments(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(message)s")
    try:
        return run_command(args)
    except ValueError as exc:
        print(f"python -m validation.reproduce: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
