"""Empirical checks of Theorems 1-4 on any model, value and policy.

Interfaces (all batched, numpy):

* value ``V(x)``: x (N, n) -> (N,);
* policy ``pi(x)``: x (N, n) -> (N, m);
* deterministic dynamics ``f(x, u)``: (N, n), (N, m) -> (N, n);
* utility ``l(x', u)``: (N, n), (N, m) -> (N,) (charged on the next state, eq. 2);
* noise: any object with ``.mean`` (n,) and ``.cov`` (n, n) (an IBE, a :class:`mixedrl.noise.GaussianNoise`).

Expectations over ``xi_hat ~ N(mean, cov)`` use the nodes of :mod:`mixedrl.expectation` (the same
module, support cut-off and ``h`` of eq. 37 as Algorithm 2: :func:`expected_cost_to_go` is
:func:`mixedrl.expectation.expected_cost_to_go`, re-exported) with a stated rule:
:class:`~mixedrl.expectation.SigmaPoints` by default, exact for polynomials of degree <= 3 (so exact for
quadratic values and utilities); :class:`~mixedrl.expectation.GaussHermite` otherwise.

A check evaluates a *margin* at every given state, positive when the inequality holds with room, and
counts the inequality as held where ``margin >= -tol``, with the rounding tolerance
``tol = rtol * (|lhs| + |rhs|)`` (default ``rtol = 1e-9``: exact PEV/PIM results agree with their
equations to about 1e-12 relative, so this only absorbs rounding; it is not tuned to make a check pass).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from mixedrl.checks import as_batch
from mixedrl.expectation import GaussHermite, SigmaPoints, expected_cost_to_go, gaussian_expectation
from mixedrl.gaussian import kl_divergence
from mixedrl.pim import mvc_terms

__all__ = [
    "DEFAULT_RTOL",
    "CheckReport",
    "IBEShiftReport",
    "lyapunov_decrease",
    "value_decrease",
    "mvc",
    "ibe_shift",
    "expected_cost_to_go",
]

#: Relative rounding tolerance of every check (see the module docstring).
DEFAULT_RTOL = 1e-9

Rule = SigmaPoints | GaussHermite | None


@dataclass(frozen=True)
class CheckReport:
    """Outcome of a pointwise check on a batch of states.

    Attributes
    ----------
    name : str
        Which check (``"lyapunov_decrease"``, ``"value_decrease"``, ``"mvc"``).
    equation : str
        The equation checked (project numbering).
    states : ndarray, shape (N, n)
    margins : ndarray, shape (N,)
        ``rhs - lhs`` of the inequality ``lhs <= rhs``: positive where it holds with room.
    tolerance : ndarray, shape (N,)
        Rounding tolerance per state; held where ``margin >= -tolerance``.
    extra : dict
        Check-specific figures (documented in each check).
    """

    name: str
    equation: str
    states: np.ndarray
    margins: np.ndarray
    tolerance: np.ndarray
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def held_mask(self) -> np.ndarray:
        """Boolean (N,): where the inequality held."""
        return self.margins >= -self.tolerance

    @property
    def n_states(self) -> int:
        """Number of states checked."""
        return int(self.margins.shape[0])

    @property
    def held_fraction(self) -> float:
        """Fraction of states where the inequality held."""
        return float(np.mean(self.held_mask)) if self.n_states else 1.0

    @property
    def held(self) -> bool:
        """True when it held at every state."""
        return bool(np.all(self.held_mask))

    @property
    def worst_margin(self) -> float:
        """Smallest margin (negative: the largest violation)."""
        return float(np.min(self.margins)) if self.n_states else float("inf")

    @property
    def failed_states(self) -> np.ndarray:
        """States (K, n) where it failed."""
        return self.states[~self.held_mask]

    @property
    def failed_margins(self) -> np.ndarray:
        """Margins (K,) where it failed."""
        return self.margins[~self.held_mask]

    def failed_norm_range(self) -> tuple[float, float] | None:
        """``(min, max)`` Euclidean norm of the failed states, ``None`` if it never failed."""
        if self.held:
            return None
        norms = np.linalg.norm(self.failed_states, axis=1)
        return float(norms.min()), float(norms.max())

    def summary(self) -> dict[str, Any]:
        """JSON-serialisable summary: name, equation, n_states, held_fraction, worst_margin, failed norm range."""
        rng = self.failed_norm_range()
        out: dict[str, Any] = {
            "name": self.name,
            "equation": self.equation,
            "n_states": self.n_states,
            "held_fraction": self.held_fraction,
            "worst_margin": self.worst_margin,
            "failed_norm_min": None if rng is None else rng[0],
            "failed_norm_max": None if rng is None else rng[1],
        }
        for key, val in self.extra.items():
            if isinstance(val, (bool, int, float, str)) or val is None:
                out[key] = val
        return out


@dataclass(frozen=True)
class IBEShiftReport:
    """Outcome of :func:`ibe_shift`: how far the noise moved between two iterations (eq. 45).

    Attributes
    ----------
    kl : float
        ``KL(N(mu_k, K_k) || N(mu_{k+1}, K_{k+1}))`` (``inf`` if the supports differ).
    mean_shift : float
        ``||mu_{k+1} - mu_k||_2``.
    cov_shift : float
        ``||K_{k+1} - K_k||_F``.
    """

    kl: float
    mean_shift: float
    cov_shift: float

    def summary(self) -> dict[str, Any]:
        """JSON-serialisable summary."""
        return {"name": "ibe_shift", "equation": "45", "kl": self.kl, "mean_shift": self.mean_shift, "cov_shift": self.cov_shift}


def _states(states: Any) -> np.ndarray:
    arr = np.asarray(states, dtype=np.float64)
    return as_batch(arr, "states", arr.shape[-1] if arr.ndim else 0)


def _values(fn: Callable[..., Any], name: str, n: int, *args: np.ndarray) -> np.ndarray:
    out = np.asarray(fn(*args), dtype=np.float64)
    if out.shape != (n,):
        raise ValueError(f"{name}: expected output shape ({n},), got {out.shape}")
    return out


def lyapunov_decrease(
    value: Callable[[np.ndarray], np.ndarray],
    policy: Callable[[np.ndarray], np.ndarray],
    f: Callable[[np.ndarray, np.ndarray], np.ndarray],
    noise: Any,
    states: Any,
    rule: Rule = None,
    rtol: float = DEFAULT_RTOL,
) -> CheckReport:
    """Check eq. (28) / eq. (41): ``E V^k(x') <= V^k(x)`` with ``x' = f(x, pi^{k+1}(x)) + xi_hat``.

    .. math:: V^k(x) \\ge \\mathbb{E}_{\\hat\\xi}\\{ V^k(x') \\},\\qquad x' = f(x, \\pi^{k+1}(x)) + \\hat\\xi

    Parameters
    ----------
    value : callable
        ``V^k``, (N, n) -> (N,).
    policy : callable
        ``pi^{k+1}``, (N, n) -> (N, m).
    f : callable
        Deterministic dynamics.
    noise : object
        ``xi_hat``: ``xi_hat_k`` for Theorem 1 (eq. 28, fixed noise), ``xi_hat_{k+1}`` for Theorem 3
        (eq. 41, varying noise).
    states : array_like, shape (N, n)
        Where to check.
    rule : SigmaPoints or GaussHermite, optional
    rtol : float
        Rounding tolerance (module docstring).

    Returns
    -------
    CheckReport
        margin ``V^k(x) - E V^k(x')``; ``extra["expected_next"]`` (N,) holds ``E V^k(x')``.

    Raises
    ------
    ValueError
        Shapes do not match, or a callable returns the wrong shape.

    Notes
    -----
    Theorem 1 assumes ``V^k`` and ``l`` positive definite. With noise the value at the target is
    not zero (``c > 0``, and a mean shift makes the target itself move), so the inequality cannot
    hold near the target (EQUATIONS.md point 13); the report says where it failed.
    """
    x = _states(states)
    vx = _values(value, "value", x.shape[0], x)
    u = np.asarray(policy(x), dtype=np.float64).reshape(x.shape[0], -1)
    centers = np.asarray(f(x, u), dtype=np.float64)
    ev = gaussian_expectation(lambda z: np.asarray(value(z), dtype=np.float64), centers, noise.mean, noise.cov, rule)
    margin = vx - ev
    tol = rtol * (np.abs(vx) + np.abs(ev))
    return CheckReport("lyapunov_decrease", "28/41", x, margin, tol, {"expected_next": ev})


def value_decrease(
    value: Callable[[np.ndarray], np.ndarray],
    next_value: Callable[[np.ndarray], np.ndarray],
    states: Any,
    rtol: float = DEFAULT_RTOL,
) -> CheckReport:
    """Check eq. (29) / eq. (42): ``V^{k+1}(x) <= V^k(x)``.

    .. math:: V^k(x) \\ge V^{k+1}(x)

    Parameters
    ----------
    value : callable
        ``V^k``, (N, n) -> (N,).
    next_value : callable
        ``V^{k+1}``, (N, n) -> (N,).
    states : array_like, shape (N, n)
    rtol : float

    Returns
    -------
    CheckReport
        margin ``V^k(x) - V^{k+1}(x)``.

    Raises
    ------
    ValueError
        A callable returns the wrong shape.
    """
    x = _states(states)
    v0 = _values(value, "value", x.shape[0], x)
    v1 = _values(next_value, "next_value", x.shape[0], x)
    return CheckReport("value_decrease", "29/42", x, v0 - v1, rtol * (np.abs(v0) + np.abs(v1)))


def mvc(
    value: Callable[[np.ndarray], np.ndarray],
    policy: Callable[[np.ndarray], np.ndarray],
    next_policy: Callable[[np.ndarray], np.ndarray],
    f: Callable[[np.ndarray, np.ndarray], np.ndarray],
    utility: Callable[[np.ndarray, np.ndarray], np.ndarray],
    gamma: float,
    noise: Any,
    next_noise: Any,
    states: Any,
    rule: Rule = None,
    rtol: float = DEFAULT_RTOL,
) -> CheckReport:
    """Check the maximum variation condition, eq. (38), with ``e_k`` from eq. (39).

    .. math::
        h(x, u^{k+1}, \\hat\\xi_{k+1}) - h(x, u^{k+1}, \\hat\\xi_k) \\le e_k(x),\\qquad
        e_k(x) = h(x, u^k, \\hat\\xi_k) - h(x, u^{k+1}, \\hat\\xi_k) \\ge 0

    with ``h`` of eq. (37) (:func:`expected_cost_to_go`), ``u^k = pi^k(x)``, ``u^{k+1} = pi^{k+1}(x)``;
    both sides come from :func:`mixedrl.pim.mvc_terms`, the function of Algorithm 2's MVC.

    Parameters
    ----------
    value : callable
        ``V^k``.
    policy, next_policy : callable
        ``pi^k`` and ``pi^{k+1}``.
    f, utility : callable
        Deterministic dynamics and utility (eq. 2).
    gamma : float
    noise, next_noise : object
        ``xi_hat_k`` and ``xi_hat_{k+1}`` (``.mean``, ``.cov``).
    states : array_like, shape (N, n)
    rule : SigmaPoints or GaussHermite, optional
    rtol : float

    Returns
    -------
    CheckReport
        margin ``e_k(x) - [h(x,u^{k+1},xi_{k+1}) - h(x,u^{k+1},xi_k)]`` (pointwise MVC, every state).
        ``extra``: ``e`` (N,), ``variation`` (N,) (the left side), ``e_nonnegative_fraction`` and
        ``e_worst`` (eq. 39's claim ``e_k >= 0``, with the same tolerance), ``held_on_batch_mean``
        (the batch form ``mean(variation) <= mean(e)``; EQUATIONS.md point 12).

    Raises
    ------
    ValueError
        Shapes do not match, or a callable returns the wrong shape.

    Notes
    -----
    When ``V^k`` is the exact PEV solution under ``xi_hat_k``, ``h(x, u^k, xi_hat_k) = V^k(x)``
    (eq. 35), so the MVC margin equals ``V^k(x) - h(x, u^{k+1}, xi_hat_{k+1})``, the margin of eq. (40).
    """
    x = _states(states)
    uk = np.asarray(policy(x), dtype=np.float64).reshape(x.shape[0], -1)
    uk1 = np.asarray(next_policy(x), dtype=np.float64).reshape(x.shape[0], -1)
    h_k_k = expected_cost_to_go(value, f, utility, gamma, x, uk, noise, rule)
    h_k1_k = expected_cost_to_go(value, f, utility, gamma, x, uk1, noise, rule)
    h_k1_k1 = expected_cost_to_go(value, f, utility, gamma, x, uk1, next_noise, rule)
    scale = np.abs(h_k_k) + np.abs(h_k1_k) + np.abs(h_k1_k1)
    tol = rtol * scale
    # eqs. (38)-(39), the function Algorithm 2's MVC uses
    terms = mvc_terms(h_k1_k1, h_k1_k, h_k_k, tolerance=tol)
    e, variation = terms.e, terms.variation
    e_ok = e >= -rtol * (np.abs(h_k_k) + np.abs(h_k1_k))
    extra = {
        "e": e,
        "variation": variation,
        "e_nonnegative_fraction": float(np.mean(e_ok)),
        "e_worst": float(np.min(e)),
        "held_on_batch_mean": terms.held_on_mean,
    }
    return CheckReport("mvc", "38/39", x, e - variation, tol, extra)


def ibe_shift(noise: Any, next_noise: Any) -> IBEShiftReport:
    """Measure eq. (45): ``KL(p(xi_hat_k) || p(xi_hat_{k+1}))`` between successive noise estimates.

    .. math:: D_{KL}\\big(p(\\hat\\xi_k) \\,\\|\\, p(\\hat\\xi_{k+1})\\big),\\quad
        p(\\hat\\xi_k) = N(\\hat\\mu_k, \\hat K_k)

    Parameters
    ----------
    noise, next_noise : object
        ``.mean`` (n,), ``.cov`` (n, n) of iterations k and k+1.

    Returns
    -------
    IBEShiftReport

    Raises
    ------
    ValueError
        Shapes do not match, or a covariance is not symmetric PSD (from
        :func:`mixedrl.gaussian.kl_divergence`).

    Notes
    -----
    Theorem 4 claims this tends to 0 with probability one; the check measures it, with no threshold.
    """
    m0, c0 = np.asarray(noise.mean, dtype=np.float64), np.asarray(noise.cov, dtype=np.float64)
    m1, c1 = np.asarray(next_noise.mean, dtype=np.float64), np.asarray(next_noise.cov, dtype=np.float64)
    kl = kl_divergence(m0, c0, m1, c1)
    return IBEShiftReport(kl=float(kl), mean_shift=float(np.linalg.norm(m1 - m0)), cov_shift=float(np.linalg.norm(c1 - c0)))
