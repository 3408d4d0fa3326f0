"""Run directories, metrics, and the training loop shared by every method.

The checkpoint codec, the atomic writes and the sha256 sidecars are :mod:`mixedrl.checkpoint`; their
names are re-exported here (``mixedrl.runs.save_checkpoint``, ``load_checkpoint``, ...).

A run lives in one directory::

    RUN_DIR/
        config.json      the TrainConfig of the run (mixedrl.config)
        checkpoint.pt    the latest checkpoint (written to a temporary file, then renamed: atomic;
                         plain data, read with torch.load(weights_only=True): safe to share)
        metrics.jsonl    one JSON object per iteration (namespaced keys, see below)
        metrics.csv      the same table as CSV, written when the run ends
        results.json     final evaluation, convergence, wall time
        config.json.sha256, checkpoint.pt.sha256, results.json.sha256
                         the sha256 of each (sha256sum format), verified on every load
        .lock            the one-writer lock (fcntl.flock; holds the writer's pid, host, start time;
                         created without following links, never truncated: :func:`hold_lock`)

The writes come in an order that makes every kill point resumable: at each checkpoint ``config.json``
(with the first one), the new ``metrics.jsonl`` rows, then ``checkpoint.pt``; at the end ``metrics.csv``
and ``results.json``; each file after its digest (:func:`write_with_digest`). A directory is therefore
always *fresh* (the lock, ``config.json``, rows up to the first checkpoint: resumed from scratch, the rows
discarded) or *at checkpoint k* (rows beyond ``k`` discarded on resume).

Training never replaces a run: without ``resume`` the directory must be absent or empty (anything the
package did not write, a planted ``.lock`` included, makes it not a run); with it the saved config must
match (a larger ``iterations`` extends the budget) and ``metrics.jsonl`` must be complete up to the
checkpoint (docs/algorithm2.rst, "Run directories").

Metric keys (every row has ``iteration``):

* ``train/critic_loss``, ``train/actor_objective`` (Algorithm 2) or ``train/actor_loss`` (DDPG),
  ``train/value_mean``, ``train/value_change``, ``train/policy_change``;
* ``mvc/held`` (1 if the MVC held on the batch after the inner loop), ``mvc/fraction_states``,
  ``mvc/lhs_mean``, ``mvc/e_mean``, ``mvc/e_nonnegative``, ``mvc/inner_steps`` (Algorithm 2 only);
* ``ibe/mean_<i>``, ``ibe/cov_<i><i>``, ``ibe/mean_error`` (max abs error of the mean against the true
  noise), ``ibe/mean_rel_error``, ``ibe/count`` (Algorithm 2 only);
* ``eval/cost``, ``eval/lateral_mae``, ``eval/speed_mae``, ... every ``eval_every`` iterations (all runs
  of a batch at once, :func:`evaluate_together`: the periodic ones with batched policy calls, which may
  differ in the float32 last bits; the last one exact, and it is the final evaluation of ``results.json``);
* ``time/elapsed_s`` (wall time of the run so far, excluding evaluations).

:func:`train` drives any trainer with the small interface of :class:`mixedrl.algorithms.agpi.AGPI`
(``k``, ``iteration()``, ``evaluate(seeds)``, ``state_dict()``, ``load_state_dict()``, ``stopped``),
checkpoints it, and writes the results. Resuming from the checkpoint continues with exactly the
generator states, optimiser states, replay buffer, IBE state and counters of the interrupted run, so it
ends with exactly the weights of an uninterrupted run.
"""

from __future__ import annotations

import contextlib
import csv
import errno
import io
import json
import logging
import math
import os
import re
import socket
import stat
import sys
import time
from pathlib import Path
from typing import Any, Callable, Iterator, Protocol

import numpy as np
import torch

from mixedrl.algorithms.agpi import AGPI
from mixedrl.algorithms.ddpg import DDPG
from mixedrl.checkpoint import (atomic_write_bytes, atomic_write_text, default_file_mode, digest_path,
                                is_temporary, load_checkpoint, regular_file, save_checkpoint, verify_digest,
                                write_with_digest)
from mixedrl.checks import check_finite_metrics, check_positive_int
from mixedrl.config import ANCHORED_FEEDFORWARDS, TrainConfig, flatten_table, task_names
from mixedrl import departures
from mixedrl.plant import credit_evaluations, plant_transitions
from mixedrl.precision import run_policy_gap
from mixedrl.tasks import Task, task_from_config
from mixedrl.tensorboard import TB_DIR, TensorBoardLogger

__all__ = [
    "RunDirectory",
    "save_checkpoint",
    "load_checkpoint",
    "atomic_write_bytes",
    "atomic_write_text",
    "write_with_digest",
    "verify_digest",
    "digest_path",
    "RunLockedError",
    "hold_lock",
    "is_lock_file",
    "LOCK_NAME",
    "RUN_FILES",
    "iterations_to_converge",
    "eval_seeds",
    "evaluate_run",
    "evaluate_together",
    "PeriodicObserver",
    "config_record",
    "train",
    "train_batch",
    "IterationObserver",
    "check_run_directory",
    "check_state",
    "load_trainer",
    "make_trainer",
    "CONVERGENCE_RTOL",
]

logger = logging.getLogger(__name__)

#: Relative tolerance of the convergence criterion (:func:`iterations_to_converge`).
CONVERGENCE_RTOL = 0.10

#: The files that make a directory a run (any one of them): never replaced without ``resume``.
RUN_FILES = ("config.json", "checkpoint.pt", "metrics.jsonl", "results.json")
#: The lock file of a run directory (see :meth:`RunDirectory.lock`).
LOCK_NAME = ".lock"
#: Names whose presence means a run was started here: :data:`RUN_FILES` and the digests written before them.
_STARTED = RUN_FILES + tuple(f"{name}.sha256" for name in ("config.json", "checkpoint.pt", "results.json"))


def _temporary_of_run(name: str) -> bool:
    """True for a temporary file :func:`atomic_write_bytes` leaves when killed while writing a run's file."""
    stem = name[1:].rsplit(".", 2)[0] if is_temporary(name) and name.count(".") >= 3 else ""
    return stem in _STARTED + ("metrics.csv",)


class RunLockedError(ValueError):
    """Another process holds the run directory's lock (a second writer is refused)."""


#: The lock file's content: the holder's line, padded with spaces to this many bytes (so it is rewritten in
#: place, never truncated).
_LOCK_WIDTH = 256
#: What a lock file this package wrote holds: nothing, or a holder's line and padding.
_LOCK_TEXT = re.compile(rb"(pid [0-9]+ on \S+ since \S+\n)? *")


def is_lock_file(path: Path) -> bool:
    """Whether ``path`` is a lock file this package wrote: a regular file of one link holding nothing but a
    holder's line (:data:`_LOCK_TEXT`); a symbolic link, a hard link to another file, or any other content
    is not."""
    try:
        st = os.lstat(path)
        if not stat.S_ISREG(st.st_mode) or st.st_nlink != 1 or st.st_size > _LOCK_WIDTH:
            return False
        with open(path, "rb") as fh:
            return _LOCK_TEXT.fullmatch(fh.read(_LOCK_WIDTH + 1)) is not None
    except OSError:
        return False


@contextlib.contextmanager
def hold_lock(path: str | Path, what: str = "out") -> Iterator[None]:
    """Hold the exclusive lock of the file ``path`` (``fcntl.flock``) for the duration of the ``with`` block.

    The file is created if needed, without following a symbolic link (``O_NOFOLLOW``), and is never
    truncated: an existing file is used only if it is one this package wrote (a regular file of one link
    holding a holder's line), and the holder's line (pid, host, start time) is written over it in place,
    padded to a fixed width. The kernel releases the lock when the holder exits, however it dies, so a lock
    left by a killed process is recovered by the next holder. The descriptor is not inherited by child
    processes (``O_CLOEXEC``).

    Parameters
    ----------
    path : str or pathlib.Path
        The lock file (its directory must exist).
    what : str
        The prefix of the error messages (the argument that named the directory).

    Raises
    ------
    RunLockedError
        Another process holds the lock (the message names the directory and the holder).
    ValueError
        ``path`` is a symbolic link, not a regular file, a hard link or holds something else than a
        holder's line (nothing is written into it), or the directory cannot be written.
    """
    import fcntl

    path = Path(path)
    foreign = (f"{what}: {path} is not a lock file mixedrl wrote (a symbolic link, a hard link, a special file or "
               f"other content); the directory is not mixedrl's: choose a new directory")
    flags = os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(path, flags | getattr(os, "O_NONBLOCK", 0), default_file_mode())
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise ValueError(foreign) from None
        raise ValueError(f"{what}: cannot write in {path.parent} ({exc.strerror})") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or st.st_nlink != 1 or st.st_size > _LOCK_WIDTH:
            raise ValueError(foreign)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, _LOCK_WIDTH, 0).decode("utf-8", "replace").strip() or "unknown"
            raise RunLockedError(f"{what}: {path.parent} is being written by another process ({holder}); "
                                 f"one writer per directory") from None
        if _LOCK_TEXT.fullmatch(os.pread(fd, _LOCK_WIDTH + 1, 0)) is None:
            raise ValueError(foreign)
        host = socket.gethostname().replace(" ", "_")[:120] or "unknown"
        info = f"pid {os.getpid()} on {host} since {time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())}\n"
        os.pwrite(fd, info.encode().ljust(_LOCK_WIDTH), 0)
        yield
    finally:
        os.close(fd)  # releases the flock


def _metrics_row(line: bytes, number: int, path: Path) -> dict[str, Any]:
    """One row of ``metrics.jsonl`` (line ``number``): a JSON object with a positive integer ``iteration``."""
    try:
        row = json.loads(line.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise ValueError(f"metrics: {path} line {number} is not UTF-8 text ({exc.reason} at byte {exc.start})") \
            from None
    if not isinstance(row, dict):
        raise ValueError(f"metrics: {path} line {number} is a JSON {type(row).__name__}, expected an object")
    k = row.get("iteration")
    if type(k) is not int or k < 1:
        raise ValueError(f"metrics: {path} line {number} has iteration {k!r}, expected a positive integer")
    return row


class RunDirectory:
    """The files of one run (see the module docstring).

    Parameters
    ----------
    path : str or pathlib.Path
        Directory; created by the first write (not by reading or validating).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    config_path = property(lambda self: self.path / "config.json")
    checkpoint_path = property(lambda self: self.path / "checkpoint.pt")
    metrics_path = property(lambda self: self.path / "metrics.jsonl")
    csv_path = property(lambda self: self.path / "metrics.csv")
    results_path = property(lambda self: self.path / "results.json")
    lock_path = property(lambda self: self.path / LOCK_NAME)

    def _check_link(self) -> None:
        """Refuse a ``path`` that is a symbolic link leading nowhere (a loop or a missing target)."""
        if self.path.is_symlink() and not os.path.exists(self.path):
            raise ValueError(f"out: {self.path} is a symbolic link that does not resolve (a loop or a missing "
                             f"target)")

    def _mkdir(self) -> None:
        self._check_link()
        try:
            self.path.mkdir(parents=True, exist_ok=True)
        except FileExistsError:
            raise ValueError(f"out: {self.path} is a file, not a directory") from None
        except OSError as exc:
            raise ValueError(f"out: cannot create the directory {self.path} ({exc.strerror})") from None

    def entries(self) -> list[str]:
        """Names in the directory other than its lock and leftover temporary files ([] if it does not exist).

        The lock file is listed when it is not one this package wrote (a symbolic or hard link, other
        content): such a directory is not a run.

        Raises
        ------
        ValueError
            ``path`` exists and is not a directory, is a symbolic link that does not resolve, or cannot be
            listed.
        """
        self._check_link()
        if not self.path.exists():
            return []
        if not self.path.is_dir():
            raise ValueError(f"out: {self.path} is a file, not a directory")
        try:
            names = os.listdir(self.path)
        except OSError as exc:
            raise ValueError(f"out: cannot read the directory {self.path} ({exc.strerror})") from None
        return sorted(n for n in names if not _temporary_of_run(n)
                      and not (n == LOCK_NAME and is_lock_file(self.path / n)))

    def holds_run(self) -> bool:
        """True if a run was started here: any of :data:`RUN_FILES`, a digest of one (a write that was
        killed), or this package's lock file."""
        return (any(name in _STARTED for name in self.entries())
                or (self.lock_path.exists() and is_lock_file(self.lock_path)))

    def check_new(self) -> None:
        """Refuse to start a new run here unless the directory is absent or empty; creates nothing.

        Empty means: nothing but this package's lock file and temporary files (a run killed before it wrote
        anything).

        Raises
        ------
        ValueError
            ``path`` is a file, holds a run (resume it, or choose a new directory), or holds other files.
        """
        names = self.entries()
        found = [n for n in names if n in _STARTED]
        if found:
            raise ValueError(f"out: {self.path} already holds a run ({', '.join(found)}); pass --resume "
                             f"(resume=True) to continue it, or choose a new directory")
        if names:
            shown = ", ".join(names[:3]) + (", ..." if len(names) > 3 else "")
            raise ValueError(f"out: {self.path} is not empty and holds no run ({shown}); choose a new or "
                             f"empty directory")

    @contextlib.contextmanager
    def lock(self) -> Iterator[None]:
        """Hold the directory's one-writer lock (``<path>/.lock``, :func:`hold_lock`) for the duration of the
        ``with`` block. The directory is created if needed.

        Raises
        ------
        RunLockedError
            Another process holds the lock (the message names the directory and the holder).
        ValueError
            The directory cannot be created or written, or its ``.lock`` is not one this package wrote.
        """
        self._mkdir()
        with hold_lock(self.lock_path):
            yield

    def write_config(self, config: TrainConfig, task: Any = None) -> None:
        """Save the run's config as ``config.json`` (:func:`config_record`: with the user's own ``task``,
        its name), with its sha256 in ``config.json.sha256``."""
        self._mkdir()
        text = json.dumps(config_record(config, task), indent=2, sort_keys=True) + "\n"
        write_with_digest(self.config_path, text.encode("utf-8"))

    def read_config(self) -> TrainConfig:
        """Load ``config.json`` (unknown keys are an error), verified against its sha256 sidecar.

        Raises
        ------
        ValueError
            No ``config.json``, one that does not match its digest, or one that is not a valid config; one
            recorded for the user's own task (``task.name`` not a built-in or registered task) is refused
            with a message naming the task: its :class:`~mixedrl.tasks.Task` object is needed (read the raw
            record with :meth:`read_record`).
        """
        record = self.read_record()
        task = record.get("task")
        if isinstance(task, dict) and set(task) == {"name"} and task["name"] not in task_names():
            raise ValueError(f"config: {self.config_path} records the user's own task {task['name']!r}, which "
                             f"no config can rebuild; build it and pass it to make_trainer(config, task)")
        return TrainConfig.from_dict(record)

    def read_record(self) -> dict[str, Any]:
        """The JSON object of ``config.json`` as written (:func:`config_record`), not migrated or validated;
        verified against its sha256 sidecar (``config.json.sha256``) when it has one.

        Raises
        ------
        ValueError
            ``config.json`` is missing, not a regular file, does not match its digest, or is not a JSON object.
        """
        if not regular_file(self.config_path, "config"):
            raise ValueError(f"path: {self.path} has no config.json")
        try:
            data = self.config_path.read_bytes()
        except OSError as exc:
            raise ValueError(f"config: cannot read {self.config_path} ({exc.strerror})") from None
        verify_digest(self.config_path, data, "config")
        try:
            record = json.loads(data.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ValueError(f"config: cannot read {self.config_path} as JSON ({exc})") from None
        if not isinstance(record, dict):
            raise ValueError(f"config: {self.config_path} holds a JSON {type(record).__name__}, expected an object")
        return record

    def append_metrics(self, rows: list[dict[str, Any]]) -> None:
        """Append rows to ``metrics.jsonl``."""
        if not rows:
            return
        self._mkdir()
        with open(self.metrics_path, "a") as fh:
            for row in rows:
                fh.write(json.dumps(row, allow_nan=True) + "\n")

    def read_metrics(self) -> list[dict[str, Any]]:
        """All rows of ``metrics.jsonl`` (an empty list if there is none).

        A last line without its newline that is not JSON is the torn row of an interrupted write and is
        left out.

        Raises
        ------
        ValueError
            ``metrics: ...`` naming the file and the line: the file is not a regular file, a line is not
            UTF-8, not JSON (other than a torn last line), not an object, or has no positive integer
            ``iteration``.
        """
        if not regular_file(self.metrics_path, "metrics"):
            return []
        data = self.metrics_path.read_bytes()
        lines = data.split(b"\n")
        rows = []
        for number, line in enumerate(lines, 1):
            if not line.strip():
                continue
            try:
                rows.append(_metrics_row(line, number, self.metrics_path))
            except json.JSONDecodeError as exc:
                if number == len(lines):
                    break  # a torn last line (no newline yet) of an interrupted run
                raise ValueError(f"metrics: {self.metrics_path} line {number} is not JSON ({exc})") from None
        return rows

    def truncate_metrics(self, k: int) -> None:
        """Keep only the rows with ``iteration <= k`` (used when resuming from a checkpoint at ``k``).

        Raises
        ------
        ValueError
            ``metrics.jsonl`` is missing or lacks a row of some iteration ``1..k`` (resuming would lose
            metrics); nothing is changed then.
        """
        rows = self.check_metrics(k)
        atomic_write_text(self.metrics_path, "".join(json.dumps(r) + "\n" for r in rows))

    def check_metrics(self, k: int) -> list[dict[str, Any]]:
        """The rows of iterations ``1..k`` of ``metrics.jsonl``, checked complete (see :meth:`truncate_metrics`)."""
        rows = [r for r in self.read_metrics() if r["iteration"] <= k]
        if [r["iteration"] for r in rows] != list(range(1, k + 1)):
            state = "is missing" if not self.metrics_path.is_file() else f"has {len(rows)} rows up to iteration {k}"
            raise ValueError(f"metrics: {self.metrics_path} {state}, but the checkpoint is at iteration {k} "
                             f"(one row per iteration expected); resuming would lose metrics: restore the "
                             f"file or train into a new directory")
        return rows

    def write_csv(self) -> None:
        """Write ``metrics.csv`` from ``metrics.jsonl`` (union of keys as columns)."""
        rows = self.read_metrics()
        keys: list[str] = []
        for row in rows:
            keys += [k for k in row if k not in keys]
        out = io.StringIO()
        writer = csv.DictWriter(out, fieldnames=keys)
        writer.writeheader()
        for row in rows:
            writer.writerow(row)
        self._mkdir()
        atomic_write_text(self.csv_path, out.getvalue())

    def write_results(self, results: dict[str, Any]) -> None:
        """Write ``results.json`` atomically, with its sha256 in ``results.json.sha256``."""
        self._mkdir()
        text = json.dumps(results, indent=2, sort_keys=True) + "\n"
        write_with_digest(self.results_path, text.encode("utf-8"))

    def read_results(self) -> dict[str, Any]:
        """Read ``results.json``, verified against its sha256 sidecar when it has one.

        Raises
        ------
        ValueError
            ``results: ...`` naming the file if it is missing, not a regular file, does not match its digest,
            or is not JSON.
        """
        if not regular_file(self.results_path, "results"):
            raise ValueError(f"results: {self.results_path} does not exist")
        data = self.results_path.read_bytes()
        verify_digest(self.results_path, data, "results")
        try:
            return json.loads(data)
        except json.JSONDecodeError as exc:
            raise ValueError(f"results: {self.results_path} is not valid JSON ({exc})") from None


def iterations_to_converge(iterations: list[int], costs: list[float], rtol: float = CONVERGENCE_RTOL) -> int:
    """The convergence criterion applied identically to every method.

    A run has converged at the first evaluated iteration ``k`` from which **every** later evaluation cost
    stays within ``rtol`` (10%) of the run's final level, ``J_final`` = the median of its last three
    evaluations:

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
    k_star = iterations[-1]
    for i in range(len(costs) - 1, -1, -1):
        if math.isfinite(costs[i]) and costs[i] <= bound:
            k_star = iterations[i]
        else:
            break
    return int(k_star)


def config_record(config: TrainConfig, task: Any = None) -> dict[str, Any]:
    """The content of a run's ``config.json``: ``config.to_dict()``, naming the task the run trains.

    A built-in task is built from ``config.task``, which is recorded in full. The user's own ``task`` (a
    :class:`~mixedrl.tasks.Task` whose ``name`` is not ``config.task.name``, e.g. ``"Cruise"`` trained
    with the placeholder ``TrainConfig(task="linear")``) does not use ``config.task``; the record's
    ``task`` is then ``{"name": task.name}``.
    """
    data = config.to_dict()
    name = getattr(task, "name", None)
    if task is not None and name != config.task.name:
        data["task"] = {"name": str(name)}
    return json.loads(json.dumps(data))  # exactly what config.json holds (lists, not tuples)


def _saved_record(run: RunDirectory) -> dict[str, Any]:
    """``config.json`` of ``run`` in the form :func:`config_record` writes (old flat files migrated)."""
    record = run.read_record()
    task = record.get("task")
    if isinstance(task, dict) and set(task) == {"name"} and task["name"] not in task_names():
        return record  # the user's own task: written by config_record, already in the sectioned form
    return config_record(run.read_config())


def eval_seeds(config: TrainConfig) -> list[int]:
    """Noise seeds of the evaluation episodes: fixed per run, disjoint from the training seed stream."""
    return [1_000_003 * (config.seed + 1) + i for i in range(config.run.eval_seeds)]


def make_trainer(config: TrainConfig, task: Task | None = None) -> AGPI | DDPG:
    """Build the trainer of ``config.method`` (Algorithm 2 for mixed/model/oracle, DDPG for ddpg).

    The task is built from ``config.task`` (:func:`mixedrl.tasks.task_from_config`) unless ``task`` is given.
    """
    if task is None:
        task = task_from_config(config.task)
    if config.method == "ddpg":
        return DDPG(task, config)
    return AGPI(task, config)


def evaluate_run(path: str | Path, *, seeds: int | None = None, feedforward: str | None = None,
                 task: Task | None = None) -> dict[str, Any]:
    """Evaluate a run directory's final policy on its task (``mixedrl evaluate``); reads only.

    Parameters
    ----------
    path : str or Path
        A run directory with ``config.json`` and a checkpoint.
    seeds : int, optional
        Number of noise seeds (default the run's ``run.eval_seeds``; the seeds are :func:`eval_seeds`).
    feedforward : str, optional
        Evaluate with this ``algorithm.feedforward`` instead of the run's (``"lq"``: the actor shifted to
        the LQ optimum's action at the equilibrium for the method's own noise mean). Training does not
        read ``"lq"``, so this evaluates what the run would have deployed with it; ``"lq_train"``,
        ``"lq_affine"`` and ``"lq_affine_ss"`` change training and are refused unless they are the run's own.
    task : Task, optional
        The task object of a user's own task (not rebuilt from the config).

    Returns
    -------
    dict
        ``config`` (the :class:`TrainConfig` evaluated), ``iteration``, ``metrics`` (the task's
        evaluation), ``policy_gap`` and ``policy_gap_reason`` (:func:`mixedrl.precision.run_policy_gap`).

    Raises
    ------
    ValueError
        If ``path`` is not a run directory, or as :class:`TrainConfig` for a bad ``feedforward``.
    """
    run = RunDirectory(path)
    if not run.path.is_dir():
        raise ValueError(f"run_dir: {run.path} is not a directory" if run.path.exists()
                         else f"run_dir: {run.path} does not exist")
    config = run.read_config()
    if seeds is not None:
        config = config.replace(**{"run.eval_seeds": seeds})
    if feedforward is not None:
        trained = {feedforward, config.algorithm.feedforward} & set(ANCHORED_FEEDFORWARDS)
        if trained and feedforward != config.algorithm.feedforward:
            raise ValueError(f"feedforward: {sorted(trained)[0]!r} is a training-time policy class (an anchored "
                             f"actor); the run "
                             f"was trained with algorithm.feedforward = {config.algorithm.feedforward!r}, it cannot be "
                             f"evaluated with {feedforward!r}")
        config = config.replace(**{"algorithm.feedforward": feedforward})
    trainer = make_trainer(config, task)
    load_trainer(trainer, run.checkpoint_path)
    metrics = trainer.evaluate(eval_seeds(config))
    gap, reason = run_policy_gap(trainer)
    return {"config": config, "iteration": int(trainer.k), "metrics": metrics, "policy_gap": gap,
            "policy_gap_reason": reason}


def _evaluation_due(trainer: Any) -> bool:
    """Whether ``trainer`` is evaluated after its current iteration: every ``run.eval_every`` iterations,
    at the budget and when it stopped."""
    return trainer.k % trainer.config.run.eval_every == 0 or _finished(trainer)


def _finished(trainer: Any) -> bool:
    """Whether ``trainer`` has reached its budget or stopped (its evaluation now is its final one)."""
    return trainer.k >= trainer.config.algorithm.iterations or bool(trainer.stopped)


def _shared_task(trainers: list[Any]) -> Any:
    """The task all ``trainers`` evaluate on (a built-in task of one configuration, or one task object),
    or ``None`` when they have none in common or a trainer evaluates otherwise than AGPI and DDPG do."""
    # a trainer's own evaluate() might do something else: only AGPI's and DDPG's (the task's evaluate of
    # the policy) are batched
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
    """The evaluations of several runs at once: their policies on their seeds, in one call of the task's
    :meth:`~mixedrl.tasks.Task.evaluate_many` (the courses in lock step).

    With ``exact=False`` (the periodic evaluations of training: the ``eval/*`` metrics rows, a monitor, and
    ``iterations_to_converge``) the policies are called once per step on all their courses, and the
    numbers may differ from the trainer's own ``evaluate`` in the float32 last bits of a batched policy
    call (about 1e-8 relative, docs/reproduction.rst). With ``exact=True`` (a run's last iteration, whose
    evaluation is also its final one in ``results.json``) each equals ``trainer.evaluate(seeds)`` bit for
    bit. Trainers without a common task are evaluated one by one with their own ``evaluate``.

    Parameters
    ----------
    trainers : list of AGPI or DDPG
        The runs (any trainer with ``evaluate(seeds)``; AGPI and DDPG runs on one task are batched).
    seeds : list of list of int
        Each run's evaluation seeds (:func:`eval_seeds`).
    exact : bool, optional
        Bit-identical to each trainer's ``evaluate`` (per-course policy calls) or not (batched calls).

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


def _scalar_eval(ev: dict[str, Any]) -> dict[str, float]:
    return {f"eval/{k}": float(v) for k, v in ev.items() if isinstance(v, (int, float, np.floating))}


#: The dotted name of the budget, the one field ``resume`` may change (to a larger value).
_BUDGET = "algorithm.iterations"


def _config_conflicts(saved: dict[str, Any], requested: dict[str, Any]) -> list[tuple[str, Any, Any]]:
    """``(dotted name, saved value, requested value)`` of the fields where two :func:`config_record`
    forms differ; a larger ``iterations`` is not a conflict (an explicit extension of the budget)."""
    a, b = flatten_table(saved), flatten_table(requested)
    out = [(k, a.get(k), b.get(k)) for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]
    if [k for k, _, _ in out] == [_BUDGET] and b[_BUDGET] > a[_BUDGET]:
        return []
    return out


def check_run_directory(run: RunDirectory, config: TrainConfig, resume: bool = False) -> None:
    """Whether :func:`train` would accept ``run`` for ``config`` (reads only, changes nothing).

    Raises
    ------
    ValueError
        As :func:`train` would: ``run`` holds a run or other files and ``resume`` is false; with
        ``resume`` a config that contradicts the saved one, a corrupted or invalid checkpoint, or files but
        no checkpoint.
    """
    _open_run(run, config, resume)


#: What a run directory may hold without ``checkpoint.pt`` and still be resumed from scratch: a run killed
#: before its first checkpoint was in place (its metrics rows are discarded).
_BEFORE_FIRST_CHECKPOINT = ("config.json", "config.json.sha256", "checkpoint.pt.sha256", "metrics.jsonl", TB_DIR)


def _open_run(run: RunDirectory, cfg: TrainConfig, resume: bool, task: Any = None,
              template: dict[str, Any] | None = None) -> dict[str, Any] | None:
    """Validate ``run`` for training ``cfg`` (creating nothing) and return the checkpoint to resume from.

    Without ``resume`` the directory must be absent or empty. With ``resume``: a checkpoint (its config
    must equal ``cfg``, up to a larger ``iterations``: an extension; its record is checked field by field,
    against ``template``, a fresh trainer's ``state_dict()``, when given; ``metrics.jsonl`` must hold every
    iteration up to it), or what a run killed before its first checkpoint leaves (``config.json``, metrics
    rows of iterations up to the first checkpoint: it starts again, the rows are discarded), or nothing
    at all (a run not started yet).
    """
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
        conflicts = _config_conflicts(_saved_record(run), config_record(cfg, task))
        if conflicts:
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


def _real(value: Any) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def _check_fields(value: Any, template: Any, where: str, path: Path) -> None:
    """Check ``value`` against ``template`` (what a fresh trainer's ``state_dict()`` holds there): the kind of
    every field (dict with the template's keys, list, tensor or array of the template's dtype and number of
    dimensions, bool, integer, real number, string, generator); ``None`` in the template is not checked."""
    def bad(problem: str) -> ValueError:
        return ValueError(f"checkpoint: {path} field {where} {problem}")

    if template is None:
        return
    if isinstance(template, dict):
        if not isinstance(value, dict):
            raise bad(f"is a {type(value).__name__}, expected a dict")
        for key, sub in template.items():
            if key not in value:
                raise bad(f"has no key {key!r}")
            _check_fields(value[key], sub, f"{where}.{key}", path)
    elif isinstance(template, (list, tuple)):
        if not isinstance(value, (list, tuple)):
            raise bad(f"is a {type(value).__name__}, expected a list")
        for i, (v, t) in enumerate(zip(value, template)):
            _check_fields(v, t, f"{where}[{i}]", path)
    elif isinstance(template, (torch.Tensor, np.ndarray)):
        if type(value) is not type(template):
            raise bad(f"is a {type(value).__name__}, expected a {type(template).__name__}")
        if value.dtype != template.dtype or value.ndim != template.ndim:
            raise bad(f"has dtype {value.dtype} and {value.ndim} dimension(s), expected {template.dtype} and "
                      f"{template.ndim}")
    elif isinstance(template, (bool, np.bool_)):
        if not isinstance(value, (bool, np.bool_)):
            raise bad(f"is {value!r}, expected true or false")
    elif isinstance(template, (int, np.integer)):
        if not _real(value) or not float(value).is_integer():
            raise bad(f"is {value!r}, expected an integer")
    elif _real(template):
        if not _real(value):
            raise bad(f"is {value!r}, expected a number")
    elif not isinstance(value, type(template)):
        raise bad(f"is a {type(value).__name__}, expected a {type(template).__name__}")


def check_state(state: Any, path: str | Path, budget: int | None = None,
                template: dict[str, Any] | None = None) -> None:
    """Check a loaded checkpoint's record field by field before it is used (:func:`train`, ``evaluate``).

    Parameters
    ----------
    state : Any
        What :func:`load_checkpoint` returned.
    path : str or pathlib.Path
        The checkpoint (named in the errors).
    budget : int, optional
        The run's ``algorithm.iterations``: the largest iteration a checkpoint of it can be at.
    template : dict, optional
        A fresh trainer's ``state_dict()``: every field of it must be in ``state["trainer"]``, of its kind.

    Raises
    ------
    ValueError
        ``checkpoint: <path> field <name> ...``: ``trainer`` missing or not a dict, ``trainer.k`` not an
        integer in ``[0, budget]``, ``elapsed`` not a finite number ``>= 0``, ``trainer.stop_count`` not an
        integer ``>= 0``, or a field of ``template`` missing or of another kind.
    """
    path = Path(path)
    if not isinstance(state, dict) or not isinstance(state.get("trainer"), dict):
        found = type(state.get("trainer")).__name__ if isinstance(state, dict) and "trainer" in state else "missing"
        raise ValueError(f"checkpoint: {path} field trainer is {found}, expected a dict (a trainer's state)")
    trainer = state["trainer"]
    k, top = trainer.get("k"), "" if budget is None else f", {budget}"
    if type(k) is not int or k < 0 or (budget is not None and k > budget):
        raise ValueError(f"checkpoint: {path} field trainer.k is {k!r}, expected an integer in [0{top}]")
    elapsed = state.get("elapsed", 0.0)
    if not _real(elapsed) or not math.isfinite(elapsed) or elapsed < 0:
        raise ValueError(f"checkpoint: {path} field elapsed is {elapsed!r}, expected a finite number >= 0")
    count = trainer.get("stop_count", 0)
    if type(count) is not int or count < 0:
        raise ValueError(f"checkpoint: {path} field trainer.stop_count is {count!r}, expected an integer >= 0")
    if template is not None:
        _check_fields(trainer, template, "trainer", path)


def load_trainer(trainer: Any, path: str | Path, state: dict[str, Any] | None = None) -> dict[str, Any]:
    """Restore ``trainer`` from the checkpoint ``path`` (or its already loaded ``state``), checked first
    (:func:`check_state` against the trainer's own fields and budget).

    Returns
    -------
    dict
        The checkpoint's record.

    Raises
    ------
    ValueError
        ``checkpoint: <path> ...``: unreadable, invalid, or a state the trainer does not accept.
    """
    if state is None:
        state = load_checkpoint(path)
    check_state(state, path, trainer.config.algorithm.iterations, trainer.state_dict())
    try:
        trainer.load_state_dict(state["trainer"])
    except (ValueError, KeyError, TypeError, IndexError, RuntimeError, AttributeError) as exc:
        text = " ".join(str(exc).split())[:300]
        raise ValueError(f"checkpoint: {path} field trainer does not fit the run's trainer "
                         f"({type(exc).__name__}: {text})") from None
    return state


class IterationObserver(Protocol):
    """What :func:`train` calls around every iteration of a run (for example the empirical checks of the
    paper's theorems, :class:`validation.reproduce.TheoryObserver`).

    ``before(trainer)`` is called just before the iteration and returns anything (a snapshot of what the
    check needs, or ``None`` to skip this iteration); ``after(trainer, token, row)`` just after it, with
    that token and the iteration's metrics row, and returns extra metrics for the row (or ``None``). An
    observer only reads the trainer: it must not draw from the run's generator or change its state.
    """

    def before(self, trainer: Any) -> Any: ...

    def after(self, trainer: Any, token: Any, row: dict[str, float]) -> dict[str, float] | None: ...


class PeriodicObserver:
    """An :class:`IterationObserver` that records every ``every`` iterations: after the iteration ``k`` with
    ``k % every == 0`` it returns :meth:`record` ``(trainer)`` as extra metrics of the row; nothing before
    the iteration. Subclasses implement :meth:`record` (reading the trainer only).

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

    A run directory has one writer: the run holds :meth:`RunDirectory.lock` from its validation to its
    last write, and a second process training into the same directory is refused. Nothing is created or
    changed in ``run`` before the validation has passed.

    Parameters
    ----------
    trainer : AGPI or DDPG
        A freshly built trainer (its config decides budget, evaluation and checkpoint periods).
    run : RunDirectory, optional
        Where to write config, checkpoints, metrics and results; ``None`` keeps everything in memory.
        Without ``resume`` it must be absent or empty.
    resume : bool
        Continue from ``run``'s checkpoint. A directory holding only ``config.json`` (killed before its
        first checkpoint) or nothing starts from scratch; one holding other files but no checkpoint is
        refused. The saved config must equal the trainer's, except a larger ``iterations`` (the budget
        is extended).
    progress : bool, optional
        Show a tqdm progress bar (on stderr); by default shown when stderr is a terminal, as on the CLI.
        ``False`` turns it off.
    stop_after : int, optional
        Stop (after checkpointing) once ``trainer.k`` reaches this value: simulates an interruption.
    callback : callable, optional
        Called with every metrics row.
    tensorboard : bool
        Also write the metrics rows as TensorBoard scalars into ``<run>/tb/`` (:mod:`mixedrl.tensorboard`;
        needs ``run`` and the optional extra ``tensorboard``).
    observer : IterationObserver, optional
        Called around every iteration (:class:`IterationObserver`); the metrics it returns join the
        iteration's row (the theory checks of ``mixedrl reproduce`` are one).

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
        checkpoint, a config that differs from the saved one, no checkpoint beside other files, or
        ``metrics.jsonl`` missing rows up to the checkpoint (nothing is changed then); ``tensorboard``
        without ``run``.
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

    :func:`train` is this function with one run. Every run keeps what a run alone has: its directory
    (the same layout), its lock (all are taken before anything is written, so a batch never shares a
    directory with another writer), its checkpoints, metrics, evaluation and ``results.json``, its
    budget (a run that reached it, or stopped, leaves the batch's iterations), and ``resume``.

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
        One per trainer (``None`` entries: none), as ``observer`` of :func:`train`.

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
        As for :func:`train` (for any run: nothing is then written into any of them); ``runs`` of another
        length than ``trainers``; two runs on one directory; several trainers that cannot share a batch
        (Algorithm-2 and DDPG runs mixed, another task or a shared field that differs).
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
    for trainer, run in zip(trainers, runs):  # refuse before creating anything
        if run is not None:
            _open_run(run, trainer.config, resume, getattr(trainer, "task", None), trainer.state_dict())
    if tensorboard:
        try:  # the extra missing: its error (TensorBoardLogger's, naming the extra) before anything is created
            import torch.utils.tensorboard  # noqa: F401
        except ImportError:
            TensorBoardLogger(Path(paths[0]) / TB_DIR)
    with contextlib.ExitStack() as stack:
        for run in runs:
            if run is not None:
                stack.enter_context(run.lock())
        # again under the locks: the directories may have changed meanwhile
        states = [None if run is None else _open_run(run, t.config, resume, getattr(t, "task", None),
                                                     t.state_dict())
                  for t, run in zip(trainers, runs)]
        boards = [TensorBoardLogger(run.path / TB_DIR) if tensorboard and run is not None else None for run in runs]
        return _train(trainers, engine, runs, states, progress, stop_after, callback, boards, observers)


def _engine(trainers: list[Any]) -> Callable[[list[bool]], list[dict[str, float] | None]]:
    """``iteration(active) -> rows`` for the trainers: one trainer's own iteration, or a batch's."""
    if len(trainers) == 1:
        trainer = trainers[0]
        return lambda active: [trainer.iteration() if active[0] else None]
    kind = AGPI if isinstance(trainers[0], AGPI) else DDPG
    for i, t in enumerate(trainers):
        if not isinstance(t, (AGPI, DDPG)):
            raise ValueError(f"trainers: entry {i} is a {type(t).__name__}; only Algorithm-2 (AGPI) or DDPG runs "
                             f"train in a batch")
        if not isinstance(t, kind):
            raise ValueError(f"trainers: entry {i} is {type(t).__name__} ({t.config.method}), entry 0 "
                             f"{kind.__name__} ({trainers[0].config.method}); Algorithm-2 and DDPG runs train in "
                             f"batches of their own kind")
    from mixedrl.algorithms.batched import BatchedAGPI
    from mixedrl.algorithms.batched_ddpg import BatchedDDPG

    engine_class = BatchedAGPI if kind is AGPI else BatchedDDPG
    engine_class.check_members(trainers)  # a mismatched batch is refused before any directory is touched
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
    # a run started from scratch writes config.json with its first checkpoint: a run that fails before it
    # (an invalid setting found by the first iteration) leaves its directory empty, free for a plain rerun
    config_due = [False] * n
    for i, (trainer, run, state) in enumerate(zip(trainers, runs, states)):
        if run is None:
            continue
        if state is not None:
            load_trainer(trainer, run.checkpoint_path, state)
            elapsed[i] = float(state.get("elapsed", 0.0))
            run.truncate_metrics(trainer.k)
        elif run.metrics_path.is_file():  # rows of a run killed before its first checkpoint: it starts again
            run.truncate_metrics(0)
        if state is None:
            config_due[i] = True
        elif config_record(trainer.config, getattr(trainer, "task", None)) != _saved_record(run):
            run.write_config(trainer.config, getattr(trainer, "task", None))  # an extended budget
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

    def running(i: int) -> bool:
        return not interrupted[i] and not _finished(trainers[i])

    bar = None
    if progress or (progress is None and sys.stderr.isatty()):
        from tqdm.auto import tqdm

        first = trainers[0].config
        desc = f"{first.method} seed {first.seed}" if n == 1 else f"{n} runs"
        bar = tqdm(total=sum(t.config.algorithm.iterations for t in trainers), initial=sum(t.k for t in trainers),
                   desc=desc, leave=False)
    try:
        while True:
            active = [running(i) for i in range(n)]
            if not any(active):
                break
            tokens = [obs.before(trainers[i]) if obs is not None and active[i] else None
                      for i, obs in enumerate(observers)]
            t0 = time.perf_counter()
            rows = engine(active)
            dt = time.perf_counter() - t0
            # the evaluations due at this iteration, of every run of the batch at once: the periodic ones (a
            # monitor) with batched policy calls, a run's last one exact (it is also its final evaluation)
            due = [i for i in range(n) if active[i] and _evaluation_due(trainers[i])]
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
                if i in evaluations:
                    row.update(_scalar_eval(evaluations[i]))
                check_finite_metrics(row, f"{cfg.method} seed {cfg.seed}" if runs[i] is None else str(runs[i].path))
                pending[i].append(row)
                if callback is not None:
                    callback(row)
                if bar is not None:
                    bar.update(1)
                    if "eval/cost" in row and n == 1:
                        bar.set_postfix(cost=f"{row['eval/cost']:.4g}")
                if trainer.k % cfg.run.checkpoint_every == 0:
                    checkpoint(i)
                if stop_after is not None and trainer.k >= stop_after:
                    checkpoint(i)
                    interrupted[i] = True
    finally:
        if bar is not None:
            bar.close()
    out: list[dict[str, Any]] = []
    for i, trainer in enumerate(trainers):
        if interrupted[i]:
            if boards[i] is not None:
                boards[i].close()
            out.append({"interrupted_at": trainer.k})
            continue
        checkpoint(i)
        if boards[i] is not None:
            boards[i].close()
        rows_i = runs[i].read_metrics() if runs[i] is not None else memory_rows[i]
        results = summarize(trainer, rows_i, elapsed[i], seeds[i], finals.get(i))
        if n > 1:
            results["batch_size_runs"] = n
        if runs[i] is not None:
            runs[i].write_csv()
            runs[i].write_results(results)
        else:
            results["metrics"] = memory_rows[i]
        out.append(results)
    return out


def summarize(trainer: Any, rows: list[dict[str, Any]], elapsed: float, seeds: list[int],
              final: dict[str, Any] | None = None) -> dict[str, Any]:
    """Final evaluation and convergence figures of a finished run (the content of ``results.json``).

    ``final`` is the trainer's exact evaluation on ``seeds`` when the caller already has it (the training
    loop evaluates a run's last iteration exactly); otherwise ``trainer.evaluate(seeds)`` is called.

    ``policy_gap`` is the policy at the task's equilibrium against the discounted LQ optimum for the
    method's own noise mean (:func:`mixedrl.precision.run_policy_gap`), ``null`` with ``policy_gap_reason``
    when the task has no equilibrium.
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
        "iterations_to_converge": iterations_to_converge([e[0] for e in evals], [e[1] for e in evals])
        if evals else int(trainer.k),
        "convergence_criterion": f"first evaluated iteration after which eval/cost stays <= "
                                 f"(1 + {CONVERGENCE_RTOL}) x median of the last 3 evaluations",
    }
    for key in ("lateral_mae", "speed_mae", "cost"):
        if key in final:
            results[key] = float(final[key])
    if hasattr(trainer, "true_transitions"):
        count = trainer.true_transitions
        results["true_transitions"] = None if count is None else int(count)
        results["plant_transitions"] = plant_transitions(trainer)
    if hasattr(trainer, "noise"):
        # the departures from the paper's Algorithm 2 the run used (mixedrl.departures; [] = the paper's)
        results["departures"] = departures.used(cfg)
        # the planning noise at the end (for a state-dependent source its mean over the last batch)
        mean, cov = trainer.noise_moments()
        results["final_ibe_mean"] = np.asarray(mean, dtype=float).tolist()
        results["final_ibe_cov_diag"] = np.diag(np.asarray(cov, dtype=float)).tolist()
        mvc = [r["mvc/held"] for r in rows if "mvc/held" in r]
        results["mvc_held_fraction"] = float(np.mean(mvc)) if mvc else None
        inner = [r["mvc/inner_steps"] for r in rows if "mvc/inner_steps" in r]
        results["mean_inner_steps"] = float(np.mean(inner)) if inner else None
    # the precision yardstick at the equilibrium (mixedrl.precision; evaluation only): null with a reason
    # when the task has none
    results["policy_gap"], reason = run_policy_gap(trainer)
    if reason is not None:
        results["policy_gap_reason"] = reason
    feedforward = cfg.algorithm.feedforward
    if feedforward != "learned":
        # the evaluated policy's action at the equilibrium is the LQ optimum's by construction
        results["feedforward"] = feedforward
    if feedforward == "lq":  # ... and the trained actor's own, before the shift
        results["policy_gap_learned"], _ = run_policy_gap(trainer, trainer.learned_policy)
    return results
