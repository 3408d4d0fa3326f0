"""The training loop shared by every method, and the public face of runs.

Re-exports the public names of :mod:`mixedrl.checkpoint`, :mod:`mixedrl.run_directory` (the files of a
run directory, its lock and resume rules) and :mod:`mixedrl.run_results` (evaluations, convergence,
``results.json``).

Metric keys (every row has ``iteration``):

* ``train/critic_loss``, ``train/actor_objective`` (Algorithm 2) or ``train/actor_loss`` (DDPG),
  ``train/value_mean``, ``train/value_change``, ``train/policy_change``;
* Algorithm 2 only: ``mvc/held`` (the MVC held on the batch after the inner loop), ``mvc/fraction_states``,
  ``mvc/lhs_mean``, ``mvc/e_mean``, ``mvc/e_nonnegative``, ``mvc/inner_steps``; ``ibe/mean_<i>``,
  ``ibe/cov_<i><i>``, ``ibe/mean_error`` (max abs error of the mean against the true noise),
  ``ibe/mean_rel_error``, ``ibe/count``;
* ``eval/cost``, ``eval/lateral_mae``, ``eval/speed_mae``, ... every ``eval_every`` iterations
  (:func:`evaluate_together`);
* ``time/elapsed_s`` (wall time of the run so far, excluding evaluations).

:func:`train` drives any trainer with the interface of :class:`mixedrl.algorithms.agpi.AGPI` (``k``,
``iteration()``, ``evaluate(seeds)``, ``state_dict()``, ``load_state_dict()``, ``stopped``). A resumed
run ends with exactly the weights of an uninterrupted one.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
from pathlib import Path
from typing import Any, Callable, Protocol

import numpy as np
import torch

from mixedrl.algorithms.agpi import AGPI
from mixedrl.checkpoint import (atomic_write_bytes, atomic_write_text, digest_path, load_checkpoint, save_checkpoint,
                                verify_digest, write_with_digest)
from mixedrl.checks import check_finite_metrics, check_positive_int
from mixedrl.config import TrainConfig, flatten_table, task_names
from mixedrl.tensorboard import TB_DIR, TensorBoardLogger
from mixedrl.run_directory import (LOCK_NAME, RUN_FILES, RunDirectory, RunLockedError, check_state, config_record,
                                   hold_lock, is_lock_file, load_trainer)
from mixedrl.run_results import (CONVERGENCE_RTOL, eval_seeds, evaluate_run, evaluate_together,
                                 iterations_to_converge, make_trainer, summarize, training_curve)

__all__ = ["RunDirectory", "save_checkpoint", "load_checkpoint", "atomic_write_bytes", "atomic_write_text",
           "write_with_digest", "verify_digest", "digest_path", "RunLockedError", "hold_lock", "is_lock_file",
           "LOCK_NAME", "RUN_FILES", "iterations_to_converge", "eval_seeds", "evaluate_run", "evaluate_together",
           "PeriodicObserver", "config_record", "train", "train_batch", "IterationObserver", "check_run_directory",
           "check_state", "load_trainer", "make_trainer", "CONVERGENCE_RTOL"]

def _saved_record(run: RunDirectory) -> dict[str, Any]:
    """``config.json`` of ``run`` in the form :func:`config_record` writes (old flat files migrated)."""
    record = run.read_record()
    task = record.get("task")
    if isinstance(task, dict) and set(task) == {"name"} and task["name"] not in task_names():
        return record  # the user's own task: written by config_record, already in the sectioned form
    return config_record(run.read_config())


def _finished(trainer: Any) -> bool:
    """Whether ``trainer`` has reached its budget or stopped (its evaluation now is its final one)."""
    return trainer.k >= trainer.config.algorithm.iterations or bool(trainer.stopped)


#: The dotted name of the budget, the one field ``resume`` may change (to a larger value).
_BUDGET = "algorithm.iterations"


def check_run_directory(run: RunDirectory, config: TrainConfig, resume: bool = False) -> None:
    """Whether :func:`train` would accept ``run`` for ``config`` (reads only, changes nothing).

    Raises
    ------
    ValueError
        As :func:`train` would.
    """
    _open_run(run, config, resume)


#: What a run killed before its first checkpoint leaves: resumed from scratch (the rows discarded).
_BEFORE_FIRST_CHECKPOINT = ("config.json", "config.json.sha256", "checkpoint.pt.sha256", "metrics.jsonl", TB_DIR)


def _open_run(run: RunDirectory, cfg: TrainConfig, resume: bool, task: Any = None,
              template: dict[str, Any] | None = None) -> dict[str, Any] | None:
    """Validate ``run`` for training ``cfg`` (creating nothing) and return the checkpoint to resume from
    (``None``: start from scratch). ``template``: a fresh trainer's ``state_dict()`` (:func:`check_state`)."""
    if not resume:
        run.check_new()
        return None
    names = run.entries()
    if "checkpoint.pt" not in names:
        others = [n for n in names if n not in _BEFORE_FIRST_CHECKPOINT]
        if others:
            raise ValueError(f"resume: {run.path} has no checkpoint.pt to resume from but holds "
                             f"{', '.join(others[:4])}; nothing was changed (train into a new directory)")
    if "checkpoint.pt" in names and "config.json" not in names:
        raise ValueError(f"resume: {run.path} has a checkpoint.pt but no config.json (it is written before the "
                         f"first checkpoint: it was removed); nothing was changed (train into a new directory)")
    if "config.json" in names:
        # (dotted name, saved value, requested value) where they differ; a larger budget is an extension
        a, b = flatten_table(_saved_record(run)), flatten_table(config_record(cfg, task))
        conflicts = [(k, a.get(k), b.get(k)) for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]
        if conflicts and not ([k for k, _, _ in conflicts] == [_BUDGET] and b[_BUDGET] > a[_BUDGET]):
            shown = "; ".join(f"{k} {v!r} (saved: {w!r})" for k, w, v in conflicts[:4])
            more = f" and {len(conflicts) - 4} more" if len(conflicts) > 4 else ""
            hint = (" (resume can only extend the budget)" if any(k == _BUDGET for k, _, _ in conflicts) else "")
            raise ValueError(f"config: {shown}{more} contradict(s) the saved {run.config_path}{hint}; resume with "
                             f"the run's config, or train into a new directory")
    if "checkpoint.pt" not in names:
        last = max((r["iteration"] for r in run.read_metrics()), default=0)
        if last > cfg.run.checkpoint_every:
            raise ValueError(f"resume: {run.metrics_path} has rows up to iteration {last}, but {run.path} has no "
                             f"checkpoint.pt (one was written by iteration {cfg.run.checkpoint_every}: it was "
                             f"removed); nothing was changed (train into a new directory)")
        return None
    state = load_checkpoint(run.checkpoint_path)
    check_state(state, run.checkpoint_path, cfg.algorithm.iterations, template)
    run.check_metrics(state["trainer"]["k"])
    return state



class IterationObserver(Protocol):
    """What :func:`train` calls around every iteration of a run (e.g.
    :class:`validation.reproduce.TheoryObserver`).

    ``before(trainer)`` returns a token (anything, e.g. a snapshot); ``after(trainer, token, row)`` gets it
    with the iteration's metrics row and returns extra metrics for the row (or ``None``). An observer only
    reads the trainer: it must not draw from the run's generator or change its state.
    """

    def before(self, trainer: Any) -> Any: ...

    def after(self, trainer: Any, token: Any, row: dict[str, float]) -> dict[str, float] | None: ...


class PeriodicObserver:
    """An :class:`IterationObserver` whose :meth:`record` (implemented by subclasses) adds metrics to the
    row of every ``every``-th iteration.

    Parameters
    ----------
    every : int
        Iterations between records.
    """

    def __init__(self, every: int) -> None:
        self.every = check_positive_int(every, "every")

    def before(self, trainer: Any) -> Any:
        """Nothing to snapshot: the records are read after the iteration."""
        return None

    def after(self, trainer: Any, token: Any, row: dict[str, float]) -> dict[str, float] | None:
        """:meth:`record` after every ``every``-th iteration, else ``None``."""
        return self.record(trainer) if trainer.k % self.every == 0 else None

    def record(self, trainer: Any) -> dict[str, float]:
        """The metrics of one record (override)."""
        raise NotImplementedError


def train(trainer: Any, run: RunDirectory | None = None, resume: bool = False, progress: bool | None = None,
          stop_after: int | None = None, callback: Callable[[dict[str, Any]], None] | None = None,
          tensorboard: bool = False, observer: IterationObserver | None = None) -> dict[str, Any]:
    """Run ``trainer`` to its budget (or its stopping test), with checkpoints, metrics and results.

    The run holds :meth:`RunDirectory.lock` from its validation to its last write; nothing is created or
    changed in ``run`` before the validation has passed.

    Parameters
    ----------
    trainer : AGPI or DDPG
        A freshly built trainer (its config decides budget, evaluation and checkpoint periods).
    run : RunDirectory, optional
        Where to write config, checkpoints, metrics and results; ``None`` keeps everything in memory.
        Without ``resume`` it must be absent or empty.
    resume : bool
        Continue from ``run``'s checkpoint (a run killed before its first one starts from scratch). The
        saved config must equal the trainer's, except a larger ``iterations`` (the budget is extended).
    progress : bool, optional
        Show a tqdm progress bar on stderr; by default when stderr is a terminal.
    stop_after : int, optional
        Stop (after checkpointing) once ``trainer.k`` reaches this value: simulates an interruption.
    callback : callable, optional
        Called with every metrics row.
    tensorboard : bool
        Also write the rows as TensorBoard scalars into ``<run>/tb/`` (:mod:`mixedrl.tensorboard`; needs
        ``run`` and the optional extra ``tensorboard``).
    observer : IterationObserver, optional
        Called around every iteration; the metrics it returns join the iteration's row.

    Returns
    -------
    dict
        ``results``: final evaluation (``lateral_mae``, ``speed_mae``, ``cost`` ...), ``iterations``,
        ``iterations_to_converge``, ``train_seconds``, ``final_ibe_mean`` ... (also written to
        ``results.json``); plus the in-memory ``metrics`` rows under ``"metrics"`` when ``run`` is None.

    Raises
    ------
    RunLockedError
        Another process is writing ``run``.
    ValueError
        ``run`` holds a run (or other files) and ``resume`` is false; ``resume`` with a corrupted
        checkpoint, another config, no checkpoint beside other files, or ``metrics.jsonl`` missing rows
        up to the checkpoint (nothing is changed then); ``tensorboard`` without ``run``.
    ImportError
        ``tensorboard`` without the optional extra.
    """
    return train_batch([trainer], [run], resume, progress, stop_after, callback, tensorboard,
                       None if observer is None else [observer])[0]


def train_batch(trainers: list[Any], runs: list[RunDirectory | None] | None = None, resume: bool = False,
                progress: bool | None = None, stop_after: int | None = None,
                callback: Callable[[dict[str, Any]], None] | None = None,
                tensorboard: bool = False,
                observers: list[IterationObserver | None] | None = None) -> list[dict[str, Any]]:
    """Train several runs as one computation (:class:`mixedrl.algorithms.batched.BatchedAGPI` or
    :class:`mixedrl.algorithms.batched_ddpg.BatchedDDPG`), each into its own directory.

    :func:`train` is this function with one run. Every run keeps its directory, lock (all taken before
    anything is written), checkpoints, metrics, ``results.json``, budget and ``resume``.

    Parameters
    ----------
    trainers : list of AGPI or DDPG
        Freshly built trainers. Several must all be Algorithm 2 (:class:`~mixedrl.algorithms.agpi.AGPI`)
        sharing the task and :data:`mixedrl.algorithms.batched.SHARED_FIELDS`, or all DDPG
        (:class:`~mixedrl.algorithms.ddpg.DDPG`) sharing the task and
        :data:`mixedrl.algorithms.batched.DDPG_SHARED_FIELDS`.
    runs : list of RunDirectory or None, optional
        One per trainer (``None`` entries, or ``runs=None``, keep that run in memory).
    resume, progress, stop_after, callback, tensorboard
        As for :func:`train`, per run (``callback`` gets every run's rows; ``train_seconds`` and
        ``time/elapsed_s`` are the batch's wall time while the run was in it).
    observers : list of IterationObserver or None, optional
        One per trainer (``None``: none), as ``observer`` of :func:`train`.

    Returns
    -------
    list of dict
        Per run, what :func:`train` returns; with more than one run ``results`` also hold
        ``batch_size_runs`` (the number of runs trained together).

    Raises
    ------
    RunLockedError
        Another process is writing one of the directories (nothing is written into any of them).
    ValueError
        As for :func:`train`, for any run (nothing is then written into any); ``runs`` of another length;
        two runs on one directory; trainers that cannot share a batch.
    """
    trainers = list(trainers)
    if not trainers:
        raise ValueError("trainers: expected at least one trainer, got none")
    runs = [None] * len(trainers) if runs is None else list(runs)
    if len(runs) != len(trainers):
        raise ValueError(f"runs: {len(runs)} directories for {len(trainers)} trainers")
    observers = [None] * len(trainers) if observers is None else list(observers)
    if len(observers) != len(trainers):
        raise ValueError(f"observers: {len(observers)} observers for {len(trainers)} trainers")
    for i, obs in enumerate(observers):
        if obs is not None and not (callable(getattr(obs, "before", None)) and callable(getattr(obs, "after", None))):
            raise ValueError(f"observers: entry {i} ({type(obs).__name__}) has no before(trainer) and "
                             f"after(trainer, token, row) methods")
    paths = [os.path.realpath(r.path) for r in runs if r is not None]
    if len(set(paths)) != len(paths):
        raise ValueError("runs: two runs of the batch write the same directory")
    if tensorboard and any(r is None for r in runs):
        raise ValueError("tensorboard: needs a run directory (run=RunDirectory(path)) to write into")
    engine = _engine(trainers)

    def open_runs() -> list[dict[str, Any] | None]:
        return [None if run is None else _open_run(run, t.config, resume, getattr(t, "task", None), t.state_dict())
                for t, run in zip(trainers, runs)]

    open_runs()  # refuse before creating anything
    if tensorboard:
        try:  # the extra missing: its error (TensorBoardLogger's, naming the extra) before anything is created
            import torch.utils.tensorboard  # noqa: F401
        except ImportError:
            TensorBoardLogger(Path(paths[0]) / TB_DIR)
    with contextlib.ExitStack() as stack:
        for run in runs:
            if run is not None:
                stack.enter_context(run.lock())
        states = open_runs()  # again under the locks: the directories may have changed meanwhile
        boards = [stack.enter_context(contextlib.closing(TensorBoardLogger(run.path / TB_DIR)))
                  if tensorboard and run is not None else None for run in runs]
        return _train(trainers, engine, runs, states, progress, stop_after, callback, boards, observers)


def _engine(trainers: list[Any]) -> Callable[[list[bool]], list[dict[str, float] | None]]:
    """``iteration(active) -> rows`` for the trainers: one trainer's own iteration, or a batch's."""
    if len(trainers) == 1:
        trainer = trainers[0]
        return lambda active: [trainer.iteration() if active[0] else None]
    from mixedrl.algorithms.batched import BatchedAGPI
    from mixedrl.algorithms.batched_ddpg import BatchedDDPG

    engine_class = BatchedAGPI if isinstance(trainers[0], AGPI) else BatchedDDPG
    engine_class.check_members(trainers, "trainers")  # a mismatched batch is refused before any directory is touched
    batch: list[Any] = []

    def iteration(active: list[bool]) -> list[dict[str, float] | None]:
        if not batch:  # built after the checkpoints are loaded
            batch.append(engine_class(trainers))
        return batch[0].iteration(active)

    return iteration


def _train(trainers: list[Any], engine: Callable[[list[bool]], list[dict[str, float] | None]],
           runs: list[RunDirectory | None], states: list[dict[str, Any] | None], progress: bool | None,
           stop_after: int | None, callback: Callable[[dict[str, Any]], None] | None,
           boards: list[TensorBoardLogger | None],
           observers: list[IterationObserver | None]) -> list[dict[str, Any]]:
    """The loop of :func:`train_batch` on validated (and locked) ``runs``, each from its ``state`` if given."""
    torch.set_num_threads(trainers[0].config.run.num_threads)
    n = len(trainers)
    memory_rows: list[list[dict[str, Any]]] = [[] for _ in range(n)]
    elapsed = [0.0] * n
    # config.json is written with the first checkpoint: a run failing before it leaves its directory empty
    config_due = [state is None for state in states]
    for i, (trainer, run, state) in enumerate(zip(trainers, runs, states)):
        if state is not None:
            load_trainer(trainer, run.checkpoint_path, state)
            elapsed[i] = float(state.get("elapsed", 0.0))
            run.truncate_metrics(trainer.k)
            if config_record(trainer.config, getattr(trainer, "task", None)) != _saved_record(run):
                run.write_config(trainer.config, getattr(trainer, "task", None))  # an extended budget
        elif run is not None and run.metrics_path.is_file():  # rows of a run killed before its first checkpoint
            run.truncate_metrics(0)
    seeds = [eval_seeds(t.config) for t in trainers]
    pending: list[list[dict[str, Any]]] = [[] for _ in range(n)]
    interrupted = [False] * n
    finals: dict[int, dict[str, Any]] = {}  # the exact evaluation of a run's last iteration (for summarize)

    def checkpoint(i: int) -> None:
        if runs[i] is not None:
            if config_due[i]:
                runs[i].write_config(trainers[i].config, getattr(trainers[i], "task", None))
                config_due[i] = False
            runs[i].append_metrics(pending[i])
            if boards[i] is not None:
                boards[i].write(pending[i])
            save_checkpoint(runs[i].checkpoint_path, {"trainer": trainers[i].state_dict(), "elapsed": elapsed[i]})
        memory_rows[i].extend(pending[i])
        pending[i].clear()

    from tqdm.auto import tqdm

    first = trainers[0].config
    with tqdm(total=sum(t.config.algorithm.iterations for t in trainers), initial=sum(t.k for t in trainers),
              desc=f"{first.method} seed {first.seed}" if n == 1 else f"{n} runs", leave=False,
              disable=not (progress or (progress is None and sys.stderr.isatty()))) as bar:
        # algorithm.compile: the first iterations compile the steps (cold about a minute, then loaded from the cache)
        compiling = first.algorithm.compile == "on"
        if compiling:
            from mixedrl.compiled import cache_dir

            bar.set_postfix_str(f"compiling the steps (cold: about a minute; cached in {cache_dir()})", refresh=True)
        while True:
            active = [not interrupted[i] and not _finished(trainers[i]) for i in range(n)]
            if not any(active):
                break
            tokens = [obs.before(trainers[i]) if obs is not None and active[i] else None
                      for i, obs in enumerate(observers)]
            t0 = time.perf_counter()
            rows = engine(active)
            dt = time.perf_counter() - t0
            if compiling:
                bar.set_postfix_str("", refresh=False)
                compiling = False
            # the evaluations due now, all runs at once: periodic ones batched, a run's last one exact
            due = [i for i in range(n) if active[i] and (trainers[i].k % trainers[i].config.run.eval_every == 0
                                                         or _finished(trainers[i]))]
            last = [i for i in due if _finished(trainers[i])]
            evaluations: dict[int, dict[str, Any]] = {}
            for group, exact in (([i for i in due if i not in last], False), (last, True)):
                if group:
                    evaluations.update(zip(group, evaluate_together([trainers[i] for i in group],
                                                                    [seeds[i] for i in group], exact=exact)))
            finals.update((i, evaluations[i]) for i in last)
            for i in (i for i in range(n) if active[i]):
                trainer, cfg = trainers[i], trainers[i].config
                elapsed[i] += dt
                extra = observers[i].after(trainer, tokens[i], rows[i]) if observers[i] is not None else None
                row = {"iteration": trainer.k, **rows[i], **(extra or {}), "time/elapsed_s": elapsed[i]}
                row.update({f"eval/{k}": float(v) for k, v in evaluations.get(i, {}).items()
                            if isinstance(v, (int, float, np.floating))})
                check_finite_metrics(row, f"{cfg.method} seed {cfg.seed}" if runs[i] is None else str(runs[i].path))
                pending[i].append(row)
                if callback is not None:
                    callback(row)
                bar.update(1)
                if "eval/cost" in row and n == 1:
                    bar.set_postfix(cost=f"{row['eval/cost']:.4g}")
                interrupted[i] = stop_after is not None and trainer.k >= stop_after
                if interrupted[i] or trainer.k % cfg.run.checkpoint_every == 0:
                    checkpoint(i)
    out: list[dict[str, Any]] = []
    for i, trainer in enumerate(trainers):
        if interrupted[i]:
            out.append({"interrupted_at": trainer.k})
            continue
        checkpoint(i)
        rows_i = runs[i].read_metrics() if runs[i] is not None else memory_rows[i]
        results = summarize(trainer, rows_i, elapsed[i], seeds[i], finals.get(i))
        if n > 1:
            results["batch_size_runs"] = n
        if runs[i] is not None:
            runs[i].write_csv()
            curve = training_curve(rows_i, results)
            if curve is not None:  # before results.json, which marks the run finished
                runs[i].write_curve(curve)
            runs[i].write_results(results)
        else:
            results["metrics"] = memory_rows[i]
        out.append(results)
    return out
