"""Case 1 of the IBE: the noise covariance ``K`` is known, eqs. (14)-(16).

* :func:`~mixedrl.ibe.map_mean_known_cov`: the batch MAP mean, eq. (15).
* :class:`~mixedrl.ibe.KnownCovarianceIBE`: the recursion, eq. (16), from the sufficient statistics ``(k, m_k)``.

Both evaluate eq. (15) in the covariance (Kalman) form of :mod:`mixedrl.ibe` (``_posterior_known_cov``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mixedrl.gaussian import CHOLESKY_PIVOT_FLOOR, solve_psd
from mixedrl.ibe.common import (
    GaussianNoiseEstimate,
    PosteriorGuard,
    check_posterior,
    check_state,
    real_batch,
    real_covariance,
    real_vector,
    symmetrize,
)

__all__ = ["map_mean_known_cov", "KnownCovarianceIBE"]


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
    return prior_mean + prod[:, 0], symmetrize(prod[:, 1:])


def _simultaneous_diag(prior_cov: np.ndarray,
                       noise_cov: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
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
    lam, vec = np.linalg.eigh(symmetrize(white))
    lam = np.clip(lam, 0.0, None)
    g = (chol @ vec) / inv_d[:, None]
    g_inv = (vec.T @ chol_inv) * inv_d
    return g, g_inv, lam



# ----------------------------------------------------------------------------------------------------
# eq. (15), batch
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
        Wrong shapes, zero dimensions, values that are not real numbers, NaN/inf, covariance not
        symmetric PSD, or residuals so large that the mean overflows (the message names the argument).

    Notes
    -----
    Computed in the equivalent covariance form
    ``mu_M + K_M (N K_M + K)^{-1} (sum xi - N mu_M)`` (module docstring), which needs no inverse of
    ``K`` or ``K_M``; ``N K_M + K`` is solved by :func:`mixedrl.gaussian.solve_psd`.
    """
    mu_m = real_vector(prior_mean, "prior_mean")
    n = mu_m.shape[0]
    k_m = real_covariance(prior_cov, "prior_cov", n)
    k = real_covariance(noise_cov, "noise_cov", n)
    batch = real_batch(xi, "xi", n)
    with PosteriorGuard("xi"):
        mean, _ = _posterior_known_cov(mu_m, k_m, k, batch.shape[0], batch.sum(axis=0))
    check_posterior("xi", (mean,))
    return mean



# ----------------------------------------------------------------------------------------------------
# eq. (16), recursion
# ----------------------------------------------------------------------------------------------------
class KnownCovarianceIBE(GaussianNoiseEstimate):
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
        Wrong shapes, zero dimensions (an empty ``prior_mean``), values that are not real numbers,
        NaN/inf, covariance not symmetric PSD (message names the argument).

    Notes
    -----
    ``Psi_k = K_M^{-1} + k K^{-1}`` depends on ``k`` only, so the state is ``(k, m_k)`` as in eq. (16);
    ``mu_hat_k`` and ``Psi_k^{-1}`` are evaluated in covariance form, with ``K_M`` and ``K`` diagonalised
    simultaneously once (``_simultaneous_diag``) or, for a numerically singular ``K_M``, by
    :func:`mixedrl.gaussian.solve_psd` at every update (``docs/ibe.rst``, "How inverses are computed").
    Any split of the data into batches gives eq. (15) up to the rounding of ``m_k``. An update is
    committed only if ``m_k`` and ``mu_hat_k`` are finite (``Psi_k^{-1}`` depends on ``k`` alone).
    """

    _KIND = "KnownCovarianceIBE"

    _FIELDS = ("mean_cov", "total")

    def __init__(self, prior_mean: Any, prior_cov: Any, noise_cov: Any) -> None:
        prior_mean = real_vector(prior_mean, "prior_mean")
        n = prior_mean.shape[0]
        prior_cov = real_covariance(prior_cov, "prior_cov", n)
        noise_cov = real_covariance(noise_cov, "noise_cov", n)
        self._commit(prior_mean=prior_mean, prior_cov=prior_cov, noise_cov=noise_cov, count=0, total=np.zeros(n),
                     mean=prior_mean.copy(), mean_cov=prior_cov.copy())
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

    def update(self, xi: Any) -> KnownCovarianceIBE:
        """Implements eq. (16) for one residual ``(n,)`` or a batch ``(N, n)``; returns ``self``.

        Raises
        ------
        ValueError
            ``xi`` of wrong shape, not real numbers, with NaN/inf, or so large that ``m_k`` or the mean
            would overflow; the estimator is then left unchanged.
        """
        batch = real_batch(xi, "xi", self.dim)
        nb = batch.shape[0]
        if nb == 0:
            return self
        with PosteriorGuard("xi"):
            # m_k = m_{k-1} + xi_k   (summed over the batch)
            bsum = batch[0] if nb == 1 else np.ones(nb) @ batch
            total = self.total + bsum
            count = self.count + nb
            mean, mean_cov = self._posterior(count, total)
        check_posterior("xi", (total, mean))  # Psi_k^-1 depends on k alone (finite, PSD by construction)
        self._commit(total=total, count=count, mean=mean, mean_cov=mean_cov)
        return self

    def state_dict(self) -> dict[str, Any]:
        """Return a copy of the full state (plain floats, ints and ndarrays)."""
        return self._state("prior_mean", "prior_cov", "noise_cov", "count", "total")

    def load_state_dict(self, state: dict[str, Any]) -> KnownCovarianceIBE:
        """Restore a state from :meth:`state_dict`; validate everything first.

        Raises
        ------
        ValueError
            Not a dict, unknown/missing keys, other kind, shapes of another dimension, not real numbers,
            NaN/inf, covariance not symmetric PSD, a posterior that would not be finite. The estimator
            is then left unchanged.
        """
        n = self.dim
        spec = {"kind": "str", "prior_mean": (n,), "prior_cov": (n, n), "noise_cov": (n, n), "count": "int",
                "total": (n,)}
        st = check_state(state, spec, self._KIND, psd=("prior_cov", "noise_cov"))
        new = KnownCovarianceIBE(st["prior_mean"], st["prior_cov"], st["noise_cov"])
        with PosteriorGuard("state_dict"):
            mean, mean_cov = new._posterior(st["count"], st["total"])
        check_posterior("state_dict", (mean, mean_cov))
        new._commit(mean=mean, mean_cov=mean_cov, count=st["count"], total=st["total"])
        self.__dict__.update(new.__dict__)
        return self

