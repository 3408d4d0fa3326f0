"""Checkpoints and atomic files: the codec a run directory (:mod:`mixedrl.runs`) writes and reads.

* :func:`atomic_write_bytes`, :func:`atomic_write_text`: a temporary file in the same directory, fsync,
  ``os.replace`` (a crash leaves the previous file intact);
* :func:`write_with_digest`, :func:`verify_digest`, :func:`digest_path`: the sha256 sidecar of a file
  (``checkpoint.pt.sha256``, ``results.json.sha256``, ``sha256sum`` format), verified on every load;
* :func:`save_checkpoint`, :func:`load_checkpoint`: a checkpoint as plain data (numpy arrays, numpy
  scalars and generators encoded as marked dicts of tensors) read with ``torch.load(weights_only=True)``,
  so loading a file someone else made runs no code; the CRC-32 of every zip member is verified too;
* :func:`convert_checkpoint`: the one-off, explicitly trusted conversion of an old
  ``mixedrl-checkpoint-v1`` file.

Every public name is also importable from :mod:`mixedrl.runs`.
"""

from __future__ import annotations

import hashlib
import io
import os
import pickle
import pickletools
import re
import tempfile
import zipfile
from collections import OrderedDict
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = [
    "save_checkpoint",
    "load_checkpoint",
    "convert_checkpoint",
    "atomic_write_bytes",
    "atomic_write_text",
    "write_with_digest",
    "verify_digest",
    "digest_path",
    "default_file_mode",
    "is_temporary",
]

#: Format tag of the checkpoints written now (plain data; see :func:`save_checkpoint`).
_FORMAT = "mixedrl-checkpoint-v2"
#: Older tags: v1 pickled numpy objects as such (see :func:`convert_checkpoint`).
_OLD_FORMATS = ("mixedrl-checkpoint-v1",)


def default_file_mode() -> int:
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
        os.chmod(tmp, default_file_mode())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def is_temporary(name: str) -> bool:
    """True for the name of a temporary file of :func:`atomic_write_bytes` (one a killed process left)."""
    return name.startswith(".") and name.endswith(".tmp")


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
                f"mixedrl.checkpoint.convert_checkpoint({str(path)!r}, trust=True)") from None
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
    >>> from mixedrl.checkpoint import convert_checkpoint
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
