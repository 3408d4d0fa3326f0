"""Gaussian expectations ``E g(c + xi)``, ``xi ~ N(mu, K)``, by a stated quadrature rule.

The theory checks need expectations of the value and the utility over the mixed model's noise. Two
rules are provided; both work on the numerical support of ``K`` (rank ``r``, possibly singular),
through the eigen-factor ``F`` with ``F F^T = K`` (:func:`mixedrl.gaussian.psd_factor`, columns with
zero eigenvalue dropped), ``xi = mu + F z``, ``z ~ N(0, I_r)``:

* :class:`SigmaPoints` (default): the ``2r`` symmetric points ``z = +- sqrt(r) e_i`` with equal weights
  ``1/(2r)``. It reproduces every moment of ``N(0, I_r)`` up to order 3, so it is **exact for
  polynomials of degree <= 3**, in particular for quadratic values and utilities (the LQ case):
  ``E V(c + xi) = V(c + mu) + tr(P K)`` to rounding. For a smooth non-polynomial ``g`` the error
  starts at the fourth-order Taylor term, ``O(||K||^2 sup |D^4 g|)`` (the rule gives ``r`` instead of
  ``3`` for ``E z_i^4`` and ``0`` instead of ``1`` for ``E z_i^2 z_j^2``); ``tests/test_theory.py``
  measures it on ``g = exp(a^T x)``.
* :class:`GaussHermite`: the tensor product of the ``q``-point Gauss-Hermite rule (probabilists'
  weights), ``q^r`` points, exact for polynomials of degree ``<= 2 q - 1`` in each coordinate; use it
  for non-quadratic values when ``r`` is small (the vehicle noise has ``r = 1``).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from mixedrl._checks import as_batch, as_vector, check_covariance, check_positive_int
from mixedrl.gaussian import SUPPORT_RTOL

__all__ = ["SigmaPoints", "GaussHermite", "support_factor", "gaussian_expectation"]


@dataclass(frozen=True)
class SigmaPoints:
    """Symmetric ``2r``-point rule: nodes ``+- sqrt(r) e_i``, weights ``1/(2r)``; exact to degree 3."""

    def nodes(self, r: int) -> tuple[np.ndarray, np.ndarray]:
        """Return nodes (2r, r) and weights (2r,) for ``N(0, I_r)``."""
        eye = np.sqrt(r) * np.eye(r)
        return np.vstack([eye, -eye]), np.full(2 * r, 1.0 / (2 * r))


@dataclass(frozen=True)
class GaussHermite:
    """Tensor-product Gauss-Hermite rule of ``order`` points per dimension; exact to degree ``2 order - 1``.

    Parameters
    ----------
    order : int
        Points per dimension (``>= 1``). The rule has ``order ** r`` nodes.
    """

    order: int = 5

    def __post_init__(self) -> None:
        check_positive_int(self.order, "order")

    def nodes(self, r: int) -> tuple[np.ndarray, np.ndarray]:
        """Return nodes (order^r, r) and weights (order^r,) for ``N(0, I_r)``."""
        x, w = np.polynomial.hermite_e.hermegauss(self.order)
        w = w / np.sqrt(2.0 * np.pi)
        grid = np.array(list(itertools.product(x, repeat=r)), dtype=np.float64).reshape(-1, r)
        wgrid = np.array([np.prod(c) for c in itertools.product(w, repeat=r)], dtype=np.float64)
        return grid, wgrid


def support_factor(cov: np.ndarray, rtol: float = SUPPORT_RTOL) -> np.ndarray:
    """Return ``F`` (n, r) with ``F F^T = cov`` restricted to the numerical support (eigenvalues > rtol * max).

    Parameters
    ----------
    cov : ndarray, shape (n, n), symmetric PSD
    rtol : float
        Relative eigenvalue floor (default :data:`mixedrl.gaussian.SUPPORT_RTOL`).

    Returns
    -------
    ndarray, shape (n, r)
    """
    lam, vec = np.linalg.eigh(cov)
    top = lam[-1] if lam.size else 0.0
    keep = lam > rtol * top if top > 0 else np.zeros_like(lam, dtype=bool)
    return vec[:, keep] * np.sqrt(lam[keep])


def gaussian_expectation(
    g: Callable[..., np.ndarray],
    centers: Any,
    mean: Any,
    cov: Any,
    rule: SigmaPoints | GaussHermite | None = None,
    extra: Any = None,
) -> np.ndarray:
    """Return ``E g(c_i + xi)`` for each row ``c_i`` of ``centers``, ``xi ~ N(mean, cov)``, by quadrature.

    .. math:: \\mathbb{E}\\, g(c + \\xi) \\approx \\sum_j w_j\\, g(c + \\mu + F z_j), \\qquad F F^T = K

    Parameters
    ----------
    g : callable
        Batched function: ``g(x)`` with x (M, n) -> (M,), or ``g(x, e)`` when ``extra`` is given.
    centers : array_like, shape (N, n) or (n,)
        The deterministic parts ``f(x, u)``.
    mean : array_like, shape (n,)
    cov : array_like, shape (n, n)
        Symmetric PSD, possibly singular.
    rule : SigmaPoints or GaussHermite, optional
        Default :class:`SigmaPoints` (exact for polynomials of degree <= 3).
    extra : array_like, shape (N, m), optional
        Per-row extra argument (e.g. the action ``u`` of ``l(x', u)``), repeated for every node.

    Returns
    -------
    ndarray, shape (N,)

    Raises
    ------
    ValueError
        Shapes do not match, non-finite input, ``cov`` not symmetric PSD, or ``g`` returns the wrong shape.
    """
    c = as_batch(centers, "centers", np.shape(centers)[-1])
    n = c.shape[1]
    mu = as_vector(mean, "mean", n)
    K = check_covariance(cov, "cov", n)
    rule = SigmaPoints() if rule is None else rule
    F = support_factor(K)
    r = F.shape[1]
    if r == 0:
        z, w = np.zeros((1, 0)), np.ones(1)
    else:
        z, w = rule.nodes(r)
    M = w.shape[0]
    pts = (c[:, None, :] + mu + (z @ F.T)[None, :, :]).reshape(-1, n)
    if extra is None:
        vals = np.asarray(g(pts), dtype=np.float64)
    else:
        e = np.asarray(extra, dtype=np.float64)
        e = e.reshape(c.shape[0], -1)
        vals = np.asarray(g(pts, np.repeat(e, M, axis=0)), dtype=np.float64)
    if vals.shape != (c.shape[0] * M,):
        raise ValueError(f"g: expected output shape ({c.shape[0] * M},), got {vals.shape}")
    return vals.reshape(c.shape[0], M) @ w
