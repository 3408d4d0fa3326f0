"""Checkpoints and atomic files: the codec a run directory (:mod:`mixedrl.runs`) writes and reads.

* :func:`atomic_write_bytes`, :func:`atomic_write_text`: a crash leaves the previous file intact;
* :func:`write_with_digest`, :func:`verify_digest`, :func:`digest_path`: a file's sha256 sidecar
  (``sha256sum`` format), verified on every load;
* :func:`save_checkpoint`, :func:`load_checkpoint`: a checkpoint as plain data, read with
  ``torch.load(weights_only=True)`` (loading a file someone else made runs no code).

Every public name is also importable from :mod:`mixedrl.runs`.
"""

from __future__ import annotations

import hashlib
import io
import os
import pickle
import pickletools
import re
import stat
import tempfile
import zipfile
from collections import OrderedDict
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = ["save_checkpoint", "load_checkpoint", "regular_file", "OLD_FORMAT_READER", "atomic_write_bytes",
           "atomic_write_text", "write_with_digest", "verify_digest", "digest_path", "default_file_mode",
           "is_temporary"]

#: Format tag of the checkpoints written now (plain data; see :func:`save_checkpoint`).
_FORMAT = "mixedrl-checkpoint-v2"
#: Older tags, refused with a message naming :data:`OLD_FORMAT_READER`.
_OLD_FORMATS = ("mixedrl-checkpoint-v1",)
#: The release that reads (and converts) a checkpoint of :data:`_OLD_FORMATS`.
OLD_FORMAT_READER = "mixedrl 0.1.0 from git commit b510485 (mixedrl.checkpoint.convert_checkpoint)"


def default_file_mode() -> int:
    """``0o666`` minus the process umask: the mode ``open()`` would give a new file (mkstemp gives 0600)."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (a temporary file in the same directory, fsync, ``os.replace``):
    a crash during the write leaves the previous file intact."""
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
# Integrity: a sha256 sidecar per file
# ----------------------------------------------------------------------------------------------------
def digest_path(path: str | Path) -> Path:
    """The sidecar of ``path`` holding its sha256 (``sha256sum`` format: ``<hex>  <name>``)."""
    path = Path(path)
    return path.with_name(path.name + ".sha256")


def _sidecar_digests(path: Path, what: str = "digest") -> list[str] | None:
    """The digests listed in ``path``'s sidecar (None without one); ``ValueError`` (``<what>: ...``) for a
    sidecar that is a link, not UTF-8, or lists no sha256."""
    sidecar = digest_path(path)
    if not regular_file(sidecar, what):
        return None
    try:
        lines = sidecar.read_bytes().decode("utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{what}: cannot read {sidecar} ({exc})") from None
    digests = [line.split()[0].lower() for line in lines if line.strip()]
    if not digests or not all(re.fullmatch(r"[0-9a-f]{64}", d) for d in digests):
        raise ValueError(f"{what}: {sidecar} lists no sha256 digest (expected lines '<64 hex digits>  {path.name}')")
    return digests


def write_with_digest(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically together with its sha256 in the sidecar :func:`digest_path`.

    Crash-safe: the sidecar first lists the new digest beside the old one, then the file is replaced,
    then the sidecar keeps the new digest only (each step an atomic replace), so the file on disk always
    matches a digest of its sidecar.
    """
    path = Path(path)
    new = hashlib.sha256(data).hexdigest()
    old: list[str] = []
    if path.is_file():  # without a sidecar, the old file's own digest
        old = _sidecar_digests(path) or [hashlib.sha256(path.read_bytes()).hexdigest()]
    atomic_write_text(digest_path(path), "".join(f"{d}  {path.name}\n" for d in [new, *old[:1]]))
    atomic_write_bytes(path, data)
    if old:
        atomic_write_text(digest_path(path), f"{new}  {path.name}\n")


def verify_digest(path: str | Path, data: bytes, what: str) -> None:
    """Check ``data`` (the bytes read from ``path``) against ``path``'s sidecar, if it has one.

    Raises
    ------
    ValueError
        ``<what>: <path> is corrupted: its sha256 ... does not match <sidecar>``.
    """
    path = Path(path)
    digests = _sidecar_digests(path, what)
    if digests is None:
        return  # no sidecar: loads unverified (docs/algorithm2.rst, "Run directories")
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
    """``value`` with numpy arrays/scalars and generators replaced by marked dicts of tensors and plain data;
    ``ValueError`` naming ``where`` (the key path) for anything else that is not plain data."""
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
    out = type(value)((key, _decode(v, path)) for key, v in value.items())
    if hasattr(value, "_metadata"):
        out._metadata = _decode(value._metadata, path)  # type: ignore[attr-defined]
    return out


def _format_tag(path: Path) -> str | None:
    """The ``mixedrl-checkpoint-*`` tag of a torch zip checkpoint, read without unpickling (the opcodes of
    its ``data.pkl``, :func:`pickletools.genops`); None if unreadable or untagged."""
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
    :class:`torch.Generator` replaced by a dict marked ``{"__mixedrl_encoded__": kind, ...}`` holding a
    tensor or plain state; :func:`load_checkpoint` restores them bit for bit. Written with
    :func:`write_with_digest` (atomic, with ``<path>.sha256``).

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


def regular_file(path: str | Path, what: str) -> bool:
    """Whether ``path`` exists, as a regular file; a symbolic link or a special file there is an error.

    Parameters
    ----------
    path : str or pathlib.Path
        The file.
    what : str
        The prefix of the error message (``"checkpoint"``, ``"config"``, ...).

    Returns
    -------
    bool
        ``False`` if nothing is at ``path``, ``True`` for a regular file.

    Raises
    ------
    ValueError
        ``<what>: <path> is a symbolic link ...`` or ``... is not a regular file ...``.
    """
    path = Path(path)
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return False
    except OSError as exc:
        raise ValueError(f"{what}: cannot read {path} ({exc.strerror})") from None
    if stat.S_ISLNK(mode):
        raise ValueError(f"{what}: {path} is a symbolic link; a run's files are regular files (nothing was read "
                         f"through it)")
    if not stat.S_ISREG(mode):
        raise ValueError(f"{what}: {path} is not a regular file (a directory, device or pipe)")
    return True


def _old_format(path: Path, tag: str) -> ValueError:
    """The error for a checkpoint of an older format (:data:`_OLD_FORMATS`)."""
    return ValueError(f"checkpoint: {path} is a {tag} file, written by mixedrl before {_FORMAT}; this version does "
                      f"not read it: read it with {OLD_FORMAT_READER}")


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Read a checkpoint written by :func:`save_checkpoint`, safely: nothing stored in the file is run.

    The bytes are checked against ``<path>.sha256`` (if present) and the CRC-32 of every zip member, then
    read with ``torch.load(..., weights_only=True)``, which refuses any pickled object but tensors and
    plain containers before creating it.

    Raises
    ------
    ValueError
        ``checkpoint: ...`` naming ``path``: missing, not a regular file, truncated, corrupted, not a
        mixedrl checkpoint, holding pickled objects other than plain data, or of an older format (the
        message names :data:`OLD_FORMAT_READER`).
    """
    path = Path(path)
    if not regular_file(path, "checkpoint"):
        raise ValueError(f"checkpoint: {path} does not exist")
    data = path.read_bytes()
    verify_digest(path, data, "checkpoint")
    _verify_zip(path, data)
    try:
        payload = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any failure: explain it without running the file
        tag = _format_tag(path)
        if tag in _OLD_FORMATS:
            raise _old_format(path, tag) from None
        # the global that torch's weights_only unpickler refused, from its message
        refused = re.search(r"GLOBAL ([\w.]+)", str(exc)) if isinstance(exc, pickle.UnpicklingError) else None
        if refused:
            raise ValueError(
                f"checkpoint: {path} holds pickled objects that are not plain data ({refused.group(1)}); refused "
                f"without creating them, since loading them could execute code") from None
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        raise ValueError(f"checkpoint: {path} is corrupted, truncated or not a mixedrl checkpoint "
                         f"({type(exc).__name__}: {first[:200]})") from None
    if not isinstance(payload, dict) or "state" not in payload or not isinstance(payload["state"], dict):
        raise ValueError(f"checkpoint: {path} is not a {_FORMAT} file")
    if payload.get("format") in _OLD_FORMATS:
        raise _old_format(path, payload["format"])
    if payload.get("format") != _FORMAT:
        raise ValueError(f"checkpoint: {path} is not a {_FORMAT} file (format {payload.get('format')!r})")
    return _decode(payload["state"], path)
