"""Checks of two premises of the paper's proofs: Theorem 1's choice of gamma and Lemma 2's full-rank prior.

* :func:`gamma_condition` -- eq. (27), the condition on the discount factor in the proof of Theorem 1:
  ``l(x', u^{k+1}) - (1 - gamma) V^k(x') >= 0``, i.e. ``gamma >= 1 - l(x', u^{k+1}) / V^k(x')``.
  Measured in expectation over ``xi_hat`` (the form that turns eq. (26) into eq. (28)), with the
  smallest admissible gamma per state and the exact split of the Lyapunov margin of eq. (28) into the
  weak-Bellman slack of eq. (25) plus the margin of eq. (27).
* :func:`prior_full_rank` -- Lemma 2's premise: "the covariance matrix of the prior distribution is full
  rank". Reports the prior's rank at a stated relative tolerance, its condition number, the deficient
  directions and, given a noise covariance, how many samples the prior is worth along each direction.

Both take the same batched numpy interfaces as :mod:`theory.checks` (value ``V(x)`` (N, n) -> (N,),
policy (N, n) -> (N, m), dynamics ``f(x, u)``, utility ``l(x', u)`` charged on the next state (eq. 2),
noise objects with ``.mean`` (n,) and ``.cov`` (n, n)). Neither is tuned to pass: they report where the
premise holds and where it fails (docs/theory.rst, "Premises").
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from theory.checks import DEFAULT_RTOL, CheckReport
from mixedrl.checks import check_fraction, check_number
from mixedrl.expectation import GaussHermite, SigmaPoints, gaussian_expectation

__all__ = [
    "PRIOR_RANK_RTOL",
    "PriorRankReport",
    "gamma_condition",
    "prior_full_rank",
]

#: Default relative eigenvalue tolerance of :func:`prior_full_rank`: ``sqrt(machine epsilon)``
#: (about ``1.49e-8``). Past it (condition number above ``1 / sqrt(eps)``, about ``6.7e7``) the prior's
#: inverse, which eqs. (14)-(17) need, loses more than half of its significant digits in double
#: precision (relative error up to ``cond * eps > sqrt(eps)``).
PRIOR_RANK_RTOL = math.sqrt(float(np.finfo(np.float64).eps))


def _finite_batch(states: Any) -> np.ndarray:
    """States as a finite float64 (N, n) array; a single state (n,) becomes (1, n)."""
    try:
        x = np.array(states, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"states: cannot be converted to a float array ({exc})") from None
    if x.ndim == 1:
        x = x[None, :]
    if x.ndim != 2 or x.shape[1] == 0:
        raise ValueError(f"states: expected shape (n,) or (N, n), got {np.shape(states)}")
    if not np.all(np.isfinite(x)):
        raise ValueError("states: contains NaN or inf")
    return x


def _call_batch(fn: Callable[..., Any], name: str, shape: tuple[int, ...], *args: np.ndarray) -> np.ndarray:
    """Evaluate a user callable and insist on a finite float64 result of the stated shape."""
    out = np.asarray(fn(*args), dtype=np.float64)
    if out.shape != shape:
        raise ValueError(f"{name}: expected output shape {shape}, got {out.shape}")
    if not np.all(np.isfinite(out)):
        raise ValueError(f"{name}: returned NaN or inf")
    return out


def _discount(gamma: Any) -> float:
    if isinstance(gamma, bool) or not isinstance(gamma, numbers.Real):
        raise ValueError(f"gamma: expected a float in (0, 1), got {gamma!r}")
    g = float(gamma)
    if not 0.0 < g < 1.0:
        raise ValueError(f"gamma: must lie in (0, 1) (eq. 27 needs gamma < 1), got {gamma!r}")
    return g


def gamma_condition(
    value: Callable[[np.ndarray], np.ndarray],
    policy: Callable[[np.ndarray], np.ndarray],
    f: Callable[[np.ndarray, np.ndarray], np.ndarray],
    utility: Callable[[np.ndarray, np.ndarray], np.ndarray],
    gamma: float,
    noise: Any,
    states: Any,
    rule: SigmaPoints | GaussHermite | None = None,
    rtol: float = DEFAULT_RTOL,
) -> CheckReport:
    """Implements eq. (27): Theorem 1's condition on gamma, ``E{l(x', u^{k+1}) - (1 - gamma) V^k(x')} >= 0``.

    .. math::
        l(x', u^{k+1}) - (1-\\gamma)\\, V^k(x') \\ge 0
        \\quad\\Longleftrightarrow\\quad
        1 - \\frac{l(x', u^{k+1})}{V^k(x')} \\le \\gamma < 1,
        \\qquad x' = f(x, \\pi^{k+1}(x)) + \\hat\\xi

    The paper writes eq. (27) for ``x'``; the proof only uses it inside the expectation of eq. (26),

    .. math::
        V^k(x) - \\mathbb{E}_{\\hat\\xi} V^k(x')
        = \\underbrace{V^k(x) - \\mathbb{E}_{\\hat\\xi}\\{l(x', u^{k+1}) + \\gamma V^k(x')\\}}_{\\text{slack of eq. (25)}}
        + \\underbrace{\\mathbb{E}_{\\hat\\xi}\\{l(x', u^{k+1}) - (1-\\gamma) V^k(x')\\}}_{\\text{margin of eq. (27)}},

    so the check measures the expected form (the weakest one that, with eq. (25), gives eq. (28)), and
    the threshold :math:`\\gamma_{\\min}(x) = 1 - \\mathbb{E} l / \\mathbb{E} V^k` per state.

    Parameters
    ----------
    value : callable
        ``V^k``, (N, n) -> (N,), evaluated at the next states.
    policy : callable
        ``pi^{k+1}``, (N, n) -> (N, m).
    f : callable
        Deterministic dynamics ``f(x, u)``, (N, n), (N, m) -> (N, n).
    utility : callable
        ``l(x', u)``, (N, n), (N, m) -> (N,), charged on the next state (eq. 2).
    gamma : float
        The discount factor in (0, 1) with which ``V^k`` was evaluated.
    noise : object
        ``xi_hat`` (``.mean`` (n,), ``.cov`` (n, n)): ``xi_hat_k`` for Theorem 1, ``xi_hat_{k+1}`` for
        Theorem 3 (eq. 41).
    states : array_like, shape (N, n) or (n,)
        Where to check.
    rule : SigmaPoints or GaussHermite, optional
        Quadrature of the expectations (default sigma points, exact for quadratic ``V`` and ``l``).
    rtol : float
        Rounding tolerance: held where ``margin >= -rtol (|E l| + (1 - gamma) |E V|)`` (as in
        :mod:`theory.checks`; it only absorbs rounding).

    Returns
    -------
    CheckReport
        ``name="gamma_condition"``, ``equation="27"``, margin ``E l - (1 - gamma) E V^k`` per state.
        ``extra``:

        * ``gamma_min`` (N,): ``1 - E l / E V^k`` where ``E V^k > 0``, ``-inf`` where ``E V^k <= 0``
          and ``E l >= 0`` (every gamma works), ``nan`` where ``E V^k <= 0 > E l`` (no lower bound exists);
        * ``gamma_required`` (float): the largest finite ``gamma_min`` (the smallest gamma that satisfies
          eq. (27) at every given state with this ``V^k``; ``>= 1``: no admissible gamma);
        * ``expected_utility``, ``expected_value`` (N,): ``E l(x', u^{k+1})``, ``E V^k(x')``;
        * ``bellman_slack`` (N,): ``V^k(x) - E{l + gamma V^k(x')}``, the margin of eq. (25);
        * ``lyapunov_margin`` (N,): ``bellman_slack + margin = V^k(x) - E V^k(x')``, the margin of
          eq. (28) (equal to :func:`theory.lyapunov_decrease`'s margin to rounding).

    Raises
    ------
    ValueError
        ``gamma`` not in (0, 1); ``states`` not a finite (N, n) array; ``noise`` without ``.mean`` /
        ``.cov``, or a covariance that is not symmetric PSD; a callable returning the wrong shape or
        NaN/inf; ``rtol`` negative.

    Notes
    -----
    ``gamma_min`` holds ``V^k`` fixed, but ``V^k`` is itself evaluated with gamma (eq. 21), so "choose
    gamma" in the paper is an implicit condition: changing gamma changes ``V^k``. With a noise of
    non-zero mean or covariance ``V^k`` is not positive definite (``V^k(0) > 0``) and near the target
    ``E l`` is small against ``E V^k``, so eq. (27) fails there for the gamma of the problem
    (EQUATIONS.md point 13); the report says where.
    """
    g = _discount(gamma)
    check_number(rtol, "rtol", nonneg=True)
    if not (hasattr(noise, "mean") and hasattr(noise, "cov")):
        raise ValueError(f"noise: expected an object with .mean and .cov, got {type(noise).__name__}")
    x = _finite_batch(states)
    count, n = x.shape
    u = np.asarray(policy(x), dtype=np.float64)
    if u.ndim != 2 or u.shape[0] != count or not np.all(np.isfinite(u)):
        raise ValueError(f"policy: expected a finite output of shape ({count}, m), got {u.shape}")
    centers = _call_batch(f, "f", (count, n), x, u)
    v_now = _call_batch(value, "value", (count,), x)
    rule = SigmaPoints() if rule is None else rule

    def value_at(z: np.ndarray) -> np.ndarray:
        return _call_batch(value, "value", (z.shape[0],), z)

    def utility_at(z: np.ndarray, a: np.ndarray) -> np.ndarray:
        return _call_batch(utility, "utility", (z.shape[0],), z, a)

    # E V^k(x') and E l(x', u^{k+1}), x' = f(x, pi^{k+1}(x)) + xi_hat
    e_value = gaussian_expectation(value_at, centers, noise.mean, noise.cov, rule)
    e_utility = gaussian_expectation(utility_at, centers, noise.mean, noise.cov, rule, extra=u)
    # eq. (27) in expectation: E l - (1 - gamma) E V^k >= 0
    margin = e_utility - (1.0 - g) * e_value
    tol = rtol * (np.abs(e_utility) + (1.0 - g) * np.abs(e_value))
    # eq. (25): V^k(x) >= E{l + gamma V^k(x')}; its slack plus the eq. (27) margin is eq. (28)'s margin
    slack = v_now - (e_utility + g * e_value)
    positive = e_value > 0.0
    gamma_min = np.where(e_utility >= 0.0, -np.inf, np.nan)
    gamma_min[positive] = 1.0 - e_utility[positive] / e_value[positive]
    finite = gamma_min[np.isfinite(gamma_min)]
    extra = {
        "gamma": g,
        "gamma_min": gamma_min,
        "gamma_required": float(np.max(finite)) if finite.size else -math.inf,
        "expected_utility": e_utility,
        "expected_value": e_value,
        "bellman_slack": slack,
        "lyapunov_margin": slack + margin,
    }
    return CheckReport("gamma_condition", "27", x, margin, tol, extra)


@dataclass(frozen=True)
class PriorRankReport:
    """Outcome of :func:`prior_full_rank`: does the prior covariance ``K_M`` meet Lemma 2's premise?

    Attributes
    ----------
    eigenvalues : ndarray, shape (n,)
        Eigenvalues of ``K_M``, ascending.
    eigenvectors : ndarray, shape (n, n)
        The matching orthonormal eigenvectors (columns).
    rtol : float
        Relative tolerance: an eigenvalue counts when it is ``> rtol * lambda_max``.
    rank : int
        Numerical rank at ``rtol``.
    condition_number : float
        ``lambda_max / lambda_min`` (``inf`` if ``lambda_min <= 0``).
    equivalent_samples : ndarray or None, shape (n,)
        Given a noise covariance ``K``: ``v_i^T K v_i / lambda_i`` per eigenvector ``v_i`` of ``K_M``,
        the number of residuals at which data and prior carry equal weight along ``v_i`` (exact for
        Case 1, eq. (15), when ``K`` and ``K_M`` share eigenvectors); ``inf`` where ``lambda_i = 0 <
        v_i^T K v_i``, ``0`` where the noise has no variance along ``v_i``.
    """

    eigenvalues: np.ndarray
    eigenvectors: np.ndarray
    rtol: float
    rank: int
    condition_number: float
    equivalent_samples: np.ndarray | None = None

    @property
    def dim(self) -> int:
        """Dimension ``n`` of the prior."""
        return int(self.eigenvalues.shape[0])

    @property
    def full_rank(self) -> bool:
        """True when the rank at ``rtol`` is ``n``: Lemma 2's premise holds (numerically)."""
        return self.rank == self.dim

    @property
    def held(self) -> bool:
        """Alias of :attr:`full_rank`, as in :class:`theory.CheckReport`."""
        return self.full_rank

    @property
    def deficient_directions(self) -> np.ndarray:
        """Eigenvectors (n, n - rank) whose eigenvalues are ``<= rtol * lambda_max``."""
        return self.eigenvectors[:, ~self._kept(self.rtol)]

    def _kept(self, rtol: float) -> np.ndarray:
        top = float(self.eigenvalues[-1])
        if top <= 0.0:
            return np.zeros(self.dim, dtype=bool)
        return self.eigenvalues > rtol * top

    def rank_at(self, rtol: float) -> int:
        """Numerical rank at another relative tolerance ``rtol`` (eigenvalues ``> rtol * lambda_max``).

        Raises
        ------
        ValueError
            ``rtol`` not in [0, 1).
        """
        return int(np.sum(self._kept(_relative_tolerance(rtol))))

    def summary(self) -> dict[str, Any]:
        """JSON-serialisable summary."""
        return {
            "name": "prior_full_rank",
            "premise": "Lemma 2",
            "dim": self.dim,
            "rank": self.rank,
            "rtol": self.rtol,
            "full_rank": self.full_rank,
            "condition_number": self.condition_number,
            "eigenvalues": self.eigenvalues.tolist(),
            "equivalent_samples": None if self.equivalent_samples is None else self.equivalent_samples.tolist(),
        }


def _relative_tolerance(rtol: Any) -> float:
    return check_fraction(rtol, "rtol", high_open=True)


def _symmetric_psd(value: Any, name: str, n: int | None = None) -> np.ndarray:
    """A finite, square, symmetric, positive semi-definite float64 matrix (tolerances relative to its scale)."""
    try:
        c = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: cannot be converted to a float array ({exc})") from None
    if c.ndim != 2 or c.shape[0] != c.shape[1] or c.shape[0] == 0 or (n is not None and c.shape[0] != n):
        want = f"({n}, {n})" if n is not None else "(n, n) with n >= 1"
        raise ValueError(f"{name}: expected a square matrix of shape {want}, got {c.shape}")
    if not np.all(np.isfinite(c)):
        raise ValueError(f"{name}: contains NaN or inf")
    scale = float(np.max(np.abs(c)))
    asym = float(np.max(np.abs(c - c.T)))
    if asym > 1e-10 * scale:
        raise ValueError(f"{name}: not symmetric (max |C - C^T| = {asym:.3g})")
    c = 0.5 * (c + c.T)
    low = float(np.linalg.eigvalsh(c)[0])
    if low < -1e-10 * scale:
        raise ValueError(f"{name}: not positive semi-definite (smallest eigenvalue {low:.3g})")
    return c


def prior_full_rank(prior_cov: Any, rtol: float = PRIOR_RANK_RTOL, noise_cov: Any = None) -> PriorRankReport:
    """Check Lemma 2's premise: the prior covariance ``K_M`` of eq. (8) is full rank.

    Lemma 2 (the paper's convergence criterion of Bayesian estimation, used for eq. (44) of Theorem 4)
    requires a Gaussian prior whose covariance is full rank. With the eigen-decomposition
    :math:`K_M = \\sum_i \\lambda_i v_i v_i^T`, :math:`\\lambda_1 \\le \\dots \\le \\lambda_n`,

    .. math::
        \\operatorname{rank}_{\\rm rtol}(K_M) = \\#\\{i : \\lambda_i > \\mathrm{rtol}\\,\\lambda_n\\},\\qquad
        \\kappa(K_M) = \\lambda_n / \\lambda_1,\\qquad
        N_i = \\frac{v_i^T K v_i}{\\lambda_i}.

    :math:`N_i` is why the premise matters: by eq. (15) (Case 1) the posterior mean along :math:`v_i`
    is :math:`\\hat\\mu = \\mu_M + K_M (K_M + K/N)^{-1} (\\bar\\xi_N - \\mu_M)`, the sample mean
    :math:`\\bar\\xi_N` weighted by :math:`N / (N + N_i)` when :math:`K` and :math:`K_M` share
    eigenvectors: the data overtake the prior only after :math:`N \\gg N_i` residuals, never if
    :math:`\\lambda_i = 0`.

    Parameters
    ----------
    prior_cov : array_like, shape (n, n)
        ``K_M``, symmetric PSD (possibly singular).
    rtol : float, optional
        Relative eigenvalue tolerance in [0, 1) (default :data:`PRIOR_RANK_RTOL` = ``sqrt(eps)``).
    noise_cov : array_like, shape (n, n), optional
        A noise covariance ``K`` (the truth, or the one the designer expects) for ``equivalent_samples``.

    Returns
    -------
    PriorRankReport

    Raises
    ------
    ValueError
        ``prior_cov`` or ``noise_cov`` not a finite, square, symmetric PSD matrix (shapes must match);
        ``rtol`` not in [0, 1).

    Notes
    -----
    In exact arithmetic any ``K_M`` with positive eigenvalues is full rank; the question is numerical and
    statistical, so the tolerance is stated. The vehicle's prior
    ``K_M = diag(1e-20, 1e-20, (4T/m)^2, 1e-20, 1e-20)`` (``T = 1/200``, ``m = 1500``) has condition number
    ``(4T/m)^2 / 1e-20 = 1.78e10`` and rank 1 at the default tolerance (rank 5 at
    :data:`mixedrl.gaussian.SUPPORT_RTOL` = 1e-13): Lemma 2 does not apply, so Theorem 4's eq. (44) is
    not guaranteed along the four pinned components. There the estimate stays at the prior's mean
    (0) for any feasible amount of data; the vehicle's true disturbance happens to be 0 there too, so
    nothing is lost on this task, but a true disturbance along a pinned component would not be learned
    (docs/theory.rst, "Premises").

    Examples
    --------
    >>> import numpy as np
    >>> from theory import prior_full_rank
    >>> T, m = 1 / 200, 1500
    >>> rep = prior_full_rank(np.diag([1e-20, 1e-20, (4 * T / m) ** 2, 1e-20, 1e-20]))
    >>> rep.full_rank, rep.rank, f"{rep.condition_number:.3g}", rep.rank_at(1e-13)
    (False, 1, '1.78e+10', 5)
    """
    r = _relative_tolerance(rtol)
    k_m = _symmetric_psd(prior_cov, "prior_cov")
    lam, vec = np.linalg.eigh(k_m)
    top, low = float(lam[-1]), float(lam[0])
    cond = top / low if low > 0.0 else math.inf
    rank = int(np.sum(lam > r * top)) if top > 0.0 else 0
    samples = None
    if noise_cov is not None:
        k = _symmetric_psd(noise_cov, "noise_cov", k_m.shape[0])
        along = np.einsum("ji,jk,ki->i", vec, k, vec)  # v_i^T K v_i
        noisy = along > 1e-12 * float(np.max(np.abs(k)))  # rounding of an exact zero is not variance
        samples = np.zeros_like(lam)
        samples[noisy & (lam <= 0.0)] = math.inf
        both = noisy & (lam > 0.0)
        samples[both] = along[both] / lam[both]
    return PriorRankReport(eigenvalues=lam, eigenvectors=vec, rtol=r, rank=rank, condition_number=cond,
                           equivalent_samples=samples)
