"""Run directories, atomic checkpoints, metrics, and the training loop shared by every method.

A run lives in one directory::

    RUN_DIR/
        config.json      the TrainConfig of the run (mixedrl.config)
        checkpoint.pt    the latest checkpoint (written to a temporary file, then renamed: atomic;
                         plain data, read with torch.load(weights_only=True): safe to share)
        metrics.jsonl    one JSON object per iteration (namespaced keys, see below)
        metrics.csv      the same table as CSV, written when the run ends
        results.json     final evaluation, convergence, wall time
        checkpoint.pt.sha256, results.json.sha256
                         the sha256 of each (sha256sum format), verified on every load
        .lock            the one-writer lock (fcntl.flock; holds the writer's pid, host, start time)

Training never replaces a run: without ``resume`` the directory must be absent or empty; with it the
saved config must match (a larger ``iterations`` extends the budget) and ``metrics.jsonl`` must be
complete up to the checkpoint (docs/algorithm2.rst, "Run directories").

Metric keys (every row has ``iteration``):

* ``train/critic_loss``, ``train/actor_objective`` (Algorithm 2) or ``train/actor_loss`` (DDPG),
  ``train/value_mean``, ``train/value_change``, ``train/policy_change``;
* ``mvc/held`` (1 if the MVC held on the batch after the inner loop), ``mvc/fraction_states``,
  ``mvc/lhs_mean``, ``mvc/e_mean``, ``mvc/e_nonnegative``, ``mvc/inner_steps`` (Algorithm 2 only);
* ``ibe/mean_<i>``, ``ibe/cov_<i><i>``, ``ibe/mean_error`` (max abs error of the mean against the true
  noise), ``ibe/mean_rel_error``, ``ibe/count`` (Algorithm 2 only);
* ``eval/cost``, ``eval/lateral_mae``, ``eval/speed_mae``, ... every ``eval_every`` iterations;
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
import hashlib
import io
import json
import logging
import math
import os
import pickle
import pickletools
import re
import socket
import sys
import tempfile
import time
import zipfile
from collections import OrderedDict
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
import torch

from mixedrl.algorithms.agpi import AGPI
from mixedrl.algorithms.ddpg import DDPG
from mixedrl.config import TrainConfig, flatten_table
from mixedrl.precision import run_policy_gap
from mixedrl.tasks import Task, task_from_config
from mixedrl.tensorboard import TB_DIR, TensorBoardLogger

__all__ = [
    "RunDirectory",
    "save_checkpoint",
    "load_checkpoint",
    "convert_checkpoint",
    "atomic_write_bytes",
    "atomic_write_text",
    "write_with_digest",
    "verify_digest",
    "digest_path",
    "RunLockedError",
    "RUN_FILES",
    "iterations_to_converge",
    "eval_seeds",
    "train",
    "make_trainer",
    "CONVERGENCE_RTOL",
]

logger = logging.getLogger(__name__)

#: Format tag of the checkpoints written now (plain data; see :func:`save_checkpoint`).
_FORMAT = "mixedrl-checkpoint-v2"
#: Older tags: v1 pickled numpy objects as such (see :func:`convert_checkpoint`).
_OLD_FORMATS = ("mixedrl-checkpoint-v1",)
#: Relative tolerance of the convergence criterion (:func:`iterations_to_converge`).
CONVERGENCE_RTOL = 0.10


def _default_mode() -> int:
    """``0o666`` minus the process umask: the mode ``open()`` would give a new file (mkstemp gives 0600)."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically: a temporary file in the same directory, fsync, ``os.replace``.

    A crash during the write leaves the previous file intact (the temporary file is removed).
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, _default_mode())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically (see :func:`atomic_write_bytes`)."""
    atomic_write_bytes(path, text.encode("utf-8"))


# ----------------------------------------------------------------------------------------------------
# Integrity: a sha256 sidecar per file (``checkpoint.pt.sha256``, ``results.json.sha256``)
# ----------------------------------------------------------------------------------------------------
def digest_path(path: str | Path) -> Path:
    """The sidecar of ``path`` holding its sha256 (``sha256sum`` format: ``<hex>  <name>``)."""
    path = Path(path)
    return path.with_name(path.name + ".sha256")


def _sidecar_digests(path: Path) -> list[str] | None:
    """The digests listed in ``path``'s sidecar (None without a sidecar)."""
    sidecar = digest_path(path)
    if not sidecar.is_file():
        return None
    return [line.split()[0].lower() for line in sidecar.read_text(encoding="utf-8").splitlines() if line.strip()]


def write_with_digest(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically together with its sha256 in the sidecar :func:`digest_path`.

    Crash-safe in every order of events: the sidecar first lists the new digest beside the old file's,
    then the file is replaced, then the sidecar is rewritten with the new digest only; so at any moment
    the file on disk matches one digest of its sidecar (each step is an atomic replace).
    """
    path = Path(path)
    new = hashlib.sha256(data).hexdigest()
    old = _sidecar_digests(path) if path.is_file() else None
    if old:
        atomic_write_text(digest_path(path), "".join(f"{d}  {path.name}\n" for d in [new, *old[:1]]))
    atomic_write_bytes(path, data)
    atomic_write_text(digest_path(path), f"{new}  {path.name}\n")


def verify_digest(path: str | Path, data: bytes, what: str) -> None:
    """Check ``data`` (the bytes read from ``path``) against ``path``'s sidecar, if it has one.

    Raises
    ------
    ValueError
        ``<what>: <path> is corrupted: its sha256 ... does not match <sidecar>``.
    """
    path = Path(path)
    digests = _sidecar_digests(path)
    if digests is None:
        return  # written before digests existed: still loads (documented in docs/run_directories)
    actual = hashlib.sha256(data).hexdigest()
    if actual not in digests:
        raise ValueError(f"{what}: {path} is corrupted: its sha256 {actual[:16]}... does not match "
                         f"{digest_path(path).name} ({digests[0][:16]}...); the file was changed after it was "
                         f"written")


# ----------------------------------------------------------------------------------------------------
# Checkpoints: plain data only, read with ``torch.load(weights_only=True)``
# ----------------------------------------------------------------------------------------------------
#: Key that marks an encoded value (a numpy array, numpy scalar or generator) in a v2 checkpoint.
_MARK = "__mixedrl_encoded__"
_PLAIN = (type(None), bool, int, float, complex, str, bytes, torch.dtype, torch.device, torch.Size)


def _tensor_of(arr: np.ndarray, where: str) -> torch.Tensor:
    """A tensor holding a copy of ``arr`` (native byte order), same dtype, shape and bits."""
    try:
        return torch.from_numpy(np.array(arr, dtype=arr.dtype.newbyteorder("="), order="C", copy=True))
    except TypeError as exc:
        raise ValueError(f"state: {where} is a numpy array of dtype {arr.dtype}, which torch cannot hold "
                         f"({exc})") from None


def _encode(value: Any, where: str) -> Any:
    """``value`` with numpy arrays/scalars and generators replaced by marked dicts of tensors and plain data.

    Raises ``ValueError`` naming ``where`` (the key path) for anything else that is not plain data.
    """
    if isinstance(value, torch.Tensor) or type(value) in _PLAIN:
        return value
    if isinstance(value, np.ndarray):
        if value.dtype.hasobject or value.dtype.kind not in "biufc":
            raise ValueError(f"state: {where} is a numpy array of dtype {value.dtype}; a checkpoint stores "
                             f"only numeric and boolean arrays")
        return {_MARK: "ndarray", "data": _tensor_of(value, where)}
    if isinstance(value, np.generic) and value.dtype.kind in "biufc":
        return {_MARK: "numpy_scalar", "data": _tensor_of(np.array(value), where)}
    if isinstance(value, np.random.Generator):
        return {_MARK: "numpy_generator", "state": _encode(value.bit_generator.state, f"{where}.state")}
    if isinstance(value, torch.Generator):
        return {_MARK: "torch_generator", "state": value.get_state(), "device": str(value.device)}
    if type(value) in (list, tuple):
        items = [_encode(v, f"{where}[{i}]") for i, v in enumerate(value)]
        return items if type(value) is list else tuple(items)
    if type(value) in (dict, OrderedDict):
        if _MARK in value:
            raise ValueError(f"state: {where} has the reserved key {_MARK!r}")
        out = type(value)()
        for key, v in value.items():
            if type(key) not in (str, int, float, bool, type(None)):
                raise ValueError(f"state: {where} has a key of type {type(key).__name__}; a checkpoint stores "
                                 f"str, int, float, bool or None keys")
            out[key] = _encode(v, f"{where}[{key!r}]")
        if hasattr(value, "_metadata"):  # nn.Module.state_dict() keeps per-module versions here
            out._metadata = _encode(value._metadata, f"{where}._metadata")  # type: ignore[attr-defined]
        return out
    raise ValueError(f"state: {where} is a {type(value).__module__}.{type(value).__qualname__}; a checkpoint "
                     f"stores only tensors, numpy arrays, generators, numbers, strings, lists, tuples and dicts")


def _decode(value: Any, path: Path) -> Any:
    """Inverse of :func:`_encode` on data loaded with ``weights_only=True``."""
    if type(value) in (list, tuple):
        items = [_decode(v, path) for v in value]
        return items if type(value) is list else tuple(items)
    if type(value) not in (dict, OrderedDict):
        return value
    if _MARK in value:
        kind = value[_MARK]
        if kind == "ndarray" and isinstance(value.get("data"), torch.Tensor):
            return value["data"].numpy().copy()
        if kind == "numpy_scalar" and isinstance(value.get("data"), torch.Tensor):
            return value["data"].numpy()[()]
        if kind == "numpy_generator" and isinstance(value.get("state"), dict):
            state = _decode(value["state"], path)
            name = state.get("bit_generator")
            if name not in ("PCG64", "PCG64DXSM", "MT19937", "Philox", "SFC64"):
                raise ValueError(f"checkpoint: {path} holds a numpy generator of unknown kind {name!r}")
            bit_generator = getattr(np.random, name)()
            bit_generator.state = state
            return np.random.Generator(bit_generator)
        if kind == "torch_generator" and isinstance(value.get("state"), torch.Tensor):
            gen = torch.Generator(device=str(value.get("device", "cpu")))
            gen.set_state(value["state"])
            return gen
        raise ValueError(f"checkpoint: {path} holds an encoded value of unknown or malformed kind {kind!r}")
    out = type(value)()
    for key, v in value.items():
        out[key] = _decode(v, path)
    if hasattr(value, "_metadata"):
        out._metadata = _decode(value._metadata, path)  # type: ignore[attr-defined]
    return out


def _format_tag(path: Path) -> str | None:
    """The ``mixedrl-checkpoint-*`` tag of a torch zip checkpoint, read *without* unpickling.

    :func:`pickletools.genops` only parses the opcodes of the archive's ``data.pkl``; nothing in the
    file is created or run. None when the file is not a readable torch zip archive or has no tag.
    """
    try:
        with zipfile.ZipFile(path) as archive:
            names = [n for n in archive.namelist() if n.rsplit("/", 1)[-1] == "data.pkl"]
            data = archive.read(names[0]) if names else b""
        for _, arg, _ in pickletools.genops(data):
            if isinstance(arg, str) and arg.startswith("mixedrl-checkpoint-"):
                return arg
    except Exception:  # noqa: BLE001 - unreadable means: no tag to report
        return None
    return None


def _refused_global(exc: BaseException) -> str | None:
    """The name of the global that torch's ``weights_only`` unpickler refused, from its message."""
    match = re.search(r"GLOBAL ([\w.]+)", str(exc)) if isinstance(exc, pickle.UnpicklingError) else None
    return match.group(1) if match else None


def _verify_zip(path: Path, data: bytes) -> None:
    """Check the CRC-32 of every member of a torch zip checkpoint (torch.load does not)."""
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            bad = archive.testzip()
    except (zipfile.BadZipFile, OSError, EOFError):
        return  # not a zip at all: torch.load reports it below
    except Exception as exc:  # noqa: BLE001 - a member that cannot even be decompressed
        raise ValueError(f"checkpoint: {path} is corrupted ({type(exc).__name__}: {exc})") from None
    if bad is not None:
        raise ValueError(f"checkpoint: {path} is corrupted: the CRC-32 of its member {bad!r} does not match")


def save_checkpoint(path: str | Path, state: dict[str, Any]) -> None:
    """Write ``state`` to ``path`` atomically, as plain data that loads with ``weights_only=True``.

    The file is ``torch.save({"format": "mixedrl-checkpoint-v2", "state": encoded})``, where ``encoded``
    is ``state`` with every numpy array, numpy scalar, :class:`numpy.random.Generator` and
    :class:`torch.Generator` replaced by a dict marked ``{"__mixedrl_encoded__": kind, ...}`` that holds
    a tensor (or the generator's plain state); tensors, numbers, strings, lists, tuples and dicts are kept
    as they are. :func:`load_checkpoint` turns the marks back into the original objects (same dtypes,
    shapes and bits, so a resumed run continues exactly).

    The data goes to a temporary file in the same directory, then ``os.replace``: a crash during the
    write leaves the previous checkpoint intact. Its sha256 goes to ``<path>.sha256``
    (:func:`write_with_digest`), which :func:`load_checkpoint` verifies.

    Parameters
    ----------
    path : str or pathlib.Path
        The checkpoint file.
    state : dict
        What to store (e.g. ``{"trainer": trainer.state_dict(), "elapsed": ...}``).

    Raises
    ------
    ValueError
        ``state: ...`` naming the key path of a value that is not plain data (e.g. a function or an
        arbitrary object); nothing is written then.
    """
    encoded = _encode(state, "state")
    buffer = io.BytesIO()
    torch.save({"format": _FORMAT, "state": encoded}, buffer)
    write_with_digest(path, buffer.getvalue())


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Read a checkpoint written by :func:`save_checkpoint`, safely: nothing stored in the file is run.

    The file is read with ``torch.load(..., weights_only=True)``, which builds only tensors and plain
    containers and refuses any other pickled object (a function, a class whose ``__reduce__`` would run
    code) *before* creating it; so evaluating or resuming a run directory made by someone else cannot
    execute code. The marked values of :func:`save_checkpoint` are then turned back into numpy arrays and
    generators. Before that the file's bytes are checked against their sha256 in ``<path>.sha256`` (when
    the sidecar exists: checkpoints written before digests existed have none and still load) and the CRC-32
    of every member of the zip archive is verified, so a flipped bit is an error, not a different policy.

    Raises
    ------
    ValueError
        ``checkpoint: ...`` naming ``path`` if the file is missing, truncated, corrupted (its digest or a
        zip CRC does not match), not a mixedrl
        checkpoint, holds pickled objects other than plain data (refused, not run), or is an old
        ``mixedrl-checkpoint-v1`` file holding numpy objects (convert such a file you trust once with
        :func:`convert_checkpoint`).

    Notes
    -----
    A v1 file (written before checkpoints were plain data) that happens to hold only tensors and plain
    data loads as it is; one that holds numpy arrays (every Algorithm 2 run: the IBE state) is refused
    with a message pointing to :func:`convert_checkpoint`.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"checkpoint: {path} does not exist")
    data = path.read_bytes()
    verify_digest(path, data, "checkpoint")
    _verify_zip(path, data)
    try:
        payload = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any failure: explain it without running the file
        tag, refused = _format_tag(path), _refused_global(exc)
        if tag in _OLD_FORMATS and refused:
            raise ValueError(
                f"checkpoint: {path} is an old {tag} file, which can be read only by unpickling arbitrary "
                f"objects (it holds {refused}); if you made it or trust it, convert it once with "
                f"mixedrl.runs.convert_checkpoint({str(path)!r}, trust=True)") from None
        if refused:
            raise ValueError(
                f"checkpoint: {path} holds pickled objects that are not plain data ({refused}); refused "
                f"without creating them, since loading them could execute code") from None
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        raise ValueError(f"checkpoint: {path} is corrupted, truncated or not a mixedrl checkpoint "
                         f"({type(exc).__name__}: {first[:200]})") from None
    if not isinstance(payload, dict) or "state" not in payload or not isinstance(payload["state"], dict):
        raise ValueError(f"checkpoint: {path} is not a {_FORMAT} file")
    if payload.get("format") in _OLD_FORMATS:
        return payload["state"]  # plain data already (weights_only accepted it); v1 had no marks
    if payload.get("format") != _FORMAT:
        raise ValueError(f"checkpoint: {path} is not a {_FORMAT} file (format {payload.get('format')!r})")
    return _decode(payload["state"], path)


def convert_checkpoint(path: str | Path, *, trust: bool = False, out: str | Path | None = None) -> Path:
    """One-off conversion of an old ``mixedrl-checkpoint-v1`` file into the current, safe format.

    A v1 checkpoint was written with numpy objects pickled as such, so reading it requires
    ``torch.load(weights_only=False)``, which runs whatever code the file carries. Call this function
    explicitly, once, on a file you made or trust; it loads the file that way and rewrites it (atomically)
    with :func:`save_checkpoint`, after which :func:`load_checkpoint` reads it safely. A file already in
    the current format is rewritten unchanged in content.

    Parameters
    ----------
    path : str or pathlib.Path
        The old checkpoint (e.g. ``RUN_DIR/checkpoint.pt``).
    trust : bool
        Must be True: the explicit statement that the file is trusted.
    out : str or pathlib.Path, optional
        Where to write the converted checkpoint (default: replace ``path``).

    Returns
    -------
    pathlib.Path
        The converted file.

    Raises
    ------
    ValueError
        ``trust`` not True (``trust: ...``, nothing is read); ``checkpoint: ...`` if the file is missing,
        corrupted or not a mixedrl checkpoint; ``state: ...`` if it holds a value a checkpoint cannot
        store.

    Examples
    --------
    >>> from mixedrl.runs import convert_checkpoint
    >>> convert_checkpoint("old_run/checkpoint.pt", trust=True)  # doctest: +SKIP
    PosixPath('old_run/checkpoint.pt')
    """
    if trust is not True:
        raise ValueError("trust: converting unpickles the file with weights_only=False, which runs any code "
                         "stored in it; call convert_checkpoint(path, trust=True) only on a file you trust")
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"checkpoint: {path} does not exist")
    target = path if out is None else Path(out)
    try:
        payload = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure means a corrupted file
        raise ValueError(f"checkpoint: {path} is corrupted or truncated ({type(exc).__name__}: {exc})") from None
    if not isinstance(payload, dict) or "state" not in payload:
        raise ValueError(f"checkpoint: {path} is not a mixedrl checkpoint")
    if payload.get("format") == _FORMAT:
        state = _decode(payload["state"], path)
    elif payload.get("format") in _OLD_FORMATS:
        state = payload["state"]
    else:
        raise ValueError(f"checkpoint: {path} is not a mixedrl checkpoint (format {payload.get('format')!r})")
    save_checkpoint(target, state)
    return target


#: The files that make a directory a run (any one of them): never replaced without ``resume``.
RUN_FILES = ("config.json", "checkpoint.pt", "metrics.jsonl", "results.json")
#: The lock file of a run directory (see :meth:`RunDirectory.lock`).
LOCK_NAME = ".lock"


class RunLockedError(ValueError):
    """Another process holds the run directory's lock (a second writer is refused)."""


def _is_temporary(name: str) -> bool:
    """A temporary file of :func:`atomic_write_bytes` left by a killed process."""
    return name.startswith(".") and name.endswith(".tmp")


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

    def _mkdir(self) -> None:
        try:
            self.path.mkdir(parents=True, exist_ok=True)
        except FileExistsError:
            raise ValueError(f"out: {self.path} is a file, not a directory") from None
        except OSError as exc:
            raise ValueError(f"out: cannot create the directory {self.path} ({exc.strerror})") from None

    def entries(self) -> list[str]:
        """Names in the directory other than its lock and leftover temporary files ([] if it does not exist).

        Raises
        ------
        ValueError
            ``path`` exists and is not a directory, or cannot be listed.
        """
        if not self.path.exists():
            return []
        if not self.path.is_dir():
            raise ValueError(f"out: {self.path} is a file, not a directory")
        try:
            names = os.listdir(self.path)
        except OSError as exc:
            raise ValueError(f"out: cannot read the directory {self.path} ({exc.strerror})") from None
        return sorted(n for n in names if n != LOCK_NAME and not _is_temporary(n))

    def holds_run(self) -> bool:
        """True if the directory holds any of :data:`RUN_FILES` (a run, finished or not)."""
        return any(name in RUN_FILES for name in self.entries())

    def check_new(self) -> None:
        """Refuse to start a new run here unless the directory is absent or empty; creates nothing.

        Raises
        ------
        ValueError
            ``path`` is a file, holds a run (resume it, or choose a new directory), or holds other files.
        """
        names = self.entries()
        found = [n for n in names if n in RUN_FILES]
        if found:
            raise ValueError(f"out: {self.path} already holds a run ({', '.join(found)}); pass --resume "
                             f"(resume=True) to continue it, or choose a new directory")
        if names:
            shown = ", ".join(names[:3]) + (", ..." if len(names) > 3 else "")
            raise ValueError(f"out: {self.path} is not empty and holds no run ({shown}); choose a new or "
                             f"empty directory")

    @contextlib.contextmanager
    def lock(self) -> Iterator[None]:
        """Hold the directory's one-writer lock (``<path>/.lock``) for the duration of the ``with`` block.

        The lock is an exclusive ``fcntl.flock`` on the lock file, which records the holder (pid, host,
        start time). The kernel releases it when the holder exits, however it dies, so a lock left by a
        killed process is recovered by the next writer. The directory is created if needed.

        Raises
        ------
        RunLockedError
            Another process holds the lock (the message names the directory and the holder).
        ValueError
            The directory cannot be created or written.
        """
        import fcntl

        self._mkdir()
        try:
            fd = os.open(self.lock_path, os.O_RDWR | os.O_CREAT, _default_mode())
        except OSError as exc:
            raise ValueError(f"out: cannot write in {self.path} ({exc.strerror})") from None
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.pread(fd, 4096, 0).decode("utf-8", "replace").strip() or "unknown"
                raise RunLockedError(f"out: {self.path} is being written by another process ({holder}); "
                                     f"one writer per run directory") from None
            info = (f"pid {os.getpid()} on {socket.gethostname()} since "
                    f"{time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())}\n").encode()
            os.ftruncate(fd, 0)
            os.pwrite(fd, info, 0)
            try:
                yield
            finally:
                os.ftruncate(fd, 0)
                fcntl.flock(fd, fcntl.LOCK_UN)
        finally:
            os.close(fd)

    def write_config(self, config: TrainConfig) -> None:
        """Save the run's config as ``config.json``."""
        self._mkdir()
        atomic_write_text(self.config_path, json.dumps(config.to_dict(), indent=2, sort_keys=True) + "\n")

    def read_config(self) -> TrainConfig:
        """Load ``config.json`` (unknown keys are an error)."""
        if not self.config_path.is_file():
            raise ValueError(f"path: {self.path} has no config.json")
        return TrainConfig.load(self.config_path)

    def append_metrics(self, rows: list[dict[str, Any]]) -> None:
        """Append rows to ``metrics.jsonl``."""
        if not rows:
            return
        self._mkdir()
        with open(self.metrics_path, "a") as fh:
            for row in rows:
                fh.write(json.dumps(row, allow_nan=True) + "\n")

    def read_metrics(self) -> list[dict[str, Any]]:
        """All rows of ``metrics.jsonl`` (an empty list if there is none)."""
        if not self.metrics_path.is_file():
            return []
        rows = []
        with open(self.metrics_path) as fh:
            for line in fh:
                line = line.strip()
                if line:
                    try:
                        rows.append(json.loads(line))
                    except json.JSONDecodeError:
                        break  # a torn last line of an interrupted run
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
        rows = [r for r in self.read_metrics() if r.get("iteration", k + 1) <= k]
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
            ``results: ...`` naming the file if it is missing, does not match its digest, or is not JSON.
        """
        if not self.results_path.is_file():
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


def _scalar_eval(ev: dict[str, Any]) -> dict[str, float]:
    return {f"eval/{k}": float(v) for k, v in ev.items() if isinstance(v, (int, float, np.floating))}


#: The dotted name of the budget, the one field ``resume`` may change (to a larger value).
_BUDGET = "algorithm.iterations"


def _config_conflicts(saved: TrainConfig, requested: TrainConfig) -> list[tuple[str, Any, Any]]:
    """``(dotted name, saved value, requested value)`` of the fields where the configs differ; a larger
    ``iterations`` is not a conflict (an explicit extension of the budget)."""
    a, b = flatten_table(saved.to_dict()), flatten_table(requested.to_dict())
    out = [(k, a.get(k), b.get(k)) for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]
    if [k for k, _, _ in out] == [_BUDGET] and requested.algorithm.iterations > saved.algorithm.iterations:
        return []
    return out


def _open_run(run: RunDirectory, cfg: TrainConfig, resume: bool) -> dict[str, Any] | None:
    """Validate ``run`` for training ``cfg`` (creating nothing) and return the checkpoint to resume from.

    Without ``resume`` the directory must be absent or empty. With ``resume``: a checkpoint (its config
    must equal ``cfg``, up to a larger ``iterations``: an extension; ``metrics.jsonl`` must hold every
    iteration up to it), or only ``config.json`` (a run killed before its first checkpoint: it starts
    again), or nothing at all (a run not started yet).
    """
    if not resume:
        run.check_new()
        return None
    names = run.entries()
    if "checkpoint.pt" not in names:
        others = [n for n in names if n not in ("config.json", TB_DIR)]
        if others:
            raise ValueError(f"resume: {run.path} has no checkpoint.pt to resume from but holds "
                             f"{', '.join(others[:4])}; nothing was changed (train into a new directory)")
        if "config.json" not in names:
            return None
    saved = run.read_config()
    conflicts = _config_conflicts(saved, cfg)
    if conflicts:
        shown = "; ".join(f"{k} {v!r} (saved: {w!r})" for k, w, v in conflicts[:4])
        more = f" and {len(conflicts) - 4} more" if len(conflicts) > 4 else ""
        hint = (" (resume can only extend the budget)" if any(k == _BUDGET for k, _, _ in conflicts) else "")
        raise ValueError(f"config: {shown}{more} contradict(s) the saved {run.config_path}{hint}; resume with "
                         f"the run's config, or train into a new directory")
    if "checkpoint.pt" not in names:
        return None
    state = load_checkpoint(run.checkpoint_path)
    run.check_metrics(int(state["trainer"]["k"]))
    return state


def train(trainer: Any, run: RunDirectory | None = None, resume: bool = False, progress: bool | None = None,
          stop_after: int | None = None, callback: Callable[[dict[str, Any]], None] | None = None,
          tensorboard: bool = False) -> dict[str, Any]:
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
    if tensorboard and run is None:
        raise ValueError("tensorboard: needs a run directory (run=RunDirectory(path)) to write into")
    if run is None:
        return _train(trainer, None, None, progress, stop_after, callback, None)
    cfg: TrainConfig = trainer.config
    _open_run(run, cfg, resume)  # refuse before creating anything
    if tensorboard:
        try:  # the extra missing: its error (TensorBoardLogger's, naming the extra) before anything is created
            import torch.utils.tensorboard  # noqa: F401
        except ImportError:
            TensorBoardLogger(run.path / TB_DIR)
    with run.lock():
        state = _open_run(run, cfg, resume)  # again under the lock: the directory may have changed meanwhile
        board = TensorBoardLogger(run.path / TB_DIR) if tensorboard else None
        return _train(trainer, run, state, progress, stop_after, callback, board)


def _train(trainer: Any, run: RunDirectory | None, state: dict[str, Any] | None, progress: bool | None,
           stop_after: int | None, callback: Callable[[dict[str, Any]], None] | None,
           board: TensorBoardLogger | None) -> dict[str, Any]:
    """The loop of :func:`train` on a validated (and locked) ``run``, from ``state`` if given."""
    cfg: TrainConfig = trainer.config
    torch.set_num_threads(cfg.run.num_threads)
    memory_rows: list[dict[str, Any]] = []
    elapsed = 0.0
    if run is not None:
        if state is not None:
            trainer.load_state_dict(state["trainer"])
            elapsed = float(state.get("elapsed", 0.0))
            run.truncate_metrics(trainer.k)
        if state is None or cfg.to_dict() != run.read_config().to_dict():
            run.write_config(cfg)
    seeds = eval_seeds(cfg)
    pending: list[dict[str, Any]] = []

    def checkpoint() -> None:
        if run is not None:
            run.append_metrics(pending)
            if board is not None:
                board.write(pending)
            save_checkpoint(run.checkpoint_path, {"trainer": trainer.state_dict(), "elapsed": elapsed})
        memory_rows.extend(pending)
        pending.clear()

    bar = None
    if progress or (progress is None and sys.stderr.isatty()):
        from tqdm.auto import tqdm

        bar = tqdm(total=cfg.algorithm.iterations, initial=trainer.k, desc=f"{cfg.method} seed {cfg.seed}", leave=False)
    try:
        while trainer.k < cfg.algorithm.iterations and not trainer.stopped:
            t0 = time.perf_counter()
            row = trainer.iteration()
            elapsed += time.perf_counter() - t0
            row = {"iteration": trainer.k, **row, "time/elapsed_s": elapsed}
            if trainer.k % cfg.run.eval_every == 0 or trainer.k == cfg.algorithm.iterations or trainer.stopped:
                row.update(_scalar_eval(trainer.evaluate(seeds)))
            pending.append(row)
            if callback is not None:
                callback(row)
            if bar is not None:
                bar.update(1)
                if "eval/cost" in row:
                    bar.set_postfix(cost=f"{row['eval/cost']:.4g}")
            if trainer.k % cfg.run.checkpoint_every == 0:
                checkpoint()
            if stop_after is not None and trainer.k >= stop_after:
                checkpoint()
                if board is not None:
                    board.close()
                return {"interrupted_at": trainer.k}
    finally:
        if bar is not None:
            bar.close()
    checkpoint()
    if board is not None:
        board.close()
    rows = run.read_metrics() if run is not None else memory_rows
    results = summarize(trainer, rows, elapsed, seeds)
    if run is not None:
        run.write_csv()
        run.write_results(results)
    else:
        results["metrics"] = memory_rows
    return results


def summarize(trainer: Any, rows: list[dict[str, Any]], elapsed: float, seeds: list[int]) -> dict[str, Any]:
    """Final evaluation and convergence figures of a finished run (the content of ``results.json``).

    ``policy_gap`` is the policy at the task's equilibrium against the discounted LQ optimum for the
    method's own noise mean (:func:`mixedrl.precision.run_policy_gap`), ``null`` with ``policy_gap_reason``
    when the task has no equilibrium.
    """
    cfg: TrainConfig = trainer.config
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
    if hasattr(trainer, "noise"):
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
    return results
