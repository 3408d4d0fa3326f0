"""Tests of mixedrl.gaussian: PSD solves, singular-safe sampling, KL divergence."""

import math

import numpy as np
import pytest
import torch
from scipy import stats

from mixedrl.gaussian import kl_divergence, pinv_psd, psd_factor, sample_gaussian, solve_psd


def _random_spd(rng, n, cond=10.0):
    q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    lam = np.geomspace(1.0, cond, n)
    return (q * lam) @ q.T


def test_solve_psd_matches_numpy_on_spd(rng):
    s = _random_spd(rng, 5, 1e3)
    b = rng.standard_normal((5, 3))
    np.testing.assert_allclose(solve_psd(s, b), np.linalg.solve(s, b), rtol=1e-11, atol=0)
    np.testing.assert_allclose(solve_psd(s, b[:, 0]), np.linalg.solve(s, b[:, 0]), rtol=1e-11)


def test_solve_psd_badly_scaled_diagonal_is_exact():
    # the vehicle prior: entries 1.8e-10 and 1e-20 (condition number 1.8e10)
    s = np.diag([1e-20, 1e-20, 1.8e-10, 1e-20, 1e-20])
    b = np.array([1e-20, 2e-20, 1.8e-10, 0.0, 3e-20])
    np.testing.assert_allclose(solve_psd(s, b), [1.0, 2.0, 1.0, 0.0, 3.0], rtol=1e-15)


def test_solve_psd_singular_is_generalised_inverse(rng):
    # S = K_M + K singular: null(S) = null(K_M) & null(K), so K_M S^g b is the same for every
    # generalised inverse S^g; compare with the Moore-Penrose one, and check S x = b on range(S).
    a = rng.standard_normal((5, 2))
    k_m = a @ a.T  # rank 2
    k = np.outer(a[:, 0], a[:, 0])  # rank 1, range inside range(K_M)
    s = k_m + k
    b = s @ rng.standard_normal(5)  # b in range(S)
    x = solve_psd(s, b)
    np.testing.assert_allclose(s @ x, b, atol=1e-9 * np.abs(b).max())
    np.testing.assert_allclose(k_m @ x, k_m @ np.linalg.pinv(s, rcond=1e-10) @ b, atol=1e-9 * np.abs(b).max())
    # zero rows/columns
    s2 = np.diag([2.0, 0.0, 4.0])
    np.testing.assert_allclose(solve_psd(s2, np.array([2.0, 5.0, 4.0])), [1.0, 0.0, 1.0])


def test_pinv_psd_properties(rng):
    a = rng.standard_normal((4, 2))
    c = a @ a.T
    p = pinv_psd(c)
    np.testing.assert_allclose(c @ p @ c, c, atol=1e-12)
    np.testing.assert_allclose(p @ c @ p, p, atol=1e-10)


def test_psd_factor_rank_one():
    c = np.zeros((5, 5))
    c[2, 2] = 3.0
    f = psd_factor(c)
    np.testing.assert_allclose(f @ f.T, c, atol=1e-15)


def test_sample_gaussian_moments_and_singular(rng):
    mean = np.array([1.0, -2.0, 0.5])
    a = np.array([[1.0], [2.0], [0.0]])
    cov = a @ a.T  # rank 1
    n = 20000
    x = sample_gaussian(mean, cov, n, rng)
    assert x.shape == (n, 3)
    # third component has zero variance: exactly the mean
    assert np.all(x[:, 2] == 0.5)
    # samples lie on mean + span(a): x1 - mean1 = 2 (x0 - mean0)
    np.testing.assert_allclose(x[:, 1] - mean[1], 2.0 * (x[:, 0] - mean[0]), atol=1e-12)
    # sample mean of component 0 within 4 standard errors
    assert abs(x[:, 0].mean() - 1.0) < 4.0 / math.sqrt(n)
    # sample variance: chi-square band (99.99 %)
    var = x[:, 0].var(ddof=1)
    lo, hi = stats.chi2.ppf([5e-5, 1 - 5e-5], n - 1) / (n - 1)
    assert lo < var < hi


def test_sample_gaussian_seeded_and_torch():
    mean, cov = np.zeros(2), np.eye(2)
    a = sample_gaussian(mean, cov, 5, np.random.default_rng(3))
    b = sample_gaussian(mean, cov, 5, np.random.default_rng(3))
    np.testing.assert_array_equal(a, b)
    t1 = sample_gaussian(mean, cov, 5, torch.Generator().manual_seed(3))
    t2 = sample_gaussian(mean, cov, 5, torch.Generator().manual_seed(3))
    assert isinstance(t1, torch.Tensor) and t1.shape == (5, 2) and t1.dtype == torch.float64
    assert torch.equal(t1, t2)


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"mean": [np.nan, 0.0]}, "mean"),
        ({"cov": [[1.0, 0.5], [0.0, 1.0]]}, "cov"),
        ({"cov": [[1.0, 2.0], [2.0, 1.0]]}, "cov"),
        ({"cov": np.eye(3)}, "cov"),
        ({"n": 0}, "n"),
        ({"generator": 3}, "generator"),
    ],
)
def test_sample_gaussian_bad_input(kwargs, name):
    args = {"mean": np.zeros(2), "cov": np.eye(2), "n": 3, "generator": np.random.default_rng(0)}
    args.update(kwargs)
    with pytest.raises(ValueError, match=f"^{name}"):
        sample_gaussian(**args)


def test_kl_matches_torch_on_spd(rng):
    for _ in range(5):
        m0, m1 = rng.standard_normal(4), rng.standard_normal(4)
        c0, c1 = _random_spd(rng, 4, 50.0), _random_spd(rng, 4, 20.0)
        ref = torch.distributions.kl_divergence(
            torch.distributions.MultivariateNormal(torch.as_tensor(m0), torch.as_tensor(c0)),
            torch.distributions.MultivariateNormal(torch.as_tensor(m1), torch.as_tensor(c1)),
        ).item()
        assert kl_divergence(m0, c0, m1, c1) == pytest.approx(ref, rel=1e-10)


def test_kl_singular_common_support_equals_subspace_kl(rng):
    m0, m1 = rng.standard_normal(2), rng.standard_normal(2)
    c0, c1 = _random_spd(rng, 2, 5.0), _random_spd(rng, 2, 3.0)
    ref = kl_divergence(m0, c0, m1, c1)
    # embed into 4-D: components 1 and 3 carry the distribution, 0 and 2 are degenerate at the same value
    idx = [1, 3]

    def embed(m, c):
        mm = np.full(4, 7.0)
        mm[idx] = m
        cc = np.zeros((4, 4))
        cc[np.ix_(idx, idx)] = c
        return mm, cc

    assert kl_divergence(*embed(m0, c0), *embed(m1, c1)) == pytest.approx(ref, rel=1e-10)
    assert kl_divergence(*embed(m0, c0), *embed(m0, c0)) == pytest.approx(0.0, abs=1e-12)


def test_kl_infinite_when_supports_differ():
    c_a = np.diag([1.0, 0.0])
    c_b = np.diag([0.0, 1.0])
    assert kl_divergence(np.zeros(2), c_a, np.zeros(2), c_b) == math.inf
    # same range but mean difference off the support
    assert kl_divergence(np.zeros(2), c_a, np.array([0.0, 1.0]), c_a) == math.inf
    # lower rank against full rank: N0 is not absolutely continuous
    assert kl_divergence(np.zeros(2), c_a, np.zeros(2), np.eye(2)) == math.inf
    # full rank against lower rank: also infinite
    assert kl_divergence(np.zeros(2), np.eye(2), np.zeros(2), c_a) == math.inf


def test_kl_bad_input_names_argument():
    with pytest.raises(ValueError, match="^cov1"):
        kl_divergence(np.zeros(2), np.eye(2), np.zeros(2), -np.eye(2))
    with pytest.raises(ValueError, match="^mean1"):
        kl_divergence(np.zeros(2), np.eye(2), np.zeros(3), np.eye(2))
