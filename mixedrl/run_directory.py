"""The run-directory protocol: the files of a run, its one-writer lock, its records and their checks.

:mod:`mixedrl.runs` re-exports every public name; the checkpoint codec, atomic writes and sha256 sidecars
are :mod:`mixedrl.checkpoint`. A run directory holds::

    config.json          the run's TrainConfig
    checkpoint.pt        the latest checkpoint (atomic; plain data, loaded with weights_only=True)
    metrics.jsonl        one JSON object per iteration; metrics.csv: the same table, written at the end
    training_curve.png   with matplotlib
    results.json         final evaluation, convergence, wall time
    <file>.sha256        sha256 of config.json, checkpoint.pt, results.json, verified on every load
    .lock                the one-writer lock (hold_lock)

The write order that makes every kill point resumable, and the rules of ``resume``: docs/algorithm2.rst,
"Run directories".
"""

from __future__ import annotations

import contextlib
import csv
import errno
import io
import json
import math
import os
import re
import socket
import stat
import time
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import torch

from mixedrl.checkpoint import (atomic_write_bytes, atomic_write_text, default_file_mode, is_temporary, load_checkpoint,
                                regular_file, verify_digest, write_with_digest)
from mixedrl.config import TrainConfig, task_names

__all__ = ["RunDirectory", "RunLockedError", "hold_lock", "is_lock_file", "LOCK_NAME", "RUN_FILES", "config_record",
           "check_state", "load_trainer"]

#: The files that make a directory a run (any one of them): never replaced without ``resume``.
RUN_FILES = ("config.json", "checkpoint.pt", "metrics.jsonl", "results.json")
#: The lock file of a run directory (see :meth:`RunDirectory.lock`).
LOCK_NAME = ".lock"
#: Names whose presence means a run was started here: :data:`RUN_FILES` and the digests written before them.
_STARTED = RUN_FILES + tuple(f"{name}.sha256" for name in ("config.json", "checkpoint.pt", "results.json"))


def _temporary_of_run(name: str) -> bool:
    """True for a temporary file :func:`atomic_write_bytes` leaves when killed while writing a run's file."""
    stem = name[1:].rsplit(".", 2)[0] if is_temporary(name) and name.count(".") >= 3 else ""
    return stem in _STARTED + ("metrics.csv", "training_curve.png")


class RunLockedError(ValueError):
    """Another process holds the run directory's lock (a second writer is refused)."""


#: Size of the lock file: the holder's line padded with spaces (rewritten in place, never truncated).
_LOCK_WIDTH = 256
#: What a lock file this package wrote holds: nothing, or a holder's line and padding.
_LOCK_TEXT = re.compile(rb"(pid [0-9]+ on \S+ since \S+\n)? *")


def is_lock_file(path: Path) -> bool:
    """Whether ``path`` is a lock file this package wrote: a regular file of one link holding nothing but
    a holder's line (not a symbolic link, a hard link or other content)."""
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

    The file is created without following a symbolic link and never truncated: an existing file is used
    only if :func:`is_lock_file` would accept it, and the holder's line (pid, host, start time) is written
    over it in place. The kernel releases the lock however the holder dies.

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
        ``path`` is not a lock file this package wrote (nothing is written into it), or the directory
        cannot be written.
    """
    import fcntl

    path = Path(path)
    foreign = (f"{what}: {path} is not a lock file mixedrl wrote (a symbolic link, a hard link, a special file or "
               f"other content); the directory is not mixedrl's: choose a new directory")
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK, default_file_mode())
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
    curve_path = property(lambda self: self.path / "training_curve.png")
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

        A lock file this package did not write is listed (such a directory is not a run).

        Raises
        ------
        ValueError
            ``path`` is not a directory, is a dangling symbolic link, or cannot be listed.
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
        """True if a run was started here: any of :data:`RUN_FILES`, a digest of one, or this package's lock."""
        return any(name in _STARTED for name in self.entries()) or is_lock_file(self.lock_path)

    def check_new(self) -> None:
        """Refuse to start a new run here unless the directory is absent or empty (but for this package's
        lock and temporary files); creates nothing.

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

    def lock(self) -> contextlib.AbstractContextManager[None]:
        """Hold the directory's one-writer lock (``<path>/.lock``, :func:`hold_lock`); creates the directory.

        Raises
        ------
        RunLockedError
            Another process holds the lock (the message names the directory and the holder).
        ValueError
            The directory cannot be created or written, or its ``.lock`` is not one this package wrote.
        """
        self._mkdir()
        return hold_lock(self.lock_path)

    def write_config(self, config: TrainConfig, task: Any = None) -> None:
        """Save :func:`config_record` as ``config.json``, with its sha256 in ``config.json.sha256``."""
        self._write_json(self.config_path, config_record(config, task))

    def _write_json(self, path: Path, record: dict[str, Any]) -> None:
        self._mkdir()
        write_with_digest(path, (json.dumps(record, indent=2, sort_keys=True) + "\n").encode("utf-8"))

    def read_config(self) -> TrainConfig:
        """Load ``config.json`` (unknown keys are an error), verified against its sha256 sidecar.

        Raises
        ------
        ValueError
            No ``config.json``, one that does not match its digest or is not a valid config, or one of the
            user's own task (not a built-in or registered one; :meth:`read_record` reads it).
        """
        record = self.read_record()
        task = record.get("task")
        if isinstance(task, dict) and set(task) == {"name"} and task["name"] not in task_names():
            raise ValueError(f"config: {self.config_path} records the user's own task {task['name']!r}, which "
                             f"no config can rebuild; build it and pass it to make_trainer(config, task)")
        return TrainConfig.from_dict(record)

    def read_record(self) -> dict[str, Any]:
        """The JSON object of ``config.json`` as written, not validated; verified against its sidecar if any.

        Raises
        ------
        ValueError
            ``config.json`` is missing, not a regular file, does not match its digest, or is not a JSON object.
        """
        record = self._read_json(self.config_path, "config", f"path: {self.path} has no config.json")
        if not isinstance(record, dict):
            raise ValueError(f"config: {self.config_path} holds a JSON {type(record).__name__}, expected an object")
        return record

    def _read_json(self, path: Path, what: str, missing: str) -> Any:
        """The JSON of the regular file ``path``, verified against its sidecar (errors ``<what>: ...``)."""
        if not regular_file(path, what):
            raise ValueError(missing)
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise ValueError(f"{what}: cannot read {path} ({exc.strerror})") from None
        verify_digest(path, data, what)
        try:
            return json.loads(data.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ValueError(f"{what}: cannot read {path} as JSON ({exc})") from None

    def append_metrics(self, rows: list[dict[str, Any]]) -> None:
        """Append rows to ``metrics.jsonl``."""
        if not rows:
            return
        self._mkdir()
        with open(self.metrics_path, "a") as fh:
            fh.write("".join(json.dumps(row) + "\n" for row in rows))

    def read_metrics(self) -> list[dict[str, Any]]:
        """All rows of ``metrics.jsonl`` ([] without one); a torn last line (not JSON) is left out.

        Raises
        ------
        ValueError
            ``metrics: ...`` naming the line: not a regular file, or a line not UTF-8, not JSON (but a torn
            last line), not an object, or without a positive integer ``iteration``.
        """
        if not regular_file(self.metrics_path, "metrics"):
            return []
        lines = self.metrics_path.read_bytes().split(b"\n")
        rows = []
        for number, line in enumerate(lines, 1):
            if not line.strip():
                continue
            where = f"metrics: {self.metrics_path} line {number}"
            try:
                row = json.loads(line.decode("utf-8"))
            except UnicodeDecodeError as exc:
                raise ValueError(f"{where} is not UTF-8 text ({exc.reason} at byte {exc.start})") from None
            except json.JSONDecodeError as exc:
                if number == len(lines):
                    break  # a torn last line (no newline yet) of an interrupted run
                raise ValueError(f"{where} is not JSON ({exc})") from None
            if not isinstance(row, dict):
                raise ValueError(f"{where} is a JSON {type(row).__name__}, expected an object")
            k = row.get("iteration")
            if type(k) is not int or k < 1:
                raise ValueError(f"{where} has iteration {k!r}, expected a positive integer")
            rows.append(row)
        return rows

    def truncate_metrics(self, k: int) -> None:
        """Keep only the rows with ``iteration <= k`` (used when resuming from a checkpoint at ``k``).

        Raises
        ------
        ValueError
            ``metrics.jsonl`` is missing or lacks a row of some iteration ``1..k``; nothing is changed.
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
        out = io.StringIO()
        writer = csv.DictWriter(out, fieldnames=list(dict.fromkeys(k for row in rows for k in row)))
        writer.writeheader()
        writer.writerows(rows)
        self._mkdir()
        atomic_write_text(self.csv_path, out.getvalue())

    def write_results(self, results: dict[str, Any]) -> None:
        """Write ``results.json`` atomically, with its sha256 in ``results.json.sha256``."""
        self._write_json(self.results_path, results)

    def write_curve(self, png: bytes) -> None:
        """Write ``training_curve.png`` (:func:`mixedrl.run_results.training_curve`) atomically."""
        self._mkdir()
        atomic_write_bytes(self.curve_path, png)

    def read_results(self) -> dict[str, Any]:
        """Read ``results.json``, verified against its sha256 sidecar when it has one.

        Raises
        ------
        ValueError
            ``results: ...``: missing, not a regular file, unreadable, not matching its digest, or not JSON.
        """
        return self._read_json(self.results_path, "results", f"results: {self.results_path} does not exist")



def config_record(config: TrainConfig, task: Any = None) -> dict[str, Any]:
    """The content of a run's ``config.json``: ``config.to_dict()``; for the user's own ``task`` (whose
    ``name`` is not ``config.task.name``) the record's ``task`` is ``{"name": task.name}``."""
    data = config.to_dict()
    name = getattr(task, "name", None)
    if task is not None and name != config.task.name:
        data["task"] = {"name": str(name)}
    return json.loads(json.dumps(data))  # exactly what config.json holds (lists, not tuples)


def _real(value: Any) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def _check_fields(value: Any, template: Any, where: str, path: Path) -> None:
    """Check that every field of ``value`` has the kind of ``template``'s (a fresh trainer's ``state_dict()``:
    dict keys, tensor or array dtype and ndim, bool, integer, number, ...); ``None`` there is not checked."""
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
        ``checkpoint: <path> field <name> ...``: ``trainer`` not a dict, ``trainer.k`` not in
        ``[0, budget]``, ``elapsed`` not finite ``>= 0``, ``trainer.stop_count`` not an integer ``>= 0``, or
        a field of ``template`` missing or of another kind.
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
    """Restore ``trainer`` from the checkpoint ``path`` (or its loaded ``state``) after :func:`check_state`.

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
