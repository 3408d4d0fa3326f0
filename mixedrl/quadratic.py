"""Exact representations for linear dynamics: quadratic values, affine policies, exact PEV and PIM.

For ``x' = A x + B u + xi`` with ``xi ~ N(mu_hat, K_hat)`` (the mixed model, eq. 20) and the utility
charged on the **next** state (eq. 2), ``l(x', u) = x'^T Q x' + u^T R u``, the value of an affine
policy ``u = -L x - l0`` is exactly quadratic, ``V(x) = x^T P x + 2 p^T x + c``, and the PEV (eq. 21)
and PIM (eq. 22) steps of Algorithm 1 have closed forms. This module computes them; the derivation
is in ``docs/lq.rst``.

Every expectation over ``xi`` is taken exactly with the identity, for a symmetric ``M``,

.. math:: \\mathbb{E}\\,[(m + \\xi)^T M (m + \\xi)] = (m + \\mu)^T M (m + \\mu) + \\operatorname{tr}(M K),
   \\qquad \\xi \\sim N(\\mu, K).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg

from mixedrl._checks import as_batch, as_matrix, as_vector, check_covariance

__all__ = [
    "LinearDynamics",
    "QuadraticCost",
    "QuadraticValue",
    "AffinePolicy",
    "evaluate_policy",
    "improve_policy",
    "ExactPEV",
    "ExactPIM",
    "lyapunov_solve",
    "bellman_backup",
    "is_nonnegative",
]

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


def _check_model(dynamics: LinearDynamics, cost: QuadraticCost, gamma: float) -> float:
    if cost.Q.shape[0] != dynamics.n or cost.R.shape[0] != dynamics.m:
        raise ValueError(
            f"cost: Q {cost.Q.shape} / R {cost.R.shape} do not match n={dynamics.n}, m={dynamics.m}"
        )
    g = float(gamma)
    if not (0.0 < g < 1.0):
        raise ValueError(f"gamma: must lie in (0, 1), got {gamma!r}")
    return g


def evaluate_policy(
    dynamics: LinearDynamics,
    cost: QuadraticCost,
    gamma: float,
    policy: AffinePolicy,
    noise_mean: Any,
    noise_cov: Any,
) -> QuadraticValue:
    """Implements eq. (21): exact PEV of an affine policy under the mixed model ``N(mu_hat, K_hat)``.

    .. math::
        V^k(x) = \\mathbb{E}_{\\hat\\xi_k}\\{ l(x', \\pi^k(x)) + \\gamma V^k(x') \\},\\quad
        x' = A x + B \\pi^k(x) + \\hat\\xi_k,\\ \\hat\\xi_k \\sim N(\\hat\\mu_k, \\hat K_k).

    With ``A_c = A - B L``, ``d = mu_hat - B l0``, ``S = Q + gamma P`` and ``V = x^T P x + 2 p^T x + c``,
    matching the quadratic, linear and constant terms gives

    .. math::
        P &= \\gamma A_c^T P A_c + A_c^T Q A_c + L^T R L \\\\
        (I - \\gamma A_c^T)\\, p &= A_c^T S d + L^T R\\, l_0 \\\\
        (1 - \\gamma)\\, c &= d^T S d + \\operatorname{tr}(S \\hat K) + l_0^T R\\, l_0 + 2 \\gamma\\, p^T d .

    Parameters
    ----------
    dynamics : LinearDynamics
        ``f(x, u) = A x + B u``, A (n, n), B (n, m).
    cost : QuadraticCost
        Q (n, n), R (m, m); utility on the next state (eq. 2).
    gamma : float
        Discount factor in (0, 1).
    policy : AffinePolicy
        L (m, n), l0 (m,).
    noise_mean : ndarray, shape (n,)
        ``mu_hat_k``.
    noise_cov : ndarray, shape (n, n)
        ``K_hat_k`` (symmetric PSD).

    Returns
    -------
    QuadraticValue
        ``V^k`` with P (n, n), p (n,), c.

    Raises
    ------
    ValueError
        Shapes do not match, gamma not in (0, 1), the covariance is not symmetric PSD, or the policy is
        not stabilising for the discounted problem (spectral radius of ``sqrt(gamma) A_c`` >= 1, so
        eq. 21 has no finite solution).

    Notes
    -----
    The expectation over ``xi_hat`` is exact (no sampling): ``E V(x') = V(E x') + tr(P K_hat)``.
    The quadratic term is a discrete Lyapunov equation in ``sqrt(gamma) A_c`` solved by
    :func:`lyapunov_solve`; the linear term is a linear system with matrix ``I - gamma A_c^T``,
    non-singular because ``rho(gamma A_c) < sqrt(gamma) < 1``.
    """
    g = _check_model(dynamics, cost, gamma)
    n, m = dynamics.n, dynamics.m
    if policy.L.shape != (m, n):
        raise ValueError(f"policy: gain shape {policy.L.shape} does not match (m, n) = ({m}, {n})")
    mu = as_vector(noise_mean, "noise_mean", n)
    K = check_covariance(noise_cov, "noise_cov", n)
    A, B, Q, R = dynamics.A, dynamics.B, cost.Q, cost.R
    L, l0 = policy.L, policy.l0
    Ac = A - B @ L
    rho = float(np.max(np.abs(np.linalg.eigvals(np.sqrt(g) * Ac))))
    if rho >= 1.0:
        raise ValueError(
            f"policy: not stabilising for the discounted problem (spectral radius of sqrt(gamma)(A - B L) = {rho:.6g} >= 1)"
        )
    # P = gamma A_c^T P A_c + A_c^T Q A_c + L^T R L   (quadratic terms of eq. 21)
    P = lyapunov_solve(np.sqrt(g) * Ac, Ac.T @ Q @ Ac + L.T @ R @ L)
    S = Q + g * P
    d = mu - B @ l0
    # (I - gamma A_c^T) p = A_c^T S d + L^T R l0   (linear terms of eq. 21)
    p = np.linalg.solve(np.eye(n) - g * Ac.T, Ac.T @ S @ d + L.T @ R @ l0)
    # (1 - gamma) c = d^T S d + tr(S K) + l0^T R l0 + 2 gamma p^T d   (constant terms of eq. 21)
    c = (d @ S @ d + float(np.sum(S * K)) + l0 @ R @ l0 + 2.0 * g * p @ d) / (1.0 - g)
    return QuadraticValue(P, p, c)


def improve_policy(
    dynamics: LinearDynamics,
    cost: QuadraticCost,
    gamma: float,
    value: QuadraticValue,
    noise_mean: Any,
) -> AffinePolicy:
    """Implements eq. (22): exact PIM, the closed-form minimiser under the mixed model.

    .. math::
        \\pi^{k+1}(x) = \\arg\\min_u \\mathbb{E}_{\\hat\\xi_k}\\{ l(x', u) + \\gamma V^k(x') \\}
        = -L x - l_0,\\quad
        L = (R + B^T S B)^{-1} B^T S A,\\quad
        l_0 = (R + B^T S B)^{-1} B^T (S \\hat\\mu_k + \\gamma p),

    with ``S = Q + gamma P`` from ``V^k = x^T P x + 2 p^T x + c``.

    Parameters
    ----------
    dynamics : LinearDynamics
        A (n, n), B (n, m).
    cost : QuadraticCost
        Q (n, n), R (m, m).
    gamma : float
        Discount factor in (0, 1).
    value : QuadraticValue
        ``V^k``: P (n, n), p (n,), c.
    noise_mean : ndarray, shape (n,)
        ``mu_hat_k``.

    Returns
    -------
    AffinePolicy
        ``pi^{k+1}``: L (m, n), l0 (m,).

    Raises
    ------
    ValueError
        Shapes do not match, gamma not in (0, 1), or ``R + B^T S B`` is not positive definite (the
        objective is then not strictly convex in ``u``).

    Notes
    -----
    The objective is ``u^T (R + B^T S B) u + 2 u^T B^T (S (A x + mu_hat) + gamma p) + const`` plus the
    term ``tr(S K_hat)``, which does not depend on ``u``: the noise covariance does not enter PIM.
    """
    g = _check_model(dynamics, cost, gamma)
    n = dynamics.n
    if value.P.shape != (n, n):
        raise ValueError(f"value: P shape {value.P.shape} does not match n = {n}")
    mu = as_vector(noise_mean, "noise_mean", n)
    A, B, Q, R = dynamics.A, dynamics.B, cost.Q, cost.R
    S = Q + g * value.P
    H = R + B.T @ S @ B
    try:
        chol = scipy.linalg.cho_factor(0.5 * (H + H.T))
    except np.linalg.LinAlgError:
        raise ValueError("value: R + B^T (Q + gamma P) B is not positive definite") from None
    # L = (R + B^T S B)^-1 B^T S A
    L = scipy.linalg.cho_solve(chol, B.T @ S @ A)
    # l0 = (R + B^T S B)^-1 B^T (S mu_hat + gamma p)
    l0 = scipy.linalg.cho_solve(chol, B.T @ (S @ mu + g * value.p))
    return AffinePolicy(L, l0)


def bellman_backup(
    dynamics: LinearDynamics,
    cost: QuadraticCost,
    gamma: float,
    policy: AffinePolicy,
    value: QuadraticValue,
    noise_mean: Any,
    noise_cov: Any,
) -> QuadraticValue:
    """Implements eq. (31): one PEV sweep ``V_1(x) = E_xi{ l(x', pi(x)) + gamma V(x') }``, exactly.

    .. math::
        (T^{\\pi} V)(x) = \\mathbb{E}_{\\hat\\xi}\\{ l(x', \\pi(x)) + \\gamma V(x') \\}
        = h(x, \\pi(x), \\hat\\xi)\\quad\\text{(eq. 37)}

    With ``S = Q + gamma P``, ``A_c = A - B L``, ``d = mu - B l0`` the result is
    ``P_1 = A_c^T S A_c + L^T R L``, ``p_1 = A_c^T (S d + gamma p) + L^T R l0``,
    ``c_1 = d^T S d + tr(S K) + l0^T R l0 + 2 gamma p^T d + gamma c``.

    Parameters
    ----------
    dynamics : LinearDynamics
    cost : QuadraticCost
    gamma : float
    policy : AffinePolicy
        L (m, n), l0 (m,).
    value : QuadraticValue
        P (n, n), p (n,), c.
    noise_mean : ndarray, shape (n,)
    noise_cov : ndarray, shape (n, n)

    Returns
    -------
    QuadraticValue

    Raises
    ------
    ValueError
        Shapes do not match, gamma outside (0, 1), covariance not symmetric PSD.

    Notes
    -----
    The fixed point of this map is :func:`evaluate_policy`; the theory tests use it to check the MVC
    (eq. 38) and value decrease (eq. 29) for *all* x at once (:func:`is_nonnegative`).
    """
    g = _check_model(dynamics, cost, gamma)
    n, m = dynamics.n, dynamics.m
    if policy.L.shape != (m, n) or value.P.shape != (n, n):
        raise ValueError("policy: shapes of policy/value do not match the dynamics")
    mu = as_vector(noise_mean, "noise_mean", n)
    K = check_covariance(noise_cov, "noise_cov", n)
    A, B, Q, R = dynamics.A, dynamics.B, cost.Q, cost.R
    L, l0 = policy.L, policy.l0
    Ac = A - B @ L
    S = Q + g * value.P
    d = mu - B @ l0
    P1 = Ac.T @ S @ Ac + L.T @ R @ L
    p1 = Ac.T @ (S @ d + g * value.p) + L.T @ R @ l0
    c1 = d @ S @ d + float(np.sum(S * K)) + l0 @ R @ l0 + 2.0 * g * value.p @ d + g * value.c
    return QuadraticValue(P1, p1, c1)


def is_nonnegative(value: QuadraticValue, rtol: float = 1e-9) -> bool:
    """Return whether ``V(x) = x^T P x + 2 p^T x + c >= 0`` for **every** x.

    That holds iff the ``(n+1) x (n+1)`` matrix ``[[P, p], [p^T, c]]`` is positive semi-definite;
    its smallest eigenvalue is compared with ``-rtol * max(1, largest |eigenvalue|)`` (rounding).
    """
    M = np.block([[value.P, value.p[:, None]], [value.p[None, :], np.array([[value.c]])]])
    eig = np.linalg.eigvalsh(0.5 * (M + M.T))
    return bool(eig[0] >= -rtol * max(1.0, float(np.max(np.abs(eig)))))


@dataclass(frozen=True)
class ExactPEV:
    """PEV step (eq. 21) bound to a linear-quadratic problem: ``pev(policy, noise) -> QuadraticValue``.

    ``noise`` is any object with ``.mean`` (n,) and ``.cov`` (n, n).
    """

    dynamics: LinearDynamics
    cost: QuadraticCost
    gamma: float

    def __call__(self, policy: AffinePolicy, noise: Any) -> QuadraticValue:
        """Return ``V^k`` of ``policy`` under ``N(noise.mean, noise.cov)`` (see :func:`evaluate_policy`)."""
        return evaluate_policy(self.dynamics, self.cost, self.gamma, policy, noise.mean, noise.cov)


@dataclass(frozen=True)
class ExactPIM:
    """PIM step (eq. 22) bound to a linear-quadratic problem: ``pim(value, noise) -> AffinePolicy``."""

    dynamics: LinearDynamics
    cost: QuadraticCost
    gamma: float

    def __call__(self, value: QuadraticValue, noise: Any) -> AffinePolicy:
        """Return ``pi^{k+1}`` greedy w.r.t. ``value`` under ``N(noise.mean, .)`` (see :func:`improve_policy`)."""
        return improve_policy(self.dynamics, self.cost, self.gamma, value, noise.mean)
