"""Algorithm 1's loop (mixedrl.algorithms.policy_iteration) and the noise sources (mixedrl.noise)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from mixedrl.algorithms.policy_iteration import ibe_step, pev_step, pim_step, policy_iteration
from mixedrl.ibe import UnknownCovarianceIBE
from mixedrl.noise import GaussianNoise, make_noise_source
from mixedrl.pev import ExactPEV
from mixedrl.pim import ExactPIM
from mixedrl.quadratic import AffinePolicy
from validation.lq import default_initial_gain, example_problem, optimal_solution


class Recorder:
    """A noise source that logs every call, to test the order of the three steps."""

    learns = True
    state_dependent = False

    def __init__(self, log: list) -> None:
        self.log = log
        self.mean = np.zeros(1)
        self.cov = np.eye(1)
        self.count = 0

    def update(self, xi: np.ndarray) -> "Recorder":
        self.log.append(("ibe", float(xi.sum())))
        self.mean = self.mean + xi.sum()
        self.count += xi.shape[0]
        return self


def test_steps_run_in_order_ibe_pev_pim_with_current_noise():
    log: list = []
    noise = Recorder(log)

    def collect(policy, k):
        log.append(("collect", policy, k))
        return np.full((2, 1), float(k + 1))

    def evaluate(policy, nz):
        log.append(("pev", policy, float(nz.mean[0])))
        return ("V", policy)

    def improve(value, nz):
        log.append(("pim", value[1], float(nz.mean[0])))
        return value[1] + 1

    out = policy_iteration(noise, evaluate, improve, initial_policy=0, iterations=3, collect=collect)
    kinds = [e[0] for e in log]
    assert kinds == ["collect", "ibe", "pev", "pim"] * 3
    # PEV and PIM of iteration k see the noise after the k-th IBE update; data is collected under pi^k
    assert log[0] == ("collect", 0, 0) and log[2] == ("pev", 0, 2.0) and log[3] == ("pim", 0, 2.0)
    assert log[4] == ("collect", 1, 1) and log[6] == ("pev", 1, 6.0)
    assert out.policy == 3 and [h.samples for h in out.history] == [2, 4, 6]
    assert [h.next_policy for h in out.history] == [1, 2, 3]
    assert out.history[1].noise_mean[0] == 6.0


def test_history_snapshots_do_not_alias_the_noise():
    noise = Recorder([])
    out = policy_iteration(noise, lambda p, n: 0, lambda v, n: 0, 0, 2, collect=lambda p, k: np.ones((1, 1)))
    first = out.history[0].noise_mean.copy()
    noise.mean[0] = 123.0
    assert np.array_equal(out.history[0].noise_mean, first)


def test_ibe_step_contract():
    ibe_step(GaussianNoise([0.0], [[1.0]]), None)  # fixed source: identity
    with pytest.raises(ValueError, match="^noise"):
        ibe_step(GaussianNoise([0.0], [[1.0]]), np.ones((3, 1)))
    ibe = UnknownCovarianceIBE([0.0], [[1.0]])
    ibe_step(ibe, np.ones((3, 1)))
    assert ibe.count == 3


def test_pev_pim_steps_delegate():
    assert pev_step(lambda p, n: (p, n), "pi", "xi") == ("pi", "xi")
    assert pim_step(lambda v, n: (v, n), "V", "xi") == ("V", "xi")


def test_bad_arguments():
    with pytest.raises(ValueError, match="^iterations"):
        policy_iteration(Recorder([]), lambda p, n: 0, lambda v, n: 0, 0, 0)
    with pytest.raises(ValueError, match="^tol"):
        policy_iteration(Recorder([]), lambda p, n: 0, lambda v, n: 0, 0, 2, tol=-1.0)


def test_stopping_rule_on_lq_oracle():
    prob = example_problem()
    f, cost, g = prob.dynamics, prob.cost, prob.gamma
    noise = GaussianNoise(prob.noise_mean, prob.noise_cov)
    pol0 = AffinePolicy(default_initial_gain(prob), np.zeros(1))
    out = policy_iteration(noise, ExactPEV(f, cost, g), ExactPIM(f, cost, g), pol0, 100, tol=1e-12)
    assert out.converged and len(out.history) < 20
    opt = optimal_solution(prob)
    assert np.allclose(out.policy.L, opt.gain, rtol=1e-10, atol=0)


def test_one_loop_three_noise_sources_differ_only_in_noise():
    """The same loop with the prior and with an IBE fed data: the IBE moves the model's mean."""
    prob = example_problem()
    f, cost, g = prob.dynamics, prob.cost, prob.gamma
    pol0 = AffinePolicy(default_initial_gain(prob), np.zeros(1))
    rng = np.random.default_rng(0)
    truth = GaussianNoise(prob.noise_mean, prob.noise_cov)
    ibe = UnknownCovarianceIBE(prob.prior_mean, prob.prior_cov)
    mixed = policy_iteration(ibe, ExactPEV(f, cost, g), ExactPIM(f, cost, g), pol0, 3, collect=lambda p, k: truth.sample(500, rng))
    model = policy_iteration(GaussianNoise(prob.prior_mean, prob.prior_cov), ExactPEV(f, cost, g), ExactPIM(f, cost, g), pol0, 3)
    assert np.array_equal(model.history[0].noise_mean, prob.prior_mean)
    assert not np.allclose(mixed.history[0].noise_mean, prob.prior_mean)
    assert not np.allclose(mixed.history[0].value.p, model.history[0].value.p)
    assert np.allclose(mixed.policy.L, model.policy.L, rtol=1e-12, atol=0)  # the noise never enters the gain


# --------------------------------------------------------------------------------------------------
# mixedrl.noise
# --------------------------------------------------------------------------------------------------
def test_gaussian_noise_validates_and_copies():
    with pytest.raises(ValueError, match="^mean"):
        GaussianNoise([np.nan], [[1.0]])
    with pytest.raises(ValueError, match="^cov"):
        GaussianNoise([0.0, 0.0], [[1.0, 2.0], [2.0, 1.0]])
    nz = GaussianNoise([1.0, 2.0], np.eye(2))
    m = nz.mean
    m[0] = 99.0
    assert nz.mean[0] == 1.0


def test_gaussian_noise_sample_moments_and_seed():
    nz = GaussianNoise([1.0, -2.0], [[2.0, 0.5], [0.5, 1.0]])
    a = nz.sample(20000, np.random.default_rng(1))
    b = nz.sample(20000, np.random.default_rng(1))
    assert np.array_equal(a, b)
    # Hotelling-type check of the mean: N (xbar - mu)^T K^-1 (xbar - mu) ~ chi2(2); 99.9 % quantile
    d = a.mean(axis=0) - nz.mean
    t2 = 20000 * d @ np.linalg.solve(nz.cov, d)
    assert t2 < stats.chi2.ppf(0.999, 2)


def test_gaussian_noise_state_dict_roundtrip_and_rejection():
    nz = GaussianNoise([1.0], [[2.0]])
    other = GaussianNoise([0.0], [[1.0]])
    other.load_state_dict(nz.state_dict())
    assert np.array_equal(other.mean, nz.mean) and np.array_equal(other.cov, nz.cov)
    for bad in ({"mean": [1.0]}, {"mean": [1.0], "cov": [[-1.0]]}, {"mean": [1.0], "cov": [[1.0]], "x": 1}, [1]):
        with pytest.raises(ValueError):
            other.load_state_dict(bad)
        assert np.array_equal(other.mean, [1.0]) and np.array_equal(other.cov, [[2.0]])


def test_algorithm1_plans_with_the_ibe_updated_by_this_iterations_data():
    """Every PEV and PIM of iteration k uses the IBE after the k-th batch (Algorithm 1's IBE step)."""
    prob = example_problem()
    f, cost, g = prob.dynamics, prob.cost, prob.gamma
    rng = np.random.default_rng(4)
    truth = GaussianNoise(prob.noise_mean, prob.noise_cov)
    batches = [truth.sample(200, rng) for _ in range(3)]
    seen: dict[str, list[np.ndarray]] = {"pev": [], "pim": []}

    def evaluate(policy, noise):
        seen["pev"].append(noise.mean.copy())
        return ExactPEV(f, cost, g)(policy, noise)

    def improve(value, noise):
        seen["pim"].append(noise.mean.copy())
        return ExactPIM(f, cost, g)(value, noise)

    ibe = make_noise_source("mixed", prob)
    out = policy_iteration(ibe, evaluate, improve, AffinePolicy(default_initial_gain(prob), np.zeros(1)), 3,
                           collect=lambda p, k: batches[k])
    reference = make_noise_source("mixed", prob)
    for k, batch in enumerate(batches):
        reference.update(batch)
        assert np.array_equal(seen["pev"][k], reference.mean)
        assert np.array_equal(seen["pim"][k], reference.mean)
        assert np.array_equal(out.history[k].noise_mean, reference.mean)
    assert ibe.count == 600
    assert np.max(np.abs(seen["pev"][0] - prob.prior_mean)) > 0.01  # prior 0.02, truth 0.05
