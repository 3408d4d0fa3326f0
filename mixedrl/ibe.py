"""Iterative Bayesian estimator (IBE) of the additive model noise, eqs. (8)-(19).

The analytical model (eq. (8)) is ``x' = f(x, u) + xi``, ``xi ~ N(mu_M, K_M)`` a priori. Data triples
give residuals ``xi_j = x_{j+1} - f(x_j, u_j)`` (eq. (10), :func:`residuals`), and the IBE fuses the
designer's prior with them:

* Case 1, :class:`KnownCovarianceIBE` and :func:`map_mean_known_cov`: ``K`` known, eqs. (14)-(16).
* Case 2, :class:`UnknownCovarianceIBE` and :func:`map_mean_cov`: ``mu`` and ``K`` unknown, eqs. (17)-(18).
* Case 3, :class:`StateDependentIBE`: state-dependent mean ``mu = phi(x, u; w)``, eq. (19);
  :class:`LinearFeatureIBE`: the same for a ``phi`` linear in ``w`` (fixed features), solved in closed form.

How inverses are computed
-------------------------
The vehicle task has a rank-1 true noise covariance and a prior ``K_M`` with entries ``1e-20``
(EQUATIONS.md point 5), so ``K^{-1}`` may not exist and ``K_M^{-1}`` has entries ``1e20``. Cases 1 and 2
therefore use the *covariance (Kalman) form* of eq. (15),

.. math::
    \\hat\\mu = \\mu_M + \\mathcal{K}_M (N\\mathcal{K}_M + \\mathcal{K})^{-1}
    \\Big(\\sum_j \\xi_j - N\\mu_M\\Big), \\qquad
    \\Psi_N^{-1} = \\mathcal{K}_M (N\\mathcal{K}_M + \\mathcal{K})^{-1} \\mathcal{K},

which equals eq. (15) whenever both are defined and inverts only ``S = N K_M + K``. ``S`` is
Jacobi-equilibrated and Cholesky-factored; if it is numerically singular (squared pivot of the scaled
matrix ``< 1e-13``) the eigenvalue pseudo-inverse is used (:func:`mixedrl.gaussian.solve_psd`), which
keeps the prior exactly in directions where both ``K_M`` and ``K`` vanish. Only the literal eq. (18)
(``recursion="paper"``) needs ``K_hat^{-1}`` and ``K_M^{-1}``; it uses pseudo-inverses
(:func:`mixedrl.gaussian.pinv_psd`, on the support of :func:`mixedrl.expectation.support`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from mixedrl.checks import (
    as_batch,
    as_vector,
    check_covariance,
    check_finite,
    check_positive_int,
    check_unknown_keys,
)
from mixedrl.expectation import support
from mixedrl.gaussian import CHOLESKY_PIVOT_FLOOR, pinv_psd, psd_solver, sample_gaussian, solve_psd

__all__ = [
    "residuals",
    "map_mean_known_cov",
    "map_mean_cov",
    "KnownCovarianceIBE",
    "UnknownCovarianceIBE",
    "StateDependentIBE",
    "LinearFeatureIBE",
]

logger = logging.getLogger(__name__)

#: Relative stopping tolerance of the eq. (17) fixed-point iteration (see :func:`map_mean_cov`).
FIXED_POINT_RTOL = 1e-13
#: Iteration cap of the eq. (17) fixed-point iteration.
FIXED_POINT_MAX_ITER = 10_000


# ----------------------------------------------------------------------------------------------------
# eq. (10)
# ----------------------------------------------------------------------------------------------------
def residuals(
    f: Callable[[Any, Any], Any],
    x: np.ndarray | torch.Tensor,
    u: np.ndarray | torch.Tensor,
    x_next: np.ndarray | torch.Tensor,
) -> np.ndarray | torch.Tensor:
    """Implements eq. (10): the residual of a transition under the model's deterministic part.

    .. math:: \\xi_j^{\\mathcal{D}} = x_{j+1}^{\\mathcal{D}} - f(x_j^{\\mathcal{D}}, u_j^{\\mathcal{D}})

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

    Returns
    -------
    ndarray or Tensor, shape (..., n)
        Same kind as the inputs (numpy in, numpy out; torch in, torch out).

    Raises
    ------
    ValueError
        Inputs of mixed kinds, non-finite, of inconsistent shapes, or ``f`` returning a wrong shape.
    """
    is_torch = [isinstance(a, torch.Tensor) for a in (x, u, x_next)]
    if any(is_torch) and not all(is_torch):
        raise ValueError("x: x, u and x_next must all be numpy arrays or all torch tensors")
    if not all(is_torch):
        x = np.asarray(x, dtype=np.float64)
        u = np.asarray(u, dtype=np.float64)
        x_next = np.asarray(x_next, dtype=np.float64)
    for name, val in (("x", x), ("u", u), ("x_next", x_next)):
        if val.ndim < 1:
            raise ValueError(f"{name}: expected at least one dimension, got a scalar")
        check_finite(val, name)
    if tuple(x.shape) != tuple(x_next.shape):
        raise ValueError(f"x_next: expected the shape of x {tuple(x.shape)}, got {tuple(x_next.shape)}")
    if tuple(u.shape[:-1]) != tuple(x.shape[:-1]):
        raise ValueError(f"u: leading dimensions {tuple(u.shape[:-1])} differ from x's {tuple(x.shape[:-1])}")
    fx = f(x, u)
    if tuple(fx.shape) != tuple(x_next.shape):
        raise ValueError(f"f: returned shape {tuple(fx.shape)}, expected {tuple(x_next.shape)}")
    # xi_j = x_{j+1} - f(x_j, u_j)
    return x_next - fx


# ----------------------------------------------------------------------------------------------------
# shared numerics
# ----------------------------------------------------------------------------------------------------
def _fast_batch(xi: Any, n: int) -> np.ndarray:
    """Validate residuals as ``(N, n)`` float64 without copying float64 ndarrays (cheap single path)."""
    if type(xi) is np.ndarray and xi.dtype == np.float64:
        if xi.ndim == 1 and xi.shape[0] == n:
            batch = xi[None, :]
        elif xi.ndim == 2 and xi.shape[1] == n:
            batch = xi
        else:
            return as_batch(xi, "xi", n)  # raises with the shared message
        check_finite(batch, "xi")
        return batch
    return as_batch(xi, "xi", n)


def _sym(a: np.ndarray) -> np.ndarray:
    return 0.5 * (a + a.T)


def _posterior_known_cov(
    prior_mean: np.ndarray, prior_cov: np.ndarray, noise_cov: np.ndarray, count: int, total: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Covariance form of eqs. (15)/(16) from the sufficient statistics ``(k, m_k)``."""
    if count == 0:
        return prior_mean.copy(), prior_cov.copy()
    # S = k K_M + K   (Psi_k = K_M^-1 + k K^-1 = K_M^-1 S K^-1)
    s = count * prior_cov + noise_cov
    rhs = np.empty((prior_mean.shape[0], prior_mean.shape[0] + 1))
    rhs[:, 0] = total - count * prior_mean
    rhs[:, 1:] = noise_cov
    sol = solve_psd(s, rhs)
    # mu_hat_k = Psi_k^-1 (K_M^-1 mu_M + K^-1 m_k) = mu_M + K_M S^-1 (m_k - k mu_M)
    # Psi_k^-1 = K_M S^-1 K
    prod = prior_cov @ sol
    return prior_mean + prod[:, 0], _sym(prod[:, 1:])


def _simultaneous_diag(prior_cov: np.ndarray, noise_cov: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``G, G^{-1}, lam`` with ``K_M = G G^T`` and ``K = G diag(lam) G^T``, or ``None``.

    ``D = diag(K_M)^{-1/2}``, ``D K_M D = L L^T`` (Cholesky), ``L^{-1} D K D L^{-T} = V diag(lam) V^T``
    (eigh), ``G = D^{-1} L V``. Returns ``None`` when ``K_M`` is numerically singular (a zero diagonal or a
    squared pivot of ``D K_M D`` below ``CHOLESKY_PIVOT_FLOOR``); callers then use :func:`solve_psd`.
    """
    diag = prior_cov.diagonal()
    if diag.min() <= 0.0:
        return None
    inv_d = 1.0 / np.sqrt(diag)
    try:
        chol = np.linalg.cholesky(prior_cov * inv_d * inv_d[:, None])
    except np.linalg.LinAlgError:
        return None
    if chol.diagonal().min() ** 2 < CHOLESKY_PIVOT_FLOOR:
        return None
    chol_inv = np.linalg.solve(chol, np.eye(chol.shape[0]))
    white = chol_inv @ (noise_cov * inv_d * inv_d[:, None]) @ chol_inv.T
    lam, vec = np.linalg.eigh(_sym(white))
    lam = np.clip(lam, 0.0, None)
    g = (chol @ vec) / inv_d[:, None]
    g_inv = (vec.T @ chol_inv) * inv_d
    return g, g_inv, lam


def _solve_eq17_stats(
    prior_mean: np.ndarray,
    prior_cov: np.ndarray,
    count: int,
    xbar: np.ndarray,
    scatter: np.ndarray,
    max_iter: int,
    rtol: float,
    prior_scale: float | None = None,
) -> tuple[np.ndarray, np.ndarray, int, bool]:
    """Fixed point of eq. (17) from ``(N, xbar, sum (xi - xbar)(xi - xbar)^T)``.

    Uses ``K(mu) = C + d d^T`` with ``C = scatter / N`` and ``d = xbar - mu``, and the rank-1
    (Sherman-Morrison) update of the Cholesky-solved ``S_0 = N K_M + C``.
    """
    c = scatter / count
    r = xbar - prior_mean
    scale = _fp_scale(prior_mean, prior_cov, xbar, c, prior_scale)
    solve = psd_solver(count * prior_cov + c)  # S_0 = N K_M + C, factored once per update
    a = solve(r)
    nkm = count * prior_cov
    base = prior_mean + nkm @ a
    # canonical start: mu_0 = xbar, i.e. d = 0 and K_0 = C (maximum-likelihood covariance)
    mu = xbar
    d = None
    converged = False
    it = 0
    for it in range(1, max_iter + 1):
        # mu_hat = (K_M^-1 + N K_hat^-1)^-1 (K_M^-1 mu_M + K_hat^-1 sum xi) = mu_M + N K_M S^-1 (xbar - mu_M),
        # S = S_0 + d d^T  =>  S^-1 r = a - b (d^T a) / (1 + d^T b),  b = S_0^-1 d   (Sherman-Morrison)
        if d is None:
            mu_new = base
        else:
            b = solve(d)
            mu_new = base - (nkm @ b) * (float(d @ a) / (1.0 + float(d @ b)))
        step = float(np.abs(mu_new - mu).max())
        mu = mu_new
        # K_hat = 1/N sum (xi - mu_hat)(xi - mu_hat)^T = C + (xbar - mu_hat)(xbar - mu_hat)^T
        d = xbar - mu
        if step <= rtol * scale:
            converged = True
            break
    k_hat = c + np.outer(d, d)
    return mu, k_hat, it, converged


def _mean_cov_case2(prior_cov: np.ndarray, count: int, k_hat: np.ndarray) -> np.ndarray:
    """``Psi^{-1} = (K_M^-1 + N K_hat^-1)^-1 = K_M (N K_M + K_hat)^-1 K_hat`` (covariance form)."""
    if count == 0:
        return prior_cov.copy()
    return _sym(prior_cov @ solve_psd(count * prior_cov + k_hat, k_hat))


def _prior_scale(prior_mean: np.ndarray, prior_cov: np.ndarray) -> float:
    """The prior's part of the fixed-point tolerance scale (constant for an estimator)."""
    return float(np.abs(prior_mean).max()) + math.sqrt(float(prior_cov.diagonal().max()))


def _fp_scale(
    prior_mean: np.ndarray, prior_cov: np.ndarray, xbar: np.ndarray, c: np.ndarray, prior_scale: float | None = None
) -> float:
    if prior_scale is None:
        prior_scale = _prior_scale(prior_mean, prior_cov)
    scale = float(np.abs(xbar).max()) + math.sqrt(max(float(c.diagonal().max()), 0.0)) + prior_scale
    return scale if scale > 0.0 else 1.0


# ----------------------------------------------------------------------------------------------------
# batch references: eq. (15) and eq. (17)
# ----------------------------------------------------------------------------------------------------
def map_mean_known_cov(prior_mean: Any, prior_cov: Any, noise_cov: Any, xi: Any) -> np.ndarray:
    """Implements eq. (15): the MAP mean of Case 1 (noise covariance known) from a batch.

    .. math::
        \\hat\\mu = \\left(\\mathcal{K}_M^{-1} + N\\mathcal{K}^{-1}\\right)^{-1}
        \\left(\\mathcal{K}_M^{-1}\\mu_M + \\mathcal{K}^{-1}\\sum_{j=1}^N \\xi_j\\right)

    Parameters
    ----------
    prior_mean : array_like, shape (n,)
        ``mu_M``.
    prior_cov : array_like, shape (n, n)
        ``K_M``, symmetric PSD (may be singular).
    noise_cov : array_like, shape (n, n)
        ``K``, symmetric PSD (may be singular).
    xi : array_like, shape (N, n) or (n,)
        Residuals (eq. (10)). ``N = 0`` returns ``mu_M``.

    Returns
    -------
    ndarray, shape (n,)

    Raises
    ------
    ValueError
        Wrong shapes, NaN/inf, covariance not symmetric PSD (the message names the argument).

    Notes
    -----
    Computed in the equivalent covariance form
    ``mu_M + K_M (N K_M + K)^{-1} (sum xi - N mu_M)`` (module docstring), which needs no inverse of
    ``K`` or ``K_M``; ``N K_M + K`` is solved by :func:`mixedrl.gaussian.solve_psd`.
    """
    mu_m = as_vector(prior_mean, "prior_mean")
    n = mu_m.shape[0]
    k_m = check_covariance(prior_cov, "prior_cov", n)
    k = check_covariance(noise_cov, "noise_cov", n)
    batch = as_batch(xi, "xi", n)
    mean, _ = _posterior_known_cov(mu_m, k_m, k, batch.shape[0], batch.sum(axis=0))
    return mean


def map_mean_cov(
    prior_mean: Any,
    prior_cov: Any,
    xi: Any,
    max_iter: int = FIXED_POINT_MAX_ITER,
    rtol: float = FIXED_POINT_RTOL,
) -> tuple[np.ndarray, np.ndarray]:
    """Implements eq. (17): the Case 2 estimate of mean and covariance, solved as a fixed point.

    .. math::
        \\hat\\mu = \\left(\\mathcal{K}_M^{-1} + N\\hat{\\mathcal{K}}^{-1}\\right)^{-1}
        \\left(\\mathcal{K}_M^{-1}\\mu_M + \\hat{\\mathcal{K}}^{-1}\\sum_j \\xi_j\\right), \\qquad
        \\hat{\\mathcal{K}} = \\frac1N\\sum_j (\\xi_j - \\hat\\mu)(\\xi_j - \\hat\\mu)^T

    Parameters
    ----------
    prior_mean : array_like, shape (n,)
    prior_cov : array_like, shape (n, n)
        Symmetric PSD.
    xi : array_like, shape (N, n) or (n,)
        Residuals, ``N >= 1``.
    max_iter : int
        Iteration cap (a ``logging`` warning is emitted if it is reached).
    rtol : float
        Stop when ``max|mu_{i+1} - mu_i| <= rtol * scale``, ``scale = max|xbar| + max|mu_M|
        + sqrt(max diag C) + sqrt(max diag K_M)``.

    Returns
    -------
    mean : ndarray, shape (n,)
    cov : ndarray, shape (n, n)
        ``K_hat``, symmetric PSD (singular when the data are, e.g. rank 1 on the vehicle).

    Raises
    ------
    ValueError
        Wrong shapes, NaN/inf, covariance not symmetric PSD, empty ``xi``.

    Notes
    -----
    * Eq. (17) couples ``mu_hat`` and ``K_hat`` (EQUATIONS.md point 2). It is solved by alternating its
      two lines (block-coordinate descent on the negative log posterior, so the objective never
      increases), **starting from the data**: ``mu_0 = xbar``, ``K_0 = C`` (the maximum-likelihood
      estimate). When a confident prior disagrees with few data, eq. (17) can have several fixed points
      (the cubic ``(e - d)(c + d^2) = N k d`` in the scalar case); the start from the data selects the
      one closest to the data, and the recursive :class:`UnknownCovarianceIBE` uses the same start, so
      both agree after every update.
    * The mean line is evaluated in covariance form ``mu_M + N K_M (N K_M + K_hat)^{-1} (xbar - mu_M)``
      (no inverse of the possibly singular ``K_hat``). This batch reference recomputes ``K_hat`` from the
      raw residuals at every iteration (it shares no statistics code with the recursion).
    * With ``N = 1`` the maximum-likelihood covariance is 0 and eq. (17) gives ``mu_hat = xi_1``,
      ``K_hat = 0`` (the degenerate but literal answer).
    """
    mu_m = as_vector(prior_mean, "prior_mean")
    n = mu_m.shape[0]
    k_m = check_covariance(prior_cov, "prior_cov", n)
    batch = as_batch(xi, "xi", n)
    if batch.shape[0] == 0:
        raise ValueError("xi: eq. (17) needs at least one residual")
    max_iter = check_positive_int(max_iter, "max_iter")
    count = batch.shape[0]
    total = batch.sum(axis=0)
    xbar = total / count
    centred = batch - xbar
    c = centred.T @ centred / count
    scale = _fp_scale(mu_m, k_m, xbar, c)
    mu = xbar.copy()
    k_hat = c
    for _ in range(max_iter):
        # mu_hat = (K_M^-1 + N K_hat^-1)^-1 (K_M^-1 mu_M + K_hat^-1 sum xi)   [covariance form]
        mu_new = mu_m + k_m @ solve_psd(count * k_m + k_hat, total - count * mu_m)
        step = float(np.max(np.abs(mu_new - mu)))
        mu = mu_new
        # K_hat = 1/N sum_j (xi_j - mu_hat)(xi_j - mu_hat)^T
        dev = batch - mu
        k_hat = _sym(dev.T @ dev / count)
        if step <= rtol * scale:
            break
    else:
        logger.warning("map_mean_cov: eq. (17) fixed point not converged after %d iterations", max_iter)
    return mu, k_hat


# ----------------------------------------------------------------------------------------------------
# state-dict helpers
# ----------------------------------------------------------------------------------------------------
def _check_state(state: Any, spec: dict[str, Any], kind: str) -> dict[str, Any]:
    """Validate a state dict against ``spec`` (key -> shape tuple | 'int' | 'float' | 'str')."""
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
            if isinstance(val, bool) or not isinstance(val, (int, np.integer)) or val < 0:
                raise ValueError(f"state_dict: {key} must be a non-negative int, got {val!r}")
            out[key] = int(val)
        elif want == "float":
            if isinstance(val, bool) or not isinstance(val, (int, float, np.floating)) or not math.isfinite(val):
                raise ValueError(f"state_dict: {key} must be a finite float, got {val!r}")
            out[key] = float(val)
        else:
            try:
                arr = np.array(val, dtype=np.float64)
            except (TypeError, ValueError):
                raise ValueError(f"state_dict: {key} is not a float array") from None
            if arr.shape != want:
                raise ValueError(f"state_dict: {key} has shape {arr.shape}, expected {want}")
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"state_dict: {key} contains NaN or inf")
            out[key] = arr
    return out


# ----------------------------------------------------------------------------------------------------
# Case 1
# ----------------------------------------------------------------------------------------------------
class _ReadOnlyArray:
    """Descriptor that stores a public array (``mean``, ``cov``, ...) as a read-only view.

    Updates replace these arrays rather than writing into them, so handing out a read-only view is
    free and guarantees that a caller who writes into ``est.mean`` gets an error instead of silently
    changing the estimator's state. Only the named attributes pay for it (no ``__setattr__`` hook).
    """

    def __set_name__(self, owner: type, name: str) -> None:
        self.key = "_ro_" + name

    def __get__(self, obj: Any, objtype: type | None = None) -> Any:
        if obj is None:
            return self
        try:
            return obj.__dict__[self.key]
        except KeyError:
            raise AttributeError(self.key[4:]) from None

    def __set__(self, obj: Any, value: Any) -> None:
        if isinstance(value, np.ndarray):
            value = value.view()
            value.flags.writeable = False
        obj.__dict__[self.key] = value


class _ReadOnlyArrays:
    """Base class giving the estimators read-only public arrays (see :class:`_ReadOnlyArray`)."""

    mean = _ReadOnlyArray()
    prior_mean = _ReadOnlyArray()
    prior_cov = _ReadOnlyArray()
    noise_cov = _ReadOnlyArray()


class _GaussianNoiseEstimate(_ReadOnlyArrays):
    """Shared part of Cases 1 and 2: the mixed-model noise ``N(mean, cov)`` (eq. (20))."""

    #: A learning source (:class:`mixedrl.noise.NoiseSource`): the algorithms call ``update``.
    learns = True
    #: One mean for every state (Cases 1 and 2).
    state_dependent = False

    mean: np.ndarray
    cov: np.ndarray
    mean_cov: np.ndarray
    count: int

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


class KnownCovarianceIBE(_GaussianNoiseEstimate):
    """Implements eq. (16): Case 1 recursive IBE, noise covariance ``K`` known.

    .. math::
        \\Psi_k = \\Psi_{k-1} + \\mathcal{K}^{-1}, \\quad m_k = m_{k-1} + \\xi_k, \\quad
        \\hat\\mu_k = \\Psi_k^{-1}\\left(\\mathcal{K}_M^{-1}\\mu_M + \\mathcal{K}^{-1} m_k\\right)

    Parameters
    ----------
    prior_mean : array_like, shape (n,)
        ``mu_M`` (eq. (8)).
    prior_cov : array_like, shape (n, n)
        ``K_M``: prior covariance of the mean, symmetric PSD (may be singular).
    noise_cov : array_like, shape (n, n)
        ``K``: the known noise covariance, symmetric PSD (may be singular, e.g. rank 1).

    Attributes
    ----------
    mean : ndarray, shape (n,)
        ``mu_hat_k`` (``mu_M`` before any data).
    mean_cov : ndarray, shape (n, n)
        Posterior covariance of the mean ``Psi_k^{-1}`` (``K_M`` before any data).
    count : int
        ``k``, number of residuals seen.

    Raises
    ------
    ValueError
        Wrong shapes, NaN/inf, covariance not symmetric PSD (message names the argument).

    Notes
    -----
    ``Psi_k = K_M^{-1} + k K^{-1}`` depends on ``k`` only, so the state is ``(k, m_k)`` as in eq. (16),
    and ``mu_hat_k`` and ``Psi_k^{-1}`` are evaluated in covariance form (module docstring), which needs
    neither ``K^{-1}`` nor ``K_M^{-1}``. Any split of the data into batches gives eq. (15) up to the
    rounding of ``m_k``. Because ``K_M`` and ``K`` are fixed, they are diagonalised simultaneously once
    (``K_M = G G^T``, ``K = G diag(lambda) G^T``, from a Cholesky factor of the Jacobi-scaled ``K_M`` and
    one ``eigh``), so that ``K_M (k K_M + K)^{-1} = G (k I + diag(lambda))^{-1} G^{-1}`` and an update costs
    three ``n x n`` products and no factorisation. If ``K_M`` is numerically singular (squared Cholesky
    pivot of the scaled ``K_M`` below ``1e-13``) each update instead solves ``k K_M + K`` with
    :func:`mixedrl.gaussian.solve_psd` (pseudo-inverse on its null space: there the prior is kept).
    """

    _KIND = "KnownCovarianceIBE"

    mean_cov = _ReadOnlyArray()

    def __init__(self, prior_mean: Any, prior_cov: Any, noise_cov: Any) -> None:
        self.prior_mean = as_vector(prior_mean, "prior_mean")
        n = self.prior_mean.shape[0]
        self.prior_cov = check_covariance(prior_cov, "prior_cov", n)
        self.noise_cov = check_covariance(noise_cov, "noise_cov", n)
        self.count = 0
        self.total = np.zeros(n)
        self.mean, self.mean_cov = self.prior_mean.copy(), self.prior_cov.copy()
        self._diag = _simultaneous_diag(self.prior_cov, self.noise_cov)

    def _posterior(self, count: int, total: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(mu_hat_k, Psi_k^{-1})`` from ``(k, m_k)``; simultaneous diagonalisation when available."""
        if self._diag is None or count == 0:
            return _posterior_known_cov(self.prior_mean, self.prior_cov, self.noise_cov, count, total)
        g, g_inv, lam = self._diag
        # K_M (k K_M + K)^-1 = G (k I + Lambda)^-1 G^-1
        w = (g_inv @ (total - count * self.prior_mean)) / (count + lam)
        # mu_hat_k = mu_M + K_M (k K_M + K)^-1 (m_k - k mu_M)
        mean = self.prior_mean + g @ w
        # Psi_k^-1 = K_M (k K_M + K)^-1 K = G diag(lam / (k + lam)) G^T
        mean_cov = (g * (lam / (count + lam))) @ g.T
        return mean, mean_cov

    @property
    def dim(self) -> int:
        """Dimension ``n`` of the noise."""
        return self.prior_mean.shape[0]

    @property
    def cov(self) -> np.ndarray:
        """Noise covariance used by the mixed model (eq. (20)): here the known ``K``, shape (n, n)."""
        return self.noise_cov

    def update(self, xi: Any) -> KnownCovarianceIBE:
        """Implements eq. (16) for one residual ``(n,)`` or a batch ``(N, n)``; returns ``self``.

        Raises
        ------
        ValueError
            ``xi`` of wrong shape or with NaN/inf; the estimator is then left unchanged.
        """
        batch = _fast_batch(xi, self.prior_mean.shape[0])
        nb = batch.shape[0]
        if nb == 0:
            return self
        # m_k = m_{k-1} + xi_k   (summed over the batch)
        bsum = batch[0] if nb == 1 else np.ones(nb) @ batch
        total = self.total + bsum
        count = self.count + nb
        mean, mean_cov = self._posterior(count, total)
        self.total, self.count, self.mean, self.mean_cov = total, count, mean, mean_cov
        return self

    def state_dict(self) -> dict[str, Any]:
        """Return a copy of the full state (plain floats, ints and ndarrays)."""
        return {
            "kind": self._KIND,
            "prior_mean": self.prior_mean.copy(),
            "prior_cov": self.prior_cov.copy(),
            "noise_cov": self.noise_cov.copy(),
            "count": self.count,
            "total": self.total.copy(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> KnownCovarianceIBE:
        """Restore a state from :meth:`state_dict`; validate everything first.

        Raises
        ------
        ValueError
            Not a dict, unknown/missing keys, other kind, shapes of another dimension, NaN/inf,
            covariance not symmetric PSD. The estimator is then left unchanged.
        """
        n = self.dim
        spec = {"kind": "str", "prior_mean": (n,), "prior_cov": (n, n), "noise_cov": (n, n), "count": "int", "total": (n,)}
        st = _check_state(state, spec, self._KIND)
        prior_cov = check_covariance(st["prior_cov"], "state_dict: prior_cov", n)
        noise_cov = check_covariance(st["noise_cov"], "state_dict: noise_cov", n)
        new = KnownCovarianceIBE(st["prior_mean"], prior_cov, noise_cov)
        new.mean, new.mean_cov = new._posterior(st["count"], st["total"])
        new.count, new.total = st["count"], st["total"]
        self.__dict__.update(new.__dict__)
        return self


# ----------------------------------------------------------------------------------------------------
# Case 2
# ----------------------------------------------------------------------------------------------------
class UnknownCovarianceIBE(_GaussianNoiseEstimate):
    """Implements eqs. (17)-(18): Case 2 IBE, mean and covariance both unknown.

    .. math::
        \\hat\\mu_k = \\left(\\mathcal{K}_M^{-1} + k\\hat{\\mathcal{K}}_k^{-1}\\right)^{-1}
        \\left(\\mathcal{K}_M^{-1}\\mu_M + \\hat{\\mathcal{K}}_k^{-1} m_k\\right), \\qquad
        \\hat{\\mathcal{K}}_k = \\frac1k\\sum_{j\\le k}(\\xi_j - \\hat\\mu_k)(\\xi_j - \\hat\\mu_k)^T

    Parameters
    ----------
    prior_mean : array_like, shape (n,)
        ``mu_M``.
    prior_cov : array_like, shape (n, n)
        ``K_M``, symmetric PSD.
    recursion : {"exact", "paper"}
        ``"exact"`` (default): the exact recursive form of eq. (17). ``"paper"``: eq. (18) literally.
    max_iter : int
        Iteration cap of the eq. (17) fixed point (``"exact"`` only).

    Attributes
    ----------
    mean : ndarray, shape (n,)
        ``mu_hat_k``.
    cov : ndarray, shape (n, n)
        ``K_hat_k`` (``K_hat_0 = K_M`` as in Algorithm 1).
    count : int
        ``k``.
    iterations : int
        Fixed-point iterations of the last update (``"exact"``).
    converged : bool
        Whether the last fixed-point solve met its tolerance (``"exact"``).

    Raises
    ------
    ValueError
        Wrong shapes, NaN/inf, covariance not symmetric PSD, unknown ``recursion``.

    Notes
    -----
    * ``"exact"`` keeps the sufficient statistics ``N``, ``xbar`` and the centred scatter
      ``sum (xi - xbar)(xi - xbar)^T`` (merged with Chan's parallel formula instead of raw
      ``sum xi xi^T``, which loses ``(|mean|/std)^2`` digits to cancellation), and re-solves the eq. (17)
      fixed point after every update with the same start as :func:`map_mean_cov` (the data:
      ``mu_0 = xbar``), so that it equals the batch eq. (17) on all data so far even where eq. (17) has
      several fixed points. It is *not* warm-started from the previous estimate: a warm start would
      follow whichever branch it was on (hysteresis) and could differ from the batch answer. Each
      iteration costs one triangular solve (rank-1 Sherman-Morrison update of the Cholesky-factored
      ``N K_M + C``). Departure from the paper: eq. (18) is not used (EQUATIONS.md point 3).
    * ``"paper"`` is eq. (18) literally, initialised as Algorithm 1 (``mu_hat_0 = mu_M``,
      ``K_hat_0 = K_M``, ``Psi_0 = K_M^{-1}``; EQUATIONS.md point 4: this uses the prior covariance of
      the mean as a noise covariance). After one sample ``K_hat_1`` has rank 1, so ``K_hat_{k-1}^{-1}``
      and ``K_M^{-1}`` are **pseudo-inverses** (eigenvalues below ``SUPPORT_RTOL`` times the largest are
      dropped, :data:`mixedrl.expectation.SUPPORT_RTOL`; i.e. directions without observed spread carry no data precision), and ``Psi_k`` is
      solved with :func:`mixedrl.gaussian.solve_psd`. Batches are processed one residual at a time.
    """

    _KIND = "UnknownCovarianceIBE"
    _RECURSIONS = ("exact", "paper")

    cov = _ReadOnlyArray()
    _mean_cov = _ReadOnlyArray()

    def __init__(self, prior_mean: Any, prior_cov: Any, recursion: str = "exact", max_iter: int = FIXED_POINT_MAX_ITER) -> None:
        self.prior_mean = as_vector(prior_mean, "prior_mean")
        n = self.prior_mean.shape[0]
        self.prior_cov = check_covariance(prior_cov, "prior_cov", n)
        if recursion not in self._RECURSIONS:
            raise ValueError(f"recursion: expected one of {self._RECURSIONS}, got {recursion!r}")
        self.recursion = recursion
        self.max_iter = check_positive_int(max_iter, "max_iter")
        self._reset()

    def _reset(self) -> None:
        n = self.dim
        self.count = 0
        self.mean = self.prior_mean.copy()
        self.cov = self.prior_cov.copy()  # K_hat_0 = K_M (Algorithm 1)
        self._prior_scale: float | None = None  # cached part of the fixed-point tolerance
        self._mean_cov: np.ndarray | None = self.prior_cov.copy()
        self.iterations = 0
        self.converged = True
        # exact: sufficient statistics
        self.data_mean = np.zeros(n)
        self.scatter = np.zeros((n, n))
        # paper: eq. (18) state
        self._prior_prec = pinv_psd(self.prior_cov)
        self.psi = self._prior_prec.copy()
        self.total = np.zeros(n)

    @property
    def dim(self) -> int:
        """Dimension ``n`` of the noise."""
        return self.prior_mean.shape[0]

    @property
    def mean_cov(self) -> np.ndarray:
        """``Psi_k^{-1}``, posterior covariance of the mean, shape (n, n).

        In ``"exact"`` mode it is computed on first access after an update (covariance form
        ``K_M (N K_M + K_hat)^{-1} K_hat``), so updates do not pay for it.
        """
        if self._mean_cov is None:
            self._mean_cov = _mean_cov_case2(self.prior_cov, self.count, self.cov)
        return self._mean_cov

    def update(self, xi: Any) -> UnknownCovarianceIBE:
        """Add one residual ``(n,)`` or a batch ``(N, n)``; returns ``self``.

        Raises
        ------
        ValueError
            ``xi`` of wrong shape or with NaN/inf; the estimator is then left unchanged.
        """
        batch = _fast_batch(xi, self.dim)
        if batch.shape[0] == 0:
            return self
        if self.recursion == "exact":
            self._update_exact(batch)
        else:
            self._update_paper(batch)
        return self

    def _update_exact(self, batch: np.ndarray) -> None:
        nb = batch.shape[0]
        if nb == 1:
            bmean = batch[0]
            bscatter = None
        else:
            shift = batch[0]
            centred = batch - shift
            ysum = np.ones(nb) @ centred
            ybar = ysum / nb
            bmean = shift + ybar
            bscatter = centred.T @ centred - nb * np.outer(ybar, ybar)
        # Chan et al. merge of (N_a, mean_a, M2_a) and (N_b, mean_b, M2_b)
        na = self.count
        count = na + nb
        delta = bmean - self.data_mean
        data_mean = self.data_mean + delta * (nb / count)
        scatter = self.scatter + np.outer(delta, delta) * (na * nb / count)
        if bscatter is not None:
            # (outer(delta, delta) is exactly symmetric, so single updates keep symmetry bitwise)
            scatter = _sym(scatter + bscatter)
        if self._prior_scale is None:
            self._prior_scale = _prior_scale(self.prior_mean, self.prior_cov)
        mean, cov, it, ok = _solve_eq17_stats(
            self.prior_mean, self.prior_cov, count, data_mean, scatter, self.max_iter, FIXED_POINT_RTOL, self._prior_scale
        )
        if not ok:
            logger.warning("UnknownCovarianceIBE: eq. (17) fixed point not converged after %d iterations", it)
        self.count, self.data_mean, self.scatter = count, data_mean, scatter
        self.mean, self.cov, self._mean_cov, self.iterations, self.converged = mean, cov, None, it, ok

    def _update_paper(self, batch: np.ndarray) -> None:
        psi, total, mean, cov, k = self.psi, self.total, self.mean, self.cov, self.count
        prior_term = self._prior_prec @ self.prior_mean
        for xi_k in batch:
            k += 1
            k_prev_inv = pinv_psd(cov)  # K_hat_{k-1}^+  (pseudo-inverse, see Notes)
            # Psi_k = Psi_{k-1} + K_hat_{k-1}^-1
            psi = psi + k_prev_inv
            # m_k = m_{k-1} + xi_k
            total = total + xi_k
            # mu_hat_k = Psi_k^-1 (K_M^-1 mu_M + K_hat_{k-1}^-1 m_k)
            new_mean = solve_psd(psi, prior_term + k_prev_inv @ total)
            # K_hat_k = ((k-1) K_hat_{k-1} + (xi_k - mu_hat_{k-1})(xi_k - mu_hat_{k-1})^T) / k
            dev = xi_k - mean
            cov = _sym(((k - 1) * cov + np.outer(dev, dev)) / k)
            mean = new_mean
        mean_cov = _sym(solve_psd(psi, np.eye(self.dim)))
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(cov)) and np.all(np.isfinite(psi))):
            raise ValueError("xi: eq. (18) produced non-finite values; update rejected")
        self.psi, self.total, self.mean, self.cov, self.count, self._mean_cov = psi, total, mean, cov, k, mean_cov

    def state_dict(self) -> dict[str, Any]:
        """Return a copy of the full state (plain floats, ints, strs and ndarrays)."""
        st: dict[str, Any] = {
            "kind": self._KIND,
            "recursion": self.recursion,
            "max_iter": self.max_iter,
            "prior_mean": self.prior_mean.copy(),
            "prior_cov": self.prior_cov.copy(),
            "count": self.count,
        }
        if self.recursion == "exact":
            st["data_mean"] = self.data_mean.copy()
            st["scatter"] = self.scatter.copy()
        else:
            st.update(psi=self.psi.copy(), total=self.total.copy(), mean=self.mean.copy(), cov=self.cov.copy())
        return st

    def load_state_dict(self, state: dict[str, Any]) -> UnknownCovarianceIBE:
        """Restore a state from :meth:`state_dict`; validate everything first.

        Raises
        ------
        ValueError
            Not a dict, unknown/missing keys, other kind or recursion, wrong shapes, NaN/inf,
            covariance not symmetric PSD. The estimator is then left unchanged.
        """
        n = self.dim
        if not isinstance(state, dict):
            raise ValueError(f"state_dict: expected a dict, got {type(state).__name__}")
        if state.get("recursion") not in self._RECURSIONS:
            raise ValueError(f"state_dict: recursion must be one of {self._RECURSIONS}, got {state.get('recursion')!r}")
        spec: dict[str, Any] = {
            "kind": "str", "recursion": "str", "max_iter": "int", "prior_mean": (n,), "prior_cov": (n, n), "count": "int",
        }
        if state["recursion"] == "exact":
            spec.update(data_mean=(n,), scatter=(n, n))
        else:
            spec.update(psi=(n, n), total=(n,), mean=(n,), cov=(n, n))
        st = _check_state(state, spec, self._KIND)
        if st["max_iter"] < 1:
            raise ValueError("state_dict: max_iter must be >= 1")
        prior_cov = check_covariance(st["prior_cov"], "state_dict: prior_cov", n)
        new = UnknownCovarianceIBE.__new__(UnknownCovarianceIBE)
        new.prior_mean, new.prior_cov, new.recursion, new.max_iter = st["prior_mean"], prior_cov, st["recursion"], st["max_iter"]
        new._reset()
        new.count = st["count"]
        if new.recursion == "exact":
            new.data_mean = st["data_mean"]
            new.scatter = check_covariance(st["scatter"], "state_dict: scatter", n)
            if new.count == 0 and (np.any(new.data_mean != 0) or np.any(new.scatter != 0)):
                raise ValueError("state_dict: count is 0 but the statistics are not empty")
            if new.count > 0:
                (new.mean, new.cov, new.iterations, new.converged) = _solve_eq17_stats(
                    new.prior_mean, new.prior_cov, new.count, new.data_mean, new.scatter, new.max_iter, FIXED_POINT_RTOL
                )
                new._mean_cov = None
        else:
            new.psi = check_covariance(st["psi"], "state_dict: psi", n)
            new.cov = check_covariance(st["cov"], "state_dict: cov", n)
            new.total, new.mean = st["total"], st["mean"]
            new._mean_cov = _sym(solve_psd(new.psi, np.eye(n)))
        self.__dict__.update(new.__dict__)
        return self


# ----------------------------------------------------------------------------------------------------
# Case 3
# ----------------------------------------------------------------------------------------------------
class StateDependentIBE(_ReadOnlyArrays):
    """Implements eq. (19): Case 3 IBE with a state-dependent mean ``mu = phi(x, u; w)``.

    .. math::
        \\mathcal{L}(w) = \\frac12\\sum_{j=1}^N \\big(\\xi_j - \\phi(x_j, u_j; w)\\big)^T \\mathcal{K}^{+}
        \\big(\\xi_j - \\phi(x_j, u_j; w)\\big) + \\frac{1}{2\\sigma_w^2}\\lVert w - w_0\\rVert^2 + C

    the negative log posterior (EQUATIONS.md point 1) with Gaussian prior ``w ~ N(w_0, sigma_w^2 I)``.

    Parameters
    ----------
    phi : torch.nn.Module
        ``forward(x, u)`` maps ``(B, n_x)`` and ``(B, n_u)`` tensors to ``(B, n)``. Its parameters at
        construction are the prior mean ``w_0``; they are converted to float64.
    noise_cov : array_like, shape (n, n)
        Known noise covariance ``K`` (symmetric PSD).
    state_dim : int
        ``n_x``.
    action_dim : int
        ``n_u``.
    prior_std : float
        ``sigma_w > 0``.
    max_iter : int
        L-BFGS iterations per :meth:`update` (full batch, strong-Wolfe line search; deterministic).

    Attributes
    ----------
    count : int
        Number of residuals seen.

    Raises
    ------
    ValueError
        Bad covariance, non-positive ``prior_std``/``max_iter``/dimensions, ``phi`` not a module.

    Notes
    -----
    * ``K^{+}`` is the pseudo-inverse on the support of ``K`` (:func:`mixedrl.expectation.support`): directions without
      noise do not enter the likelihood, so ``phi`` there is set by the prior on ``w`` alone. The paper
      gives no treatment; a full-rank ``K`` is the intended use.
    * Every update refits on all data seen so far (warm-started from the current ``w``). The fit is
      deterministic (no randomness); the user's module initialisation should be seeded.
    * The paper's Case 3 leaves ``K`` unspecified; here it is known (as in Case 1).
    """

    _KIND = "StateDependentIBE"
    #: A learning source (:class:`mixedrl.noise.StateDependentNoiseSource`).
    learns = True
    #: The mean is ``mean_at(x, u)``: Algorithm 2 plans with per-state nodes.
    state_dependent = True

    def __init__(
        self,
        phi: torch.nn.Module,
        noise_cov: Any,
        state_dim: int,
        action_dim: int,
        prior_std: float = 1.0,
        max_iter: int = 200,
    ) -> None:
        if not isinstance(phi, torch.nn.Module):
            raise ValueError(f"phi: expected a torch.nn.Module, got {type(phi).__name__}")
        self.noise_cov = check_covariance(noise_cov, "noise_cov")
        self.state_dim = check_positive_int(state_dim, "state_dim")
        self.action_dim = check_positive_int(action_dim, "action_dim")
        if isinstance(prior_std, bool) or not isinstance(prior_std, (int, float)) or not (math.isfinite(prior_std) and prior_std > 0):
            raise ValueError(f"prior_std: expected a finite positive float, got {prior_std!r}")
        self.prior_std = float(prior_std)
        self.max_iter = check_positive_int(max_iter, "max_iter")
        self.phi = phi.double()
        self._prior_w = [p.detach().clone() for p in self.phi.parameters()]
        lam, vec = support(self.noise_cov)
        # whitening W with W W^T = K^+ : r^T K^+ r = |r W|^2
        self._whiten = torch.as_tensor(vec / np.sqrt(lam))
        self.count = 0
        self._x = torch.zeros((0, self.state_dim), dtype=torch.float64)
        self._u = torch.zeros((0, self.action_dim), dtype=torch.float64)
        self._xi = torch.zeros((0, self.dim), dtype=torch.float64)
        with torch.no_grad():
            out = self.phi(torch.zeros((1, self.state_dim), dtype=torch.float64), torch.zeros((1, self.action_dim), dtype=torch.float64))
        if tuple(out.shape) != (1, self.dim):
            raise ValueError(f"phi: returned shape {tuple(out.shape)} for one input, expected (1, {self.dim})")

    @property
    def dim(self) -> int:
        """Dimension ``n`` of the noise."""
        return self.noise_cov.shape[0]

    @property
    def cov(self) -> np.ndarray:
        """Noise covariance ``K`` of the mixed model, shape (n, n)."""
        return self.noise_cov

    def negative_log_posterior(self) -> torch.Tensor:
        """Implements eq. (19) as a negative log posterior on the data seen so far (constant dropped)."""
        pred = self.phi(self._x, self._u)
        # (xi_j - phi(x_j, u_j; w))^T K^+ (xi_j - phi(x_j, u_j; w))
        white = (self._xi - pred) @ self._whiten
        nll = 0.5 * torch.sum(white * white)
        # -log p(w) = |w - w_0|^2 / (2 sigma_w^2)
        prior = sum(torch.sum((p - p0) ** 2) for p, p0 in zip(self.phi.parameters(), self._prior_w))
        return nll + 0.5 * prior / self.prior_std**2

    def _as_inputs(self, x: Any, u: Any, xi: Any | None) -> tuple[torch.Tensor, ...]:
        xb = torch.as_tensor(as_batch(x, "x", self.state_dim))
        ub = torch.as_tensor(as_batch(u, "u", self.action_dim))
        if ub.shape[0] != xb.shape[0]:
            raise ValueError(f"u: {ub.shape[0]} rows, but x has {xb.shape[0]}")
        if xi is None:
            return xb, ub
        xib = torch.as_tensor(as_batch(xi, "xi", self.dim))
        if xib.shape[0] != xb.shape[0]:
            raise ValueError(f"xi: {xib.shape[0]} rows, but x has {xb.shape[0]}")
        return xb, ub, xib

    def update(self, x: Any, u: Any, xi: Any) -> StateDependentIBE:
        """Add transitions ``(x, u, xi)`` and refit ``w`` by minimising eq. (19); returns ``self``.

        Parameters
        ----------
        x : array_like, shape (N, n_x) or (n_x,)
        u : array_like, shape (N, n_u) or (n_u,)
        xi : array_like, shape (N, n) or (n,)
            Residuals (eq. (10)) of those transitions.

        Raises
        ------
        ValueError
            Wrong shapes, NaN/inf, or a fit that ends non-finite; the estimator is then unchanged.
        """
        xb, ub, xib = self._as_inputs(x, u, xi)
        if xb.shape[0] == 0:
            return self
        saved = [p.detach().clone() for p in self.phi.parameters()]
        old = (self._x, self._u, self._xi, self.count)
        self._x, self._u, self._xi = torch.cat([self._x, xb]), torch.cat([self._u, ub]), torch.cat([self._xi, xib])
        self.count += xb.shape[0]
        try:
            self._fit()
            ok = all(bool(torch.isfinite(p).all()) for p in self.phi.parameters())
        except RuntimeError:
            ok = False
        if not ok:
            with torch.no_grad():
                for p, s in zip(self.phi.parameters(), saved):
                    p.copy_(s)
            self._x, self._u, self._xi, self.count = old
            raise ValueError("xi: fitting eq. (19) diverged (non-finite parameters); update rejected")
        return self

    def _fit(self) -> None:
        params = list(self.phi.parameters())
        opt = torch.optim.LBFGS(
            params, lr=1.0, max_iter=self.max_iter, tolerance_grad=1e-12, tolerance_change=1e-15,
            history_size=50, line_search_fn="strong_wolfe",
        )

        def closure() -> torch.Tensor:
            opt.zero_grad()
            loss = self.negative_log_posterior()
            loss.backward()
            return loss

        opt.step(closure)

    def mean_at(self, x: Any, u: Any) -> np.ndarray | torch.Tensor:
        """Posterior-mode mean ``phi(x, u; w_hat)``; with no data ``phi(x, u; w_0)`` (the prior).

        Parameters
        ----------
        x : array_like or Tensor, shape (B, n_x) or (n_x,)
        u : array_like or Tensor, shape (B, n_u) or (n_u,)

        Returns
        -------
        ndarray or Tensor, shape (B, n) or (n,)
            A tensor if ``x`` is a tensor, else an ndarray.

        Raises
        ------
        ValueError
            Wrong shapes or NaN/inf.
        """
        single = np.ndim(x) == 1
        xb, ub = self._as_inputs(x, u, None)
        with torch.no_grad():
            out = self.phi(xb, ub)
        if single:
            out = out[0]
        return out.clone() if isinstance(x, torch.Tensor) else out.numpy().copy()

    def sample(self, n: int, generator: np.random.Generator | torch.Generator, x: Any, u: Any) -> np.ndarray | torch.Tensor:
        """Draw ``xi_hat ~ N(phi(x, u; w_hat), K)`` at one state-action pair.

        Parameters
        ----------
        n : int
        generator : numpy.random.Generator or torch.Generator
        x : array_like, shape (n_x,)
        u : array_like, shape (n_u,)

        Returns
        -------
        ndarray or Tensor, shape (n, d)

        Raises
        ------
        ValueError
            Bad ``n``, ``generator``, ``x`` or ``u``.
        """
        x = as_vector(x, "x", self.state_dim)
        u = as_vector(u, "u", self.action_dim)
        return sample_gaussian(self.mean_at(x, u), self.noise_cov, n, generator)

    def state_dict(self) -> dict[str, Any]:
        """Return a copy of the full state: parameters, prior, data, covariance."""
        return {
            "kind": self._KIND,
            "noise_cov": self.noise_cov.copy(),
            "prior_std": self.prior_std,
            "max_iter": self.max_iter,
            "count": self.count,
            "params": [p.detach().numpy().copy() for p in self.phi.parameters()],
            "prior_params": [p.numpy().copy() for p in self._prior_w],
            "x": self._x.numpy().copy(),
            "u": self._u.numpy().copy(),
            "xi": self._xi.numpy().copy(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> StateDependentIBE:
        """Restore a state from :meth:`state_dict`; validate everything first.

        Raises
        ------
        ValueError
            Not a dict, unknown/missing keys, other kind, wrong shapes, NaN/inf, bad covariance.
            The estimator is then left unchanged.
        """
        n = self.dim
        if not isinstance(state, dict):
            raise ValueError(f"state_dict: expected a dict, got {type(state).__name__}")
        check_unknown_keys(state, {"kind", "noise_cov", "prior_std", "max_iter", "count", "params", "prior_params", "x", "u", "xi"}, "state_dict")
        count = state.get("count")
        if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 0:
            raise ValueError(f"state_dict: count must be a non-negative int, got {count!r}")
        shapes = [tuple(p.shape) for p in self.phi.parameters()]
        spec: dict[str, Any] = {
            "kind": "str", "noise_cov": (n, n), "prior_std": "float", "max_iter": "int", "count": "int",
            "x": (int(count), self.state_dim), "u": (int(count), self.action_dim), "xi": (int(count), n),
        }
        for key in ("params", "prior_params"):
            val = state.get(key)
            if not isinstance(val, (list, tuple)) or len(val) != len(shapes):
                raise ValueError(f"state_dict: {key} must be a list of {len(shapes)} arrays")
            for i, (arr, shp) in enumerate(zip(val, shapes)):
                spec[f"{key}.{i}"] = shp
        flat = {k: v for k, v in state.items() if k not in ("params", "prior_params")}
        for key in ("params", "prior_params"):
            for i, arr in enumerate(state[key]):
                flat[f"{key}.{i}"] = arr
        st = _check_state(flat, spec, self._KIND)
        noise_cov = check_covariance(st["noise_cov"], "state_dict: noise_cov", n)
        if st["prior_std"] <= 0 or st["max_iter"] < 1:
            raise ValueError("state_dict: prior_std must be > 0 and max_iter >= 1")
        lam, vec = support(noise_cov)
        with torch.no_grad():
            for i, p in enumerate(self.phi.parameters()):
                p.copy_(torch.as_tensor(st[f"params.{i}"]))
        self._prior_w = [torch.as_tensor(st[f"prior_params.{i}"]).clone() for i in range(len(shapes))]
        self.noise_cov, self.prior_std, self.max_iter, self.count = noise_cov, st["prior_std"], st["max_iter"], st["count"]
        self._whiten = torch.as_tensor(vec / np.sqrt(lam))
        self._x, self._u, self._xi = (torch.as_tensor(st[k]).clone() for k in ("x", "u", "xi"))
        return self


class LinearFeatureIBE(_ReadOnlyArrays):
    """Implements eq. (19) in closed form: Case 3 IBE with a mean linear in its parameters.

    .. math::
        \\phi(x, u; W) = W^T g(x, u), \\qquad
        \\mathcal{L}(W) = \\frac12\\sum_{j=1}^N \\big(\\xi_j - W^T g_j\\big)^T \\mathcal{K}^{+}
        \\big(\\xi_j - W^T g_j\\big) + \\frac{1}{2\\sigma_w^2}\\lVert W - W_0\\rVert_F^2 + C

    with fixed features ``g(x, u)`` (``p`` of them) and weights ``W`` (``p x n``). ``L`` is quadratic in
    ``W``, so its minimiser (the posterior mode, and mean, of eq. 19) is exact: with
    ``K^+ = sum_i v_i v_i^T / lambda_i`` on the support of ``K``, ``G = sum_j g_j g_j^T`` and
    ``S = sum_j g_j xi_j^T``,

    .. math::
        \\big(G + \\tfrac{\\lambda_i}{\\sigma_w^2} I\\big)\\, W v_i = S v_i + \\tfrac{\\lambda_i}{\\sigma_w^2} W_0 v_i
        \\quad \\text{(each support direction } v_i\\text{)}, \\qquad W v = W_0 v \\ \\text{(} v \\perp
        \\text{support)}.

    The state is the sufficient statistics ``(N, G, S)`` (``O(p^2)`` memory), so an update costs the same
    at the first and at the millionth residual; :class:`StateDependentIBE` (any ``phi``, refit by L-BFGS
    on every residual kept so far) is the general form.

    Parameters
    ----------
    features : callable
        ``g(x, u)``: float64 tensors ``(B, n_x)``, ``(B, n_u)`` -> a float64 tensor ``(B, p)``. Fixed
        (it holds no learned state; it is not saved by :meth:`state_dict`).
    prior_weights : array_like, shape (p, n)
        ``W_0``, the prior mean of the weights.
    noise_cov : array_like, shape (n, n)
        The known noise covariance ``K`` (symmetric PSD, may be singular).
    state_dim, action_dim : int
        ``n_x``, ``n_u``.
    prior_std : float
        ``sigma_w > 0``: prior ``vec(W) ~ N(vec(W_0), sigma_w^2 I)``.

    Attributes
    ----------
    count : int
        Number of residuals seen.

    Raises
    ------
    ValueError
        Bad covariance or prior weights, non-positive ``prior_std``/dimensions, ``features`` not callable
        or returning a wrong shape.

    Notes
    -----
    As for :class:`StateDependentIBE`, ``K`` is known (the paper leaves Case 3's covariance unspecified)
    and directions outside its support carry no likelihood: there ``W`` stays at the prior. Any split of
    the data into batches gives the same ``W`` up to the rounding of ``G`` and ``S``. The solve is a
    Cholesky factorisation of the SPD ``p x p`` matrix ``G + (lambda_i / sigma_w^2) I``.
    """

    _KIND = "LinearFeatureIBE"
    #: A learning source (:class:`mixedrl.noise.StateDependentNoiseSource`).
    learns = True
    #: The mean is ``mean_at(x, u)``: Algorithm 2 plans with per-state nodes.
    state_dependent = True

    prior_weights = _ReadOnlyArray()
    weights = _ReadOnlyArray()
    gram = _ReadOnlyArray()
    cross = _ReadOnlyArray()

    def __init__(self, features: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], prior_weights: Any,
                 noise_cov: Any, state_dim: int, action_dim: int, prior_std: float = 1.0) -> None:
        if not callable(features):
            raise ValueError(f"features: expected a callable g(x, u), got {type(features).__name__}")
        self.features = features
        self.state_dim = check_positive_int(state_dim, "state_dim")
        self.action_dim = check_positive_int(action_dim, "action_dim")
        w0 = np.array(prior_weights, dtype=np.float64)
        if w0.ndim != 2:
            raise ValueError(f"prior_weights: expected a (p, n) matrix, got shape {w0.shape}")
        check_finite(w0, "prior_weights")
        self.noise_cov = check_covariance(noise_cov, "noise_cov", w0.shape[1])
        if isinstance(prior_std, bool) or not isinstance(prior_std, (int, float)) \
                or not (math.isfinite(prior_std) and prior_std > 0):
            raise ValueError(f"prior_std: expected a finite positive float, got {prior_std!r}")
        self.prior_std = float(prior_std)
        with torch.no_grad():
            g = features(torch.zeros((1, self.state_dim), dtype=torch.float64),
                         torch.zeros((1, self.action_dim), dtype=torch.float64))
        if tuple(g.shape) != (1, w0.shape[0]):
            raise ValueError(f"features: returned shape {tuple(g.shape)} for one input, expected (1, {w0.shape[0]}) "
                             f"(one feature per row of prior_weights)")
        self.prior_weights = w0
        self.count = 0
        self.gram = np.zeros((w0.shape[0], w0.shape[0]))
        self.cross = np.zeros(w0.shape)
        self.weights = w0.copy()
        self._support = support(self.noise_cov)

    @property
    def dim(self) -> int:
        """Dimension ``n`` of the noise."""
        return self.noise_cov.shape[0]

    @property
    def num_features(self) -> int:
        """Number ``p`` of features."""
        return self.prior_weights.shape[0]

    @property
    def cov(self) -> np.ndarray:
        """Noise covariance ``K`` of the mixed model, shape (n, n)."""
        return self.noise_cov

    def _solve(self, gram: np.ndarray, cross: np.ndarray) -> np.ndarray:
        lam, vec = self._support
        w0 = self.prior_weights
        weights = w0.copy()
        eye = np.eye(self.num_features)
        for lam_i, v in zip(lam, vec.T):
            ridge = lam_i / self.prior_std**2
            # (G + lambda_i / sigma_w^2 I) W v_i = S v_i + lambda_i / sigma_w^2 W_0 v_i
            chol = np.linalg.cholesky(gram + ridge * eye)
            rhs = cross @ v + ridge * (w0 @ v)
            wv = np.linalg.solve(chol.T, np.linalg.solve(chol, rhs))
            # replace the v_i-component of W (the prior's W_0 v_i) by the solution
            weights += np.outer(wv - w0 @ v, v)
        return weights

    def _features(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            g = self.features(x, u)
        if tuple(g.shape) != (x.shape[0], self.num_features):
            raise ValueError(f"features: returned shape {tuple(g.shape)}, expected ({x.shape[0]}, {self.num_features})")
        return g.to(torch.float64)

    def update(self, x: Any, u: Any, xi: Any) -> LinearFeatureIBE:
        """Add transitions ``(x, u, xi)`` and re-solve eq. (19) exactly; returns ``self``.

        Parameters
        ----------
        x : array_like, shape (N, n_x) or (n_x,)
        u : array_like, shape (N, n_u) or (n_u,)
        xi : array_like, shape (N, n) or (n,)
            Residuals (eq. (10)) of those transitions.

        Raises
        ------
        ValueError
            Wrong shapes, NaN/inf in the data or in the features; the estimator is then unchanged.
        """
        xb = torch.as_tensor(as_batch(x, "x", self.state_dim))
        ub = torch.as_tensor(as_batch(u, "u", self.action_dim))
        xib = as_batch(xi, "xi", self.dim)
        if ub.shape[0] != xb.shape[0] or xib.shape[0] != xb.shape[0]:
            raise ValueError(f"xi: x, u and xi need the same number of rows, got {xb.shape[0]}, {ub.shape[0]}, "
                             f"{xib.shape[0]}")
        if xb.shape[0] == 0:
            return self
        g = self._features(xb, ub).numpy()
        check_finite(g, "features(x, u)")
        # G = sum_j g_j g_j^T ;  S = sum_j g_j xi_j^T
        gram, cross = self.gram + g.T @ g, self.cross + g.T @ xib
        weights = self._solve(gram, cross)
        self.gram, self.cross, self.weights, self.count = gram, cross, weights, self.count + xb.shape[0]
        return self

    def mean_at(self, x: Any, u: Any) -> np.ndarray | torch.Tensor:
        """The posterior mean ``phi(x, u; W_hat) = W_hat^T g(x, u)`` (the prior's ``W_0`` before any data).

        Parameters
        ----------
        x : array_like or Tensor, shape (B, n_x) or (n_x,)
        u : array_like or Tensor, shape (B, n_u) or (n_u,)

        Returns
        -------
        ndarray or Tensor, shape (B, n) or (n,)
            A float64 tensor if ``x`` is a tensor, else an ndarray.

        Raises
        ------
        ValueError
            Wrong shapes or NaN/inf.
        """
        single = np.ndim(x) == 1
        xb = torch.as_tensor(as_batch(x.detach() if isinstance(x, torch.Tensor) else x, "x", self.state_dim))
        ub = torch.as_tensor(as_batch(u.detach() if isinstance(u, torch.Tensor) else u, "u", self.action_dim))
        if ub.shape[0] != xb.shape[0]:
            raise ValueError(f"u: {ub.shape[0]} rows, but x has {xb.shape[0]}")
        out = self._features(xb, ub) @ torch.tensor(self.weights)
        if single:
            out = out[0]
        return out if isinstance(x, torch.Tensor) else out.numpy()

    def state_dict(self) -> dict[str, Any]:
        """Return a copy of the full state: prior, covariance, sufficient statistics (not the features)."""
        return {
            "kind": self._KIND,
            "noise_cov": self.noise_cov.copy(),
            "prior_std": self.prior_std,
            "prior_weights": self.prior_weights.copy(),
            "count": self.count,
            "gram": self.gram.copy(),
            "cross": self.cross.copy(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> LinearFeatureIBE:
        """Restore a state from :meth:`state_dict` (same features); validate everything first.

        Raises
        ------
        ValueError
            Not a dict, unknown/missing keys, other kind, wrong shapes, NaN/inf, bad covariance or
            ``prior_std``. The estimator is then left unchanged.
        """
        p, n = self.prior_weights.shape
        spec = {"kind": "str", "noise_cov": (n, n), "prior_std": "float", "prior_weights": (p, n), "count": "int",
                "gram": (p, p), "cross": (p, n)}
        st = _check_state(state, spec, self._KIND)
        noise_cov = check_covariance(st["noise_cov"], "state_dict: noise_cov", n)
        if st["prior_std"] <= 0:
            raise ValueError("state_dict: prior_std must be > 0")
        check_covariance(st["gram"], "state_dict: gram", p)
        new = LinearFeatureIBE(self.features, st["prior_weights"], noise_cov, self.state_dim, self.action_dim,
                               st["prior_std"])
        new.gram, new.cross, new.count = st["gram"], st["cross"], st["count"]
        new.weights = new._solve(new.gram, new.cross)
        self.__dict__.update(new.__dict__)
        return self
