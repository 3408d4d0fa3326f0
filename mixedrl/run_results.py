"""The evaluation of runs, the convergence criterion and the ``results.json`` record of a finished run.

:mod:`mixedrl.runs` re-exports every public name of this module.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from mixedrl.algorithms.agpi import AGPI
from mixedrl.algorithms.ddpg import DDPG
from mixedrl.config import TrainConfig
from mixedrl import departures
from mixedrl.plant import credit_evaluations, plant_transitions
from mixedrl.precision import run_policy_gap, run_references
from mixedrl.tasks import Task, task_from_config
from mixedrl.run_directory import RunDirectory, load_trainer

__all__ = ["iterations_to_converge", "eval_seeds", "make_trainer", "evaluate_run", "evaluate_together", "summarize",
           "training_curve", "CONVERGENCE_RTOL"]

logger = logging.getLogger(__name__)

#: Relative tolerance of the convergence criterion (:func:`iterations_to_converge`).
CONVERGENCE_RTOL = 0.10

def iterations_to_converge(iterations: list[int], costs: list[float], rtol: float = CONVERGENCE_RTOL) -> int:
    """The convergence criterion applied identically to every method.

    The first evaluated iteration from which **every** later evaluation cost stays within ``rtol`` of the
    final level ``J_final``, the median of the last three evaluations:

    .. math::

        k^\\star = \\min\\{k_i : J(k_j) \\le (1 + \\mathrm{rtol})\\, J_{\\rm final}\\ \\forall j \\ge i\\}.

    Parameters
    ----------
    iterations : list of int
        Evaluated iterations, increasing.
    costs : list of float
        Evaluation cost at each (non-finite counts as not converged).
    rtol : float
        Relative tolerance.

    Returns
    -------
    int
        ``k*`` (the last evaluated iteration if the run never settles).

    Raises
    ------
    ValueError
        ``iterations`` empty or lengths differ.
    """
    if not iterations or len(iterations) != len(costs):
        raise ValueError(f"iterations: expected equal non-empty lists, got {len(iterations)} and {len(costs)}")
    final = float(np.median(costs[-3:]))
    bound = (1.0 + rtol) * final if final >= 0 else (1.0 - rtol) * final
    c = np.asarray(costs, dtype=float)
    bad = np.flatnonzero(~(np.isfinite(c) & (c <= bound)))  # the settled tail starts after the last bad one
    return int(iterations[min(bad[-1] + 1, len(c) - 1) if bad.size else 0])


def eval_seeds(config: TrainConfig) -> list[int]:
    """Noise seeds of the evaluation episodes: fixed per run, disjoint from the training seed stream."""
    return [1_000_003 * (config.seed + 1) + i for i in range(config.run.eval_seeds)]


def make_trainer(config: TrainConfig, task: Task | None = None) -> AGPI | DDPG:
    """Build the trainer of ``config.method`` (Algorithm 2 for mixed/model/oracle, DDPG for ddpg).

    The task is built from ``config.task`` (:func:`mixedrl.tasks.task_from_config`) unless ``task`` is given.
    """
    return (DDPG if config.method == "ddpg" else AGPI)(task_from_config(config.task) if task is None else task, config)


def evaluate_run(path: str | Path, *, seeds: int | None = None, feedforward: str | None = None,
                 task: Task | None = None, calibration: int | None = None) -> dict[str, Any]:
    """Evaluate a run directory's final policy on its task (``mixedrl evaluate``); reads only.

    Parameters
    ----------
    path : str or Path
        A run directory with ``config.json`` and a checkpoint.
    seeds : int, optional
        Number of noise seeds (default the run's ``run.eval_seeds``; the seeds are :func:`eval_seeds`).
    feedforward : str, optional
        Evaluate with this ``algorithm.feedforward`` instead of the run's (``"lq_ss"``: the actor shifted to
        the LQ optimum's action near its steady state for the method's own noise mean).
    task : Task, optional
        The task object of a user's own task (not rebuilt from the config).
    calibration : int, optional
        Evaluate with this ``algorithm.feedforward_calibration`` instead of the run's (0: the shift alone). A run
        saved before the setting existed holds none and is read at today's default.

    Returns
    -------
    dict
        ``config`` (the :class:`TrainConfig` evaluated), ``iteration``, ``metrics`` (the task's
        evaluation), ``policy_gap`` and ``policy_gap_reason`` (:func:`mixedrl.precision.run_policy_gap`).

    Raises
    ------
    ValueError
        If ``path`` is not a run directory, or as :class:`TrainConfig` for a bad ``feedforward`` or
        ``calibration``.
    """
    run = RunDirectory(path)
    if not run.path.is_dir():
        raise ValueError(f"run_dir: {run.path} is not a directory" if run.path.exists()
                         else f"run_dir: {run.path} does not exist")
    config = run.read_config()
    for key, value in (("run.eval_seeds", seeds), ("algorithm.feedforward", feedforward),
                       ("algorithm.feedforward_calibration", calibration)):
        if value is not None:
            config = config.replace(**{key: value})
    trainer = make_trainer(config, task)
    load_trainer(trainer, run.checkpoint_path)
    if getattr(trainer, "feedforward", None) == "lq_handover" and trainer.trained_box is None:
        logger.warning("algorithm.feedforward 'lq_handover': the checkpoint of %s holds no box of the trained "
                       "observations (trained with another feed-forward); 'lq_ss' is evaluated", run.path)
    metrics = trainer.evaluate(eval_seeds(config))
    gap, reason = run_policy_gap(trainer)
    return {"config": config, "iteration": int(trainer.k), "metrics": metrics, "policy_gap": gap,
            "policy_gap_reason": reason}


def _shared_task(trainers: list[Any]) -> Any:
    """The task all ``trainers`` evaluate on, or ``None`` when they have none in common or one of them
    overrides AGPI's and DDPG's ``evaluate``."""
    if not all(type(t).evaluate in (AGPI.evaluate, DDPG.evaluate) for t in trainers):
        return None
    first = trainers[0]
    for t in trainers[1:]:
        same_builtin = (type(t.task) is type(first.task) and getattr(t.task, "name", None) == t.config.task.name
                        and getattr(first.task, "name", None) == first.config.task.name
                        and t.config.task == first.config.task)
        if t.task is not first.task and not same_builtin:
            return None
    return first.task if hasattr(first.task, "evaluate_many") else None


def evaluate_together(trainers: list[Any], seeds: list[list[int]], *, exact: bool = False) -> list[dict[str, Any]]:
    """The evaluations of several runs at once, in one call of the task's
    :meth:`~mixedrl.tasks.Task.evaluate_many` (the courses in lock step).

    With ``exact=True`` each equals ``trainer.evaluate(seeds)`` bit for bit; with ``exact=False`` (batched
    policy calls) it may differ in the float32 last bits (docs/reproduction.rst). Trainers without a
    common task are evaluated one by one.

    Parameters
    ----------
    trainers : list of AGPI or DDPG
        The runs (any trainer with ``evaluate(seeds)``; AGPI and DDPG runs on one task are batched).
    seeds : list of list of int
        Each run's evaluation seeds (:func:`eval_seeds`).
    exact : bool, optional
        Per-course policy calls (bit-identical) or batched ones.

    Returns
    -------
    list of dict
        Per run, the task's evaluation.

    Raises
    ------
    ValueError
        ``seeds`` not one list per trainer.
    """
    if len(seeds) != len(trainers):
        raise ValueError(f"seeds: {len(seeds)} lists of seeds for {len(trainers)} trainers")
    if not trainers:
        return []
    task = _shared_task(trainers)
    if task is None:
        return [t.evaluate(s) for t, s in zip(trainers, seeds)]
    return credit_evaluations(trainers, task, task.evaluate_many([t.policy for t in trainers],
                                                                 [list(s) for s in seeds], exact=exact))


def summarize(trainer: Any, rows: list[dict[str, Any]], elapsed: float, seeds: list[int],
              final: dict[str, Any] | None = None) -> dict[str, Any]:
    """Final evaluation and convergence figures of a finished run (the content of ``results.json``).

    ``final``: the trainer's exact evaluation on ``seeds`` if the caller has it, else
    ``trainer.evaluate(seeds)`` is called. ``policy_gap`` (:func:`mixedrl.precision.run_policy_gap`) is
    ``null`` with ``policy_gap_reason`` when the task has no equilibrium.
    """
    cfg: TrainConfig = trainer.config
    if final is None:
        final = trainer.evaluate(seeds)
    evals = [(r["iteration"], r["eval/cost"]) for r in rows if "eval/cost" in r]
    results: dict[str, Any] = {
        "method": cfg.method,
        "seed": cfg.seed,
        "task": getattr(trainer.task, "name", cfg.task.name),
        "iterations": int(trainer.k),
        "train_seconds": float(elapsed),
        "final": {k: float(v) for k, v in final.items() if isinstance(v, (int, float, np.floating))},
        "iterations_to_converge": iterations_to_converge(*map(list, zip(*evals))) if evals else int(trainer.k),
        "convergence_criterion": f"first evaluated iteration after which eval/cost stays <= "
                                 f"(1 + {CONVERGENCE_RTOL}) x median of the last 3 evaluations",
    }
    results.update({key: float(final[key]) for key in ("lateral_mae", "speed_mae", "cost") if key in final})
    if hasattr(trainer, "true_transitions"):
        count = trainer.true_transitions
        results["true_transitions"] = None if count is None else int(count)
        results["plant_transitions"] = plant_transitions(trainer)
    if hasattr(trainer, "noise"):
        results["departures"] = departures.used(cfg)  # [] = the paper's Algorithm 2
        # the planning noise at the end (a state-dependent source: its mean over the last batch)
        mean, cov = trainer.noise_moments()
        results["final_ibe_mean"] = np.asarray(mean, dtype=float).tolist()
        results["final_ibe_cov_diag"] = np.diag(np.asarray(cov, dtype=float)).tolist()
        for key, name in (("mvc/held", "mvc_held_fraction"), ("mvc/inner_steps", "mean_inner_steps")):
            values = [r[key] for r in rows if key in r]
            results[name] = float(np.mean(values)) if values else None
    # the references: the LQR with the true mean's feed-forward, evaluated like the run (null with a reason)
    for key, (value, reason) in (("policy_gap", run_policy_gap(trainer)),
                                 ("references", run_references(trainer, seeds))):
        results[key] = value
        if reason is not None:
            results[f"{key}_reason"] = reason
    if getattr(trainer, "region_budget", 1) != 1:  # a global task's budget (schedule.resolve_budget)
        results["region_budget"] = trainer.region_budget
    feedforward = getattr(trainer, "feedforward", "learned")  # the trainer's, "auto" resolved
    if feedforward != "learned":
        results["feedforward"] = feedforward
    if feedforward != "learned":  # the trained actor's own gap, before the shift
        results["policy_gap_learned"], _ = run_policy_gap(trainer, trainer.learned_policy)
    return results


def training_curve(rows: list[dict[str, Any]], results: dict[str, Any]) -> bytes | None:
    """The run's training curve as a PNG: ``eval/cost`` against the iteration, with
    ``results["references"]["lqr_true_mean"]`` as a line.

    Parameters
    ----------
    rows : list of dict
        The run's metrics rows.
    results : dict
        Its :func:`summarize` record.

    Returns
    -------
    bytes or None
        The PNG; ``None`` without evaluations or without matplotlib (an optional extra, ``plots``).
    """
    evals = np.asarray([(r["iteration"], r["eval/cost"]) for r in rows if "eval/cost" in r], dtype=float)
    plt = pyplot() if evals.size else None
    if plt is None:
        return None
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    ax.plot(evals[:, 0], evals[:, 1], marker="o", markersize=3, label=f"{results['method']} (seed {results['seed']})")
    reference = (results.get("references") or {}).get("lqr_true_mean")
    if reference is not None:
        ax.axhline(reference["cost"], color="k", linestyle="--",
                   label=f"discounted LQR, true feed-forward: {reference['cost']:.4g}")
    finite = evals[np.isfinite(evals[:, 1]), 1]
    if finite.size and finite.min() > 0 and finite.max() > 20 * finite.min():
        ax.set_yscale("log")
    ax.set_xlabel("iteration")
    ax.set_ylabel("evaluated cost")
    ax.set_title(f"task {results['task']}: final cost {results['final'].get('cost', float('nan')):.4g}", fontsize=9)
    ax.legend(fontsize=8)
    return png(fig, dpi=100)


def pyplot() -> Any:
    """``matplotlib.pyplot`` on the non-interactive Agg backend, or ``None`` without matplotlib (extra ``plots``)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    return plt


def png(fig: Any, dpi: int) -> bytes:
    """A figure of :func:`pyplot`, laid out tightly, as PNG bytes; the figure is closed."""
    import io

    import matplotlib.pyplot as plt

    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi)
    plt.close(fig)
    return buffer.getvalue()
