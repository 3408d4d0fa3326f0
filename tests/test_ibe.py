"""Equation-level tests of mixedrl.ibe (eqs. (10), (15)-(19)).

References are independent of the code under test: the literal information form of eqs. (15)/(17)
with ``np.linalg.inv`` on well-conditioned cases, filterpy's KalmanFilter, the literal eq. (18)
transcribed here, and the closed-form ridge solution for a linear Case 3 model (``np.kron`` normal
equations), which also checks :class:`LinearFeatureIBE` (and it against :class:`StateDependentIBE`).
"""

import copy

import numpy as np
import pytest
import torch
from filterpy.kalman import KalmanFilter
from hypothesis import given
from hypothesis import strategies as st

from mixedrl.ibe import (
    KnownCovarianceIBE,
    LinearFeatureIBE,
    StateDependentIBE,
    UnknownCovarianceIBE,
    map_mean_cov,
    map_mean_known_cov,
    residuals,
)

T, M = 1.0 / 200.0, 1500.0
S = T / M


def vehicle_case(n_samples, seed):
    """Prior and rank-1 true noise of the vehicle task on v_x (index 2; EQUATIONS.md points 5-7)."""
    mu_m = np.array([0.0, 0.0, 150 * S, 0.0, 0.0])
    k_m = np.diag([1e-20, 1e-20, (4 * S) ** 2, 1e-20, 1e-20])
    k_true = np.zeros((5, 5))
    k_true[2, 2] = 32 * S**2
    rng = np.random.default_rng(seed)
    xi = np.zeros((n_samples, 5))
    xi[:, 2] = 261 * S + np.sqrt(32) * S * rng.standard_normal(n_samples)
    return mu_m, k_m, k_true, xi


def well_posed_case(seed, n, n_samples):
    rng = np.random.default_rng(seed)
    a = rng.standard_normal((n, n))
    k_m = a @ a.T / n + 0.5 * np.eye(n)
    b = rng.standard_normal((n, n))
    k = b @ b.T / n + 0.5 * np.eye(n)
    mu_m = 3.0 + rng.standard_normal(n)
    mu_true = mu_m + rng.multivariate_normal(np.zeros(n), k_m)
    xi = rng.multivariate_normal(mu_true, k, size=n_samples)
    return mu_m, k_m, k, xi


def eq15_information_form(mu_m, k_m, k, xi):
    """Eq. (15) literally (test reference, PD matrices only)."""
    inv = np.linalg.inv
    n_s = xi.shape[0]
    psi = inv(k_m) + n_s * inv(k)
    return np.linalg.solve(psi, inv(k_m) @ mu_m + inv(k) @ xi.sum(axis=0)), inv(psi)


def rel_err(a, b):
    return np.max(np.abs(np.asarray(a) - np.asarray(b))) / np.max(np.abs(b))


def splits(draw_sizes, total):
    """Turn a list of positive sizes into consecutive slices covering ``total`` rows."""
    out, start = [], 0
    for size in draw_sizes:
        if start >= total:
            break
        out.append(slice(start, min(total, start + size)))
        start += size
    if start < total:
        out.append(slice(start, total))
    return out


# ---------------------------------------------------------------------------------------------- eq. (10)
def test_residuals_numpy_and_torch_batched():
    a = np.array([[0.9, 0.1], [0.0, 0.8]])

    def f(x, u):
        return x @ a.T + u if isinstance(x, np.ndarray) else x @ torch.as_tensor(a).T + u

    rng = np.random.default_rng(0)
    x = rng.standard_normal((3, 4, 2))
    u = rng.standard_normal((3, 4, 2))
    xi = rng.standard_normal((3, 4, 2))
    x_next = f(x, u) + xi
    out = residuals(f, x, u, x_next)
    assert isinstance(out, np.ndarray)
    np.testing.assert_allclose(out, xi, atol=1e-14)
    tx, tu, tn = (torch.as_tensor(v) for v in (x, u, x_next))
    out_t = residuals(f, tx, tu, tn)
    assert isinstance(out_t, torch.Tensor)
    np.testing.assert_allclose(out_t.numpy(), xi, atol=1e-14)


def test_residuals_bad_input():
    def f(x, u):
        return x

    with pytest.raises(ValueError, match="^x_next"):
        residuals(f, np.zeros((3, 2)), np.zeros((3, 1)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="^u"):
        residuals(f, np.zeros((3, 2)), np.zeros((4, 1)), np.zeros((3, 2)))
    with pytest.raises(ValueError, match="^x"):
        residuals(f, np.full((3, 2), np.nan), np.zeros((3, 1)), np.zeros((3, 2)))
    with pytest.raises(ValueError, match="^x"):
        residuals(f, torch.zeros(3, 2), np.zeros((3, 1)), np.zeros((3, 2)))
    with pytest.raises(ValueError, match="^f"):
        residuals(lambda x, u: x[:, :1], np.zeros((3, 2)), np.zeros((3, 1)), np.zeros((3, 2)))


# ------------------------------------------------------------------------------------- Case 1
@given(
    seed=st.integers(0, 2**31 - 1),
    n=st.integers(1, 4),
    n_samples=st.integers(1, 40),
    sizes=st.lists(st.integers(1, 15), min_size=1, max_size=8),
)
def test_eq15_equals_eq16_for_any_split(seed, n, n_samples, sizes):
    mu_m, k_m, k, xi = well_posed_case(seed, n, n_samples)
    est = KnownCovarianceIBE(mu_m, k_m, k)
    for sl in splits(sizes, n_samples):
        batch = xi[sl] if sl.stop - sl.start > 1 else xi[sl.start]
        assert est.update(batch) is est
        seen = xi[: sl.stop]
        ref_mean, ref_cov = eq15_information_form(mu_m, k_m, k, seen)
        assert est.count == sl.stop
        assert rel_err(est.mean, map_mean_known_cov(mu_m, k_m, k, seen)) < 1e-12
        assert rel_err(est.mean, ref_mean) < 1e-12
        assert rel_err(est.mean_cov, ref_cov) < 1e-12


def test_case1_equals_filterpy_kalman_filter():
    n = 4
    mu_m, k_m, k, xi = well_posed_case(7, n, 300)
    kf = KalmanFilter(dim_x=n, dim_z=n)
    kf.F, kf.H, kf.Q, kf.R = np.eye(n), np.eye(n), np.zeros((n, n)), k.copy()
    kf.x, kf.P = mu_m.reshape(n, 1).copy(), k_m.copy()
    est = KnownCovarianceIBE(mu_m, k_m, k)
    for z in xi:
        kf.predict()
        kf.update(z)
        est.update(z)
        np.testing.assert_allclose(est.mean, kf.x[:, 0], rtol=1e-10, atol=1e-10 * np.abs(kf.x).max())
        np.testing.assert_allclose(est.mean_cov, kf.P, rtol=1e-10, atol=1e-10 * np.abs(kf.P).max())
    assert est.cov is not None and np.array_equal(est.cov, k)


def test_case1_singular_prior_uses_solve_path():
    # K_M singular (zero variance on component 1): prior is certain there, mean stays at mu_M[1]
    mu_m = np.array([1.0, 2.0])
    k_m = np.diag([1.0, 0.0])
    k = np.eye(2)
    xi = np.array([[3.0, 5.0], [5.0, 7.0]])
    est = KnownCovarianceIBE(mu_m, k_m, k).update(xi)
    assert est._diag is None
    # component 0: scalar eq. (15) = (1 + 8) / (1 + 2) = 3
    np.testing.assert_allclose(est.mean, [3.0, 2.0], rtol=1e-14)
    np.testing.assert_allclose(est.mean_cov, np.diag([1.0 / 3.0, 0.0]), atol=1e-15)
    np.testing.assert_allclose(map_mean_known_cov(mu_m, k_m, k, xi), est.mean, rtol=1e-14)


def test_vehicle_case1_and_case2_are_finite_and_correct():
    mu_m, k_m, k_true, xi = vehicle_case(2000, seed=11)
    for est in (KnownCovarianceIBE(mu_m, k_m, k_true), UnknownCovarianceIBE(mu_m, k_m)):
        for chunk in np.array_split(xi, 7):
            est.update(chunk)
        assert np.all(np.isfinite(est.mean)) and np.all(np.isfinite(est.cov)) and np.all(np.isfinite(est.mean_cov))
        assert abs(est.mean[2] - 261 * S) <= 0.02 * 261 * S
        np.testing.assert_array_equal(est.mean[[0, 1, 3, 4]], mu_m[[0, 1, 3, 4]])
        assert np.all(np.linalg.eigvalsh(est.mean_cov) >= -1e-30)
    # Case 2 one residual at a time gives the same as batches (exact recursion)
    one = UnknownCovarianceIBE(mu_m, k_m)
    for z in xi:
        one.update(z)
    assert abs(one.mean[2] - est.mean[2]) <= 1e-9 * est.mean[2]


def test_vehicle_paper_recursion_stays_finite():
    mu_m, k_m, _, xi = vehicle_case(2000, seed=12)
    est = UnknownCovarianceIBE(mu_m, k_m, recursion="paper")
    for i, z in enumerate(xi):
        est.update(z)
        if i == 0:
            # K_hat_1 = (xi_1 - mu_M)(xi_1 - mu_M)^T has rank 1
            assert np.linalg.matrix_rank(est.cov, tol=1e-30) == 1
        assert np.all(np.isfinite(est.mean)) and np.all(np.isfinite(est.cov)) and np.all(np.isfinite(est.psi))
    np.testing.assert_array_equal(est.mean[[0, 1, 3, 4]], 0.0)


# ------------------------------------------------------------------------------------- Case 2
def eq17_residual(mu_m, k_m, xi, mean, cov):
    """Residual of both lines of eq. (17) in the literal information form (PD case)."""
    inv = np.linalg.inv
    n_s = xi.shape[0]
    psi = inv(k_m) + n_s * inv(cov)
    mean_rhs = np.linalg.solve(psi, inv(k_m) @ mu_m + inv(cov) @ xi.sum(axis=0))
    dev = xi - mean
    cov_rhs = dev.T @ dev / n_s
    return rel_err(mean, mean_rhs), rel_err(cov, cov_rhs)


@given(
    seed=st.integers(0, 2**31 - 1),
    n=st.integers(1, 4),
    n_samples=st.integers(1, 40),
    sizes=st.lists(st.integers(1, 15), min_size=1, max_size=8),
)
def test_case2_exact_recursion_equals_eq17_for_any_split(seed, n, n_samples, sizes):
    mu_m, k_m, _, xi = well_posed_case(seed, n, n_samples)
    est = UnknownCovarianceIBE(mu_m, k_m)
    for sl in splits(sizes, n_samples):
        est.update(xi[sl])
        seen = xi[: sl.stop]
        ref_mean, ref_cov = map_mean_cov(mu_m, k_m, seen)
        assert est.converged
        assert rel_err(est.mean, ref_mean) < 1e-9
        assert np.max(np.abs(est.cov - ref_cov)) < 1e-9 * np.max(np.abs(ref_cov) + np.abs(k_m))
        if sl.stop > 2 * n:  # K_hat positive definite: check eq. (17) itself
            r_mean, r_cov = eq17_residual(mu_m, k_m, seen, est.mean, est.cov)
            assert r_mean < 1e-9 and r_cov < 1e-9


def test_eq17_single_sample_is_the_degenerate_ml_answer():
    mu_m, k_m, _, xi = well_posed_case(3, 3, 1)
    mean, cov = map_mean_cov(mu_m, k_m, xi)
    np.testing.assert_allclose(mean, xi[0], rtol=1e-13)
    np.testing.assert_allclose(cov, 0.0, atol=1e-24)


def eq18_literal(mu_m, k_m, xi):
    """Eq. (18) transcribed with np.linalg.inv (test reference; needs PD K_hat, so start at k=n+2)."""
    inv = np.linalg.inv
    psi, m, mean, cov = inv(k_m), np.zeros_like(mu_m), mu_m.copy(), k_m.copy()
    out = []
    for k, z in enumerate(xi, start=1):
        k_prev_inv = inv(cov)
        psi = psi + k_prev_inv
        m = m + z
        new_mean = np.linalg.solve(psi, inv(k_m) @ mu_m + k_prev_inv @ m)
        cov = ((k - 1) * cov + np.outer(z - mean, z - mean)) / k
        mean = new_mean
        out.append((mean.copy(), cov.copy()))
    return out


def test_paper_recursion_is_eq18_literally():
    # scalar case: K_hat_k stays positive (k * K_hat_k = K_M + sum of squares), so inv() is defined
    mu_m, k_m, _, xi = well_posed_case(5, 1, 50)
    ref = eq18_literal(mu_m, k_m, xi)
    est = UnknownCovarianceIBE(mu_m, k_m, recursion="paper")
    for z, (rm, rc) in zip(xi, ref):
        est.update(z)
        assert rel_err(est.mean, rm) < 1e-12 and rel_err(est.cov, rc) < 1e-12
    # the batch form of "paper" processes rows one at a time: same result
    est2 = UnknownCovarianceIBE(mu_m, k_m, recursion="paper").update(xi)
    np.testing.assert_allclose(est2.mean, est.mean, rtol=1e-14)


# ------------------------------------------------------------------------------ bad input, state
def _estimators():
    mu_m, k_m, k, xi = well_posed_case(1, 3, 20)
    return [
        KnownCovarianceIBE(mu_m, k_m, k).update(xi),
        UnknownCovarianceIBE(mu_m, k_m).update(xi),
        UnknownCovarianceIBE(mu_m, k_m, recursion="paper").update(xi),
    ]


def _assert_same_state(a, b):
    assert a.keys() == b.keys()
    for key in a:
        if isinstance(a[key], np.ndarray):
            np.testing.assert_array_equal(a[key], b[key])
        else:
            assert a[key] == b[key]


@pytest.mark.parametrize("bad", [np.array([np.nan, 0.0, 0.0]), np.array([np.inf, 0, 0]), np.zeros(4), np.zeros((2, 2)), np.zeros((2, 2, 3)), "abc"])
def test_bad_update_rejected_and_state_unchanged(bad):
    for est in _estimators():
        before = copy.deepcopy(est.state_dict())
        mean, cov, mean_cov = est.mean.copy(), est.cov.copy(), est.mean_cov.copy()
        with pytest.raises(ValueError, match="^xi"):
            est.update(bad)
        _assert_same_state(before, est.state_dict())
        np.testing.assert_array_equal(est.mean, mean)
        np.testing.assert_array_equal(est.cov, cov)
        np.testing.assert_array_equal(est.mean_cov, mean_cov)


def test_bad_constructor_arguments_name_the_argument():
    good = (np.zeros(2), np.eye(2), np.eye(2))
    with pytest.raises(ValueError, match="^prior_mean"):
        KnownCovarianceIBE(np.array([np.nan, 0.0]), np.eye(2), np.eye(2))
    with pytest.raises(ValueError, match="^prior_cov"):
        KnownCovarianceIBE(good[0], np.array([[1.0, 0.3], [0.0, 1.0]]), np.eye(2))
    with pytest.raises(ValueError, match="^noise_cov"):
        KnownCovarianceIBE(good[0], np.eye(2), np.diag([1.0, -1.0]))
    with pytest.raises(ValueError, match="^noise_cov"):
        KnownCovarianceIBE(good[0], np.eye(2), np.eye(3))
    with pytest.raises(ValueError, match="^prior_cov"):
        UnknownCovarianceIBE(good[0], np.full((2, 2), np.inf))
    with pytest.raises(ValueError, match="^recursion"):
        UnknownCovarianceIBE(good[0], np.eye(2), recursion="Paper")
    with pytest.raises(ValueError, match="^xi"):
        map_mean_cov(good[0], np.eye(2), np.zeros((0, 2)))
    with pytest.raises(ValueError, match="^xi"):
        map_mean_known_cov(good[0], np.eye(2), np.eye(2), np.zeros((3, 3)))


def test_state_dict_round_trip_exact():
    for est in _estimators():
        st_ = est.state_dict()
        fresh = type(est)(est.prior_mean, est.prior_cov, est.noise_cov) if isinstance(est, KnownCovarianceIBE) else (
            UnknownCovarianceIBE(est.prior_mean, est.prior_cov, recursion=est.recursion)
        )
        fresh.load_state_dict(copy.deepcopy(st_))
        np.testing.assert_array_equal(fresh.mean, est.mean)
        np.testing.assert_array_equal(fresh.cov, est.cov)
        np.testing.assert_array_equal(fresh.mean_cov, est.mean_cov)
        assert fresh.count == est.count
        _assert_same_state(fresh.state_dict(), st_)
        # continuing after the round trip gives identical results
        z = np.array([0.3, -0.2, 0.1])
        np.testing.assert_array_equal(fresh.update(z).mean, est.update(z).mean)


@pytest.mark.parametrize(
    "corrupt",
    [
        lambda s: s.pop("count"),
        lambda s: s.update(extra=1),
        lambda s: s.update(kind="Other"),
        lambda s: s.update(prior_mean=np.zeros(4)),
        lambda s: s.update(prior_cov=np.full((3, 3), np.nan)),
        lambda s: s.update(prior_cov=-np.eye(3)),
        lambda s: s.update(count=-1),
        lambda s: s.update(count=1.5),
    ],
)
def test_load_state_dict_rejects_corrupt_input(corrupt):
    for est in _estimators():
        before = copy.deepcopy(est.state_dict())
        bad = copy.deepcopy(before)
        corrupt(bad)
        with pytest.raises(ValueError, match="^state_dict"):
            est.load_state_dict(bad)
        _assert_same_state(before, est.state_dict())
    with pytest.raises(ValueError, match="^state_dict"):
        _estimators()[0].load_state_dict([1, 2])


def test_sample_singular_cov_numpy_and_torch():
    mu_m, k_m, k_true, xi = vehicle_case(500, seed=4)
    for est in (KnownCovarianceIBE(mu_m, k_m, k_true).update(xi), UnknownCovarianceIBE(mu_m, k_m).update(xi)):
        x = est.sample(4000, np.random.default_rng(0))
        assert x.shape == (4000, 5)
        np.testing.assert_array_equal(x[:, [0, 1, 3, 4]], 0.0)  # rank-1 noise: exactly the mean there
        # v_x sample mean within 5 standard errors of the estimator's mean
        sd = np.sqrt(est.cov[2, 2])
        assert abs(x[:, 2].mean() - est.mean[2]) < 5 * sd / np.sqrt(4000)
        np.testing.assert_array_equal(x, est.sample(4000, np.random.default_rng(0)))
        t = est.sample(3, torch.Generator().manual_seed(0))
        assert isinstance(t, torch.Tensor) and t.shape == (3, 5)
    with pytest.raises(ValueError, match="^n"):
        est.sample(0, np.random.default_rng(0))


# ------------------------------------------------------------------------------------- Case 3
class Linear(torch.nn.Module):
    def __init__(self, n_x, n_u, n):
        super().__init__()
        self.lin = torch.nn.Linear(n_x + n_u, n)

    def forward(self, x, u):
        return self.lin(torch.cat([x, u], dim=-1))


def test_case3_linear_phi_equals_closed_form_map():
    # phi linear in w: eq. (19) is ridge regression with a closed-form minimiser
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    n_x, n_u, n, n_s = 3, 1, 2, 200
    phi = Linear(n_x, n_u, n)
    w0 = torch.cat([phi.lin.weight.detach().T.reshape(-1), phi.lin.bias.detach()]).double().numpy()
    b = rng.standard_normal((n, n))
    k = b @ b.T / n + 0.3 * np.eye(n)
    x, u = rng.standard_normal((n_s, n_x)), rng.standard_normal((n_s, n_u))
    feats = np.hstack([x, u])
    a_true = rng.standard_normal((n_x + n_u, n))
    xi = feats @ a_true + 0.5 + rng.multivariate_normal(np.zeros(n), k, n_s)
    sigma_w = 2.0
    est = StateDependentIBE(phi, k, n_x, n_u, prior_std=sigma_w, max_iter=500)
    est.update(x[:120], u[:120], xi[:120]).update(x[120:], u[120:], xi[120:])
    # closed form: w = vec([W; b]) with phi = [f, 1] @ [W; b]; normal equations with K^-1 weighting
    design = np.hstack([feats, np.ones((n_s, 1))])  # (N, p)
    kinv = np.linalg.inv(k)
    p = design.shape[1]
    # W0 layout (p, n) row-major in w0: weight.T (p-1, n) then bias (n,)
    w0_mat = w0.reshape(p, n)
    lhs = np.kron(design.T @ design, kinv) + np.eye(p * n) / sigma_w**2
    rhs = (design.T @ xi @ kinv).reshape(-1) + w0_mat.reshape(-1) / sigma_w**2
    w_hat = np.linalg.solve(lhs, rhs).reshape(p, n)
    ref = np.hstack([x[:5], u[:5]]) @ w_hat[:-1] + w_hat[-1]
    np.testing.assert_allclose(est.mean_at(x[:5], u[:5]), ref, rtol=1e-6, atol=1e-7)
    assert est.count == n_s


def test_case3_recovers_nonlinear_mean_and_prior_without_data():
    torch.manual_seed(1)
    rng = np.random.default_rng(1)
    n_s = 600

    class MLP(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.net = torch.nn.Sequential(torch.nn.Linear(2, 16), torch.nn.Tanh(), torch.nn.Linear(16, 1))

        def forward(self, x, u):
            return self.net(torch.cat([x, u], dim=-1))

    phi = MLP()
    est = StateDependentIBE(phi, np.array([[0.01]]), 1, 1, prior_std=10.0, max_iter=300)
    xt, ut = np.array([[0.3], [-0.5]]), np.array([[0.1], [0.2]])
    with torch.no_grad():
        prior_out = phi(torch.as_tensor(xt), torch.as_tensor(ut)).numpy()
    np.testing.assert_array_equal(est.mean_at(xt, ut), prior_out)

    def true_mean(x, u):
        return np.sin(2.0 * x) + 0.5 * u

    x = rng.uniform(-1, 1, (n_s, 1))
    u = rng.uniform(-1, 1, (n_s, 1))
    xi = true_mean(x, u) + 0.1 * rng.standard_normal((n_s, 1))
    est.update(x, u, xi)
    xg = np.linspace(-0.9, 0.9, 50)[:, None]
    ug = np.linspace(0.9, -0.9, 50)[:, None]
    rmse = np.sqrt(np.mean((est.mean_at(xg, ug) - true_mean(xg, ug)) ** 2))
    # noise sd 0.1; a well-fitted mean is far below it (the untrained prior is ~0.5 off)
    assert rmse < 0.03, rmse
    s = est.sample(3, np.random.default_rng(0), xg[0], ug[0])
    assert s.shape == (3, 1)


def test_case3_bad_input_and_state_dict():
    torch.manual_seed(2)
    est = StateDependentIBE(Linear(2, 1, 2), np.eye(2), 2, 1, max_iter=50)
    rng = np.random.default_rng(2)
    est.update(rng.standard_normal((10, 2)), rng.standard_normal((10, 1)), rng.standard_normal((10, 2)))
    before = copy.deepcopy(est.state_dict())
    with pytest.raises(ValueError, match="^xi"):
        est.update(np.zeros((3, 2)), np.zeros((3, 1)), np.full((3, 2), np.nan))
    with pytest.raises(ValueError, match="^u"):
        est.update(np.zeros((3, 2)), np.zeros((4, 1)), np.zeros((3, 2)))
    after = est.state_dict()
    for key in before:
        if isinstance(before[key], list):
            for a, b in zip(before[key], after[key]):
                np.testing.assert_array_equal(a, b)
        elif isinstance(before[key], np.ndarray):
            np.testing.assert_array_equal(before[key], after[key])
        else:
            assert before[key] == after[key]
    torch.manual_seed(99)
    other = StateDependentIBE(Linear(2, 1, 2), np.eye(2), 2, 1, max_iter=50)
    other.load_state_dict(copy.deepcopy(before))
    xq, uq = rng.standard_normal((4, 2)), rng.standard_normal((4, 1))
    np.testing.assert_array_equal(other.mean_at(xq, uq), est.mean_at(xq, uq))
    bad = copy.deepcopy(before)
    bad["params"][0] = np.zeros((5, 5))
    with pytest.raises(ValueError, match="^state_dict"):
        other.load_state_dict(bad)
    np.testing.assert_array_equal(other.mean_at(xq, uq), est.mean_at(xq, uq))
    with pytest.raises(ValueError, match="^prior_std"):
        StateDependentIBE(Linear(2, 1, 2), np.eye(2), 2, 1, prior_std=0.0)
    with pytest.raises(ValueError, match="^phi"):
        StateDependentIBE(Linear(2, 1, 3), np.eye(2), 2, 1)


def test_case3_deterministic():
    outs = []
    for _ in range(2):
        torch.manual_seed(5)
        rng = np.random.default_rng(5)
        est = StateDependentIBE(Linear(1, 1, 1), np.eye(1), 1, 1, max_iter=30)
        est.update(rng.standard_normal((20, 1)), rng.standard_normal((20, 1)), rng.standard_normal((20, 1)))
        outs.append(est.mean_at(np.array([0.2]), np.array([0.1])))
    np.testing.assert_array_equal(outs[0], outs[1])


def test_public_arrays_are_read_only_so_callers_cannot_corrupt_the_estimator():
    k_m = np.diag([1.0, 2.0])
    for est in (
        KnownCovarianceIBE(np.zeros(2), k_m, np.eye(2)),
        UnknownCovarianceIBE(np.zeros(2), k_m),
        UnknownCovarianceIBE(np.zeros(2), k_m, recursion="paper"),
    ):
        est.update(np.array([[1.0, -1.0], [2.0, 0.5], [0.3, 0.1]]))
        before = (est.mean.copy(), est.cov.copy(), est.mean_cov.copy())
        for arr in (est.mean, est.cov, est.mean_cov):
            with pytest.raises(ValueError, match="read-only"):
                arr[0] = 123.0
        np.testing.assert_array_equal(est.mean, before[0])
        np.testing.assert_array_equal(est.cov, before[1])
        est.update(np.array([0.5, 0.5]))  # updates still work after the arrays were handed out
        assert est.count == 4


# ----------------------------------------------------------------------------------------------------
# Case 3 in closed form: LinearFeatureIBE
# ----------------------------------------------------------------------------------------------------
def _affine_features(x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """g(x, u) = [1, x, u]."""
    return torch.cat([torch.ones(x.shape[0], 1, dtype=torch.float64), x, u], dim=-1)


def _kron_map(design, xi, k_plus, w0, sigma_w):
    """Minimiser of eq. (19) for phi = W^T g, from the literal normal equations in vec form (row-major
    vec(W), W of shape (p, n)): (G kron K^+ + I / sigma^2) vec(W) = vec(S K^+) + vec(W_0) / sigma^2."""
    p, n = w0.shape
    lhs = np.kron(design.T @ design, k_plus) + np.eye(p * n) / sigma_w**2
    rhs = (design.T @ xi @ k_plus).reshape(-1) + w0.reshape(-1) / sigma_w**2
    return np.linalg.solve(lhs, rhs).reshape(p, n)


def _case3_data(seed, n_s=300, n_x=3, n_u=1, n=2):
    rng = np.random.default_rng(seed)
    x, u = rng.standard_normal((n_s, n_x)), rng.standard_normal((n_s, n_u))
    w_true = rng.standard_normal((1 + n_x + n_u, n))
    b = rng.standard_normal((n, n))
    k = b @ b.T / n + 0.3 * np.eye(n)
    design = np.hstack([np.ones((n_s, 1)), x, u])
    xi = design @ w_true + rng.multivariate_normal(np.zeros(n), k, n_s)
    return x, u, xi, design, k, rng.standard_normal((1 + n_x + n_u, n))


def test_linear_feature_ibe_equals_the_normal_equations_full_rank():
    x, u, xi, design, k, w0 = _case3_data(0)
    est = LinearFeatureIBE(_affine_features, w0, k, 3, 1, prior_std=0.7)
    assert est.learns and est.state_dependent and est.num_features == 5
    np.testing.assert_allclose(est.mean_at(x[:4], u[:4]), design[:4] @ w0, rtol=1e-14)  # the prior before data
    est.update(x[:100], u[:100], xi[:100]).update(x[100:], u[100:], xi[100:])
    w_ref = _kron_map(design, xi, np.linalg.inv(k), w0, 0.7)
    np.testing.assert_allclose(est.weights, w_ref, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(est.mean_at(x[:7], u[:7]), design[:7] @ w_ref, rtol=1e-10, atol=1e-12)
    got = est.mean_at(torch.as_tensor(x[:7]), torch.as_tensor(u[:7]))
    assert isinstance(got, torch.Tensor) and got.dtype == torch.float64
    assert est.count == 300


def test_linear_feature_ibe_rank_deficient_k_keeps_the_prior_off_the_support():
    """The vehicle's K has rank 1: only the support of K carries likelihood (K^+), W v = W_0 v elsewhere."""
    x, u, xi, design, _, w0 = _case3_data(1, n=3)
    k = np.diag([0.0, 0.5, 0.0])
    k[0, 0] = 1e-30  # numerically zero: outside the support
    est = LinearFeatureIBE(_affine_features, w0, k, 3, 1, prior_std=2.0)
    est.update(x, u, xi)
    k_plus = np.diag([0.0, 2.0, 0.0])
    np.testing.assert_allclose(est.weights, _kron_map(design, xi, k_plus, w0, 2.0), rtol=1e-10, atol=1e-12)
    np.testing.assert_array_equal(est.weights[:, [0, 2]], w0[:, [0, 2]])


def test_linear_feature_ibe_with_a_constant_feature_is_case_1():
    """g = [1]: phi is a constant mean with prior N(mu_M, sigma_w^2 I), i.e. Case 1 (eq. 16) with
    K_M = sigma_w^2 I: the two estimators must agree."""
    mu_m, _, k_true, xi = vehicle_case(500, seed=3)
    sigma = 4 * S
    est = LinearFeatureIBE(lambda x, u: torch.ones(x.shape[0], 1, dtype=torch.float64), mu_m[None, :], k_true, 6, 2,
                           prior_std=sigma)
    case1 = KnownCovarianceIBE(mu_m, sigma**2 * np.eye(5), k_true)
    for chunk in np.array_split(xi, 4):
        est.update(np.zeros((len(chunk), 6)), np.zeros((len(chunk), 2)), chunk)
        case1.update(chunk)
        np.testing.assert_allclose(est.mean_at(np.zeros(6), np.zeros(2)), case1.mean, rtol=1e-12, atol=1e-18)


def test_linear_feature_ibe_equals_state_dependent_ibe_with_the_same_linear_phi():
    """Both minimise eq. (19); L-BFGS (StateDependentIBE) converges to the closed form."""
    torch.manual_seed(4)
    x, u, xi, design, k, _ = _case3_data(4, n_s=200)
    phi = Linear(3, 1, 2)
    w0 = torch.cat([phi.lin.bias.detach()[None, :], phi.lin.weight.detach().T]).double().numpy()  # rows: 1, x, u
    general = StateDependentIBE(phi, k, 3, 1, prior_std=1.5, max_iter=500)
    closed = LinearFeatureIBE(_affine_features, w0, k, 3, 1, prior_std=1.5)
    general.update(x, u, xi)
    closed.update(x, u, xi)
    np.testing.assert_allclose(closed.mean_at(x[:10], u[:10]), general.mean_at(x[:10], u[:10]), rtol=1e-6, atol=1e-8)


def test_linear_feature_ibe_batches_state_dict_and_bad_input():
    x, u, xi, _, k, w0 = _case3_data(5)
    one = LinearFeatureIBE(_affine_features, w0, k, 3, 1).update(x, u, xi)
    many = LinearFeatureIBE(_affine_features, w0, k, 3, 1)
    for i in range(0, 300, 7):
        many.update(x[i:i + 7], u[i:i + 7], xi[i:i + 7])
    np.testing.assert_allclose(many.weights, one.weights, rtol=1e-11, atol=1e-13)
    before = copy.deepcopy(one.state_dict())
    with pytest.raises(ValueError, match="^xi"):
        one.update(x[:3], u[:3], np.full((3, 2), np.nan))
    with pytest.raises(ValueError, match="^xi: x, u and xi"):
        one.update(x[:3], u[:4], xi[:3])
    with pytest.raises(ValueError, match="^features"):
        LinearFeatureIBE(lambda a, b: torch.ones(a.shape[0], 2, dtype=torch.float64), w0, k, 3, 1).update(x, u, xi)
    after = one.state_dict()
    assert after["count"] == before["count"] == 300
    for key in ("gram", "cross", "prior_weights", "noise_cov"):
        np.testing.assert_array_equal(after[key], before[key])
    other = LinearFeatureIBE(_affine_features, np.zeros_like(w0), np.eye(2), 3, 1, prior_std=9.0)
    other.load_state_dict(copy.deepcopy(before))
    np.testing.assert_array_equal(other.weights, one.weights)
    bad = copy.deepcopy(before)
    bad["gram"] = np.zeros((4, 4))
    with pytest.raises(ValueError, match="^state_dict"):
        other.load_state_dict(bad)
    np.testing.assert_array_equal(other.weights, one.weights)
    with pytest.raises(ValueError):
        one.weights[0, 0] = 1.0  # read-only: a caller cannot corrupt the estimate
    for kwargs, name in (({"prior_std": 0.0}, "prior_std"), ({"state_dim": 0}, "state_dim"),
                         ({"features": 3}, "features"), ({"prior_weights": np.zeros(5)}, "prior_weights"),
                         ({"noise_cov": np.eye(3)}, "noise_cov")):
        args = {"features": _affine_features, "prior_weights": w0, "noise_cov": k, "state_dim": 3, "action_dim": 1,
                **kwargs}
        with pytest.raises(ValueError, match=f"^{name}"):
            LinearFeatureIBE(**args)
