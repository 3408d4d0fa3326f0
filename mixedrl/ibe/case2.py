"""Case 2 of the IBE: mean and covariance of the noise both unknown, eqs. (17)-(18).

* :func:`~mixedrl.ibe.map_mean_cov`: the batch fixed point of eq. (17), from the raw residuals.
* :class:`~mixedrl.ibe.UnknownCovarianceIBE`: the recursion; ``recursion="exact"`` (default) re-solves eq. (17) from
  the sufficient statistics ``(N, xbar, scatter)`` after every update (``_solve_eq17``),
  ``recursion="paper"`` is eq. (18) literally.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from mixedrl.checks import check_positive_int
from mixedrl.gaussian import pinv_psd, psd_solver, solve_psd
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

__all__ = ["FIXED_POINT_RTOL", "FIXED_POINT_MAX_ITER", "map_mean_cov", "UnknownCovarianceIBE"]

logger = logging.getLogger(__name__)

#: Relative stopping tolerance of the eq. (17) fixed-point iteration (see :func:`map_mean_cov`).
FIXED_POINT_RTOL = 1e-13
#: Iteration cap of the eq. (17) fixed-point iteration.
FIXED_POINT_MAX_ITER = 10_000


def _solve_eq17(
    prior_mean: np.ndarray,
    prior_cov: np.ndarray,
    count: int,
    xbar: np.ndarray,
    scatter: np.ndarray,
    max_iter: int,
    rtol: float,
) -> tuple[np.ndarray, np.ndarray, int, bool]:
    """Implements eq. (17): the Case 2 fixed point from the sufficient statistics of ``N`` residuals.

    .. math::
        \\hat\\mu = \\left(\\mathcal{K}_M^{-1} + N\\hat{\\mathcal{K}}^{-1}\\right)^{-1}
        \\left(\\mathcal{K}_M^{-1}\\mu_M + \\hat{\\mathcal{K}}^{-1}\\sum_j \\xi_j\\right), \\qquad
        \\hat{\\mathcal{K}} = \\frac1N\\sum_j (\\xi_j - \\hat\\mu)(\\xi_j - \\hat\\mu)^T

    The one implementation of eq. (17): the batch :func:`map_mean_cov` and the recursive
    :class:`UnknownCovarianceIBE` (``recursion="exact"``) both call it, on statistics they compute their own
    way (from the raw residuals; merged update by update).

    Parameters
    ----------
    prior_mean : ndarray, shape (n,)
        ``mu_M``.
    prior_cov : ndarray, shape (n, n)
        ``K_M``.
    count : int
        ``N >= 1``.
    xbar : ndarray, shape (n,)
        Mean of the residuals.
    scatter : ndarray, shape (n, n)
        Centred scatter ``sum_j (xi_j - xbar)(xi_j - xbar)^T``.
    max_iter, rtol
        Iteration cap and relative stopping tolerance (see :func:`map_mean_cov`).

    Returns
    -------
    mean : ndarray, shape (n,)
    cov : ndarray, shape (n, n)
    iterations : int
    converged : bool

    Notes
    -----
    Starts from ``mu_0 = xbar`` and alternates the two lines; with ``C = scatter / N`` and ``d = xbar - mu``
    the covariance line is ``K(mu) = C + d d^T`` and the mean line ``mu_M + N K_M (N K_M + K_hat)^{-1}
    (xbar - mu_M)`` is a rank-1 (Sherman-Morrison) update of the solve of ``S_0 = N K_M + C``. Stops,
    not converged, at a non-finite iterate (the caller's ``check_posterior`` refuses it).
    """
    c = scatter / count
    r = xbar - prior_mean
    prior_scale = float(np.abs(prior_mean).max()) + math.sqrt(float(prior_cov.diagonal().max()))
    scale = float(np.abs(xbar).max()) + math.sqrt(max(float(c.diagonal().max()), 0.0)) + prior_scale
    scale = scale if scale > 0.0 else 1.0
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
        if not math.isfinite(step):
            break
    k_hat = c + np.outer(d, d)
    return mu, k_hat, it, converged


# ----------------------------------------------------------------------------------------------------
# eq. (17), batch
# ----------------------------------------------------------------------------------------------------
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
        Wrong shapes, zero dimensions, values that are not real numbers, NaN/inf, covariance not
        symmetric PSD, empty ``xi``, or residuals so large that the estimate would not be finite.

    Notes
    -----
    Eq. (17) couples ``mu_hat`` and ``K_hat`` (EQUATIONS.md point 2); ``_solve_eq17`` alternates its two
    lines **starting from the data** (``mu_0 = xbar``, ``K_0 = C``), which selects the fixed point closest
    to the data where eq. (17) has several (``docs/ibe.rst``, "Solving the fixed point"). The recursive
    :class:`UnknownCovarianceIBE` uses the same start, so both agree after every update. With ``N = 1``
    eq. (17) gives ``mu_hat = xi_1``, ``K_hat = 0`` (the degenerate but literal answer).
    """
    mu_m = real_vector(prior_mean, "prior_mean")
    n = mu_m.shape[0]
    k_m = real_covariance(prior_cov, "prior_cov", n)
    batch = real_batch(xi, "xi", n)
    if batch.shape[0] == 0:
        raise ValueError("xi: eq. (17) needs at least one residual")
    max_iter = check_positive_int(max_iter, "max_iter")
    count = batch.shape[0]
    with PosteriorGuard("xi"):
        xbar = batch.sum(axis=0) / count
        centred = batch - xbar
        scatter = symmetrize(centred.T @ centred)
        check_posterior("xi", (xbar,), (scatter,))
        mu, k_hat, _, converged = _solve_eq17(mu_m, k_m, count, xbar, scatter, max_iter, rtol)
    check_posterior("xi", (mu,), (k_hat,))
    if not converged:
        logger.warning("map_mean_cov: eq. (17) fixed point not converged after %d iterations", max_iter)
    return mu, k_hat



# ----------------------------------------------------------------------------------------------------
# eqs. (17)-(18), recursion
# ----------------------------------------------------------------------------------------------------
class UnknownCovarianceIBE(GaussianNoiseEstimate):
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
    * ``"exact"`` keeps the sufficient statistics ``N``, ``xbar`` and the centred scatter (merged with Chan's
      parallel formula) and re-solves eq. (17) after every update from the same start as
      :func:`map_mean_cov` (not warm-started), so it equals the batch eq. (17) on all data so far.
      Departure from the paper: eq. (18) is not used (EQUATIONS.md point 3).
    * ``"paper"`` is eq. (18) literally, initialised as Algorithm 1 (``mu_hat_0 = mu_M``, ``K_hat_0 = K_M``,
      ``Psi_0 = K_M^{-1}``; EQUATIONS.md point 4), with pseudo-inverses of ``K_hat_{k-1}`` and ``K_M``
      (:func:`mixedrl.gaussian.pinv_psd`, floor :data:`mixedrl.expectation.SUPPORT_RTOL`); batches are
      processed one residual at a time.
    * ``docs/ibe.rst`` (Case 2) gives the details. Either way an update is committed only if it is finite
      and ``K_hat`` (and ``Psi_k``) symmetric PSD; a single residual adds a rank-1 PSD term to the scatter,
      so only a batch's merged scatter gets the eigenvalue check.
    """

    _KIND = "UnknownCovarianceIBE"
    _RECURSIONS = ("exact", "paper")

    _FIELDS = ("cov", "_mean_cov", "recursion", "max_iter", "iterations", "converged", "data_mean", "scatter", "psi",
               "total")

    def __init__(self, prior_mean: Any, prior_cov: Any, recursion: str = "exact",
                 max_iter: int = FIXED_POINT_MAX_ITER) -> None:
        prior_mean = real_vector(prior_mean, "prior_mean")
        prior_cov = real_covariance(prior_cov, "prior_cov", prior_mean.shape[0])
        if recursion not in self._RECURSIONS:
            raise ValueError(f"recursion: expected one of {self._RECURSIONS}, got {recursion!r}")
        n = prior_mean.shape[0]
        self._prior_prec = pinv_psd(prior_cov)
        # K_hat_0 = K_M (Algorithm 1); exact: sufficient statistics; paper: eq. (18) state
        self._commit(prior_mean=prior_mean, prior_cov=prior_cov, recursion=recursion,
                     max_iter=check_positive_int(max_iter, "max_iter"), count=0, mean=prior_mean.copy(),
                     cov=prior_cov.copy(), _mean_cov=prior_cov.copy(), iterations=0, converged=True,
                     data_mean=np.zeros(n), scatter=np.zeros((n, n)), psi=self._prior_prec.copy(), total=np.zeros(n))

    @property
    def mean_cov(self) -> np.ndarray:
        """``Psi_k^{-1}``, posterior covariance of the mean, shape (n, n).

        In ``"exact"`` mode it is computed on first access after an update (covariance form
        ``K_M (N K_M + K_hat)^{-1} K_hat``), so updates do not pay for it.
        """
        if self._mean_cov is None:
            # Psi^{-1} = (K_M^-1 + N K_hat^-1)^-1 = K_M (N K_M + K_hat)^-1 K_hat
            solved = solve_psd(self.count * self.prior_cov + self.cov, self.cov)
            self._commit(_mean_cov=symmetrize(self.prior_cov @ solved))
        return self._mean_cov

    def update(self, xi: Any) -> UnknownCovarianceIBE:
        """Add one residual ``(n,)`` or a batch ``(N, n)``; returns ``self``.

        Raises
        ------
        ValueError
            ``xi`` of wrong shape, not real numbers, with NaN/inf, or such that the posterior would not
            be finite and symmetric PSD (e.g. overflow); the estimator is then left unchanged.
        """
        batch = real_batch(xi, "xi", self.dim)
        if batch.shape[0] == 0:
            return self
        if self.recursion == "exact":
            self._update_exact(batch)
        else:
            self._update_paper(batch)
        return self

    def _update_exact(self, batch: np.ndarray) -> None:
        nb = batch.shape[0]
        with PosteriorGuard("xi"):
            if nb == 1:
                bmean, bscatter = batch[0], None
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
            # The scatter stays PSD by construction under rank-1 merges (w >= 0 times delta delta^T), and so
            # does K_hat = scatter / N + d d^T; only a batch's own scatter needs the eigenvalue check.
            # (outer(delta, delta) is exactly symmetric, so single updates keep symmetry bitwise)
            if bscatter is None:
                check_posterior("xi", (data_mean, scatter))
            else:
                scatter = symmetrize(scatter + bscatter)
                check_posterior("xi", (data_mean,), (scatter,))
            mean, cov, it, ok = _solve_eq17(self.prior_mean, self.prior_cov, count, data_mean, scatter, self.max_iter,
                                            FIXED_POINT_RTOL)
        check_posterior("xi", (mean, cov))
        if not ok:
            logger.warning("UnknownCovarianceIBE: eq. (17) fixed point not converged after %d iterations", it)
        self._commit(count=count, data_mean=data_mean, scatter=scatter, mean=mean, cov=cov, _mean_cov=None,
                     iterations=it, converged=ok)

    def _update_paper(self, batch: np.ndarray) -> None:
        psi, total, mean, cov, k = self.psi, self.total, self.mean, self.cov, self.count
        prior_term = self._prior_prec @ self.prior_mean
        with PosteriorGuard("xi"):
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
                cov = symmetrize(((k - 1) * cov + np.outer(dev, dev)) / k)
                mean = new_mean
            mean_cov = symmetrize(solve_psd(psi, np.eye(self.dim)))
        check_posterior("xi", (total, mean, mean_cov), (cov, psi))
        self._commit(psi=psi, total=total, mean=mean, cov=cov, count=k, _mean_cov=mean_cov)

    def state_dict(self) -> dict[str, Any]:
        """Return a copy of the full state (plain floats, ints, strs and ndarrays)."""
        state = ("data_mean", "scatter") if self.recursion == "exact" else ("psi", "total", "mean", "cov")
        return self._state("recursion", "max_iter", "prior_mean", "prior_cov", "count", *state)

    def load_state_dict(self, state: dict[str, Any]) -> UnknownCovarianceIBE:
        """Restore a state from :meth:`state_dict`; validate everything first.

        Raises
        ------
        ValueError
            Not a dict, unknown/missing keys, other kind or recursion, wrong shapes, not real numbers,
            NaN/inf, covariance not symmetric PSD, or a posterior that would not be finite and
            symmetric PSD. The estimator is then left unchanged.
        """
        n = self.dim
        if not isinstance(state, dict):
            raise ValueError(f"state_dict: expected a dict, got {type(state).__name__}")
        if state.get("recursion") not in self._RECURSIONS:
            raise ValueError(f"state_dict: recursion must be one of {self._RECURSIONS}, got {state.get('recursion')!r}")
        spec: dict[str, Any] = {"kind": "str", "recursion": "str", "max_iter": "int", "prior_mean": (n,),
                                "prior_cov": (n, n), "count": "int"}
        if state["recursion"] == "exact":
            spec.update(data_mean=(n,), scatter=(n, n))
        else:
            spec.update(psi=(n, n), total=(n,), mean=(n,), cov=(n, n))
        st = check_state(state, spec, self._KIND, psd=("prior_cov", "scatter", "psi", "cov"))
        check_positive_int(st["max_iter"], "state_dict: max_iter")
        new = UnknownCovarianceIBE(st["prior_mean"], st["prior_cov"], st["recursion"], st["max_iter"])
        new._commit(count=st["count"])
        if new.recursion == "exact":
            data_mean, scatter = st["data_mean"], st["scatter"]
            if new.count == 0 and (np.any(data_mean != 0) or np.any(scatter != 0)):
                raise ValueError("state_dict: count is 0 but the statistics are not empty")
            new._commit(data_mean=data_mean, scatter=scatter)
            if new.count > 0:
                with PosteriorGuard("state_dict"):
                    mean, cov, iterations, converged = _solve_eq17(
                        new.prior_mean, new.prior_cov, new.count, data_mean, scatter, new.max_iter, FIXED_POINT_RTOL
                    )
                check_posterior("state_dict", (mean,), (cov,))
                new._commit(mean=mean, cov=cov, iterations=iterations, converged=converged, _mean_cov=None)
        else:
            with PosteriorGuard("state_dict"):
                mean_cov = symmetrize(solve_psd(st["psi"], np.eye(n)))
            check_posterior("state_dict", (mean_cov,))
            new._commit(psi=st["psi"], cov=st["cov"], total=st["total"], mean=st["mean"], _mean_cov=mean_cov)
        self.__dict__.update(new.__dict__)
        return self

