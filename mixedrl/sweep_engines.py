"""Sweep execution: the batches of a sweep (:func:`plan_batches`), one batch trained (:func:`run_points`),
and the executors that run them here, on a process pool or on Ray (re-exported by :mod:`mixedrl.sweep`).
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import ctypes
import functools
import multiprocessing
import os
import signal
import sys
import threading
import time
from typing import Any, Iterator, Sequence

import numpy as np

from mixedrl.config import TrainConfig
from mixedrl.algorithms.batched import batch_key
from mixedrl.checks import check_positive_int
from mixedrl.sweep_spec import SweepRun, resolve_observer
from mixedrl.runs import RunDirectory, check_run_directory, load_trainer, make_trainer, train_batch
from mixedrl.schedule import resolve_budget
from mixedrl.tasks import task_from_config

__all__ = ["run_point", "run_points", "plan_batches", "DEFAULT_BATCH"]

#: Most runs trained as one computation (:func:`mixedrl.runs.train_batch`) by default (docs/sweeps.rst).
DEFAULT_BATCH = 16


def run_point(config: dict[str, Any], path: str, resume: bool = False) -> dict[str, Any]:
    """Train one run of a sweep into ``path`` alone: exactly ``mixedrl train`` (``--batch 1``).

    Parameters
    ----------
    config : dict
        ``TrainConfig.to_dict()`` of the run.
    path : str
        The run directory.
    resume : bool
        If the run has ``results.json``, return it without training; else continue from its checkpoint.

    Returns
    -------
    dict
        The run's results (the content of ``results.json``).

    Raises
    ------
    ValueError
        ``resume`` and the run directory holds a different config.
    """
    return run_points([config], [path], resume)[0]


def run_points(configs: list[dict[str, Any]], paths: list[str], resume: bool = False,
               observer: str | None = None) -> list[dict[str, Any]]:
    """Train the runs of one batch of a sweep, each into its path (:func:`mixedrl.runs.train_batch`).

    Parameters
    ----------
    configs : list of dict
        ``TrainConfig.to_dict()`` of each run (several: they must share a
        :func:`mixedrl.algorithms.batched.batch_key`).
    paths : list of str
        The run directories.
    resume : bool
        A run with ``results.json`` is returned without training; the others continue from their
        checkpoints, in one batch (docs/sweeps.rst, "Resuming").
    observer : str, optional
        The spec's ``observer`` (:func:`resolve_observer`).

    Returns
    -------
    list of dict
        Per run its results (the content of its ``results.json``).

    Raises
    ------
    ValueError
        A run directory is refused (the others of the batch have trained), or ``configs`` and ``paths``
        of different lengths.
    """
    outcomes, _ = _train_points(configs, paths, resume, observer)
    for results, error in outcomes:
        if error is not None:
            raise ValueError(error)
    return [results for results, _ in outcomes]


def _train_points(configs: list[dict[str, Any]], paths: list[str], resume: bool, observer: str | None
                  ) -> tuple[list[tuple[dict[str, Any] | None, str | None]], float]:
    """:func:`run_points`, per run ``(results, None)`` or ``(None, error text)`` (a refused run fails alone), and
    the wall time in seconds."""
    t0 = time.perf_counter()
    if len(configs) != len(paths):
        raise ValueError(f"paths: {len(paths)} paths for {len(configs)} configs")
    cfgs = [TrainConfig.from_dict(c) for c in configs]
    dirs = [RunDirectory(p) for p in paths]
    outcomes: list[tuple[dict[str, Any] | None, str | None]] = [(None, None)] * len(cfgs)
    todo, finished = [], []
    for i, (cfg, run_dir) in enumerate(zip(cfgs, dirs)):
        try:
            # the budget resolved on the task, as the trainer and its config.json have it
            if cfg.method != "ddpg":
                cfg = resolve_budget(cfg, task_from_config(cfg.task))[0]
            if resume and run_dir.results_path.is_file():
                if run_dir.read_config().to_dict() != cfg.to_dict():
                    raise ValueError(f"config: differs from the saved {run_dir.config_path}; resume with the same "
                                     f"spec")
                outcomes[i] = (run_dir.read_results(), None)
                finished.append(i)
            else:
                check_run_directory(run_dir, cfg, resume)
                todo.append(i)
        except Exception as exc:  # noqa: BLE001 - this run fails, the batch's others train
            outcomes[i] = (None, _error_text(exc))
    if todo:
        factory = None if observer is None else resolve_observer(observer)
        trainers = [make_trainer(cfgs[i]) for i in todo]
        run_dirs: list[RunDirectory | None] = [dirs[i] for i in todo]
        observers = [None if factory is None else factory(cfgs[i]) for i in todo]
        if len(todo) == 1 and finished:
            # one finished run, restored and inactive, keeps this run batched
            companion = make_trainer(cfgs[finished[0]])
            load_trainer(companion, dirs[finished[0]].checkpoint_path)
            trainers.append(companion)
            run_dirs.append(None)
            observers.append(None)
        trained = train_batch(trainers, run_dirs, resume=resume, progress=False, observers=observers)
        for i, res in zip(todo, trained):
            outcomes[i] = (res, None)
    return outcomes, time.perf_counter() - t0


def plan_batches(runs: Sequence[SweepRun], batch: int = DEFAULT_BATCH, workers: int = 1,
                 ddpg: bool = False) -> list[list[int]]:
    """Group a sweep's runs into batches trained as one computation each (docs/sweeps.rst, "Running on this
    machine": groups of equal :func:`mixedrl.algorithms.batched.batch_key`, split into near-equal batches).

    Parameters
    ----------
    runs : sequence of SweepRun
    batch : int
        Most runs per batch (``>= 1``).
    workers : int
        Processes that will train the batches.
    ddpg : bool
        Batch the DDPG runs too (:class:`mixedrl.algorithms.batched_ddpg.BatchedDDPG`); default: each alone.

    Returns
    -------
    list of list of int
        Indices into ``runs``, each batch in the runs' order, batches in the order of their first run.
    """
    check_positive_int(batch, "batch")
    check_positive_int(workers, "workers")
    groups: dict[Any, list[int]] = {}
    for i, r in enumerate(runs):
        key = batch_key(r.config) if batch > 1 and (ddpg or r.config.method != "ddpg") else None
        groups.setdefault(("alone", i) if key is None else key, []).append(i)
    batches = []
    for members in groups.values():
        n = len(members)
        count = max(-(-n // batch), min(workers, n // 2)) if n > 1 else 1
        while count > 1 and n // count < 2:
            count -= 1
        batches += [part.tolist() for part in np.array_split(members, count)]  # near-equal, the larger first
    return sorted(batches, key=lambda b: b[0])


def _error_text(exc: BaseException) -> str:
    cause = getattr(exc, "cause", None)  # a RayTaskError wraps the run's own exception
    err = cause if isinstance(cause, BaseException) else exc
    return f"{type(err).__name__}: {err}"


#: A job: one batch of runs, ``(configs, paths, resume, observer)`` (the arguments of :func:`run_points`).
Job = tuple[list[dict[str, Any]], list[str], bool, "str | None"]
#: A finished job: (index, per run (results, error text) or None, the batch's error text or None, wall seconds).
Done = tuple[int, "list[tuple[dict[str, Any] | None, str | None]] | None", "str | None", "float | None"]


def _done(i: int, get: Any) -> Done:
    """Job ``i`` finished: ``get()``'s outcomes and wall time, or the batch's error (one failed batch must not
    stop the others)."""
    try:
        results, wall = get()
        return i, results, None, wall
    except Exception as exc:  # noqa: BLE001
        return i, None, _error_text(exc), None


def run_here(jobs: list[Job]) -> Iterator[Done]:
    """Run the jobs one after the other in this process (``workers=1``)."""
    for i, job in enumerate(jobs):
        yield _done(i, functools.partial(_train_points, *job))


def _watch_parent(parent: int) -> None:
    """End this process as soon as its parent is no longer ``parent`` (it died: this process was re-parented)."""
    while os.getppid() == parent:
        time.sleep(0.5)
    os._exit(1)


def _die_with_parent(parent: int) -> None:
    """The initializer of a pool worker: the worker ends when the sweep driver (``parent``) dies, however it
    dies (on Linux ``prctl(PR_SET_PDEATHSIG)``; everywhere a daemon thread polls the parent's pid)."""
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError, AttributeError):  # no prctl: the thread below does it
            ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL), 0, 0, 0)  # 1: PR_SET_PDEATHSIG
    if os.getppid() != parent:  # the driver died before the signal was armed
        os._exit(1)
    threading.Thread(target=_watch_parent, args=(parent,), name="watch-sweep-driver", daemon=True).start()


def run_pool(jobs: list[Job], workers: int) -> Iterator[Done]:
    """Run the jobs on a local pool of ``workers`` ``spawn`` processes (each ends if this process dies),
    yielding them as they finish."""
    context = multiprocessing.get_context("spawn")
    with concurrent.futures.ProcessPoolExecutor(max_workers=workers, mp_context=context, initializer=_die_with_parent,
                                                initargs=(os.getpid(),)) as pool:
        futures = {pool.submit(_train_points, *job): i for i, job in enumerate(jobs)}
        try:
            for future in concurrent.futures.as_completed(futures):
                yield _done(futures[future], future.result)
        finally:
            for future in futures:
                future.cancel()


def run_ray(jobs: list[Job], ray: Any) -> Iterator[Done]:
    """Run the jobs as Ray tasks (one task per batch, ``num_cpus=1`` each) on the initialised cluster,
    yielding them as they finish (``ray.wait``)."""
    task = ray.remote(num_cpus=1)(_train_points)
    refs = {task.remote(*job): i for i, job in enumerate(jobs)}
    pending = list(refs)
    while pending:
        done, pending = ray.wait(pending, num_returns=1)
        yield _done(refs[done[0]], functools.partial(ray.get, done[0]))
