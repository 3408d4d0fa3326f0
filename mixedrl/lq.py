"""The discounted linear-quadratic problem, in one representation: :class:`LQProblem` and its optimum.

The problem (EQUATIONS.md, last section): ``x' = A x + B u + xi``, ``xi ~ N(mu, K)``, utility charged on
the next state ``l(x', u) = x'^T Q x' + u^T R u`` (eq. 2), discount ``gamma``, and the designer's prior
``N(mu_M, K_M)`` on the noise (eq. 8). Its other faces (:class:`mixedrl.linear_task.LinearTask`,
:class:`mixedrl.config.LinearTaskConfig`, :mod:`validation.lq`) are views of one :class:`LQProblem`, and
:func:`discounted_lq_optimum` is the one implementation of its optimum ``u = -L x - l0``,
``V*(x) = x^T P x + 2 p^T x + c`` (derived in docs/lq.rst).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import scipy.linalg

from mixedrl.checks import as_vector, check_covariance, check_fraction
from mixedrl.quadratic import AffinePolicy, LinearDynamics, QuadraticCost, QuadraticValue

__all__ = ["LQProblem", "LQSolution", "PBH_RTOL", "discounted_lq_optimum", "optimal_solution"]

#: Tolerance (relative to the largest singular value of ``[A - lambda I, B]``) of the PBH
#: stabilisability test in :class:`LQProblem`.
PBH_RTOL = 1e-10


def _sym(a: np.ndarray) -> np.ndarray:
    return 0.5 * (a + a.T)


@dataclass(frozen=True)
class LQProblem:
    """A discounted LQ problem with mean-shifted Gaussian noise and a designer's prior on the mean.

    Parameters
    ----------
    A : array_like, shape (n, n)
    B : array_like, shape (n, m)
        ``(A, B)`` must be stabilisable.
    Q : array_like, shape (n, n)
        Symmetric PSD state weight, charged on the next state (eq. 2).
    R : array_like, shape (m, m)
        Symmetric positive definite input weight.
    gamma : float
        Discount factor in (0, 1).
    noise_mean : array_like, shape (n,)
        True ``mu`` of eq. (1).
    noise_cov : array_like, shape (n, n)
        True ``K`` of eq. (1), symmetric PSD.
    prior_mean : array_like, shape (n,)
        ``mu_M`` of eq. (8).
    prior_cov : array_like, shape (n, n)
        ``K_M`` of eq. (8), symmetric PSD.

    Raises
    ------
    ValueError
        Wrong shapes, NaN/inf, covariances or Q not symmetric PSD, R not positive definite, gamma
        outside (0, 1), or ``(A, B)`` not stabilisable; the message starts with the argument name.
    """

    A: np.ndarray
    B: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    gamma: float
    noise_mean: np.ndarray
    noise_cov: np.ndarray
    prior_mean: np.ndarray
    prior_cov: np.ndarray
    n = LinearDynamics.n
    m = LinearDynamics.m

    @property
    def true_mean(self) -> np.ndarray:
        """``noise_mean`` (the name :func:`mixedrl.noise.make_noise_source` reads)."""
        return self.noise_mean

    @property
    def true_cov(self) -> np.ndarray:
        """``noise_cov`` (the name :func:`mixedrl.noise.make_noise_source` reads)."""
        return self.noise_cov

    def __post_init__(self) -> None:
        dynamics = LinearDynamics(self.A, self.B)
        A, B, n, m = dynamics.A, dynamics.B, dynamics.n, dynamics.m
        if m < 1:
            raise ValueError("B: needs at least one column")
        cost = QuadraticCost(check_covariance(self.Q, "Q", n), check_covariance(self.R, "R", m))  # R: definite
        gamma = check_fraction(self.gamma, "gamma", low_open=True, high_open=True)
        vals = {"A": A, "B": B, "Q": cost.Q, "R": cost.R, "gamma": gamma}
        for key, check in (("noise_mean", as_vector), ("noise_cov", check_covariance), ("prior_mean", as_vector),
                           ("prior_cov", check_covariance)):
            vals[key] = check(getattr(self, key), key, n)
        eigs = np.linalg.eigvals(A)
        for lam in eigs[np.abs(eigs) >= 1.0]:  # PBH test: rank [A - lambda I, B] = n for every |lambda| >= 1
            sv = np.linalg.svd(np.hstack([A - lam * np.eye(n), B.astype(complex)]), compute_uv=False)
            if sv[-1] <= PBH_RTOL * max(1.0, sv[0]):
                raise ValueError("A: (A, B) is not stabilisable (PBH test)")
        for key, val in vals.items():
            object.__setattr__(self, key, val)

    @property
    def dynamics(self) -> LinearDynamics:
        """``f(x, u) = A x + B u``."""
        return LinearDynamics(self.A, self.B)

    @property
    def cost(self) -> QuadraticCost:
        """``l(x', u) = x'^T Q x' + u^T R u``."""
        return QuadraticCost(self.Q, self.R)

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form (lists)."""
        return {f.name: np.asarray(getattr(self, f.name)).tolist() for f in fields(self)}


@dataclass(frozen=True)
class LQSolution:
    """The optimal (affine policy, quadratic value) of an :class:`LQProblem` for a given noise.

    Attributes
    ----------
    gain : ndarray, shape (m, n)
        ``L``.
    offset : ndarray, shape (m,)
        ``l0``.
    P : ndarray, shape (n, n)
    p : ndarray, shape (n,)
    c : float
        ``V*(x) = x^T P x + 2 p^T x + c``.
    S : ndarray, shape (n, n)
        ``S = Q + gamma P``, the DARE solution.
    """

    gain: np.ndarray
    offset: np.ndarray
    P: np.ndarray
    p: np.ndarray
    c: float
    S: np.ndarray

    @property
    def policy(self) -> AffinePolicy:
        """``u = -L x - l0``."""
        return AffinePolicy(self.gain, self.offset)

    @property
    def value(self) -> QuadraticValue:
        """``V*``."""
        return QuadraticValue(self.P, self.p, self.c)


def discounted_lq_optimum(A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray, gamma: float,
                          mu: np.ndarray, K: np.ndarray | None = None) -> LQSolution:
    """Implements the discounted LQ optimum with next-state cost and mean-shifted noise (EQUATIONS.md, last section).

    .. math::
        S &= \\mathrm{DARE}(\\sqrt\\gamma A, \\sqrt\\gamma B, Q, \\gamma R),\\quad P = (S - Q)/\\gamma,\\quad
        L = (R + B^T S B)^{-1} B^T S A \\\\
        \\begin{bmatrix} I - \\gamma A_c^T & A_c^T S B - L^T R \\\\ -\\gamma B^T & R + B^T S B \\end{bmatrix}
        \\begin{bmatrix} p \\\\ l_0 \\end{bmatrix} &=
        \\begin{bmatrix} A_c^T S \\mu \\\\ B^T S \\mu \\end{bmatrix},\\quad A_c = A - B L \\\\
        (1-\\gamma)\\, c &= d^T S d + \\operatorname{tr}(S K) + l_0^T R l_0 + 2\\gamma p^T d,\\quad d = \\mu - B l_0

    for ``x' = A x + B u + xi``, ``xi ~ N(mu, K)``, ``l = x'^T Q x' + u^T R u``, policy ``u = -L x - l0``,
    value ``V*(x) = x^T P x + 2 p^T x + c``. Solved with :func:`scipy.linalg.solve_discrete_are`.

    Parameters
    ----------
    A : numpy.ndarray, shape (n, n)
    B : numpy.ndarray, shape (n, m)
    Q : numpy.ndarray, shape (n, n)
        Symmetric PSD.
    R : numpy.ndarray, shape (m, m)
        Symmetric positive definite.
    gamma : float
        Discount in (0, 1] (validated by the callers; 1 is allowed: ``L``, ``l0``, ``P`` and ``p`` stay
        finite when ``A_c`` is stable, and ``c`` is then ``inf``).
    mu : numpy.ndarray, shape (n,)
        Noise mean.
    K : numpy.ndarray, shape (n, n), optional
        Noise covariance, only for ``c`` (default 0).

    Returns
    -------
    LQSolution

    Raises
    ------
    ValueError
        The DARE has no stabilising solution (message names ``Q``: e.g. ``(sqrt(gamma) A, Q^{1/2})``
        has an unobservable mode on the unit circle).

    Notes
    -----
    The block ``A_c^T S B - L^T R`` vanishes at the DARE solution (``L^T (R + B^T S B) = A^T S B``),
    so ``p = (I - gamma A_c^T)^{-1} A_c^T S mu`` (docs/lq.rst); it is kept in the system as it comes
    from the PEV and PIM equations, and the tests check the two forms agree.
    """
    A, B, Q, R, mu = (np.asarray(a, dtype=np.float64) for a in (A, B, Q, R, mu))
    n, g = A.shape[0], float(gamma)
    K = np.zeros((n, n)) if K is None else np.asarray(K, dtype=np.float64)
    # S solves the DARE with (sqrt(gamma) A, sqrt(gamma) B, Q, gamma R); L as python-control's dare(method="scipy")
    # computes it from S (the same calls, so the same bits), without importing python-control (~1 s: it pulls in
    # scipy.signal and matplotlib.pyplot); tests/test_lq.py checks both against python-control's dare, bit for bit.
    As, Bs, Rs = math.sqrt(g) * A, math.sqrt(g) * B, g * R
    try:
        S = scipy.linalg.solve_discrete_are(As, Bs, Q, Rs)
        L = scipy.linalg.solve(Bs.T @ S @ Bs + Rs, Bs.T @ S @ As)
    except (np.linalg.LinAlgError, ValueError) as exc:
        raise ValueError(f"Q: the DARE has no stabilising solution ({exc})") from None
    S = _sym(S)
    P = _sym((S - Q) / g)
    Ac = A - B @ L
    # [[I - g Ac^T, Ac^T S B - L^T R], [-g B^T, R + B^T S B]] [p; l0] = [Ac^T S mu; B^T S mu]
    M = np.block([[np.eye(n) - g * Ac.T, Ac.T @ S @ B - L.T @ R], [-g * B.T, R + B.T @ S @ B]])
    rhs = np.concatenate([Ac.T @ S @ mu, B.T @ S @ mu])
    sol = np.linalg.solve(M, rhs)
    p, l0 = sol[:n], sol[n:]
    d = mu - B @ l0
    # (1 - g) c = d^T S d + tr(S K) + l0^T R l0 + 2 g p^T d
    c = math.inf if g == 1.0 else float((d @ S @ d + np.sum(S * K) + l0 @ R @ l0 + 2.0 * g * p @ d) / (1.0 - g))
    return LQSolution(gain=L, offset=l0, P=P, p=p, c=c, S=S)


def optimal_solution(problem: LQProblem, noise_mean: Any = None, noise_cov: Any = None) -> LQSolution:
    """Implements eqs. (6)-(7) for the LQ case: :func:`discounted_lq_optimum` of an :class:`LQProblem`.

    Parameters
    ----------
    problem : LQProblem
    noise_mean : array_like, shape (n,), optional
        The mean to optimise for (default ``problem.noise_mean``). Pass ``problem.prior_mean`` to get
        the policy that the prior predicts (model-driven RL's limit), or an IBE estimate.
    noise_cov : array_like, shape (n, n), optional
        The covariance for ``c`` (default ``problem.noise_cov``); it does not affect L, l0, P or p.

    Returns
    -------
    LQSolution

    Raises
    ------
    ValueError
        Bad ``noise_mean``/``noise_cov``, or the DARE has no stabilising solution (message names ``Q``).
    """
    n = problem.n
    mu = problem.noise_mean if noise_mean is None else as_vector(noise_mean, "noise_mean", n)
    K = problem.noise_cov if noise_cov is None else check_covariance(noise_cov, "noise_cov", n)
    return discounted_lq_optimum(problem.A, problem.B, problem.Q, problem.R, problem.gamma, mu, K)
