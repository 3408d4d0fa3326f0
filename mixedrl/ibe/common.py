"""What the three Cases of the IBE share: the residuals of eq. (10) and the input and state checks.

The residuals in noise coordinates (:func:`~mixedrl.ibe.residuals`, :func:`noise_coordinates`); the
argument checks (:func:`real_batch`, :func:`real_vector`, :func:`real_covariance`); the guarded update
(:func:`PosteriorGuard`, :func:`check_posterior`: a candidate posterior is committed only once found finite
and symmetric PSD); :func:`check_state` for ``load_state_dict``; and the read-only public state
(:class:`ReadOnlyField`, :class:`ReadOnlyFields`, :class:`GaussianNoiseEstimate`).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np
import torch

from mixedrl.checks import (as_batch, as_vector, check_covariance, check_finite, check_nonnegative_int,
                            check_unknown_keys)
from mixedrl.gaussian import sample_gaussian

__all__ = ["residuals", "check_noise_matrix", "noise_coordinates", "real_array", "real_batch", "real_vector",
           "real_covariance", "check_dimension", "symmetrize", "check_posterior", "PosteriorGuard", "check_state",
           "ReadOnlyField", "ReadOnlyFields", "GaussianNoiseEstimate"]

#: numpy dtype kinds accepted as real numbers (float, signed and unsigned int).
_REAL_KINDS = frozenset("fiu")


# ----------------------------------------------------------------------------------------------------
# eq. (10)
# ----------------------------------------------------------------------------------------------------
def residuals(
    f: Callable[[Any, Any], Any],
    x: np.ndarray | torch.Tensor,
    u: np.ndarray | torch.Tensor,
    x_next: np.ndarray | torch.Tensor,
    E: np.ndarray | torch.Tensor | None = None,
) -> np.ndarray | torch.Tensor:
    """Implements eq. (10): the residual of a transition under the model's deterministic part.

    .. math:: \\xi_j^{\\mathcal{D}} = x_{j+1}^{\\mathcal{D}} - f(x_j^{\\mathcal{D}}, u_j^{\\mathcal{D}})

    With the noise matrix ``E`` of ``x' = f(x, u) + E xi`` the residual is returned in noise coordinates,
    the least-squares solution of ``E xi = x_{j+1} - f(x_j, u_j)`` (:func:`noise_coordinates`).

    Parameters
    ----------
    f : callable
        Deterministic model ``f(x, u)``, vectorised over leading dimensions, returning an array (or
        tensor) of the same kind and shape as ``x_next``.
    x : ndarray or Tensor, shape (..., n)
        States.
    u : ndarray or Tensor, shape (..., m)
        Actions, same leading dimensions as ``x``.
    x_next : ndarray or Tensor, shape (..., n)
        Next states.
    E : ndarray or Tensor, shape (n, d), optional
        How the noise enters the state; any matrix of full column rank (:func:`check_noise_matrix`).
        ``None`` (default): the residual in state coordinates (``E = I``).

    Returns
    -------
    ndarray or Tensor, shape (..., n), or (..., d) with ``E``
        Same kind as the inputs (numpy in, numpy out; torch in, torch out).

    Raises
    ------
    ValueError
        Inputs of mixed kinds, not real numbers, non-finite, of inconsistent shapes, ``f`` returning a
        wrong shape, or ``E`` not an ``(n, d)`` matrix of full column rank.
    """
    is_torch = [isinstance(a, torch.Tensor) for a in (x, u, x_next)]
    if any(is_torch) and not all(is_torch):
        raise ValueError("x: x, u and x_next must all be numpy arrays or all torch tensors")
    arrays = []
    for name, val in (("x", x), ("u", u), ("x_next", x_next)):
        val = real_array(val, name)
        val = val if is_torch[0] else np.asarray(val, dtype=np.float64)
        if val.ndim < 1:
            raise ValueError(f"{name}: expected at least one dimension, got a scalar")
        check_finite(val, name)
        arrays.append(val)
    x, u, x_next = arrays
    if tuple(x.shape) != tuple(x_next.shape):
        raise ValueError(f"x_next: expected the shape of x {tuple(x.shape)}, got {tuple(x_next.shape)}")
    if tuple(u.shape[:-1]) != tuple(x.shape[:-1]):
        raise ValueError(f"u: leading dimensions {tuple(u.shape[:-1])} differ from x's {tuple(x.shape[:-1])}")
    fx = f(x, u)
    if tuple(fx.shape) != tuple(x_next.shape):
        raise ValueError(f"f: returned shape {tuple(fx.shape)}, expected {tuple(x_next.shape)}")
    # xi_j = x_{j+1} - f(x_j, u_j)
    if E is None:
        return x_next - fx
    check_noise_matrix(E, "E", x.shape[-1])
    return noise_coordinates(x_next - fx, E)


def check_noise_matrix(E: Any, name: str, n: int | None = None) -> None:
    """Raise ``ValueError`` naming ``name`` unless ``E`` is a finite real ``(n, d)`` matrix of full column
    rank ``d`` (``d <= n`` independent columns).

    The residual of eq. (10) is a noise only if ``E xi = r`` determines ``xi``: any ``E`` with independent
    columns does (a 0/1 selection, the ``[dt, 1]^T`` of a semi-implicit Euler step, a ``B`` matrix), a
    rank-deficient one does not (two noise components moving the state the same way).
    """
    arr = real_array(E.detach() if isinstance(E, torch.Tensor) else E, name)
    arr = np.asarray(arr, dtype=np.float64)
    if arr.ndim != 2 or (n is not None and arr.shape[0] != n):
        rows = "n" if n is None else str(n)
        raise ValueError(f"{name}: expected a ({rows}, noise_dim) matrix, got shape {arr.shape}")
    check_finite(arr, name)
    rank = int(np.linalg.matrix_rank(arr)) if arr.size else 0
    if arr.shape[1] < 1 or rank < arr.shape[1]:
        raise ValueError(f"{name}: expected full column rank {arr.shape[1]} (each noise component moving the state "
                         f"in its own direction, so that E xi = x' - f(x, u) determines xi), got rank {rank}")


def noise_coordinates(r: np.ndarray | torch.Tensor, E: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
    """The least-squares ``xi = argmin |E xi - r|`` of residuals ``r`` (..., n) for a full-column-rank ``E``
    (n, d): ``(E^T E)^{-1} E^T r``, shape (..., d), the kind and dtype of ``r``.

    For ``E^T E = I`` exactly (a 0/1 selection of distinct state components) this is ``E^T r``, computed as
    such (bit for bit what the package computed before any other ``E`` was allowed); otherwise a QR
    least-squares solve (``lstsq``), without forming the normal equations.
    """
    if isinstance(r, torch.Tensor):
        Et = torch.as_tensor(E).to(r.dtype)
        d = Et.shape[1]
        if torch.equal(Et.T @ Et, torch.eye(d, dtype=r.dtype)):
            return r @ Et
        flat = r.reshape(-1, r.shape[-1]).T
        return torch.linalg.lstsq(Et, flat, driver="gelsd").solution.T.reshape(*r.shape[:-1], d)
    En = np.asarray(E.detach().numpy() if isinstance(E, torch.Tensor) else E, dtype=np.float64)
    d = En.shape[1]
    if np.array_equal(En.T @ En, np.eye(d)):
        return r @ En
    flat = np.reshape(r, (-1, r.shape[-1])).T
    return np.linalg.lstsq(En, flat, rcond=None)[0].T.reshape(*r.shape[:-1], d)



# ----------------------------------------------------------------------------------------------------
# input checks
# ----------------------------------------------------------------------------------------------------
def real_array(value: Any, name: str) -> np.ndarray | torch.Tensor:
    """Return ``value`` as an array (a tensor stays a tensor) after checking that it holds real numbers.

    Raises
    ------
    ValueError
        ``value`` is complex, bool, a string or object array, or ragged; the message names ``name``.
    """
    if isinstance(value, torch.Tensor):
        if value.dtype.is_complex or value.dtype == torch.bool:
            raise ValueError(f"{name}: expected real numbers, got a tensor of dtype {value.dtype}")
        return value
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: cannot be converted to a float array ({exc})") from None
    if arr.dtype.kind not in _REAL_KINDS:
        raise ValueError(f"{name}: expected real numbers (float or int), got dtype {arr.dtype}")
    return arr


def real_batch(value: Any, name: str, n: int, copy: bool = False) -> np.ndarray:
    """Return one sample ``(n,)`` or a batch ``(N, n)`` of real numbers as finite float64 ``(N, n)``.

    A float64 ndarray is returned without a copy (a view for one sample) unless ``copy``.

    Raises
    ------
    ValueError
        Not real numbers (:func:`real_array`), wrong shape, NaN or inf.
    """
    if type(value) is np.ndarray and value.dtype == np.float64:
        if value.ndim == 1 and value.shape[0] == n:
            batch = value[None, :]
        elif value.ndim == 2 and value.shape[1] == n:
            batch = value
        else:
            return as_batch(value, name, n)  # raises with the shared message
        check_finite(batch, name)
        return batch.copy() if copy else batch
    return as_batch(real_array(value, name), name, n)


def check_dimension(n: int, name: str) -> int:
    """Return ``n`` if it is at least 1; an estimator of zero-dimensional noise is refused."""
    if n < 1:
        raise ValueError(f"{name}: the noise needs at least one dimension, got {n}")
    return n


def real_vector(value: Any, name: str, n: int | None = None) -> np.ndarray:
    """Return a finite float64 vector of real numbers, shape ``(n,)``, and of length at least 1."""
    vec = as_vector(real_array(value, name), name, n)
    check_dimension(vec.shape[0], name)
    return vec


def real_covariance(value: Any, name: str, n: int | None = None) -> np.ndarray:
    """Return a symmetric PSD ``(n, n)`` float64 matrix of real numbers with ``n >= 1``."""
    cov = check_covariance(real_array(value, name), name, n)
    check_dimension(cov.shape[0], name)
    return cov


def symmetrize(a: np.ndarray) -> np.ndarray:
    """``(A + A^T) / 2``."""
    return 0.5 * (a + a.T)


# ----------------------------------------------------------------------------------------------------
# guarded updates
# ----------------------------------------------------------------------------------------------------
def check_posterior(name: str, finite: Sequence[np.ndarray], psd: Sequence[np.ndarray] = ()) -> None:
    """Raise ``ValueError`` unless every array of ``finite`` and ``psd`` is finite and each of ``psd``
    is a symmetric PSD matrix (call it on a candidate posterior before committing it).

    Parameters
    ----------
    name : str
        The argument that produced the candidate (``"xi"``, ``"x"``, ``"state_dict"``); it starts the
        message.
    finite : sequence of ndarray
        Arrays that must be finite.
    psd : sequence of ndarray
        Matrices that must be finite, symmetric and positive semi-definite (to the tolerances of
        :func:`mixedrl.checks.check_covariance`).

    Raises
    ------
    ValueError
        ``"<name>: update rejected: ..."``.
    """
    for arr in (*finite, *psd):
        if not np.isfinite(arr).all():
            raise ValueError(f"{name}: update rejected: the posterior would not be finite (overflow or NaN "
                             f"in float64)")
    for c in psd:
        check_covariance(c, f"{name}: update rejected: the posterior")


@contextlib.contextmanager
def PosteriorGuard(name: str) -> Iterator[None]:  # noqa: N802 (used as ``with PosteriorGuard(name):``)
    """Context for computing a candidate posterior: floating-point warnings are silenced (overflow and
    NaN are found by :func:`check_posterior` on the result) and a failed factorisation
    (``numpy.linalg.LinAlgError``) becomes ``ValueError("<name>: update rejected: ...")``.

    Parameters
    ----------
    name : str
        The argument the error message names.
    """
    try:
        with np.errstate(all="ignore"):
            yield
    except np.linalg.LinAlgError as exc:
        raise ValueError(f"{name}: update rejected: the posterior could not be computed ({exc})") from None


# ----------------------------------------------------------------------------------------------------
# state dicts
# ----------------------------------------------------------------------------------------------------
def check_state(state: Any, spec: dict[str, Any], kind: str, psd: Sequence[str] = ()) -> dict[str, Any]:
    """Validate a state dict against ``spec`` (key -> shape tuple | 'int' | 'float' | 'str'); the keys ``psd``
    (those in ``spec``) must be symmetric PSD matrices and are returned symmetrised (:func:`real_covariance`)."""
    if not isinstance(state, dict):
        raise ValueError(f"state_dict: expected a dict, got {type(state).__name__}")
    check_unknown_keys(state, set(spec), "state_dict")
    missing = sorted(set(spec) - set(state))
    if missing:
        raise ValueError(f"state_dict: missing key(s) {missing}")
    if state["kind"] != kind:
        raise ValueError(f"state_dict: kind {state['kind']!r} does not match this estimator ({kind!r})")
    out: dict[str, Any] = {}
    for key, want in spec.items():
        val = state[key]
        if want == "str":
            if not isinstance(val, str):
                raise ValueError(f"state_dict: {key} must be a str")
            out[key] = val
        elif want == "int":
            out[key] = check_nonnegative_int(val, f"state_dict: {key}")
        elif want == "float":
            if isinstance(val, bool) or not isinstance(val, (int, float, np.floating)) or not math.isfinite(val):
                raise ValueError(f"state_dict: {key} must be a finite float, got {val!r}")
            out[key] = float(val)
        else:
            val = real_array(val, f"state_dict: {key}")
            try:
                arr = np.array(val, dtype=np.float64)
            except (TypeError, ValueError):
                raise ValueError(f"state_dict: {key} is not a float array") from None
            if arr.shape != want:
                raise ValueError(f"state_dict: {key} has shape {arr.shape}, expected {want}")
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"state_dict: {key} contains NaN or inf")
            out[key] = arr
    for key in (k for k in psd if k in out):
        out[key] = real_covariance(out[key], f"state_dict: {key}", spec[key][0])
    return out



# ----------------------------------------------------------------------------------------------------
# read-only public arrays, the Gaussian noise estimate of Cases 1 and 2
# ----------------------------------------------------------------------------------------------------
class ReadOnlyField:
    """Descriptor of a public field of an estimator's state (``mean``, ``cov``, ``count`` ...): readable,
    not assignable.

    The state changes only through the estimator's own methods (``update``, ``load_state_dict``), which
    validate it (finite, of the right shape, symmetric PSD covariances, non-negative counts) before
    committing it with :meth:`ReadOnlyFields._commit`. Assigning the attribute (``ibe.mean = ...``) or
    deleting it raises ``AttributeError``; an array is handed out as a read-only view, so writing into it
    (``ibe.mean[0] = ...``) raises ``ValueError``. Updates replace the arrays rather than writing into
    them, so the views are free, and only the named attributes pay for it (no ``__setattr__`` hook).
    """

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name
        self.key = "_ro_" + name

    def __get__(self, obj: Any, objtype: type | None = None) -> Any:
        if obj is None:
            return self
        try:
            return obj.__dict__[self.key]
        except KeyError:
            raise AttributeError(self.name) from None

    def __set__(self, obj: Any, value: Any) -> None:
        raise AttributeError(f"{self.name}: read-only; {type(obj).__name__}'s state changes only through update() "
                             f"and load_state_dict(), which validate it")

    def __delete__(self, obj: Any) -> None:
        self.__set__(obj, None)


class ReadOnlyFields:
    """Base class of the estimators: read-only public fields (see :class:`ReadOnlyField`).

    ``mean``, ``prior_mean``, ``prior_cov``, ``noise_cov`` and ``count`` are fields of every estimator
    that has them; a subclass names its own in ``_FIELDS`` (a :class:`ReadOnlyField` is made for each).
    """

    _FIELDS: tuple[str, ...] = ()
    _KIND: str
    #: A learning source (:class:`mixedrl.noise.NoiseSource`): the algorithms call ``update``.
    learns = True

    mean = ReadOnlyField()
    prior_mean = ReadOnlyField()
    prior_cov = ReadOnlyField()
    noise_cov = ReadOnlyField()
    count = ReadOnlyField()

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        for name in cls.__dict__.get("_FIELDS", ()):
            field = ReadOnlyField()
            field.__set_name__(cls, name)
            setattr(cls, name, field)

    def _commit(self, **fields: Any) -> None:
        """Set the read-only fields ``fields`` (validated by the caller); arrays are stored as read-only views."""
        cls = type(self)
        for name, value in fields.items():
            if not isinstance(getattr(cls, name, None), ReadOnlyField):
                raise AttributeError(f"{name}: not a read-only field of {cls.__name__}")
            if isinstance(value, np.ndarray):
                value = value.view()
                value.flags.writeable = False
            self.__dict__["_ro_" + name] = value

    def _state(self, *names: str) -> dict[str, Any]:
        """``{"kind": ..., name: value}`` of the fields ``names`` for ``state_dict`` (arrays copied)."""
        values = {name: getattr(self, name) for name in names}
        return {"kind": self._KIND, **{k: v.copy() if isinstance(v, np.ndarray) else v for k, v in values.items()}}

    @property
    def dim(self) -> int:
        """Dimension ``n`` of the noise."""
        return self.cov.shape[0]

    @property
    def cov(self) -> np.ndarray:
        """Noise covariance of the mixed model (eq. (20)), shape (n, n): the known ``K`` (Cases 1 and 3)."""
        return self.noise_cov


class GaussianNoiseEstimate(ReadOnlyFields):
    """Shared part of Cases 1 and 2: the mixed-model noise ``N(mean, cov)`` (eq. (20))."""

    #: One mean for every state (Cases 1 and 2).
    state_dependent = False

    mean_cov: np.ndarray

    def sample(self, n: int, generator: np.random.Generator | torch.Generator) -> np.ndarray | torch.Tensor:
        """Draw ``xi_hat ~ N(mean, cov)`` (eq. (20)); works for a singular ``cov``.

        Parameters
        ----------
        n : int
            Number of samples.
        generator : numpy.random.Generator or torch.Generator
            numpy gives an ndarray ``(n, d)``, torch a float64 tensor ``(n, d)``.

        Returns
        -------
        ndarray or Tensor, shape (n, d)

        Raises
        ------
        ValueError
            ``n`` not a positive int, or ``generator`` of another type.
        """
        return sample_gaussian(self.mean, self.cov, n, generator)

