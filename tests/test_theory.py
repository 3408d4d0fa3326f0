"""The ``theory`` checks (Theorems 1-4) and the results of issue 3 item 4 on random LQ systems.

Runs in tox's ``theory`` environment. Asserts only what is mathematically guaranteed:

* quadrature: sigma points exact for polynomials of degree <= 3; Gauss-Hermite converges;
* the checks compute the margins they state (hand-made cases with known answers);
* Theorem 2 under a fixed noise (exact PEV/PIM, stabilising start): ``V^{k+1} <= V^k`` for every x;
* eq. (39): ``e_k >= 0`` for every x (PIM is an exact minimiser);
* Theorem 3's implication in its global form: if the MVC holds for every x then ``V^{k+1} <= V^k``
  for every x (checked exactly on quadratics with :func:`mixedrl.quadratic.is_nonnegative`);
* the sampled Lyapunov check agrees with the exact failure region;
* oracle = DARE, model = the prior's prediction, mixed = the IBE mean's prediction, to 1e-8;
* the offset error of mixed RL falls like ``N^{-1/2}`` (slope within 4 bootstrap standard errors).

How often the MVC held, and where Lyapunov decrease fails, are measured and reported (docs/theory.rst).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from mixedrl.noise import GaussianNoise
from mixedrl.pev import bellman_backup
from mixedrl.quadratic import AffinePolicy, QuadraticValue, is_nonnegative
from theory import GaussHermite, SigmaPoints, gaussian_expectation, ibe_shift, lyapunov_decrease, mvc, value_decrease
from validation.lq import (
    LQProblem,
    check_states,
    example_problem,
    lyapunov_region,
    offset_error_study,
    optimal_solution,
    run_algorithm1,
)

pytestmark = pytest.mark.theory

REL = 1e-8


def rel(a, b) -> float:
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)) / max(np.linalg.norm(b), 1e-300))


def random_psd(rng: np.random.Generator, n: int, rank: int | None = None) -> np.ndarray:
    F = rng.normal(size=(n, n if rank is None else rank))
    return F @ F.T


# --------------------------------------------------------------------------------------------------
# quadrature
# --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("rank", [3, 2, 1, 0])
def test_sigma_points_exact_for_quadratics(rng, rank):
    n = 3
    K = random_psd(rng, n, rank) if rank else np.zeros((n, n))
    V = QuadraticValue(random_psd(rng, n) - np.eye(n), rng.normal(size=n), 1.3)
    c, mu = rng.normal(size=(20, n)), rng.normal(size=n)
    quad = gaussian_expectation(V, c, mu, K)
    exact = V.expected(c, mu, K)  # V(c + mu) + tr(P K)
    assert np.max(np.abs(quad - exact) / np.maximum(1.0, np.abs(exact))) < 1e-12


def test_sigma_points_exact_for_cubics(rng):
    n, a = 3, rng.normal(size=3)
    K, mu = random_psd(rng, n), rng.normal(size=n)
    c = rng.normal(size=(10, n))
    quad = gaussian_expectation(lambda x: (x @ a) ** 3, c, mu, K)
    m, s2 = (c + mu) @ a, a @ K @ a
    exact = m**3 + 3 * m * s2
    assert np.max(np.abs(quad - exact) / np.maximum(1.0, np.abs(exact))) < 1e-12


@pytest.mark.parametrize("scale", [0.1, 0.3])
def test_quadrature_error_on_exponential(rng, scale):
    """E exp(a^T x) = exp(a^T m + a^T K a / 2). Sigma points: error O(s^4), s^2 = a^T K a; GH(8): < 1e-10."""
    n = 2
    K = random_psd(rng, n)
    a = rng.normal(size=n)
    a *= scale / math.sqrt(a @ K @ a)  # s = scale
    c, mu = rng.normal(size=(5, n)), np.zeros(n)
    exact = np.exp(c @ a + 0.5 * scale**2)
    err_sp = np.max(np.abs(gaussian_expectation(lambda x: np.exp(x @ a), c, mu, K, SigmaPoints()) / exact - 1))
    err_gh = np.max(np.abs(gaussian_expectation(lambda x: np.exp(x @ a), c, mu, K, GaussHermite(8)) / exact - 1))
    assert err_sp <= scale**4  # fourth-order term: (r - 3) s^4 / 24 at most r s^4 / 24 with r = 2
    assert err_sp > 0.0  # not exact: a non-polynomial integrand
    assert err_gh < 1e-10


# --------------------------------------------------------------------------------------------------
# the checks on cases with known answers
# --------------------------------------------------------------------------------------------------
def scalar_f(x, u):
    return 0.5 * x + u


def zero_policy(x):
    return np.zeros((x.shape[0], 1))


def test_value_decrease_margins():
    x = np.linspace(-2, 2, 9)[:, None]
    V0 = QuadraticValue([[2.0]], [0.0], 1.0)
    r = value_decrease(V0, QuadraticValue([[1.0]], [0.0], 1.0), x)
    assert np.allclose(r.margins, x[:, 0] ** 2) and r.held and r.held_fraction == 1.0
    r = value_decrease(V0, QuadraticValue([[2.0]], [0.0], 1.5), x)
    assert not r.held and r.held_fraction == 0.0 and r.worst_margin == pytest.approx(-0.5)
    assert r.failed_states.shape == (9, 1)


def test_lyapunov_decrease_scalar_region():
    """x' = 0.5 x + xi: E V(x') = 0.25 x^2 + s^2 (+ mean terms); fails exactly for 0.75 x^2 < s^2."""
    V = QuadraticValue([[1.0]], [0.0], 0.0)
    x = np.linspace(-3, 3, 601)[:, None]
    r = lyapunov_decrease(V, zero_policy, scalar_f, GaussianNoise([0.0], [[0.0]]), x)
    assert r.held
    s2 = 0.49
    r = lyapunov_decrease(V, zero_policy, scalar_f, GaussianNoise([0.0], [[s2]]), x)
    assert np.allclose(r.margins, 0.75 * x[:, 0] ** 2 - s2, atol=1e-14)
    inside = 0.75 * x[:, 0] ** 2 < s2 - 1e-9
    assert np.array_equal(~r.held_mask, inside)
    lo, hi = r.failed_norm_range()
    assert hi <= math.sqrt(s2 / 0.75)
    # non-zero mean: E V = (0.5 x + m)^2 + s2
    r = lyapunov_decrease(V, zero_policy, scalar_f, GaussianNoise([0.3], [[s2]]), x)
    assert np.allclose(r.margins, x[:, 0] ** 2 - (0.5 * x[:, 0] + 0.3) ** 2 - s2, atol=1e-13)


def test_mvc_fixed_noise_equals_e_and_ibe_shift():
    """Same noise at k and k+1: the variation is 0, the MVC margin is e_k."""
    V = QuadraticValue([[1.0]], [0.1], 0.2)
    nz = GaussianNoise([0.1], [[0.2]])
    x = np.linspace(-1, 1, 11)[:, None]

    def l(xn, u):
        return xn[:, 0] ** 2 + u[:, 0] ** 2

    r = mvc(V, zero_policy, lambda z: -0.3 * z, scalar_f, l, 0.9, nz, nz, x)
    assert np.allclose(r.extra["variation"], 0.0) and np.allclose(r.margins, r.extra["e"])
    assert ibe_shift(nz, nz).kl == 0.0
    # 1-D KL: 0.5 (s0/s1 + (m1-m0)^2/s1 - 1 + ln(s1/s0))
    k = ibe_shift(GaussianNoise([0.0], [[1.0]]), GaussianNoise([1.0], [[2.0]])).kl
    assert k == pytest.approx(0.5 * (0.5 + 0.5 - 1 + math.log(2.0)), rel=1e-12)


def test_checks_reject_bad_shapes():
    V = QuadraticValue([[1.0]], [0.0], 0.0)
    with pytest.raises(ValueError, match="^value"):
        value_decrease(lambda x: np.zeros(3), V, np.zeros((5, 1)))
    with pytest.raises(ValueError, match="^centers|^mean"):
        gaussian_expectation(V, np.zeros((2, 1)), np.zeros(2), np.eye(2))
    with pytest.raises(ValueError, match="^order"):
        GaussHermite(0)


# --------------------------------------------------------------------------------------------------
# theorems on the LQ example (fixed and varying noise)
# --------------------------------------------------------------------------------------------------
def global_checks(prob: LQProblem, res) -> list[dict]:
    """Exact (every x) versions of value decrease, e_k >= 0 and the MVC for each step k -> k+1 of a run.

    With V^k the exact PEV value, h(x, u^k, xi_k) = V^k(x), so (T = one PEV sweep, eq. 31, under pi^{k+1}):
    e_k >= 0 everywhere  <=>  V^k - T(pi^{k+1}, xi_k) V^k >= 0;  MVC everywhere  <=>  V^k - T(pi^{k+1}, xi_{k+1}) V^k >= 0.
    """
    f, cost, g = prob.dynamics, prob.cost, prob.gamma
    out = []
    for a, b in zip(res.history[:-1], res.history[1:]):
        pi_next = AffinePolicy(a.gain, a.offset)
        t_next = bellman_backup(f, cost, g, pi_next, a.value, b.ibe_mean, b.ibe_cov)
        t_same = bellman_backup(f, cost, g, pi_next, a.value, a.ibe_mean, a.ibe_cov)
        out.append(
            {
                "mvc_global": is_nonnegative(a.value - t_next),
                "e_global": is_nonnegative(a.value - t_same),
                "vdec_global": is_nonnegative(a.value - b.value),
            }
        )
    return out


@pytest.fixture(scope="module")
def example_runs():
    prob = example_problem()
    return prob, {m: run_algorithm1(prob, m, 30, 100, seed=0) for m in ("mixed", "model", "oracle")}


@pytest.mark.parametrize("method", ["oracle", "model"])
def test_theorem2_value_decrease_fixed_noise(example_runs, method):
    prob, runs = example_runs
    res = runs[method]
    for rec, gl in zip(res.history, global_checks(prob, res)):
        assert gl["vdec_global"] and gl["e_global"] and gl["mvc_global"]
        assert rec.checks["value_decrease"].held and rec.checks["mvc"].held
        assert rec.checks["mvc"].extra["e_nonnegative_fraction"] == 1.0


def fully_actuated_problem() -> LQProblem:
    """The example's double integrator with one input per state (m = n = 2)."""
    p = example_problem()
    return LQProblem(p.A, 0.1 * np.eye(2), p.Q, 0.01 * np.eye(2), p.gamma, p.noise_mean, p.noise_cov, p.prior_mean, p.prior_cov)


@pytest.mark.parametrize("make", [example_problem, fully_actuated_problem])
def test_e_nonnegative_and_theorem3_implication_varying_noise(make):
    """Under the varying IBE estimate: e_k >= 0 always; global MVC => global value decrease.

    With m < n (the example) the global MVC essentially never holds once the IBE mean moves (docs/theory.rst),
    so the implication is exercised on the fully actuated variant, where it holds at some steps.
    """
    prob = make()
    held = implied = 0
    for seed in range(10):
        res = run_algorithm1(prob, "mixed", 10, 100, seed=seed, n_check_states=64)
        for rec, gl in zip(res.history, global_checks(prob, res)):
            assert gl["e_global"]
            assert rec.checks["mvc"].extra["e_nonnegative_fraction"] == 1.0
            if gl["mvc_global"]:
                held += 1
                implied += gl["vdec_global"]
    assert implied == held
    if prob.m == prob.n:
        assert held > 0  # the implication was exercised


@pytest.mark.parametrize("method", ["mixed", "oracle"])
def test_sampled_lyapunov_check_agrees_with_exact_region(example_runs, method):
    prob, runs = example_runs
    for rec in runs[method].history[:-1]:
        ly, reg = rec.checks["lyapunov_decrease"], rec.checks["lyapunov_region"]
        assert reg["bounded"]
        P = -(prob.A - prob.B @ rec.gain).T @ rec.value.P @ (prob.A - prob.B @ rec.gain) + rec.value.P
        d = ly.states - reg["center"]
        q = np.einsum("ni,ij,nj->n", d, P, d)
        clearly_in, clearly_out = q < 0.999 * reg["level"], q > 1.001 * reg["level"]
        assert np.all(~ly.held_mask[clearly_in]) and np.all(ly.held_mask[clearly_out])


def test_lyapunov_zero_mean_noise_fails_only_near_origin():
    """Zero-mean noise, optimal policy: Delta(x) = x^T D x + tr(P K) -> failure set is an ellipsoid at 0."""
    prob0 = example_problem()
    prob = LQProblem(prob0.A, prob0.B, prob0.Q, prob0.R, prob0.gamma, np.zeros(2), prob0.noise_cov, np.zeros(2), prob0.prior_cov)
    sol = optimal_solution(prob)
    reg = lyapunov_region(prob, sol.value, sol.policy, np.zeros(2), prob.noise_cov)
    assert reg["bounded"] and np.allclose(reg["center"], 0.0, atol=1e-14)
    assert reg["level"] == pytest.approx(float(np.sum(sol.P * prob.noise_cov)), rel=1e-12)
    x = check_states(2, 400, (1e-3, 1e2), np.random.default_rng(0))
    ly = lyapunov_decrease(sol.value, sol.policy, prob.dynamics, GaussianNoise(np.zeros(2), prob.noise_cov), x)
    assert not ly.held
    assert ly.failed_norm_range()[1] <= reg["max_norm"]


def test_ibe_shift_tends_to_zero(example_runs):
    """Theorem 4 / eq. (45): KL between successive estimates shrinks (median of the last 10 < first / 100)."""
    _, runs = example_runs
    kls = [rec.checks["ibe_shift"].kl for rec in runs["mixed"].history[:-1]]
    assert np.median(kls[-10:]) < kls[0] / 100


# --------------------------------------------------------------------------------------------------
# slope of the offset error against samples
# --------------------------------------------------------------------------------------------------
def test_mixed_offset_error_slope_is_minus_half():
    study = offset_error_study(example_problem(), seeds=200, iterations=60, samples_per_iteration=25, skip=8)
    assert study["gain_error_max"] < REL
    assert study["slope_se"] < 0.06  # the band is informative
    assert abs(study["slope"] + 0.5) < 4 * study["slope_se"]


# --------------------------------------------------------------------------------------------------
# random systems (issue 3 item 4, hypothesis)
# --------------------------------------------------------------------------------------------------
@st.composite
def lq_problems(draw):
    n = draw(st.integers(1, 4))
    m = draw(st.integers(1, n))
    seed = draw(st.integers(0, 2**31 - 1))
    gamma = draw(st.floats(0.8, 0.99))
    rng = np.random.default_rng(seed)
    A = rng.uniform(-1.5, 1.5, size=(n, n)) / math.sqrt(n)
    B = rng.uniform(-1.0, 1.0, size=(n, m))
    Q = random_psd(rng, n) + 0.1 * np.eye(n)
    R = random_psd(rng, m) + 0.1 * np.eye(m)
    mu = 0.5 * rng.normal(size=n)
    try:
        return LQProblem(A, B, Q, R, gamma, mu, 0.1 * random_psd(rng, n) / n, mu + 0.5 * rng.normal(size=n), 0.1 * np.eye(n))
    except ValueError:
        assume(False)


@settings(deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(prob=lq_problems())
def test_random_systems_all_results(prob):
    opt = optimal_solution(prob)
    A, B, Q, R, g, S, P = prob.A, prob.B, prob.Q, prob.R, prob.gamma, opt.S, opt.P
    # Riccati residual and discounted closed-loop stability
    res_P = P - (A.T @ S @ A - A.T @ S @ B @ np.linalg.solve(R + B.T @ S @ B, B.T @ S @ A))
    assert np.abs(res_P).max() <= 1e-9 * max(1.0, np.abs(P).max())
    assert np.max(np.abs(np.linalg.eigvals(math.sqrt(g) * (A - B @ opt.gain)))) < 1.0
    runs = {mth: run_algorithm1(prob, mth, 40, 50, seed=0, theory_checks=False) for mth in ("oracle", "model", "mixed")}
    assert rel(runs["oracle"].gain, opt.gain) < REL and rel(runs["oracle"].offset, opt.offset) < REL
    assert rel(runs["model"].gain, opt.gain) < REL
    assert rel(runs["model"].offset, optimal_solution(prob, noise_mean=prob.prior_mean).offset) < REL
    assert rel(runs["mixed"].gain, opt.gain) < REL
    assert rel(runs["mixed"].offset, optimal_solution(prob, noise_mean=runs["mixed"].noise.mean).offset) < REL
    # Theorem 2 under fixed noise, every iteration, every x; e_k >= 0 for all three
    for mth in ("oracle", "model"):
        for gl in global_checks(prob, runs[mth]):
            assert gl["vdec_global"] and gl["e_global"]
    for gl in global_checks(prob, runs["mixed"]):
        assert gl["e_global"]
        if gl["mvc_global"]:
            assert gl["vdec_global"]
