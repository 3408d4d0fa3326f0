"""Statistical consistency of the IBE: 1/sqrt(N) error decay and credible-interval coverage.

Tolerances are statistical (standard errors of the fitted slope, exact binomial bands) and stated at
each assertion; every trial uses its own seeded generator.
"""

import numpy as np
from scipy import stats

from mixedrl.ibe import KnownCovarianceIBE, UnknownCovarianceIBE, map_mean_cov

N_GRID = np.array([30, 100, 300, 1000, 3000, 10000])
TRIALS = 300


def _rmse_curve(make_estimator, seed):
    """RMS error of the mean over TRIALS seeded trials, for each N (diffuse prior, so bias is negligible)."""
    n = 3
    mu_true = np.array([1.0, -2.0, 0.5])
    k = np.array([[1.0, 0.3, 0.0], [0.3, 2.0, -0.4], [0.0, -0.4, 0.5]])
    chol = np.linalg.cholesky(k)
    rmse = []
    for n_s in N_GRID:
        err2 = []
        for trial in range(TRIALS):
            rng = np.random.default_rng([seed, int(n_s), trial])
            xi = mu_true + rng.standard_normal((int(n_s), n)) @ chol.T
            est = make_estimator(k).update(xi)
            err2.append(np.sum((est.mean - mu_true) ** 2))
        rmse.append(np.sqrt(np.mean(err2)))
    return np.array(rmse)


def _check_slope(rmse):
    # log RMSE = a + s log N; each point has relative sampling error ~ sqrt(1 / (2 * TRIALS * dof));
    # sd of log RMSE <= 1 / sqrt(2 * TRIALS) = 0.041, giving a slope sd of 0.041 / sqrt(sum (logN - mean)^2)
    x = np.log(N_GRID)
    slope = np.polyfit(x, np.log(rmse), 1)[0]
    sd = (1.0 / np.sqrt(2 * TRIALS)) / np.sqrt(np.sum((x - x.mean()) ** 2))
    assert abs(slope + 0.5) < 4 * sd, (slope, sd)  # 4 sigma band (~0.03)
    return slope


def test_case1_mean_error_shrinks_like_inverse_sqrt_n():
    prior_mean, prior_cov = np.zeros(3), 1e4 * np.eye(3)
    _check_slope(_rmse_curve(lambda k: KnownCovarianceIBE(prior_mean, prior_cov, k), seed=1))


def test_case2_mean_error_shrinks_like_inverse_sqrt_n():
    prior_mean, prior_cov = np.zeros(3), 1e4 * np.eye(3)
    _check_slope(_rmse_curve(lambda k: UnknownCovarianceIBE(prior_mean, prior_cov), seed=2))


def test_case1_credible_interval_coverage():
    # Bayesian coverage is exact when the true mean is drawn from the prior: for each trial draw
    # mu ~ N(mu_M, K_M), N residuals ~ N(mu, K), and check mu in the 95 % interval of component j and in
    # the joint 95 % ellipsoid (chi-square, n dof).
    trials, n, n_s = 1000, 3, 15
    rng0 = np.random.default_rng(2024)
    a = rng0.standard_normal((n, n))
    k_m = a @ a.T / n + 0.2 * np.eye(n)
    b = rng0.standard_normal((n, n))
    k = b @ b.T / n + 0.2 * np.eye(n)
    mu_m = rng0.standard_normal(n)
    z = stats.norm.ppf(0.975)
    chi = stats.chi2.ppf(0.95, n)
    hits_marginal = np.zeros(n, dtype=int)
    hits_joint = 0
    for trial in range(trials):
        rng = np.random.default_rng([7, trial])
        mu = rng.multivariate_normal(mu_m, k_m)
        xi = rng.multivariate_normal(mu, k, size=n_s)
        est = KnownCovarianceIBE(mu_m, k_m, k).update(xi)
        sd = np.sqrt(np.diag(est.mean_cov))
        hits_marginal += np.abs(mu - est.mean) <= z * sd
        err = mu - est.mean
        hits_joint += err @ np.linalg.solve(est.mean_cov, err) <= chi
    # exact two-sided binomial band holding with probability 0.999 under coverage 0.95
    lo, hi = stats.binom.ppf([0.0005, 0.9995], trials, 0.95)
    for h in list(hits_marginal) + [hits_joint]:
        assert lo <= h <= hi, (h, lo, hi)


def test_vehicle_exact_recursion_equals_batch_after_every_update():
    # the regime where eq. (17) can have several fixed points (confident, wrong prior, few data):
    # the recursion and the batch start from the same point, so they agree after every update.
    s = 1.0 / 200.0 / 1500.0
    mu_m = np.array([0.0, 0.0, 150 * s, 0.0, 0.0])
    k_m = np.diag([1e-20, 1e-20, (4 * s) ** 2, 1e-20, 1e-20])
    rng = np.random.default_rng(3)
    xi = np.zeros((150, 5))
    xi[:, 2] = 261 * s + np.sqrt(32) * s * rng.standard_normal(150)
    est = UnknownCovarianceIBE(mu_m, k_m)
    for i, row in enumerate(xi, start=1):
        est.update(row)
        ref_mean, ref_cov = map_mean_cov(mu_m, k_m, xi[:i])
        assert est.converged
        assert abs(est.mean[2] - ref_mean[2]) <= 1e-9 * ref_mean[2]
        assert abs(est.cov[2, 2] - ref_cov[2, 2]) <= 1e-9 * max(ref_cov[2, 2], k_m[2, 2])
