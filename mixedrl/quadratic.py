"""Exact representations for linear dynamics: quadratic values, affine policies, the Lyapunov solver.

For ``x' = A x + B u + xi`` with ``xi ~ N(mu_hat, K_hat)`` (the mixed model, eq. 20) and the utility
charged on the **next** state (eq. 2), ``l(x', u) = x'^T Q x' + u^T R u``, the value of an affine
policy ``u = -L x - l0`` is exactly quadratic, ``V(x) = x^T P x + 2 p^T x + c``, and the PEV (eq. 21)
and PIM (eq. 22) steps of Algorithm 1 have closed forms: they live in :mod:`mixedrl.pev` and
:mod:`mixedrl.pim`, on the types of this module; the derivation is in ``docs/lq.rst``. The problem as a
whole (matrices, discount, true noise and prior) is one :class:`mixedrl.lq.LQProblem`, whose
``dynamics`` and ``cost`` are the :class:`LinearDynamics` and :class:`QuadraticCost` of this module.

Every expectation over ``xi`` is taken exactly with the identity, for a symmetric ``M``,

.. math:: \\mathbb{E}\\,[(m + \\xi)^T M (m + \\xi)] = (m + \\mu)^T M (m + \\mu) + \\operatorname{tr}(M K),
   \\qquad \\xi \\sim N(\\mu, K).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg

from mixedrl.checks import as_batch, as_matrix, as_vector, check_covariance

__all__ = ["LinearDynamics", "QuadraticCost", "QuadraticValue", "AffinePolicy", "lyapunov_solve", "is_nonnegative",
           "check_problem"]

#: Largest state dimension for which the discrete Lyapunov equation is solved by the Kronecker
#: ("direct") method of :func:`scipy.linalg.solve_discrete_lyapunov`; larger ones use "bilinear".
DIRECT_LYAPUNOV_MAX_N = 10


@dataclass(frozen=True)
class LinearDynamics:
    """The deterministic part ``f(x, u) = A x + B u`` of eq. (1) for a linear system.

    Parameters
    ----------
    A : ndarray, shape (n, n)
    B : ndarray, shape (n, m)
    """

    A: np.ndarray
    B: np.ndarray

    def __post_init__(self) -> None:
        A = as_matrix(self.A, "A")
        if A.shape[0] != A.shape[1]:
            raise ValueError(f"A: must be square, got {A.shape}")
        B = as_matrix(self.B, "B", (A.shape[0], None))
        object.__setattr__(self, "A", A)
        object.__setattr__(self, "B", B)

    @property
    def n(self) -> int:
        """State dimension."""
        return self.A.shape[0]

    @property
    def m(self) -> int:
        """Input dimension."""
        return self.B.shape[1]

    def __call__(self, x: Any, u: Any) -> np.ndarray:
        """Return ``f(x, u) = A x + B u`` for a batch, shape (N, n) (x: (N, n) or (n,), u: (N, m) or (m,))."""
        xb = as_batch(x, "x", self.n)
        ub = as_batch(u, "u", self.m)
        if xb.shape[0] != ub.shape[0]:
            raise ValueError(f"u: batch size {ub.shape[0]} differs from x's {xb.shape[0]}")
        return xb @ self.A.T + ub @ self.B.T


@dataclass(frozen=True)
class QuadraticCost:
    """Utility ``l(x', u) = x'^T Q x' + u^T R u`` charged on the next state (eq. 2).

    Parameters
    ----------
    Q : ndarray, shape (n, n), symmetric PSD
    R : ndarray, shape (m, m), symmetric positive definite
    """

    Q: np.ndarray
    R: np.ndarray

    def __post_init__(self) -> None:
        Q = check_covariance(self.Q, "Q")
        R = check_covariance(self.R, "R")
        if np.linalg.eigvalsh(R)[0] <= 0.0:
            raise ValueError("R: must be positive definite")
        object.__setattr__(self, "Q", Q)
        object.__setattr__(self, "R", R)

    def __call__(self, x_next: Any, u: Any) -> np.ndarray:
        """Return ``l(x', u)`` for a batch, shape (N,)."""
        xb = as_batch(x_next, "x_next", self.Q.shape[0])
        ub = as_batch(u, "u", self.R.shape[0])
        return np.einsum("ni,ij,nj->n", xb, self.Q, xb) + np.einsum("ni,ij,nj->n", ub, self.R, ub)


@dataclass(frozen=True)
class QuadraticValue:
    """Quadratic value ``V(x) = x^T P x + 2 p^T x + c``.

    Parameters
    ----------
    P : ndarray, shape (n, n), symmetric
    p : ndarray, shape (n,)
    c : float
    """

    P: np.ndarray
    p: np.ndarray
    c: float

    def __post_init__(self) -> None:
        P = as_matrix(self.P, "P")
        if P.shape[0] != P.shape[1]:
            raise ValueError(f"P: must be square, got {P.shape}")
        object.__setattr__(self, "P", 0.5 * (P + P.T))
        object.__setattr__(self, "p", as_vector(self.p, "p", P.shape[0]))
        c = float(self.c)
        if not np.isfinite(c):
            raise ValueError("c: contains NaN or inf")
        object.__setattr__(self, "c", c)

    def __call__(self, x: Any) -> np.ndarray:
        """Return ``V(x)`` for a batch, shape (N,)."""
        xb = as_batch(x, "x", self.P.shape[0])
        return np.einsum("ni,ij,nj->n", xb, self.P, xb) + 2.0 * xb @ self.p + self.c

    def expected(self, center: Any, mean: Any, cov: Any) -> np.ndarray:
        """Return ``E V(center + xi)``, ``xi ~ N(mean, cov)``, exactly: ``V(center + mean) + tr(P cov)``.

        Parameters
        ----------
        center : ndarray, shape (N, n) or (n,)
        mean : ndarray, shape (n,)
        cov : ndarray, shape (n, n)
        """
        n = self.P.shape[0]
        mu = as_vector(mean, "mean", n)
        K = check_covariance(cov, "cov", n)
        return self(as_batch(center, "center", n) + mu) + float(np.sum(self.P * K))

    def __sub__(self, other: "QuadraticValue") -> "QuadraticValue":
        """The quadratic ``V - W`` (parameters subtracted)."""
        return QuadraticValue(self.P - other.P, self.p - other.p, self.c - other.c)

    def distance(self, other: "QuadraticValue") -> float:
        """Largest absolute difference of the parameters (P, p, c): the ``|V^{k+1} - V^k|`` of Algorithm 1."""
        return float(max(np.max(np.abs(self.P - other.P)), np.max(np.abs(self.p - other.p)), abs(self.c - other.c)))


@dataclass(frozen=True)
class AffinePolicy:
    """Affine policy ``u = pi(x) = -L x - l0`` (eq. 3).

    Parameters
    ----------
    L : ndarray, shape (m, n)
        Gain.
    l0 : ndarray, shape (m,)
        Offset.
    """

    L: np.ndarray
    l0: np.ndarray

    def __post_init__(self) -> None:
        L = as_matrix(self.L, "L")
        object.__setattr__(self, "L", L)
        object.__setattr__(self, "l0", as_vector(self.l0, "l0", L.shape[0]))

    def __call__(self, x: Any) -> np.ndarray:
        """Return ``u = -L x - l0`` for a batch, shape (N, m)."""
        xb = as_batch(x, "x", self.L.shape[1])
        return -xb @ self.L.T - self.l0

    def distance(self, other: "AffinePolicy") -> float:
        """Largest absolute difference of the parameters (L, l0): the ``|pi^{k+1} - pi^k|`` of Algorithm 1."""
        return float(max(np.max(np.abs(self.L - other.L)), np.max(np.abs(self.l0 - other.l0))))


def lyapunov_solve(a: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Solve the discrete Lyapunov equation ``X = a^T X a + w`` for symmetric ``X``.

    Parameters
    ----------
    a : ndarray, shape (n, n)
        Must have spectral radius < 1.
    w : ndarray, shape (n, n), symmetric

    Returns
    -------
    X : ndarray, shape (n, n), symmetric

    Raises
    ------
    ValueError
        If ``a`` has spectral radius >= 1 (no unique solution with a convergent series).

    Notes
    -----
    Uses :func:`scipy.linalg.solve_discrete_lyapunov` (which solves ``A X A^H - X + Q = 0``) with
    ``A = a^T`` and a named method: "direct" (Kronecker) for ``n <= 10``, "bilinear" above.
    """
    rho = float(np.max(np.abs(np.linalg.eigvals(a)))) if a.size else 0.0
    if rho >= 1.0:
        raise ValueError(f"a: spectral radius {rho:.6g} >= 1, the Lyapunov series diverges")
    method = "direct" if a.shape[0] <= DIRECT_LYAPUNOV_MAX_N else "bilinear"
    X = scipy.linalg.solve_discrete_lyapunov(a.T, w, method=method)
    return 0.5 * (X + X.T)


def is_nonnegative(value: QuadraticValue, rtol: float = 1e-9) -> bool:
    """Return whether ``V(x) = x^T P x + 2 p^T x + c >= 0`` for **every** x.

    That holds iff the ``(n+1) x (n+1)`` matrix ``[[P, p], [p^T, c]]`` is positive semi-definite;
    its smallest eigenvalue is compared with ``-rtol * max(1, largest |eigenvalue|)`` (rounding).
    """
    eig = np.linalg.eigvalsh(np.block([[value.P, value.p[:, None]], [value.p[None, :], np.array([[value.c]])]]))
    return bool(eig[0] >= -rtol * max(1.0, float(np.max(np.abs(eig)))))


def check_problem(dynamics: LinearDynamics, cost: QuadraticCost, gamma: float) -> float:
    """Validate a linear-quadratic problem for the exact PEV and PIM; return ``gamma`` as a float.

    Parameters
    ----------
    dynamics : LinearDynamics
        A (n, n), B (n, m).
    cost : QuadraticCost
        Q (n, n), R (m, m).
    gamma : float
        Discount factor.

    Returns
    -------
    float
        ``gamma``.

    Raises
    ------
    ValueError
        ``Q``/``R`` do not match ``(n, m)``, or ``gamma`` not in (0, 1).
    """
    if cost.Q.shape[0] != dynamics.n or cost.R.shape[0] != dynamics.m:
        raise ValueError(
            f"cost: Q {cost.Q.shape} / R {cost.R.shape} do not match n={dynamics.n}, m={dynamics.m}"
        )
    g = float(gamma)
    if not (0.0 < g < 1.0):
        raise ValueError(f"gamma: must lie in (0, 1), got {gamma!r}")
    return g
