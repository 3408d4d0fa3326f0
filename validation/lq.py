"""Algorithm 1 on the discounted linear-quadratic problem, against the exact optimum from the DARE.

The problem (EQUATIONS.md, last section): ``x' = A x + B u + xi``, ``xi ~ N(mu, K)``, utility charged on
the next state ``l(x', u) = x'^T Q x' + u^T R u`` (eq. 2), discount ``gamma``. The optimal value is
``V*(x) = x^T P x + 2 p^T x + c`` and the optimal policy ``u = -L x - l0``:

* ``S = Q + gamma P`` solves the standard DARE with ``(sqrt(gamma) A, sqrt(gamma) B, Q, gamma R)``
  (:func:`scipy.linalg.solve_discrete_are`; bit for bit what :func:`control.dare` with ``method="scipy"`` returns,
  tests/test_lq.py), and ``L = (R + B^T S B)^{-1} B^T S A``;
* ``p`` and ``l0`` solve one linear system that depends on ``mu``, and ``c`` follows; a wrong ``mu``
  leaves ``L`` exact and biases ``l0`` (:func:`discounted_lq_optimum`, the one implementation, also
  behind :func:`validation.nmpc.discounted_lqr`; :func:`optimal_solution` for an :class:`LQProblem`).

The problem, its solution and the optimum live in the library (:mod:`mixedrl.lq`: :class:`LQProblem`,
:class:`LQSolution`, :func:`discounted_lq_optimum`, :func:`optimal_solution`, ``PBH_RTOL``); this module
re-exports them.

:func:`run_algorithm1` runs the same loop (:func:`mixedrl.algorithms.policy_iteration.policy_iteration`)
with three noise sources: ``"mixed"`` (the IBE, Case 2 by default, fed with residuals of the true system
under the current policy with exploration), ``"model"`` (the prior ``N(mu_M, K_M)``, eq. 55) and
``"oracle"`` (the true ``N(mu, K)``), and attaches the theory checks to every iteration.

``python -m validation.lq --out DIR`` writes the figures and their config (see :func:`main`).

Example
-------
>>> import numpy as np
>>> from validation.lq import LQProblem, optimal_solution, run_algorithm1
>>> prob = LQProblem(A=[[1.1]], B=[[1.0]], Q=[[1.0]], R=[[1.0]], gamma=0.9,
...                  noise_mean=[0.2], noise_cov=[[0.01]], prior_mean=[0.0], prior_cov=[[0.01]])
>>> opt = optimal_solution(prob)
>>> res = run_algorithm1(prob, method="oracle", iterations=20)
>>> bool(np.allclose(res.gain, opt.gain, rtol=1e-10) and np.allclose(res.offset, opt.offset, rtol=1e-10))
True
"""

from __future__ import annotations

import argparse
import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import control
import numpy as np

from mixedrl.checks import as_matrix, as_vector, check_covariance, check_positive_int
from mixedrl.algorithms.policy_iteration import Iteration, policy_iteration
from mixedrl.ibe import residuals
from mixedrl.lq import PBH_RTOL, LQProblem, LQSolution, discounted_lq_optimum, optimal_solution
from mixedrl.noise import GaussianNoise, make_noise_source
from mixedrl.pev import ExactPEV
from mixedrl.pim import ExactPIM
from mixedrl.quadratic import AffinePolicy, QuadraticValue
from theory import ibe_shift, lyapunov_decrease, mvc, value_decrease

__all__ = [
    "LQProblem",
    "LQSolution",
    "LQIteration",
    "LQResult",
    "optimal_solution",
    "discounted_lq_optimum",
    "default_initial_gain",
    "run_algorithm1",
    "lyapunov_region",
    "check_states",
    "offset_error_study",
    "theory_table",
    "mvc_value_crosstab",
    "example_problem",
    "main",
    "METHODS",
]

logger = logging.getLogger(__name__)

METHODS = ("mixed", "model", "oracle")


def _sym(a: np.ndarray) -> np.ndarray:
    return 0.5 * (a + a.T)


def default_initial_gain(problem: LQProblem) -> np.ndarray:
    """A stabilising initial gain ``L_0`` (m, n) that is not the answer.

    ``0`` when ``A`` is Schur stable; otherwise the undiscounted LQR gain of the *current-state* cost
    ``x^T x + 100 u^T u`` (:func:`control.dlqr`, ``method="scipy"``), which is stabilising for any
    stabilisable ``(A, B)`` and differs from the optimum of the problem (different weights, no
    discount, cost on the current state).

    Raises
    ------
    ValueError
        Propagated from :func:`control.dlqr` if it fails.
    """
    A, B = problem.A, problem.B
    if float(np.max(np.abs(np.linalg.eigvals(A)))) < 1.0:
        return np.zeros((problem.m, problem.n))
    K, _, _ = control.dlqr(A, B, np.eye(problem.n), 100.0 * np.eye(problem.m), method="scipy")
    return np.asarray(K, dtype=np.float64)


@dataclass
class LQIteration:
    """One iteration of :func:`run_algorithm1` (see :class:`mixedrl.algorithms.policy_iteration.Iteration`).

    Attributes
    ----------
    k : int
    samples : int
        Residuals seen by the noise source so far (mixed), else 0.
    gain, offset : ndarray, shapes (m, n), (m,)
        ``pi^{k+1}`` produced by this iteration's PIM.
    value : QuadraticValue
        ``V^k`` (P, p, c) from this iteration's PEV.
    ibe_mean, ibe_cov : ndarray, shapes (n,), (n, n)
        ``mu_hat_k``, ``K_hat_k`` used by PEV and PIM.
    checks : dict
        Theory reports for the step k -> k+1 (empty for the last iteration): ``lyapunov_decrease``
        (V^k, pi^{k+1}, xi_hat_{k+1}; eq. 28/41), ``value_decrease`` (V^k vs V^{k+1}; eq. 29/42),
        ``mvc`` (eqs. 38-39), ``ibe_shift`` (eq. 45), and ``lyapunov_region`` (exact, from
        :func:`lyapunov_region`).
    """

    k: int
    samples: int
    gain: np.ndarray
    offset: np.ndarray
    value: QuadraticValue
    ibe_mean: np.ndarray
    ibe_cov: np.ndarray
    checks: dict[str, Any] = field(default_factory=dict)


@dataclass
class LQResult:
    """Outcome of :func:`run_algorithm1`.

    Attributes
    ----------
    method : str
    gain, offset : ndarray
        The final policy ``pi^K`` (m, n), (m,).
    value : QuadraticValue
        The last evaluated value ``V^{K-1}``.
    history : list of LQIteration
    noise : object
        The noise source at the end (the IBE for ``"mixed"``).
    config : dict
        The arguments of the run.
    """

    method: str
    gain: np.ndarray
    offset: np.ndarray
    value: QuadraticValue
    history: list[LQIteration]
    noise: Any
    config: dict[str, Any]


def check_states(n: int, count: int, radii: tuple[float, float], generator: np.random.Generator) -> np.ndarray:
    """States for the theory checks: uniform directions, radii log-uniform in ``radii``, shape (count, n).

    Raises
    ------
    ValueError
        ``count`` not a positive int, or ``radii`` not ``0 < lo <= hi``.
    """
    count = check_positive_int(count, "count")
    lo, hi = float(radii[0]), float(radii[1])
    if not (0.0 < lo <= hi and math.isfinite(hi)):
        raise ValueError(f"radii: expected 0 < lo <= hi, got {radii!r}")
    d = generator.standard_normal((count, n))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = np.exp(generator.uniform(math.log(lo), math.log(hi), size=count))
    return d * r[:, None]


def lyapunov_region(problem: LQProblem, value: QuadraticValue, policy: AffinePolicy, mean: Any, cov: Any) -> dict[str, Any]:
    """Exact set where ``E V(x') > V(x)`` (Lyapunov decrease fails) for quadratic V, affine pi, linear f.

    .. math::
        \\Delta(x) = \\mathbb{E} V(x') - V(x) = x^T D x + 2 e^T x + f_0,\\quad
        D = A_c^T P A_c - P,\\ e = A_c^T (P b + p) - p,\\ f_0 = V(b) - c + \\operatorname{tr}(P K) ,

    with ``A_c = A - B L`` and ``b = mu - B l0``. When ``D`` is negative definite the failure set
    ``{Delta > 0}`` is the open ellipsoid ``(x - x_c)^T (-D) (x - x_c) < f_0 - e^T D^{-1} e`` centred
    at ``x_c = -D^{-1} e``: decrease holds outside it and nowhere inside.

    Parameters
    ----------
    problem : LQProblem
    value : QuadraticValue
    policy : AffinePolicy
    mean : array_like, shape (n,)
    cov : array_like, shape (n, n)

    Returns
    -------
    dict
        ``D_max_eig`` (largest eigenvalue of D), ``bounded`` (D negative definite), and if bounded
        ``center`` (n,), ``level`` (``f_0 - e^T D^{-1} e``; <= 0 means the failure set is empty),
        ``radius_max`` (largest distance of a failing point from the centre), ``origin_fails``,
        ``max_norm`` (largest ``||x||`` of a failing point).
    """
    n = problem.n
    mu = as_vector(mean, "mean", n)
    K = check_covariance(cov, "cov", n)
    P, p, c = value.P, value.p, value.c
    Ac = problem.A - problem.B @ policy.L
    b = mu - problem.B @ policy.l0
    D = _sym(Ac.T @ P @ Ac - P)
    e = Ac.T @ (P @ b + p) - p
    f0 = float(b @ P @ b + 2 * p @ b + np.sum(P * K))
    eig = np.linalg.eigvalsh(D)
    out: dict[str, Any] = {"D_max_eig": float(eig[-1]), "bounded": bool(eig[-1] < 0.0)}
    if eig[-1] < 0.0:
        xc = -np.linalg.solve(D, e)
        level = float(f0 - e @ np.linalg.solve(D, e))
        out["center"] = xc
        out["level"] = level
        out["origin_fails"] = bool(f0 > 0.0)
        if level > 0.0:
            rad = math.sqrt(level / -eig[-1])
            out["radius_max"] = rad
            out["max_norm"] = float(np.linalg.norm(xc) + rad)
        else:
            out["radius_max"] = 0.0
            out["max_norm"] = 0.0
    return out


class _Collector:
    """Mixed RL's data: transitions of the true system under ``pi^k`` plus exploration; residuals (eq. 10)."""

    def __init__(self, problem: LQProblem, samples: int, exploration_std: float, generator: np.random.Generator, reset_norm: float) -> None:
        self.problem, self.samples, self.std, self.rng, self.reset_norm = problem, samples, exploration_std, generator, reset_norm
        self.f = problem.dynamics
        self.true_noise = GaussianNoise(problem.noise_mean, problem.noise_cov)
        self.x = np.zeros(problem.n)

    def __call__(self, policy: AffinePolicy, k: int) -> np.ndarray:
        n, N = self.problem.n, self.samples
        xs = np.empty((N, n))
        us = np.empty((N, self.problem.m))
        xn = np.empty((N, n))
        xi = self.true_noise.sample(N, self.rng)
        explore = self.std * self.rng.standard_normal((N, self.problem.m))
        x = self.x
        for j in range(N):
            if not np.all(np.abs(x) < self.reset_norm):
                x = np.zeros(n)  # episode reset (keeps residual rounding errors small)
            # u_j = pi^k(x_j) + exploration = -L x_j - l0 + e_j
            u = -policy.L @ x - policy.l0 + explore[j]
            # x_{j+1} = f(x_j, u_j) + xi_j   (eq. 1, the true system)
            x_next = self.problem.A @ x + self.problem.B @ u + xi[j]
            xs[j], us[j], xn[j] = x, u, x_next
            x = x_next
        self.x = x
        # xi^D_j = x_{j+1} - f(x_j, u_j)   (eq. 10)
        return residuals(self.f, xs, us, xn)


def run_algorithm1(
    problem: LQProblem,
    method: str = "mixed",
    iterations: int = 50,
    samples_per_iteration: int = 100,
    seed: int = 0,
    initial_gain: Any = None,
    *,
    initial_offset: Any = None,
    ibe: str = "unknown",
    exploration_std: float = 0.1,
    theory_checks: bool = True,
    n_check_states: int = 256,
    check_radii: tuple[float, float] = (1e-3, 1e2),
    reset_norm: float = 1e6,
) -> LQResult:
    """Implements Algorithm 1 on the LQ problem with exact PEV (eq. 21) and PIM (eq. 22).

    .. math::
        [\\hat\\mu_k, \\hat K_k] = \\mathrm{IBE}(\\cdot, \\xi^D_k),\\
        V^k = \\mathbb{E}_{\\hat\\xi_k}\\{l + \\gamma V^k\\}|_{\\pi^k},\\
        \\pi^{k+1} = \\arg\\min \\mathbb{E}_{\\hat\\xi_k}\\{l + \\gamma V^k\\}

    Parameters
    ----------
    problem : LQProblem
    method : {"mixed", "model", "oracle"}
        The noise source: IBE posterior, prior (eq. 55), or true noise.
    iterations : int
        Number of iterations ``K`` (no early stop).
    samples_per_iteration : int
        Transitions of the true system collected per iteration (``"mixed"`` only).
    seed : int
        Seeds the data generator (``default_rng([seed, 0])``) and the check states
        (``default_rng([seed, 1])``).
    initial_gain : array_like, shape (m, n), optional
        ``L_0``; default :func:`default_initial_gain`. Must satisfy ``rho(sqrt(gamma)(A - B L_0)) < 1``.
    initial_offset : array_like, shape (m,), optional
        ``l0`` of ``pi^0`` (default 0).
    ibe : {"unknown", "known", "paper"}
        Which IBE ``"mixed"`` uses: Case 2 exact recursion (default; K is not known to the learner),
        Case 1 with the true K, or Case 2 with the paper's eq. (18).
    exploration_std : float
        Standard deviation of the Gaussian exploration added to every action of the data rollout.
    theory_checks : bool
        Attach the theory reports to each iteration (see :class:`LQIteration`).
    n_check_states : int
        Number of states for the checks.
    check_radii : (float, float)
        Radius range of the check states (:func:`check_states`).
    reset_norm : float
        The data rollout restarts at ``x = 0`` when a state component reaches this size.

    Returns
    -------
    LQResult

    Raises
    ------
    ValueError
        Unknown ``method`` or ``ibe``, bad counts, ``initial_gain`` of wrong shape or not stabilising.

    Notes
    -----
    * Data (``"mixed"``): one continuing rollout of the true system, ``samples_per_iteration`` steps
      per iteration under ``u = pi^k(x) + exploration``. With additive noise the residuals
      ``x_{j+1} - f(x_j, u_j) = xi_j`` do not depend on the policy or the exploration (to rounding), so
      both only shape which states are visited; they are kept because Algorithm 1 collects data
      under the current policy.
    * The noise covariance of the mixed model is the IBE's ``.cov``; in the LQ case it only enters
      the constant ``c`` of the value, never the policy.
    """
    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    if ibe not in ("unknown", "known", "paper"):
        raise ValueError(f"ibe: expected 'unknown', 'known' or 'paper', got {ibe!r}")
    iterations = check_positive_int(iterations, "iterations")
    samples_per_iteration = check_positive_int(samples_per_iteration, "samples_per_iteration")
    n_check_states = check_positive_int(n_check_states, "n_check_states")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed: expected a non-negative integer, got {seed!r}")
    if not (math.isfinite(exploration_std) and exploration_std >= 0.0):
        raise ValueError(f"exploration_std: expected a finite value >= 0, got {exploration_std!r}")
    if not (reset_norm > 0.0):
        raise ValueError(f"reset_norm: expected a value > 0, got {reset_norm!r}")
    n, m, g = problem.n, problem.m, problem.gamma
    L0 = default_initial_gain(problem) if initial_gain is None else as_matrix(initial_gain, "initial_gain", (m, n))
    l00 = np.zeros(m) if initial_offset is None else as_vector(initial_offset, "initial_offset", m)
    rho = float(np.max(np.abs(np.linalg.eigvals(math.sqrt(g) * (problem.A - problem.B @ L0)))))
    if rho >= 1.0:
        raise ValueError(f"initial_gain: not stabilising, spectral radius of sqrt(gamma)(A - B L0) is {rho:.6g} >= 1")

    noise = make_noise_source(method, problem, recursion="paper" if ibe == "paper" else "exact",
                              covariance="known" if ibe == "known" else "unknown")
    f, cost = problem.dynamics, problem.cost
    collect = None
    if method == "mixed":
        collect = _Collector(problem, samples_per_iteration, float(exploration_std), np.random.default_rng([seed, 0]), reset_norm)
    out = policy_iteration(
        noise, ExactPEV(f, cost, g), ExactPIM(f, cost, g), AffinePolicy(L0, l00), iterations, collect=collect
    )
    history = [_record(it) for it in out.history]
    if theory_checks:
        states = check_states(n, n_check_states, check_radii, np.random.default_rng([seed, 1]))
        for rec, it, it1 in zip(history[:-1], out.history[:-1], out.history[1:]):
            rec.checks = _theory_checks(problem, it, it1, states)
    config = {
        "method": method,
        "iterations": iterations,
        "samples_per_iteration": samples_per_iteration,
        "seed": int(seed),
        "initial_gain": L0.tolist(),
        "initial_offset": l00.tolist(),
        "ibe": ibe,
        "exploration_std": float(exploration_std),
        "n_check_states": n_check_states,
        "check_radii": list(check_radii),
        "reset_norm": reset_norm,
        "problem": problem.to_dict(),
    }
    return LQResult(method, out.policy.L.copy(), out.policy.l0.copy(), out.value, history, noise, config)


def _record(it: Iteration) -> LQIteration:
    return LQIteration(
        k=it.k,
        samples=it.samples,
        gain=it.next_policy.L.copy(),
        offset=it.next_policy.l0.copy(),
        value=it.value,
        ibe_mean=it.noise_mean.copy(),
        ibe_cov=it.noise_cov.copy(),
    )


def _theory_checks(problem: LQProblem, it: Iteration, it1: Iteration, states: np.ndarray) -> dict[str, Any]:
    f, cost, g = problem.dynamics, problem.cost, problem.gamma
    noise_k = GaussianNoise(it.noise_mean, it.noise_cov)
    noise_k1 = GaussianNoise(it1.noise_mean, it1.noise_cov)
    return {
        # eq. (28) (fixed noise) / eq. (41) (varying noise): V^k >= E_{xi_{k+1}} V^k(x'), x' under pi^{k+1}
        "lyapunov_decrease": lyapunov_decrease(it.value, it.next_policy, f, noise_k1, states),
        # eq. (29) / (42): V^k >= V^{k+1}
        "value_decrease": value_decrease(it.value, it1.value, states),
        # eqs. (38)-(39)
        "mvc": mvc(it.value, it.policy, it.next_policy, f, cost, g, noise_k, noise_k1, states),
        # eq. (45)
        "ibe_shift": ibe_shift(noise_k, noise_k1),
        "lyapunov_region": lyapunov_region(problem, it.value, it.next_policy, it1.noise_mean, it1.noise_cov),
    }


def offset_error_study(
    problem: LQProblem,
    seeds: int = 200,
    iterations: int = 60,
    samples_per_iteration: int = 25,
    skip: int = 8,
    **kwargs: Any,
) -> dict[str, Any]:
    """Offset error of ``"mixed"`` against the total number of samples, over many seeds, and its slope.

    For seeds ``0..seeds-1`` runs :func:`run_algorithm1` (no theory checks) and records
    ``e_k = ||l0^{k+1} - l0*||`` at ``N_k = (k + 1) samples_per_iteration`` samples. Fits
    ``log RMS_k = a + s log N_k`` over ``k >= skip`` (after the gain has converged), and the slope's
    standard error by a seeded bootstrap over seeds (400 resamples).

    Returns
    -------
    dict
        ``samples`` (K,), ``rms`` (K,), ``errors`` (seeds, K), ``slope``, ``slope_se`` (bootstrap
        standard error), ``intercept``, ``gain_error_max`` (largest
        relative gain error over the fitted iterations and seeds).
    """
    seeds = check_positive_int(seeds, "seeds")
    opt = optimal_solution(problem)
    errs = np.empty((seeds, iterations))
    gain_err = 0.0
    ns = None
    for s in range(seeds):
        res = run_algorithm1(problem, "mixed", iterations, samples_per_iteration, seed=s, theory_checks=False, **kwargs)
        errs[s] = [np.linalg.norm(r.offset - opt.offset) for r in res.history]
        ns = np.array([r.samples for r in res.history], dtype=np.float64)
        gain_err = max(gain_err, max(np.linalg.norm(r.gain - opt.gain) / np.linalg.norm(opt.gain) for r in res.history[skip:]))
    assert ns is not None
    rms = np.sqrt(np.mean(errs**2, axis=0))
    lx = np.log(ns[skip:])
    slope, intercept = np.polyfit(lx, np.log(rms[skip:]), 1)
    # bootstrap over seeds (seeded, 400 resamples) for the standard error of the fitted slope
    boot_rng = np.random.default_rng(12345)
    boot = np.empty(400)
    for b in range(boot.shape[0]):
        pick = boot_rng.integers(0, seeds, seeds)
        boot[b] = np.polyfit(lx, np.log(np.sqrt(np.mean(errs[pick, skip:] ** 2, axis=0))), 1)[0]
    return {
        "samples": ns,
        "rms": rms,
        "errors": errs,
        "slope": float(slope),
        "intercept": float(intercept),
        "slope_se": float(np.std(boot, ddof=1)),
        "gain_error_max": float(gain_err),
        "skip": skip,
    }


def theory_table(result: LQResult, problem: LQProblem | None = None) -> str:
    """Format the theory checks of a run as a plain-text table, one row per iteration ``k -> k+1``.

    Columns: k, samples, relative gain and offset errors of ``pi^{k+1}`` (against the true optimum,
    if ``problem`` is given), Lyapunov decrease (fraction held, largest ``||x||`` where it failed,
    and the exact failure region's largest ``||x||``), value decrease (fraction, worst margin), MVC
    (fraction pointwise, on the batch mean, fraction ``e_k >= 0``), and ``KL(xi_k || xi_{k+1})``.
    """
    opt = optimal_solution(problem) if problem is not None else None
    head = (
        f"{'k':>3} {'N':>6} {'gain err':>9} {'off err':>9} | {'lyap':>6} {'fail|x|max':>10} {'exact':>9} |"
        f" {'Vdec':>6} {'worst':>10} | {'MVC':>6} {'mean':>5} {'e>=0':>6} | {'KL':>9}"
    )
    lines = [f"method={result.method}", head, "-" * len(head)]
    for rec in result.history:
        if not rec.checks:
            continue
        ge = oe = float("nan")
        if opt is not None:
            ge = np.linalg.norm(rec.gain - opt.gain) / np.linalg.norm(opt.gain)
            oe = np.linalg.norm(rec.offset - opt.offset) / max(np.linalg.norm(opt.offset), 1e-300)
        ly, vd, mv, kl, reg = (rec.checks[k] for k in ("lyapunov_decrease", "value_decrease", "mvc", "ibe_shift", "lyapunov_region"))
        fr = ly.failed_norm_range()
        exact = reg.get("max_norm", float("inf"))
        lines.append(
            f"{rec.k:>3} {rec.samples:>6} {ge:>9.2e} {oe:>9.2e} | {ly.held_fraction:>6.3f} "
            f"{(fr[1] if fr else 0.0):>10.3g} {exact:>9.3g} | {vd.held_fraction:>6.3f} {vd.worst_margin:>10.2e} | "
            f"{mv.held_fraction:>6.3f} {('yes' if mv.extra['held_on_batch_mean'] else 'no'):>5} "
            f"{mv.extra['e_nonnegative_fraction']:>6.3f} | {kl.kl:>9.2e}"
        )
    return "\n".join(lines)


def mvc_value_crosstab(result: LQResult) -> dict[str, Any]:
    """Cross-tabulate, over every (iteration, state) pair of a run, the pointwise MVC against value decrease.

    Returns
    -------
    dict
        ``pairs``; ``mvc_held`` (count); ``vdec_given_mvc`` and ``vdec_given_not_mvc`` (fraction of
        pairs where ``V^{k+1}(x) <= V^k(x)`` among those where the MVC held / did not hold, ``nan`` if
        none); ``iterations_mvc_all`` (iterations where the MVC held at every state) and
        ``iterations_vdec_all`` (where value decrease held at every state).
    """
    m_all, v_all = [], []
    it_m = it_v = 0
    for rec in result.history:
        if not rec.checks:
            continue
        mm, vm = rec.checks["mvc"].held_mask, rec.checks["value_decrease"].held_mask
        m_all.append(mm)
        v_all.append(vm)
        it_m += int(mm.all())
        it_v += int(vm.all())
    if not m_all:
        return {"pairs": 0}
    mm, vm = np.concatenate(m_all), np.concatenate(v_all)
    return {
        "pairs": int(mm.size),
        "mvc_held": int(mm.sum()),
        "vdec_given_mvc": float(vm[mm].mean()) if mm.any() else float("nan"),
        "vdec_given_not_mvc": float(vm[~mm].mean()) if (~mm).any() else float("nan"),
        "iterations": len(m_all),
        "iterations_mvc_all": it_m,
        "iterations_vdec_all": it_v,
    }


def example_problem() -> LQProblem:
    """The shipped example: a double integrator (position, velocity; T = 0.1 s) pushed by a constant
    disturbance acceleration of 0.5 m/s^2 that the designer's prior says is zero.

    ``A = [[1, T], [0, 1]]``, ``B = [[T^2/2], [T]]``, ``Q = diag(1, 0.1)``, ``R = 0.01``, ``gamma = 0.95``;
    ``xi ~ N(B a, diag(1e-4, 4e-4))`` with ``a = 0.5`` (mean ``[0.0025, 0.05]``); the designer's prior
    believes ``a = 0.2``: ``mu_M = B 0.2 = [0.001, 0.02]``, ``K_M = diag(1e-4, 1e-3)``.
    """
    T = 0.1
    A = np.array([[1.0, T], [0.0, 1.0]])
    B = np.array([[T * T / 2.0], [T]])
    return LQProblem(
        A=A,
        B=B,
        Q=np.diag([1.0, 0.1]),
        R=np.array([[0.01]]),
        gamma=0.95,
        noise_mean=(B * 0.5).ravel(),
        noise_cov=np.diag([1e-4, 4e-4]),
        prior_mean=(B * 0.2).ravel(),
        prior_cov=np.diag([1e-4, 1e-3]),
    )


def main(argv: list[str] | None = None) -> int:
    """``python -m validation.lq --out DIR``: figures and config of the LQ validation.

    Writes ``lq_gain_error.png`` (relative gain error against iteration, three methods),
    ``lq_offset_error.png`` (offset error against iteration, three methods), ``lq_offset_vs_samples.png``
    (RMS offset error of mixed RL over seeds against samples, log-log, with a 1/sqrt(N) guide),
    ``lq_ibe_mean.png`` (the IBE mean against iteration, with the prior and true means),
    ``lq_config.json`` and ``lq_results.json`` (measured errors and the slope fit).
    """
    parser = argparse.ArgumentParser(prog="python -m validation.lq", description=main.__doc__)
    parser.add_argument("--out", required=True, help="output directory")
    parser.add_argument("--iterations", type=int, default=50)
    parser.add_argument("--samples", type=int, default=100, help="samples per iteration")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--seeds", type=int, default=200, help="seeds of the offset-vs-samples study")
    parser.add_argument("--study-iterations", type=int, default=60)
    parser.add_argument("--study-samples", type=int, default=25)
    args = parser.parse_args(argv)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    prob = example_problem()
    opt = optimal_solution(prob)
    runs = {m: run_algorithm1(prob, m, args.iterations, args.samples, seed=args.seed) for m in METHODS}
    study = offset_error_study(prob, seeds=args.seeds, iterations=args.study_iterations, samples_per_iteration=args.study_samples)
    style = {"mixed": ("C0", "-", "o"), "model": ("C1", "--", "s"), "oracle": ("C2", ":", "^")}

    panels = [  # (attribute of the history entry and of opt, y label, title, file)
        ("gain", "$\\|L^k - L^*\\| / \\|L^*\\|$", "Gain error (the noise never enters the gain)", "lq_gain_error.png"),
        ("offset", "$\\|l_0^k - l_0^*\\| / \\|l_0^*\\|$", "Offset error: the prior's bias stays, the IBE removes it",
         "lq_offset_error.png"),
    ]
    for attr, ylabel, title, fname in panels:
        fig, ax = plt.subplots(figsize=(6, 4))
        ref = getattr(opt, attr)
        for mth, res in runs.items():
            err = [np.linalg.norm(getattr(r, attr) - ref) / np.linalg.norm(ref) for r in res.history]
            c, ls, mk = style[mth]
            ax.semilogy(range(1, len(err) + 1), np.maximum(err, 1e-17), color=c, ls=ls, marker=mk, ms=3, label=mth)
        ax.set_xlabel("iteration k (policy $\\pi^{k}$)")
        ax.set_ylabel(ylabel)
        ax.set_title(title)
        ax.legend()
        fig.tight_layout()
        fig.savefig(out / fname, dpi=120)
        plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 4))
    ns, rms = study["samples"], study["rms"]
    ax.loglog(ns, rms, "o-", ms=3, label=f"mixed RL, RMS over {args.seeds} seeds")
    skip = study["skip"]
    fit = np.exp(study["intercept"]) * ns[skip:] ** study["slope"]
    ax.loglog(ns[skip:], fit, "k-", lw=1, label=f"fit: slope {study['slope']:.3f} $\\pm$ {study['slope_se']:.3f}")
    guide = rms[skip] * np.sqrt(ns[skip] / ns)
    ax.loglog(ns, guide, "k--", lw=1, label="$1/\\sqrt{N}$ guide")
    ax.set_xlabel("total samples N")
    ax.set_ylabel("$\\|l_0 - l_0^*\\|$")
    ax.set_title("Offset error against the number of samples")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "lq_offset_vs_samples.png", dpi=120)
    plt.close(fig)

    fig, axes = plt.subplots(1, prob.n, figsize=(4 * prob.n, 3.5))
    mix = runs["mixed"]
    for i, ax in enumerate(np.atleast_1d(axes)):
        ax.plot([r.samples for r in mix.history], [r.ibe_mean[i] for r in mix.history], "C0o-", ms=3, label="IBE mean")
        ax.axhline(prob.noise_mean[i], color="C2", ls=":", label="true $\\mu$")
        ax.axhline(prob.prior_mean[i], color="C1", ls="--", label="prior $\\mu_M$")
        ax.set_xlabel("samples")
        ax.set_title(f"component {i}")
        ax.legend()
    fig.tight_layout()
    fig.savefig(out / "lq_ibe_mean.png", dpi=120)
    plt.close(fig)

    results = {
        "optimal": {"gain": opt.gain.tolist(), "offset": opt.offset.tolist(), "P": opt.P.tolist(), "p": opt.p.tolist(), "c": opt.c},
        "model_offset_predicted": optimal_solution(prob, noise_mean=prob.prior_mean).offset.tolist(),
        "methods": {
            mth: {
                "gain_rel_error": float(np.linalg.norm(res.gain - opt.gain) / np.linalg.norm(opt.gain)),
                "offset_rel_error": float(np.linalg.norm(res.offset - opt.offset) / np.linalg.norm(opt.offset)),
                "offset": res.offset.tolist(),
                "samples": res.history[-1].samples,
            }
            for mth, res in runs.items()
        },
        "slope_fit": {k: study[k] for k in ("slope", "slope_se", "intercept", "gain_error_max")},
    }
    config = {
        "problem": prob.to_dict(),
        "iterations": args.iterations,
        "samples_per_iteration": args.samples,
        "seed": args.seed,
        "study": {"seeds": args.seeds, "iterations": args.study_iterations, "samples_per_iteration": args.study_samples, "skip": skip},
        "dare_method": "scipy",
        "ibe": "unknown (Case 2, exact recursion of eq. 17)",
    }
    (out / "lq_config.json").write_text(json.dumps(config, indent=2))
    (out / "lq_results.json").write_text(json.dumps(results, indent=2))
    logger.info("wrote figures to %s", out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
