"""Tests of :mod:`theory.premises`: Theorem 1's condition on gamma (eq. 27) and Lemma 2's full-rank premise.

Expected values come from hand computation (scalar closed forms), from the paper's numbers (the
vehicle prior) or from independent code (:func:`validation.lq.lyapunov_region`,
:func:`theory.lyapunov_decrease`), never from the code under test.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from mixedrl.noise import GaussianNoise
from mixedrl.quadratic import AffinePolicy, LinearDynamics, QuadraticCost, QuadraticValue
from theory import PriorRankReport, gamma_condition, lyapunov_decrease, prior_full_rank
from validation.lq import check_states, example_problem, lyapunov_region, optimal_solution, run_algorithm1

T, MASS = 1.0 / 200.0, 1500.0


def vehicle_prior() -> np.ndarray:
    """The paper's prior covariance (eq. 55): (4 T/m)^2 on v_x (index 2), 1e-20 on the other four."""
    return np.diag([1e-20, 1e-20, (4.0 * T / MASS) ** 2, 1e-20, 1e-20])


# --------------------------------------------------------------------------------------------------
# eq. (27): the condition on gamma
# --------------------------------------------------------------------------------------------------
def scalar_system(a: float, b: float, q: float, r: float, gain: float):
    return (
        LinearDynamics(np.array([[a]]), np.array([[b]])),
        QuadraticCost(np.array([[q]]), np.array([[r]])),
        AffinePolicy(np.array([[gain]]), np.zeros(1)),
    )


def test_gamma_condition_matches_hand_computation():
    a, b, q, r, gain, p, c, gamma, mu, var = 1.2, 0.5, 2.0, 0.3, 0.8, 7.0, 0.4, 0.9, 0.25, 0.04
    f, cost, policy = scalar_system(a, b, q, r, gain)
    value = QuadraticValue(np.array([[p]]), np.zeros(1), c)
    x = np.linspace(-3.0, 3.0, 13)[:, None]
    rep = gamma_condition(value, policy, f, cost, gamma, GaussianNoise([mu], [[var]]), x)
    mean_next = (a - b * gain) * x[:, 0] + mu  # E x' under u = -gain x
    second = mean_next**2 + var  # E x'^2
    e_l = q * second + r * (gain * x[:, 0]) ** 2
    e_v = p * second + c
    assert rep.name == "gamma_condition" and rep.equation == "27"
    np.testing.assert_allclose(rep.extra["expected_utility"], e_l, rtol=1e-12)
    np.testing.assert_allclose(rep.extra["expected_value"], e_v, rtol=1e-12)
    np.testing.assert_allclose(rep.margins, e_l - (1.0 - gamma) * e_v, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(rep.extra["gamma_min"], 1.0 - e_l / e_v, rtol=1e-12)
    np.testing.assert_allclose(rep.extra["bellman_slack"], p * x[:, 0] ** 2 + c - e_l - gamma * e_v, rtol=1e-12, atol=1e-12)
    assert rep.extra["gamma_required"] == pytest.approx(float(np.max(1.0 - e_l / e_v)), rel=1e-12)


def test_gamma_below_the_threshold_is_reported_as_violating():
    # zero noise, V = p x^2, l = q x'^2: eq. (27) holds iff gamma >= 1 - q / p = 0.9 (at every x' != 0)
    f, cost, policy = scalar_system(0.9, 1.0, 1.0, 1e-12, 0.0)
    value = QuadraticValue(np.array([[10.0]]), np.zeros(1), 0.0)
    noise = GaussianNoise([0.0], [[0.0]])
    x = np.linspace(0.5, 4.0, 8)[:, None]
    low = gamma_condition(value, policy, f, cost, 0.85, noise, x)
    assert not low.held and low.held_fraction == 0.0
    assert np.all(low.margins < 0.0)
    assert low.extra["gamma_required"] == pytest.approx(0.9, rel=1e-9)
    high = gamma_condition(value, policy, f, cost, 0.95, noise, x)
    assert high.held and np.all(high.margins > 0.0)
    assert high.extra["gamma_required"] == pytest.approx(0.9, rel=1e-9)


def test_gamma_condition_splits_the_lyapunov_margin_on_the_lq_example():
    """Eq. (26): V^k(x) - E V^k(x') = (slack of eq. 25) + (margin of eq. 27); eq. (25) holds for exact PEV/PIM."""
    prob = example_problem()
    res = run_algorithm1(prob, "oracle", iterations=3, theory_checks=False)
    noise = GaussianNoise(prob.noise_mean, prob.noise_cov)
    states = check_states(prob.n, 200, (1e-3, 1e2), np.random.default_rng(3))
    slack_max = []
    for it in res.history[:2]:
        nxt = AffinePolicy(it.gain, it.offset)  # pi^{k+1} = PIM(V^k)
        rep = gamma_condition(it.value, nxt, prob.dynamics, prob.cost, prob.gamma, noise, states)
        lyap = lyapunov_decrease(it.value, nxt, prob.dynamics, noise, states)
        scale = np.abs(it.value(states)) + 1.0
        assert np.max(np.abs(rep.extra["lyapunov_margin"] - lyap.margins) / scale) < 1e-10
        # eq. (25): PIM minimises h(x, ., xi_hat) and V^k = h(x, u^k, xi_hat) (eq. 35), so the slack is >= 0
        assert np.min(rep.extra["bellman_slack"] / scale) > -1e-10
        slack_max.append(float(np.max(rep.extra["bellman_slack"] / scale)))
    # from the non-optimal pi^0, PIM improves strictly (eq. 39's e_0 > 0), so the slack is not zero
    assert slack_max[0] > 1e-3


def test_gamma_condition_at_the_lq_optimum_fails_exactly_inside_the_lyapunov_region():
    """At the optimum eq. (25) is an equality, so eq. (27)'s margin is -Delta(x) of the exact region."""
    prob = example_problem()
    opt = optimal_solution(prob)
    noise = GaussianNoise(prob.noise_mean, prob.noise_cov)
    states = check_states(prob.n, 400, (1e-3, 1e2), np.random.default_rng(7))
    rep = gamma_condition(opt.value, opt.policy, prob.dynamics, prob.cost, prob.gamma, noise, states)
    region = lyapunov_region(prob, opt.value, opt.policy, prob.noise_mean, prob.noise_cov)
    assert region["bounded"] and region["level"] > 0.0
    d = states - region["center"]
    A_c = prob.A - prob.B @ opt.policy.L
    D = A_c.T @ opt.P @ A_c - opt.P
    inside = np.einsum("ni,ij,nj->n", d, -D, d) < region["level"]
    far = np.abs(np.einsum("ni,ij,nj->n", d, -D, d) - region["level"]) > 1e-6 * region["level"]
    assert inside.any() and (~inside).any()
    np.testing.assert_array_equal(~rep.held_mask[far], inside[far])
    assert rep.extra["gamma_required"] > prob.gamma  # no gamma below 1 fixes it for this V


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"gamma": 1.0}, "^gamma: must lie in"),
        ({"gamma": 0.0}, "^gamma: must lie in"),
        ({"gamma": float("nan")}, "^gamma: must lie in"),
        ({"gamma": True}, "^gamma: expected a float"),
        ({"gamma": "0.9"}, "^gamma: expected a float"),
        ({"states": [[np.nan]]}, "^states: contains NaN"),
        ({"states": np.zeros((2, 2, 1))}, "^states: expected shape"),
        ({"noise": object()}, "^noise: expected an object with .mean and .cov"),
        ({"value": lambda x: np.zeros((x.shape[0], 1))}, "^value: expected output shape"),
        ({"utility": lambda x, u: np.full(x.shape[0], np.inf)}, "^utility: returned NaN or inf"),
        ({"rtol": -1.0}, "^rtol: expected a non-negative number"),
    ],
)
def test_gamma_condition_rejects_bad_input(kwargs, match):
    f, cost, policy = scalar_system(1.0, 1.0, 1.0, 1.0, 0.5)
    args = {
        "value": QuadraticValue(np.array([[2.0]]), np.zeros(1), 0.0),
        "policy": policy,
        "f": f,
        "utility": cost,
        "gamma": 0.9,
        "noise": GaussianNoise([0.0], [[0.1]]),
        "states": np.array([[1.0], [2.0]]),
    }
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        gamma_condition(**args)


def test_gamma_condition_leaves_its_input_unchanged():
    f, cost, policy = scalar_system(1.0, 1.0, 1.0, 1.0, 0.5)
    x = np.array([[1.0], [-2.0]])
    before = x.copy()
    gamma_condition(QuadraticValue(np.array([[2.0]]), np.zeros(1), 0.0), policy, f, cost, 0.9,
                    GaussianNoise([0.1], [[0.1]]), x)
    np.testing.assert_array_equal(x, before)


# --------------------------------------------------------------------------------------------------
# Lemma 2: the prior's covariance is full rank
# --------------------------------------------------------------------------------------------------
def test_full_rank_prior_passes():
    prob = example_problem()  # K_M = diag(1e-4, 1e-3)
    rep = prior_full_rank(prob.prior_cov, noise_cov=prob.noise_cov)
    assert isinstance(rep, PriorRankReport)
    assert rep.full_rank and rep.held and rep.rank == 2 and rep.dim == 2
    assert rep.condition_number == pytest.approx(10.0, rel=1e-12)
    assert rep.deficient_directions.shape == (2, 0)
    # K = diag(1e-4, 4e-4): one sample's weight against the prior along each axis
    np.testing.assert_allclose(np.sort(rep.equivalent_samples), [0.4, 1.0], rtol=1e-12)


def test_vehicle_prior_is_flagged_as_effectively_singular():
    rep = prior_full_rank(vehicle_prior())
    assert not rep.full_rank and not rep.held
    assert rep.rank == 1
    assert rep.condition_number == pytest.approx((4.0 * T / MASS) ** 2 / 1e-20, rel=1e-12)  # 1.78e10
    assert rep.rank_at(1e-13) == 5  # mixedrl.gaussian.SUPPORT_RTOL keeps all five
    assert rep.rank_at(1e-6) == 1
    # the deficient directions are the four pinned components, not v_x
    proj = rep.deficient_directions @ rep.deficient_directions.T
    np.testing.assert_allclose(proj, np.diag([1.0, 1.0, 0.0, 1.0, 1.0]), atol=1e-12)
    summary = rep.summary()
    assert summary["full_rank"] is False and summary["rank"] == 1


def test_vehicle_prior_equivalent_samples():
    # truth: F_dis ~ N(261, 32) on v_x, so K = 32 (T/m)^2; prior std 4 N: the prior is worth 32 / 16 = 2 samples
    k = np.zeros((5, 5))
    k[2, 2] = 32.0 * (T / MASS) ** 2
    rep = prior_full_rank(vehicle_prior(), noise_cov=k)
    vx = int(np.argmax(np.abs(rep.eigenvectors[2])))
    assert rep.equivalent_samples[vx] == pytest.approx(2.0, rel=1e-12)
    assert np.all(np.delete(rep.equivalent_samples, vx) == 0.0)  # no noise on the pinned components
    # the same noise on a pinned component: 3.6e10 samples before the data weigh as much as the prior
    k_y = np.zeros((5, 5))
    k_y[0, 0] = k[2, 2]
    pinned = prior_full_rank(vehicle_prior(), noise_cov=k_y)
    assert max(pinned.equivalent_samples) == pytest.approx(k[2, 2] / 1e-20, rel=1e-12)


def test_task_prior_is_flagged():
    from mixedrl.tasks import DoubleLaneChangeTask

    task = DoubleLaneChangeTask()
    rep = prior_full_rank(task.prior_cov)
    assert not rep.full_rank and rep.rank == 1


def test_exactly_singular_and_zero_priors():
    rep = prior_full_rank(np.diag([1.0, 0.0, 2.0]), noise_cov=np.eye(3))
    assert rep.rank == 2 and rep.condition_number == math.inf and not rep.full_rank
    assert math.isinf(max(rep.equivalent_samples))
    zero = prior_full_rank(np.zeros((2, 2)))
    assert zero.rank == 0 and zero.rank_at(0.0) == 0 and zero.condition_number == math.inf
    assert prior_full_rank(np.diag([1.0, 1e-30]), rtol=0.0).full_rank  # rtol = 0: every positive eigenvalue


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"prior_cov": [[1.0, 0.5], [0.0, 1.0]]}, "^prior_cov: not symmetric"),
        ({"prior_cov": [[1.0, 2.0], [2.0, 1.0]]}, "^prior_cov: not positive semi-definite"),
        ({"prior_cov": [[np.nan, 0.0], [0.0, 1.0]]}, "^prior_cov: contains NaN or inf"),
        ({"prior_cov": np.ones((2, 3))}, "^prior_cov: expected a square matrix"),
        ({"prior_cov": "abc"}, "^prior_cov: cannot be converted"),
        ({"rtol": 1.0}, r"^rtol: expected a number in \[0, 1\)"),
        ({"rtol": -0.1}, r"^rtol: expected a number in \[0, 1\)"),
        ({"rtol": "1e-8"}, r"^rtol: expected a number, got '1e-8'"),
        ({"noise_cov": np.eye(3)}, r"^noise_cov: expected a square matrix of shape \(2, 2\)"),
    ],
)
def test_prior_full_rank_rejects_bad_input(kwargs, match):
    args = {"prior_cov": np.eye(2)}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        prior_full_rank(**args)
