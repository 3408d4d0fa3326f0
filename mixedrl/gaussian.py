"""Gaussian utilities shared by the IBE and the theory checks: sampling, KL divergence, PSD solves.

Every function here accepts *singular* covariances, the normal case in this project (EQUATIONS.md point 5):
the numerical support is :func:`mixedrl.expectation.support` (cut-off :data:`SUPPORT_RTOL`), and
:func:`solve_psd` is the Jacobi-equilibrated Cholesky solve with a pseudo-inverse fall-back described in
``docs/ibe.rst`` ("How inverses are computed, and why").
"""

from __future__ import annotations

import math

from collections.abc import Callable

import numpy as np
import torch
from scipy.linalg.lapack import dpotrf as _dpotrf
from scipy.linalg.lapack import dpotrs as _dpotrs

from mixedrl.checks import as_vector, check_covariance, check_positive_int
from mixedrl.expectation import SUPPORT_RTOL, psd_factor, support

__all__ = ["SUPPORT_RTOL", "CHOLESKY_PIVOT_FLOOR", "solve_psd", "psd_solver", "pinv_psd", "psd_factor",
           "sample_gaussian", "kl_divergence"]

#: Smallest accepted squared Cholesky pivot of a unit-diagonal (Jacobi-scaled) matrix. Below it the
#: matrix is treated as singular and :func:`solve_psd` falls back to the eigenvalue pseudo-inverse.
CHOLESKY_PIVOT_FLOOR = 1e-13


def psd_solver(s: np.ndarray, rtol: float = SUPPORT_RTOL) -> Callable[[np.ndarray], np.ndarray]:
    """Factor a symmetric PSD ``S`` once and return ``b -> S^+ b`` (see :func:`solve_psd`).

    Parameters
    ----------
    s : ndarray, shape (n, n)
    rtol : float

    Returns
    -------
    callable
        Maps ``b`` of shape (n,) or (n, m) to ``S^{-1} b`` (``S^+ b`` when singular).
    """
    diag = s.diagonal()
    if diag.min() <= 0.0:
        idx = np.flatnonzero(diag > 0.0)
        sub = psd_solver(s[np.ix_(idx, idx)], rtol) if idx.size else None

        def block_solve(b: np.ndarray) -> np.ndarray:
            out = np.zeros(b.shape, dtype=np.float64)
            if sub is not None:
                out[idx] = sub(b[idx])
            return out

        return block_solve
    inv_d = 1.0 / np.sqrt(diag)
    scaled = s * inv_d * inv_d[:, None]
    chol, info = _dpotrf(scaled, 1, 0)
    if info == 0 and chol.diagonal().min() ** 2 >= CHOLESKY_PIVOT_FLOOR:

        def scaled_solve(b: np.ndarray) -> np.ndarray:
            return _dpotrs(chol, b, 1)[0]
    else:
        lam, vec = support(scaled, rtol)
        inv = 1.0 / lam

        def scaled_solve(b: np.ndarray) -> np.ndarray:
            return vec @ (inv.reshape(-1, *(1,) * (b.ndim - 1)) * (vec.T @ b))

    def solve(b: np.ndarray) -> np.ndarray:
        d = inv_d if b.ndim == 1 else inv_d[:, None]
        return scaled_solve(b * d) * d

    return solve


def solve_psd(s: np.ndarray, b: np.ndarray, rtol: float = SUPPORT_RTOL) -> np.ndarray:
    """Solve ``S x = b`` for a symmetric PSD matrix ``S``; on a singular ``S`` use a generalised inverse.

    .. math:: x = S^{g} b, \\qquad S^{g} = S^{-1} \\text{ when } S \\succ 0,
        \\quad S^{g} = D (D S D)^{+} D \\text{ otherwise}.

    Used for every ``(A + B)^{-1}`` of the covariance (Kalman) form of eqs. (15)-(17), e.g.
    ``S = k K_M + K``.

    Parameters
    ----------
    s : ndarray, shape (n, n)
        Symmetric positive semi-definite matrix (not validated here: internal helper, callers pass
        validated covariances).
    b : ndarray, shape (n,) or (n, m)
        Right-hand side(s).
    rtol : float
        Relative eigenvalue floor for the pseudo-inverse fall-back (default :data:`SUPPORT_RTOL`).

    Returns
    -------
    ndarray, shape like ``b``

    Notes
    -----
    Rows/columns with a zero diagonal get 0 in the solution; the rest is Jacobi-scaled (``D S D``,
    ``D = diag(S)^{-1/2}``) and Cholesky-solved (LAPACK ``dpotrf``/``dpotrs``) if every squared pivot is
    ``>= CHOLESKY_PIVOT_FLOOR``, else solved with the eigenvalue pseudo-inverse of ``D S D`` (floor ``rtol``).
    ``S^g`` is a reflexive generalised inverse (``S S^g S = S``); the IBE multiplies it by ``K_M`` or ``K``,
    which vanish on ``null(S)``, so there it acts as ``S^+``.
    """
    return psd_solver(s, rtol)(b)


def pinv_psd(c: np.ndarray, rtol: float = SUPPORT_RTOL) -> np.ndarray:
    """Moore-Penrose pseudo-inverse of a symmetric PSD matrix, eigenvalues ``<= rtol * max`` dropped.

    Parameters
    ----------
    c : ndarray, shape (n, n)
    rtol : float

    Returns
    -------
    ndarray, shape (n, n), symmetric
    """
    lam, vec = support(c, rtol)
    out = (vec * (1.0 / lam)) @ vec.T
    return 0.5 * (out + out.T)


def sample_gaussian(
    mean: np.ndarray,
    cov: np.ndarray,
    n: int,
    generator: np.random.Generator | torch.Generator,
) -> np.ndarray | torch.Tensor:
    """Draw ``n`` samples of ``N(mean, cov)``, also for a singular ``cov``.

    .. math:: \\hat\\xi = \\mu + A z, \\quad z \\sim N(0, I), \\quad A A^T = \\mathcal{K}

    Parameters
    ----------
    mean : array_like, shape (d,)
    cov : array_like, shape (d, d)
        Symmetric PSD; may be singular.
    n : int
        Number of samples, ``>= 1``.
    generator : numpy.random.Generator or torch.Generator
        Source of every random number. A numpy generator gives an ndarray, a torch generator a
        float64 tensor.

    Returns
    -------
    ndarray or Tensor, shape (n, d)

    Raises
    ------
    ValueError
        ``mean``/``cov`` of wrong shape, non-finite, ``cov`` not symmetric PSD, ``n`` not a positive
        integer, or ``generator`` of another type.

    Notes
    -----
    The factor ``A`` is the eigen-factor of :func:`psd_factor`, so samples lie exactly in
    ``mean + range(cov)`` (up to rounding), e.g. the four noise-free vehicle components equal the mean.
    """
    mean = as_vector(mean, "mean")
    cov = check_covariance(cov, "cov", mean.shape[0])
    n = check_positive_int(n, "n")
    factor = psd_factor(cov)
    if isinstance(generator, np.random.Generator):
        z = generator.standard_normal((n, mean.shape[0]))
        return mean + z @ factor.T
    if isinstance(generator, torch.Generator):
        z = torch.randn((n, mean.shape[0]), generator=generator, dtype=torch.float64)
        return torch.as_tensor(mean) + z @ torch.as_tensor(factor).T
    raise ValueError(f"generator: expected numpy.random.Generator or torch.Generator, got {type(generator).__name__}")


def kl_divergence(
    mean0: np.ndarray,
    cov0: np.ndarray,
    mean1: np.ndarray,
    cov1: np.ndarray,
    rtol: float = SUPPORT_RTOL,
) -> float:
    """Kullback-Leibler divergence ``KL(N0 || N1)`` of two (possibly singular) Gaussians.

    .. math::
        D_{KL}(N_0 \\| N_1) = \\tfrac12\\left[\\operatorname{tr}(\\Sigma_1^{-1}\\Sigma_0)
        + (\\mu_1-\\mu_0)^T\\Sigma_1^{-1}(\\mu_1-\\mu_0) - r
        + \\ln\\det\\Sigma_1 - \\ln\\det\\Sigma_0\\right]

    Used for the consistency statement of Theorem 4 (eq. (45)): ``KL(p(xi_k) || p(xi_{k+1})) -> 0``.

    Parameters
    ----------
    mean0, mean1 : array_like, shape (d,)
    cov0, cov1 : array_like, shape (d, d)
        Symmetric PSD, possibly singular.
    rtol : float
        Relative eigenvalue floor that defines each support (default :data:`SUPPORT_RTOL`).

    Returns
    -------
    float
        ``>= 0``; ``math.inf`` when ``N0`` is not absolutely continuous with respect to ``N1``.

    Raises
    ------
    ValueError
        Wrong shapes, non-finite entries, covariance not symmetric PSD (message names the argument).

    Notes
    -----
    A singular Gaussian lives on the affine support ``mu + range(Sigma)`` (numerical range: eigenvalues
    ``> rtol * lambda_max``). ``KL(N0 || N1)`` is finite only when both supports coincide: equal rank
    ``r``, ``range(Sigma0) = range(Sigma1)`` and ``mu0 - mu1`` in ``range(Sigma1)`` (components outside
    the range smaller than ``sqrt(rtol) * (|mu0| + |mu1| + sqrt(lambda_max))``, i.e. rounding). Then the formula
    above is evaluated in the eigenbasis ``U`` of the support of ``Sigma1`` (``Sigma -> U^T Sigma U``,
    ``d -> r``). Otherwise the result is ``inf`` (including ``r = 0`` with different means).
    For positive definite inputs this is the usual formula.
    """
    mean0 = as_vector(mean0, "mean0")
    d = mean0.shape[0]
    mean1 = as_vector(mean1, "mean1", d)
    cov0 = check_covariance(cov0, "cov0", d)
    cov1 = check_covariance(cov1, "cov1", d)
    lam1, u1 = support(cov1, rtol)
    lam0, _ = support(cov0, rtol)
    r = lam1.shape[0]
    delta = mean1 - mean0
    if lam0.shape[0] != r or (r == 0 and np.any(delta != 0.0)):
        return math.inf
    if r == 0:
        return 0.0
    # Components of Sigma0 and of the mean difference outside range(Sigma1).
    proj = u1 @ u1.T
    off, off_mean = cov0 - proj @ cov0 @ proj, delta - proj @ delta
    top = max(float(lam1[-1]), float(np.max(np.abs(np.linalg.eigvalsh(cov0)))))
    mean_scale = float(np.max(np.abs(mean0)) + np.max(np.abs(mean1)))
    if (np.max(np.abs(off)) > math.sqrt(rtol) * top
            or np.max(np.abs(off_mean)) > math.sqrt(rtol) * (mean_scale + math.sqrt(top))):
        return math.inf
    s0 = u1.T @ cov0 @ u1  # (r, r)
    s0 = 0.5 * (s0 + s0.T)
    dr = u1.T @ delta
    lam0_sub = np.linalg.eigvalsh(s0)
    if lam0_sub[0] <= 0.0:
        return math.inf
    trace_term = float(np.sum(np.diagonal(s0) / lam1))
    maha = float(np.sum(dr * dr / lam1))
    logdet1 = float(np.sum(np.log(lam1)))
    logdet0 = float(np.sum(np.log(lam0_sub)))
    kl = 0.5 * (trace_term + maha - r + logdet1 - logdet0)
    return max(kl, 0.0)
