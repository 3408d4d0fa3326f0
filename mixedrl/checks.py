"""Input validation shared by every public function of mixedrl.

Every check raises :class:`ValueError` whose message starts with the *argument name*. Checks never modify
their input: they return a validated float64 copy (numpy) or the tensor itself (torch).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Container, Iterable, Mapping
from typing import Any

import numpy as np
import torch

__all__ = ["as_vector", "as_matrix", "as_batch", "check_covariance", "check_finite", "check_fraction", "check_int",
           "check_nonnegative_int", "check_positive_int", "check_unknown_keys", "check_number", "check_fields",
           "check_seed_lists", "check_task_types", "probe_task", "NonFiniteTrainingError", "MONITORED_PREFIXES",
           "UNMONITORED_METRICS", "check_finite_metrics"]

SYMMETRY_RTOL = 1e-10
PSD_RTOL = 1e-10


def check_finite(value: np.ndarray | torch.Tensor, name: str) -> None:
    """Raise ``ValueError`` if ``value`` holds NaN or +-inf."""
    if not bool(torch.isfinite(value).all() if isinstance(value, torch.Tensor) else np.all(np.isfinite(value))):
        raise ValueError(f"{name}: contains NaN or inf")


def _float_array(value: Any, name: str, want: str, fits: Callable[[np.ndarray], bool]) -> np.ndarray:
    """``value`` as a finite float64 array (a copy) whose shape ``fits``, else an error wanting shape ``want``."""
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: cannot be converted to a float array ({exc})") from None
    if not fits(arr):
        raise ValueError(f"{name}: expected shape {want}, got {arr.shape}")
    check_finite(arr, name)
    return arr


def as_vector(value: Any, name: str, n: int | None = None) -> np.ndarray:
    """Return ``value`` as a finite float64 vector of shape ``(n,)``.

    Raises
    ------
    ValueError
        If the shape is wrong or an entry is not finite.
    """
    want = "(n,)" if n is None else f"({n},)"
    return _float_array(value, name, want, lambda a: a.ndim == 1 and n in (None, len(a)))


def as_matrix(value: Any, name: str, shape: tuple[int | None, int | None] = (None, None)) -> np.ndarray:
    """Return ``value`` as a finite float64 matrix with the given shape (``None`` = any)."""
    want = "(" + ", ".join("?" if s is None else str(s) for s in shape) + ")"
    return _float_array(value, name, want, lambda a: a.ndim == 2
                        and all(s in (None, k) for s, k in zip(shape, a.shape)))


def as_batch(value: Any, name: str, n: int) -> np.ndarray:
    """Return one sample ``(n,)`` or a batch ``(N, n)`` as a finite float64 array of shape ``(N, n)``."""
    arr = _float_array(value, name, f"({n},) or (N, {n})", lambda a: a.ndim in (1, 2) and a.shape[-1] == n)
    return arr[None, :] if arr.ndim == 1 else arr


def check_covariance(value: Any, name: str, n: int | None = None) -> np.ndarray:
    """Return ``value`` as a symmetric positive semi-definite float64 ``(n, n)`` matrix.

    Symmetry is checked to :data:`SYMMETRY_RTOL` times ``max(1, max|C_ij|)``, and the smallest eigenvalue
    must be ``>= -PSD_RTOL`` times the largest (so tiny entries such as 1e-20 pass). The result is
    exactly symmetrised, ``(C + C^T) / 2``.

    Raises
    ------
    ValueError
        Wrong shape, NaN/inf, not symmetric, or not positive semi-definite; the message names ``name``.
    """
    arr = as_matrix(value, name, (n, n))
    if arr.shape[0] != arr.shape[1]:
        raise ValueError(f"{name}: a covariance must be square, got {arr.shape}")
    scale = max(1.0, float(np.max(np.abs(arr)))) if arr.size else 1.0
    if not np.allclose(arr, arr.T, rtol=0.0, atol=SYMMETRY_RTOL * scale):
        raise ValueError(f"{name}: covariance is not symmetric (max |C - C^T| = {np.max(np.abs(arr - arr.T)):.3g})")
    arr = 0.5 * (arr + arr.T)
    if arr.size:
        eig = np.linalg.eigvalsh(arr)
        if eig[0] < -PSD_RTOL * max(1e-300, abs(eig[-1])):
            raise ValueError(f"{name}: covariance is not positive semi-definite (smallest eigenvalue {eig[0]:.3g})")
    return arr


def check_int(value: Any, name: str, minimum: int | None = None) -> int:
    """Return ``value`` (a Python or numpy integer, not a bool) as an int, ``>= minimum`` if given.

    Raises
    ------
    ValueError
        ``value`` is not an integer or is below ``minimum``; the message starts with ``name``.
    """
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) \
            or (minimum is not None and value < minimum):
        kind = {None: "an integer", 0: "a non-negative integer", 1: "a positive integer"}.get(
            minimum, f"an integer >= {minimum}")
        raise ValueError(f"{name}: expected {kind}, got {value!r}")
    return int(value)


def check_positive_int(value: Any, name: str) -> int:
    """Return ``value`` as an int ``>= 1`` (:func:`check_int` with ``minimum=1``)."""
    return check_int(value, name, 1)


def check_nonnegative_int(value: Any, name: str) -> int:
    """Return ``value`` as an int ``>= 0`` (:func:`check_int` with ``minimum=0``), e.g. a seed or a count."""
    return check_int(value, name, 0)


def check_unknown_keys(given: dict[str, Any], allowed: set[str] | frozenset[str], where: str) -> None:
    """Raise ``ValueError`` listing every key of ``given`` that is not in ``allowed``."""
    unknown = sorted(set(given) - set(allowed))
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {unknown}; allowed: {sorted(allowed)}")


def check_number(value: Any, name: str, *, positive: bool = False, nonneg: bool = False,
                 allow_inf: bool = False) -> float:
    """Return ``value`` (an int or float, not a bool) as a finite float; ``positive`` / ``nonneg`` add ``> 0`` /
    ``>= 0``; ``allow_inf`` also accepts ``+inf`` (for "no limit").

    Raises
    ------
    ValueError
        ``value`` is not a number, not finite, or out of range; the message starts with ``name``.
    """
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name}: expected a number, got {value!r}")
    value = float(value)
    if allow_inf and value == np.inf:
        return value
    if not np.isfinite(value) or (positive and value <= 0) or (nonneg and value < 0):
        kind = "positive" if positive else ("non-negative" if nonneg else "finite")
        raise ValueError(f"{name}: expected a {kind} number, got {value!r}")
    return value


def check_fields(obj: Any, names: Iterable[str] | None = None, prefix: str = "", *,
                 positive: bool | Container[str] = False, nonneg: bool | Container[str] = False) -> None:
    """Set the fields ``names`` (default: those annotated ``float``) of the dataclass ``obj``, frozen or not, to their
    :func:`check_number` floats; ``positive`` / ``nonneg`` (True: all) are the fields that must be ``> 0`` / ``>= 0``.

    Raises
    ------
    ValueError
        At the first bad field, the message starting with ``prefix`` and its name.
    """
    names = [f.name for f in dataclasses.fields(obj) if f.type in ("float", float)] if names is None else list(names)
    positive, nonneg = (names if kind is True else kind or () for kind in (positive, nonneg))
    for name in names:
        object.__setattr__(obj, name, check_number(getattr(obj, name), prefix + name, positive=name in positive,
                                                   nonneg=name in nonneg))


def check_fraction(value: Any, name: str, *, low_open: bool = False, high_open: bool = False) -> float:
    """Return ``value`` as a float in ``[0, 1]``; ``low_open`` excludes 0, ``high_open`` excludes 1.

    Raises
    ------
    ValueError
        ``value`` is not a number or lies outside the interval; the message starts with ``name``.
    """
    v = check_number(value, name)
    if (v < 0 or v > 1) or (low_open and v == 0) or (high_open and v == 1):
        lo, hi = "(" if low_open else "[", ")" if high_open else "]"
        raise ValueError(f"{name}: expected a number in {lo}0, 1{hi}, got {value!r}")
    return v


def check_seed_lists(seeds: Any, n: int, name: str = "seeds") -> list[list[int]]:
    """``seeds`` as ``n`` non-empty lists of ints, one per policy; a flat list of ints is every policy's.

    Raises
    ------
    ValueError
        ``seeds`` empty, not ints, or not ``n`` lists (the message starts with ``name`` and names the entry).
    """

    def is_int(v: Any) -> bool:
        return isinstance(v, (int, np.integer)) and not isinstance(v, bool)

    def is_list(v: Any) -> bool:
        return isinstance(v, (list, tuple, np.ndarray)) and len(v) > 0

    if not is_list(seeds):
        raise ValueError(f"{name}: expected a non-empty list of seeds (or one list per policy), got {seeds!r:.80}")
    if all(is_int(s) for s in seeds):
        return [[int(s) for s in seeds] for _ in range(n)]
    if len(seeds) != n:
        raise ValueError(f"{name}: expected one list of seeds per policy ({n}), got {len(seeds)} entries")
    for p, entry in enumerate(seeds):
        if not is_list(entry) or not all(is_int(s) for s in entry):
            raise ValueError(f"{name}: entry {p} (policy {p}) must be a non-empty list of ints, got {entry!r:.80}")
    return [[int(s) for s in entry] for entry in seeds]


#: :func:`probe_task` probes this many batches of states (each its own seed) ...
PROBE_BATCHES = 4
#: ... of this many states, each rolled this many steps forward.
PROBE_BATCH_SIZE = 32
PROBE_STEPS = 3


def check_task_types(task: Any, probe: bool = True) -> None:
    """Check a task's sizes, array attributes and ``value_scale`` (what training relies on), then :func:`probe_task`.

    Parameters
    ----------
    task : Task
        A task (:class:`mixedrl.tasks.Task`).
    probe : bool
        Whether to :func:`probe_task` too (:func:`mixedrl.tasks.check_task` probes after its own output checks).

    Raises
    ------
    ValueError
        ``<TaskClass>.<attribute>: ...``: ``state_dim``, ``action_dim``, ``obs_dim`` or ``noise_dim`` not a
        positive integer; ``noise_matrix``, ``action_bound`` or ``obs_scale`` not a floating-point
        ``torch.Tensor`` of its shape; ``prior_mean``, ``prior_cov``, ``true_mean`` or ``true_cov`` not a real
        array (not a tensor) of its shape; an array not set, with NaN or inf, or (``action_bound``,
        ``obs_scale``) not positive; ``value_scale`` not a positive finite number; or :func:`probe_task`'s.
    """
    name = type(task).__name__
    n, m, o, d = (check_positive_int(getattr(task, a, None), f"{name}.{a}")
                  for a in ("state_dim", "action_dim", "obs_dim", "noise_dim"))
    for attr, shape in (("noise_matrix", (n, d)), ("action_bound", (m,)), ("obs_scale", (o,)), ("prior_mean", (d,)),
                        ("prior_cov", (d, d)), ("true_mean", (d,)), ("true_cov", (d, d))):
        v, where = getattr(task, attr, None), f"{name}.{attr}"
        tensor = attr in ("noise_matrix", "action_bound", "obs_scale")
        if v is None:
            raise ValueError(f"{where}: not set (expected shape {shape})")
        if tensor and not isinstance(v, torch.Tensor):
            raise ValueError(f"{where}: expected a torch.Tensor of shape {shape}, got {type(v).__name__}")
        if not tensor and isinstance(v, torch.Tensor):
            raise ValueError(f"{where}: expected a numpy array, got a torch.Tensor (use .numpy())")
        if not tensor and np.asarray(v).dtype.kind not in "fiu":
            raise ValueError(f"{where}: expected real numbers, got dtype {np.asarray(v).dtype}")
        arr = v.detach().cpu().to(torch.float64).numpy() if tensor else np.asarray(v, dtype=np.float64)
        if arr.shape != shape:
            raise ValueError(f"{where}: expected shape {shape}, got shape {arr.shape}")
        if tensor and not v.is_floating_point():
            raise ValueError(f"{where}: expected a floating-point dtype (float32 or float64), got {v.dtype}")
        check_finite(arr, where)
        if attr in ("action_bound", "obs_scale") and not (arr > 0).all():
            raise ValueError(f"{where}: expected positive values, got {arr.tolist()}")
    scale = getattr(task, "value_scale", 1.0)
    if isinstance(scale, bool) or not isinstance(scale, (int, float, np.integer, np.floating)) \
            or not math.isfinite(scale) or scale <= 0:
        raise ValueError(f"{name}.value_scale: expected a positive finite number (the critic's output is "
                         f"multiplied by it), got {scale!r}")
    if probe:
        probe_task(task)


def probe_task(task: Any) -> None:
    """Probe ``observe``, ``f`` and ``cost`` of a task that passed :func:`check_task_types` on :data:`PROBE_BATCHES`
    batches of :data:`PROBE_BATCH_SIZE` start states (seeds 1, 2, ..., float64), each rolled :data:`PROBE_STEPS`
    steps under actions uniform within the bounds (own generators: no random stream of a trainer is touched).

    Raises
    ------
    ValueError
        ``<TaskClass>.sample_initial`` of the wrong shape, or ``observe``, ``f`` or ``cost`` NaN or inf on a state.
    """
    name = type(task).__name__
    n, m = int(task.state_dim), int(task.action_dim)
    bound = task.action_bound.detach().to(torch.float64)
    with torch.no_grad():
        for probe in range(1, PROBE_BATCHES + 1):
            gen = torch.Generator().manual_seed(probe)
            s = task.sample_initial(PROBE_BATCH_SIZE, gen)
            if not isinstance(s, torch.Tensor) or tuple(s.shape) != (PROBE_BATCH_SIZE, n):
                raise ValueError(f"{name}.sample_initial: expected a tensor of shape {(PROBE_BATCH_SIZE, n)}, "
                                 f"returned {getattr(s, 'shape', type(s).__name__)}")
            s = s.to(torch.float64)
            for step in range(PROBE_STEPS):
                u = (2.0 * torch.rand(PROBE_BATCH_SIZE, m, generator=gen, dtype=torch.float64) - 1.0) * bound
                s_next = task.f(s, u)
                where = f"on states of sample_initial(seed {probe}) after {step} random-action steps"
                for fn, value in (("observe", task.observe(s)), ("f", s_next), ("cost", task.cost(s_next, u))):
                    if isinstance(value, torch.Tensor) and not bool(torch.isfinite(value).all()):
                        raise ValueError(f"{name}.{fn}: returned NaN or inf values {where}")
                s = s_next


class NonFiniteTrainingError(ValueError):
    """Training produced a non-finite loss or evaluation (:func:`check_finite_metrics`).

    Attributes
    ----------
    iteration : int or None
        The iteration whose metrics row held it.
    key : str
        The first non-finite metric of the row (``"train/critic_loss"``, ``"eval/cost"`` ...).
    value : float
        Its value (NaN or +-inf).
    """

    def __init__(self, message: str, iteration: int | None, key: str, value: float) -> None:
        super().__init__(message)
        self.iteration, self.key, self.value = iteration, key, value


#: Prefixes of the metrics :func:`check_finite_metrics` checks.
MONITORED_PREFIXES = ("train/", "mvc/", "eval/")
#: Monitored metrics that may be NaN by design (DDPG's exploration cost when every transition was
#: non-finite, :meth:`mixedrl.algorithms.ddpg.DDPG.collect`).
UNMONITORED_METRICS = frozenset({"train/env_cost"})


def check_finite_metrics(row: Mapping[str, Any], where: str = "training") -> None:
    """Raise if a metrics row of training holds a non-finite loss or evaluation result.

    Reads only; raised before the row is recorded, so a run directory keeps its last (finite) checkpoint.

    Parameters
    ----------
    row : mapping
        One iteration's metrics; the entries under :data:`MONITORED_PREFIXES`, less
        :data:`UNMONITORED_METRICS`, are checked in the row's order.
    where : str
        What the message starts with (the run).

    Raises
    ------
    NonFiniteTrainingError
        ``"<where>: iteration <k>: <key> is nan (...)"``, naming the first non-finite entry, and the others.
    """
    bad = [(k, v) for k, v in row.items()
           if k.startswith(MONITORED_PREFIXES) and k not in UNMONITORED_METRICS
           and isinstance(v, (float, int, np.floating)) and not math.isfinite(v)]
    if bad:
        key, value = bad[0]
        iteration = row.get("iteration")
        others = f"; also non-finite: {', '.join(k for k, _ in bad[1:])}" if len(bad) > 1 else ""
        raise NonFiniteTrainingError(
            f"{where}: iteration {iteration}: {key} is {value} (the first non-finite quantity of the row{others}); "
            f"training stopped, the run's last checkpoint is kept", iteration, key, float(value))
