"""Exact LQ case: DARE optimum, exact PEV/PIM (mixedrl.quadratic), Algorithm 1 with three noise sources.

Fast tests (default tox env). The hypothesis sweep over random systems and the slope fit are in
``tests/test_theory.py`` (tox env ``py``, marker ``theory``).
"""

from __future__ import annotations

import math

import control
import numpy as np
import pytest

from mixedrl.lq import discounted_lq_optimum
from mixedrl.pev import bellman_backup, evaluate_policy
from mixedrl.pim import improve_policy
from mixedrl.quadratic import AffinePolicy, QuadraticValue, is_nonnegative
from theory.quadrature import gaussian_expectation
from validation.lq import (
    LQProblem,
    default_initial_gain,
    example_problem,
    lyapunov_region,
    optimal_solution,
    run_algorithm1,
)

REL = 1e-8  # issue 3, item 4


def rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)) / max(np.linalg.norm(b), 1e-300))


@pytest.fixture(scope="module")
def prob() -> LQProblem:
    return example_problem()


@pytest.fixture(scope="module")
def opt(prob: LQProblem):
    return optimal_solution(prob)


@pytest.fixture(scope="module")
def runs(prob: LQProblem):
    return {m: run_algorithm1(prob, m, iterations=30, samples_per_iteration=100, seed=3, theory_checks=False) for m in ("mixed", "model", "oracle")}


# --------------------------------------------------------------------------------------------------
# the optimum
# --------------------------------------------------------------------------------------------------
def test_dare_residual_and_independent_reference(prob, opt):
    A, B, Q, R, g = prob.A, prob.B, prob.Q, prob.R, prob.gamma
    S, P = opt.S, opt.P
    # S = Q + gamma P
    assert np.allclose(S, Q + g * P, rtol=0, atol=1e-12 * np.abs(S).max())
    # Riccati equation of P with next-state cost: P = A^T S A - A^T S B (R + B^T S B)^-1 B^T S A
    H = R + B.T @ S @ B
    res = P - (A.T @ S @ A - A.T @ S @ B @ np.linalg.solve(H, B.T @ S @ A))
    assert np.abs(res).max() <= 1e-10 * np.abs(P).max()
    # independent reference: python-control's DARE on the scaled matrices (its scipy backend, which
    # discounted_lq_optimum calls without importing python-control): the same S and L, bit for bit
    S_ref, _, L_ref = control.dare(np.sqrt(g) * A, np.sqrt(g) * B, Q, g * R, method="scipy")
    assert np.array_equal(S, S_ref) and np.array_equal(opt.gain, L_ref)
    # L = (R + B^T S B)^-1 B^T S A
    assert rel(opt.gain, np.linalg.solve(H, B.T @ S @ A)) < 1e-12
    Ac = A - B @ opt.gain
    assert np.max(np.abs(np.linalg.eigvals(np.sqrt(g) * Ac))) < 1.0
    assert np.max(np.abs(np.linalg.eigvals(Ac))) < 1.0  # undiscounted closed loop stable on the example


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_dare_equals_python_control_on_random_systems(seed):
    rng = np.random.default_rng(seed)
    n, m, g = 3, 2, 0.95
    A, B = rng.normal(size=(n, n)), rng.normal(size=(n, m))
    Q = np.diag(rng.uniform(0.5, 2.0, n))
    R = np.diag(rng.uniform(0.1, 1.0, m))
    sol = discounted_lq_optimum(A, B, Q, R, g, np.zeros(n))
    S_ref, _, L_ref = control.dare(np.sqrt(g) * A, np.sqrt(g) * B, Q, g * R, method="scipy")
    assert np.array_equal(sol.S, S_ref) and np.array_equal(sol.gain, L_ref)


def test_offset_system_equals_simplified_form(prob, opt):
    """The block (Ac^T S B - L^T R) vanishes: p = (I - g Ac^T)^-1 Ac^T S mu, l0 = H^-1 B^T (S mu + g p)."""
    A, B, R, g, S, mu = prob.A, prob.B, prob.R, prob.gamma, opt.S, prob.noise_mean
    Ac = A - B @ opt.gain
    assert np.abs(Ac.T @ S @ B - opt.gain.T @ R).max() < 1e-12 * np.abs(S).max()
    p = np.linalg.solve(np.eye(prob.n) - g * Ac.T, Ac.T @ S @ mu)
    l0 = np.linalg.solve(R + B.T @ S @ B, B.T @ (S @ mu + g * p))
    assert rel(opt.p, p) < 1e-12 and rel(opt.offset, l0) < 1e-12


def test_undiscounted_optimum_solves_the_riccati_and_offset_equations(prob):
    """gamma = 1 (the LQR reference's case): residuals of S = Q + P, the Riccati equation and the reduced
    offset equations; c is infinite."""
    from validation.lq import discounted_lq_optimum

    A, B, Q, R, mu = prob.A, prob.B, prob.Q, prob.R, prob.noise_mean
    sol = discounted_lq_optimum(A, B, Q, R, 1.0, mu, prob.noise_cov)
    S, P = sol.S, sol.P
    H = R + B.T @ S @ B
    assert np.abs(S - Q - P).max() <= 1e-12 * np.abs(S).max()
    assert np.abs(P - (A.T @ S @ A - A.T @ S @ B @ np.linalg.solve(H, B.T @ S @ A))).max() <= 1e-10 * np.abs(P).max()
    Ac = A - B @ sol.gain
    assert rel(sol.p, np.linalg.solve(np.eye(prob.n) - Ac.T, Ac.T @ S @ mu)) < 1e-10
    assert rel(sol.offset, np.linalg.solve(H, B.T @ (S @ mu + sol.p))) < 1e-10
    assert sol.c == math.inf


def test_optimum_is_bellman_fixed_point(prob, opt):
    """PEV of pi* returns V*, and PIM of V* returns pi* (eqs. 6-7)."""
    f, cost, g = prob.dynamics, prob.cost, prob.gamma
    v = evaluate_policy(f, cost, g, opt.policy, prob.noise_mean, prob.noise_cov)
    assert rel(v.P, opt.P) < 1e-10 and rel(v.p, opt.p) < 1e-10 and abs(v.c - opt.c) < 1e-10 * abs(opt.c)
    pi = improve_policy(f, cost, g, opt.value, prob.noise_mean)
    assert rel(pi.L, opt.gain) < 1e-10 and rel(pi.l0, opt.offset) < 1e-10


def test_offset_is_linear_in_mean_and_gain_independent(prob):
    s0 = optimal_solution(prob, noise_mean=np.zeros(2))
    s1 = optimal_solution(prob, noise_mean=prob.noise_mean)
    s2 = optimal_solution(prob, noise_mean=2 * prob.noise_mean)
    assert np.abs(s0.offset).max() < 1e-14 and np.abs(s0.p).max() < 1e-14
    assert rel(s2.offset, 2 * s1.offset) < 1e-12
    assert rel(s0.gain, s1.gain) < 1e-14 and rel(s0.P, s1.P) < 1e-14


# --------------------------------------------------------------------------------------------------
# exact PEV / PIM against independent computations
# --------------------------------------------------------------------------------------------------
def test_pev_satisfies_self_consistency_by_quadrature(prob, rng):
    """eq. (21) at random states, with E over xi taken by sigma points (a different code path)."""
    f, cost, g = prob.dynamics, prob.cost, prob.gamma
    pol = AffinePolicy(default_initial_gain(prob), np.array([0.3]))
    v = evaluate_policy(f, cost, g, pol, prob.noise_mean, prob.noise_cov)
    x = rng.normal(size=(50, 2))
    u = pol(x)
    rhs = gaussian_expectation(lambda xn, un: cost(xn, un) + g * v(xn), f(x, u), prob.noise_mean, prob.noise_cov, extra=u)
    assert np.max(np.abs(v(x) - rhs) / np.abs(v(x))) < 1e-11


def test_pev_quadratic_term_is_lyapunov_solution(prob):
    f, cost, g = prob.dynamics, prob.cost, prob.gamma
    L = default_initial_gain(prob)
    v = evaluate_policy(f, cost, g, AffinePolicy(L, np.zeros(1)), np.zeros(2), np.zeros((2, 2)))
    Ac = prob.A - prob.B @ L
    W = Ac.T @ prob.Q @ Ac + L.T @ prob.R @ L
    assert np.abs(v.P - (g * Ac.T @ v.P @ Ac + W)).max() < 1e-12 * np.abs(v.P).max()
    # zero-mean, zero-cov noise and zero offset: no linear or constant terms
    assert np.abs(v.p).max() == 0.0 and v.c == 0.0


def test_pev_matches_monte_carlo_with_next_state_cost(rng):
    """The value counts l(x_{t+1}, u_t) from t = 0 (eq. 2): Monte-Carlo rollouts, 5-sigma band."""
    prob = LQProblem([[0.9]], [[1.0]], [[1.0]], [[0.5]], 0.8, [0.3], [[0.04]], [0.0], [[1.0]])
    pol = AffinePolicy(np.array([[0.4]]), np.array([0.1]))
    v = evaluate_policy(prob.dynamics, prob.cost, prob.gamma, pol, prob.noise_mean, prob.noise_cov)
    runs, T, x0 = 20000, 120, 1.5
    x = np.full(runs, x0)
    total = np.zeros(runs)
    for t in range(T):
        u = -0.4 * x - 0.1
        x = 0.9 * x + u + 0.3 + 0.2 * rng.standard_normal(runs)
        total += prob.gamma**t * (x**2 + 0.5 * u**2)
    est, se = total.mean(), total.std(ddof=1) / math.sqrt(runs)
    truncation = prob.gamma**T * 10  # < 1e-10
    assert abs(est - v(np.array([x0]))[0]) < 5 * se + truncation


def test_pim_minimises_h(prob, rng):
    """eq. (22): h(x, pi(x) + delta) >= h(x, pi(x)) for random perturbations (quadrature for E)."""
    f, cost, g = prob.dynamics, prob.cost, prob.gamma
    v = evaluate_policy(f, cost, g, AffinePolicy(default_initial_gain(prob), np.zeros(1)), prob.noise_mean, prob.noise_cov)
    pi = improve_policy(f, cost, g, v, prob.noise_mean)
    x = rng.normal(size=(40, 2))

    def h(u):
        return gaussian_expectation(lambda xn, un: cost(xn, un) + g * v(xn), f(x, u), prob.noise_mean, prob.noise_cov, extra=u)

    h0 = h(pi(x))
    for scale in (1e-3, 1e-1, 1.0):
        d = scale * rng.normal(size=(40, 1))
        assert np.all(h(pi(x) + d) - h0 >= -1e-12 * np.abs(h0))


def test_bellman_backup_fixed_point_is_pev(prob):
    f, cost, g = prob.dynamics, prob.cost, prob.gamma
    pol = AffinePolicy(default_initial_gain(prob), np.array([0.2]))
    v = evaluate_policy(f, cost, g, pol, prob.noise_mean, prob.noise_cov)
    tv = bellman_backup(f, cost, g, pol, v, prob.noise_mean, prob.noise_cov)
    assert v.distance(tv) < 1e-10 * max(1.0, np.abs(v.P).max(), abs(v.c))


def test_is_nonnegative():
    assert is_nonnegative(QuadraticValue(np.eye(2), np.zeros(2), 0.0))
    assert not is_nonnegative(QuadraticValue(np.eye(2), np.zeros(2), -1e-3))
    # x^2 + 2x + 1 = (x+1)^2 >= 0 ; x^2 + 2x + 0.9 has a negative minimum
    assert is_nonnegative(QuadraticValue([[1.0]], [1.0], 1.0))
    assert not is_nonnegative(QuadraticValue([[1.0]], [1.0], 0.9))


def test_pev_rejects_non_stabilising_policy(prob):
    with pytest.raises(ValueError, match="^policy"):
        evaluate_policy(prob.dynamics, prob.cost, prob.gamma, AffinePolicy(np.array([[-10.0, -10.0]]), np.zeros(1)), np.zeros(2), np.eye(2))


# --------------------------------------------------------------------------------------------------
# Algorithm 1 with three noise sources (issue 3, item 4)
# --------------------------------------------------------------------------------------------------
def test_oracle_reaches_dare_optimum(prob, opt, runs):
    res = runs["oracle"]
    assert rel(res.gain, opt.gain) < REL
    assert rel(res.offset, opt.offset) < REL
    assert rel(res.value.P, opt.P) < REL and rel(res.value.p, opt.p) < REL and abs(res.value.c - opt.c) < REL * abs(opt.c)
    Ac = prob.A - prob.B @ res.gain
    assert np.max(np.abs(np.linalg.eigvals(Ac))) < 1.0


def test_model_keeps_the_prior_bias(prob, opt, runs):
    res = runs["model"]
    predicted = optimal_solution(prob, noise_mean=prob.prior_mean, noise_cov=prob.prior_cov)
    assert rel(res.gain, opt.gain) < REL
    assert rel(res.offset, predicted.offset) < REL
    # the bias is real: far larger than the tolerance
    assert rel(predicted.offset, opt.offset) > 0.1


def test_mixed_gain_exact_and_offset_follows_ibe_mean(prob, opt, runs):
    res = runs["mixed"]
    assert rel(res.gain, opt.gain) < REL
    # after the gain has converged, l0 = l0*(mu_hat) exactly (docs/lq.rst); mu_hat of the last IBE step
    implied = optimal_solution(prob, noise_mean=res.noise.mean)
    assert rel(res.offset, implied.offset) < REL
    assert res.history[-1].samples == 30 * 100


def test_mixed_estimate_changes_the_model(prob, runs):
    """Guard against a mixed RL that silently trains the model-driven baseline."""
    mix, mod = runs["mixed"], runs["model"]
    assert np.abs(mix.noise.mean - prob.prior_mean).max() > 10 * np.abs(mix.noise.mean - prob.noise_mean).max()
    assert rel(mix.offset, mod.offset) > 0.1
    assert not np.allclose(mix.history[0].ibe_mean, mix.history[-1].ibe_mean)


def test_mixed_offset_error_within_statistical_band(prob, opt, runs):
    """|l0 - l0*| = |M (mu_hat - mu)| with M = d l0*/d mu; mu_hat - mu ~ N(0, K/N) up to the prior's O(1/N)."""
    res = runs["mixed"]
    N = res.history[-1].samples
    unit = [optimal_solution(prob, noise_mean=e).offset for e in np.eye(2)]
    M = np.column_stack(unit)  # (1, 2)
    sd = math.sqrt(float((M @ prob.noise_cov @ M.T)[0, 0]) / N)
    assert abs(res.offset[0] - opt.offset[0]) < 5 * sd


def test_same_seed_same_result_and_seeds_differ(prob):
    a = run_algorithm1(prob, "mixed", 5, 50, seed=11, theory_checks=False)
    b = run_algorithm1(prob, "mixed", 5, 50, seed=11, theory_checks=False)
    c = run_algorithm1(prob, "mixed", 5, 50, seed=12, theory_checks=False)
    assert np.array_equal(a.offset, b.offset) and np.array_equal(a.noise.mean, b.noise.mean)
    assert not np.array_equal(a.noise.mean, c.noise.mean)


def test_residuals_do_not_depend_on_exploration(prob):
    """Additive noise: residuals x' - f(x, u) = xi whatever the actions (to rounding)."""
    a = run_algorithm1(prob, "mixed", 4, 50, seed=5, exploration_std=0.0, theory_checks=False)
    b = run_algorithm1(prob, "mixed", 4, 50, seed=5, exploration_std=2.0, theory_checks=False)
    assert np.abs(a.noise.mean - b.noise.mean).max() < 1e-12


def test_known_covariance_ibe_option(prob, opt):
    res = run_algorithm1(prob, "mixed", 20, 100, seed=1, ibe="known", theory_checks=False)
    assert rel(res.gain, opt.gain) < REL
    assert np.array_equal(res.noise.cov, prob.noise_cov)
    assert rel(res.offset, optimal_solution(prob, noise_mean=res.noise.mean).offset) < REL


def test_history_has_theory_reports(prob):
    res = run_algorithm1(prob, "oracle", 4, seed=0, n_check_states=16)
    assert set(res.history[0].checks) == {"lyapunov_decrease", "value_decrease", "mvc", "ibe_shift", "lyapunov_region"}
    assert res.history[-1].checks == {}
    assert res.history[0].checks["mvc"].n_states == 16


def test_lyapunov_region_zero_noise_is_empty(prob, opt):
    """With mu = 0, K = 0 and the optimal policy (l0 = 0) the failure set is empty."""
    sol = optimal_solution(prob, noise_mean=np.zeros(2), noise_cov=np.zeros((2, 2)))
    reg = lyapunov_region(prob, sol.value, sol.policy, np.zeros(2), np.zeros((2, 2)))
    assert reg["bounded"] and reg["level"] <= 1e-14 and not reg["origin_fails"]


# --------------------------------------------------------------------------------------------------
# input validation
# --------------------------------------------------------------------------------------------------
GOOD = dict(
    A=np.eye(2), B=np.array([[0.0], [1.0]]) + np.array([[1.0], [0.0]]), Q=np.eye(2), R=np.eye(1), gamma=0.9,
    noise_mean=np.zeros(2), noise_cov=np.eye(2), prior_mean=np.zeros(2), prior_cov=np.eye(2),
)


@pytest.mark.parametrize(
    "key,value",
    [
        ("A", np.ones((2, 3))),
        ("A", np.array([[np.nan, 0], [0, 1]])),
        ("B", np.ones((3, 1))),
        ("Q", np.array([[1.0, 2.0], [0.0, 1.0]])),
        ("Q", -np.eye(2)),
        ("R", np.zeros((1, 1))),
        ("R", np.ones((2, 2))),
        ("gamma", 1.0),
        ("gamma", 0.0),
        ("gamma", float("nan")),
        ("gamma", "x"),
        ("noise_mean", np.zeros(3)),
        ("noise_mean", np.array([np.inf, 0.0])),
        ("noise_cov", -np.eye(2)),
        ("prior_mean", np.zeros((2, 1))),
        ("prior_cov", np.array([[1.0, 0.5], [0.4, 1.0]])),
    ],
)
def test_problem_rejects_bad_argument(key, value):
    with pytest.raises(ValueError, match=f"^{key}"):
        LQProblem(**{**GOOD, key: value})


def test_problem_rejects_unstabilisable():
    with pytest.raises(ValueError, match="^A"):
        LQProblem(**{**GOOD, "A": np.diag([1.2, 0.5]), "B": np.array([[0.0], [1.0]])})
    # an uncontrollable but stable mode is fine
    LQProblem(**{**GOOD, "A": np.diag([0.5, 1.2]), "B": np.array([[0.0], [1.0]])})


@pytest.mark.parametrize(
    "kwargs,name",
    [
        ({"method": "mixd"}, "method"),
        ({"iterations": 0}, "iterations"),
        ({"samples_per_iteration": 1.5}, "samples_per_iteration"),
        ({"seed": -1}, "seed"),
        ({"initial_gain": np.zeros((2, 2))}, "initial_gain"),
        ({"initial_gain": np.array([[-10.0, -10.0]])}, "initial_gain"),  # rho(sqrt(gamma)(A - B L)) > 1
        ({"ibe": "case3"}, "ibe"),
        ({"exploration_std": -1.0}, "exploration_std"),
    ],
)
def test_run_rejects_bad_argument(prob, kwargs, name):
    with pytest.raises(ValueError, match=f"^{name}"):
        run_algorithm1(prob, **kwargs)
