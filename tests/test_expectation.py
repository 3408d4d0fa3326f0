"""The one expectation module (mixedrl.expectation): the support cut-off, the nodes in numpy and torch,
and h of eq. (37), which Algorithm 2 and the theory checks share."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import theory
from mixedrl import gaussian
from mixedrl.expectation import (
    SUPPORT_RTOL,
    GaussHermite,
    NodeCache,
    SigmaPoints,
    expectation_nodes,
    gaussian_expectation,
    h,
    h_value,
    quadrature_nodes,
    support,
)
from mixedrl.noise import GaussianNoise
from mixedrl.tasks import LinearTask
from theory.checks import expected_cost_to_go

T, MASS = 1.0 / 200.0, 1500.0
#: The vehicle prior of the paper: diag(1e-20, ..., (4 T / m)^2) (EQUATIONS.md point 5).
VEHICLE_PRIOR = np.diag([1e-20, 1e-20, (4.0 * T / MASS) ** 2, 1e-20, 1e-20])


def test_one_cut_off_for_training_theory_and_linear_algebra() -> None:
    assert gaussian.SUPPORT_RTOL is SUPPORT_RTOL
    lam, vec = support(VEHICLE_PRIOR)
    assert lam.shape == (1,) and abs(abs(vec[2, 0]) - 1.0) < 1e-12  # rank 1: the 1e-20 entries are dropped
    # the quadrature of training (torch) and of theory (numpy) plan with the same 2 nodes
    d, _ = expectation_nodes(np.zeros(5), VEHICLE_PRIOR, torch.eye(5, dtype=torch.float64), "sigma",
                             dtype=torch.float64)
    xi, w = quadrature_nodes(np.zeros(5), VEHICLE_PRIOR)
    assert d.shape[0] == xi.shape[0] == 2
    np.testing.assert_array_equal(d.numpy(), xi)
    # just above / below the cut-off
    assert support(np.diag([1.0, 2.0 * SUPPORT_RTOL]))[0].shape == (2,)
    assert support(np.diag([1.0, 0.5 * SUPPORT_RTOL]))[0].shape == (1,)
    assert support(np.zeros((2, 2)))[0].shape == (0,)


def test_dropped_directions_error_is_within_the_stated_bound(rng: np.random.Generator) -> None:
    """Dropping eigenvalues below the cut-off changes E g by at most sum(dropped lambda) max|g''| / 2."""
    cov = np.diag([1.0, 0.5 * SUPPORT_RTOL])
    hess = np.array([[2.0, 0.3], [0.3, 4.0]])

    def g(x: np.ndarray) -> np.ndarray:
        return 0.5 * np.einsum("ni,ij,nj->n", x, hess, x)

    c = rng.standard_normal((5, 2))
    approx = gaussian_expectation(g, c, np.zeros(2), cov)
    exact = g(c) + 0.5 * np.trace(hess @ cov)
    bound = 0.5 * SUPPORT_RTOL * np.max(np.abs(np.linalg.eigvalsh(hess))) / 2
    assert np.all(np.abs(approx - exact) <= bound * (1 + 1e-9))
    assert np.all(np.abs(approx - exact) > 0)  # the direction was dropped indeed


@pytest.mark.parametrize("rule,degree", [(SigmaPoints(), 3), (GaussHermite(3), 5)])
def test_numpy_and_torch_nodes_agree_and_are_exact(rule, degree: int) -> None:
    mu, s2 = 0.7, 0.3
    xi, w = quadrature_nodes(np.array([mu]), np.array([[s2]]), rule)
    d, wt = expectation_nodes(np.array([mu]), np.array([[s2]]), torch.eye(1, dtype=torch.float64), rule,
                              dtype=torch.float64)
    np.testing.assert_allclose(d.numpy(), xi, rtol=0, atol=1e-15)
    np.testing.assert_allclose(wt.numpy(), w, rtol=1e-15)
    # E x^3 = mu^3 + 3 mu s^2, E x^5 = mu^5 + 10 mu^3 s^2 + 15 mu s^4
    moments = {3: mu**3 + 3 * mu * s2, 5: mu**5 + 10 * mu**3 * s2 + 15 * mu * s2**2}
    assert float(w @ xi[:, 0] ** degree) == pytest.approx(moments[degree], rel=1e-12)


def test_per_state_means_give_per_state_nodes(rng: np.random.Generator) -> None:
    means = rng.standard_normal((4, 2))
    cov = np.array([[1.0, 0.2], [0.2, 0.5]])
    E = torch.tensor([[1.0, 0.0], [0.0, 2.0], [1.0, 1.0]], dtype=torch.float64)
    d, w = expectation_nodes(means, cov, E, "sigma", dtype=torch.float64)
    assert d.shape == (4, 4, 3)
    np.testing.assert_allclose(torch.einsum("p,pbn->bn", w, d).numpy(), means @ E.numpy().T, atol=1e-12)
    with pytest.raises(ValueError, match="^mean"):
        expectation_nodes(means, cov, E, "samples", generator=torch.Generator())


def test_h_charges_the_cost_on_the_next_state() -> None:
    """Eq. (37) with eq. (2): h = E{l(x', u) + gamma V(x')}, x' = f(x, u) + xi -- by hand, one node."""
    x = np.array([[1.0, -2.0], [0.5, 3.0]])
    u = np.array([[0.3], [-1.0]])
    mu = np.array([0.25, -0.5])

    def f(x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return 0.5 * x + u

    def cost(xn: np.ndarray, un: np.ndarray) -> np.ndarray:
        return (xn**2).sum(1) + 3.0 * un[:, 0] ** 2

    def value(xn: np.ndarray) -> np.ndarray:
        return xn[:, 0] - 2.0 * xn[:, 1]

    xi, w = quadrature_nodes(mu, np.zeros((2, 2)))
    xn = f(x, u) + mu
    expected = cost(xn, u) + 0.9 * value(xn)
    np.testing.assert_allclose(h(f, cost, value, 0.9, x, u, xi, w), expected, rtol=1e-14)
    # the same through the torch binding of Algorithm 2 on a linear task
    task = LinearTask()
    critic = lambda z: z[:, 0] - 2.0 * z[:, 1]  # noqa: E731
    d, wt = expectation_nodes(mu, np.zeros((2, 2)), task.noise_matrix, "sigma", dtype=torch.float64)
    s, a = torch.tensor(x), torch.tensor(u)
    xn_t = task.f(s, a) + torch.tensor(mu)
    expected_t = task.cost(xn_t, a) + task.gamma * critic(xn_t)
    torch.testing.assert_close(h_value(task, critic, s, a, d, wt), expected_t, rtol=1e-14, atol=0)


def test_theory_and_training_compute_the_same_h(rng: np.random.Generator) -> None:
    task = LinearTask()
    x = rng.standard_normal((6, 2))
    u = rng.standard_normal((6, 1))
    mean, cov = np.array([0.1, 0.5]), np.diag([1e-3, 0.01])
    P = np.array([[2.0, 0.3], [0.3, 1.0]])

    def critic(z: torch.Tensor) -> torch.Tensor:
        return torch.einsum("ni,ij,nj->n", z, torch.tensor(P), z)

    d, w = expectation_nodes(mean, cov, task.noise_matrix, "sigma", dtype=torch.float64)
    train_h = h_value(task, critic, torch.tensor(x), torch.tensor(u), d, w).numpy()

    class Noise:
        pass

    noise = Noise()
    noise.mean, noise.cov = mean, cov
    theory_h = expected_cost_to_go(
        lambda z: np.einsum("ni,ij,nj->n", z, P, z),
        lambda s, a: task.f(torch.tensor(s), torch.tensor(a)).numpy(),
        lambda s, a: task.cost(torch.tensor(s), torch.tensor(a)).numpy(),
        task.gamma, x, u, noise)
    np.testing.assert_allclose(theory_h, train_h, rtol=1e-13)
    assert theory.SigmaPoints is SigmaPoints and theory.GaussHermite is GaussHermite


def test_one_eq37_function_serves_training_and_theory(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every eq.-(37) entry point (h_value of PEV/PIM/MVC, the theory checks) goes through expectation.h."""
    import theory.checks
    from mixedrl import expectation, pim

    assert theory.expected_cost_to_go is expectation.expected_cost_to_go
    assert theory.checks.expected_cost_to_go is expectation.expected_cost_to_go
    calls: list[str] = []

    def sentinel(*args: object) -> np.ndarray:
        calls.append("h")
        return np.full(np.shape(args[4])[0], 7.0)

    monkeypatch.setattr(expectation, "h", sentinel)
    noise = GaussianNoise(np.zeros(1), np.eye(1))
    x, u = np.ones((3, 1)), np.zeros((3, 1))
    one = lambda z: z[:, 0]  # noqa: E731
    lin = lambda s, a: s + a  # noqa: E731
    cost = lambda s, a: s[:, 0] ** 2  # noqa: E731
    np.testing.assert_array_equal(theory.expected_cost_to_go(one, lin, cost, 0.9, x, u, noise), 7.0)
    rep = theory.mvc(one, lambda s: 0 * s, lambda s: 0 * s, lin, cost, 0.9, noise, noise, x)
    np.testing.assert_array_equal(rep.extra["e"], 0.0)
    task = LinearTask()
    d, w = expectation_nodes(np.zeros(2), np.eye(2), task.noise_matrix, "sigma", dtype=torch.float64)
    out = pim.h_value(task, one, torch.zeros(3, 2), torch.zeros(3, 1), d, w)
    np.testing.assert_array_equal(out, 7.0)
    assert calls == ["h"] * 5


def test_h_is_the_closed_form_on_a_quadratic_value(rng: np.random.Generator) -> None:
    """Residual of eq. (37) against ``m^T (Q + gamma P) m + tr((Q + gamma P) K) + u^T R u``, ``m = A x + B u + mu``."""
    n, m_, N, gamma = 3, 2, 5, 0.95
    A, B = rng.standard_normal((n, n)), rng.standard_normal((n, m_))
    G = rng.standard_normal((n, n))
    P, Q, R = G @ G.T + np.eye(n), np.diag([1.0, 2.0, 0.5]), np.diag([0.3, 4.0])
    L = rng.standard_normal((n, n))
    K, mu = L @ L.T, rng.standard_normal(n)
    x, u = rng.standard_normal((N, n)), rng.standard_normal((N, m_))
    quad = lambda z, M: np.einsum("ni,ij,nj->n", z, M, z)  # noqa: E731
    got = expected_cost_to_go(lambda z: quad(z, P), lambda s, a: s @ A.T + a @ B.T,
                              lambda z, a: quad(z, Q) + quad(a, R), gamma, x, u, GaussianNoise(mu, K))
    S = Q + gamma * P
    mean_next = x @ A.T + u @ B.T + mu
    closed = quad(mean_next, S) + np.trace(S @ K) + quad(u, R)
    np.testing.assert_allclose(got - closed, 0.0, atol=1e-11 * np.abs(closed).max())


def test_node_cache_is_expectation_nodes_recomputed_only_on_change() -> None:
    """Issue 44: the cached nodes are expectation_nodes' bit for bit; a changed mean, cov (even -0.0 for 0.0),
    rule or noise matrix recomputes; sampled nodes and a batch of means are never cached."""
    E = torch.tensor([[1.0, 0.0], [0.5, 2.0], [0.0, 1.0]])
    mean, cov = np.array([0.1, -0.2]), np.array([[0.04, 0.01], [0.01, 0.09]])
    cache = NodeCache()
    first = cache(mean, cov, E)
    assert cache.misses == 1 and cache.hits == 0
    again = cache(mean.copy(), cov.copy(), E.clone())
    assert cache.hits == 1 and again[0] is first[0]
    for got, want in zip(again, expectation_nodes(mean, cov, E)):
        assert torch.equal(got, want) and got.dtype == want.dtype
    changed = [(mean + 1e-16, cov, E, "sigma"), (mean, cov * (1 + 1e-15), E, "sigma"),
               (mean, cov, 2 * E, "sigma"), (mean, cov, E, GaussHermite(3))]
    for m, c, e, rule in changed:
        misses = cache.misses
        got = cache(m, c, e, rule)
        assert cache.misses == misses + 1
        for a, b in zip(got, expectation_nodes(m, c, e, rule)):
            assert torch.equal(a, b)
    zero = NodeCache()
    zero(np.zeros(2), np.zeros((2, 2)), E)
    zero(np.array([-0.0, 0.0]), np.zeros((2, 2)), E)
    assert zero.misses == 2  # compared by bytes
    gen = torch.Generator().manual_seed(0)
    a = cache(mean, cov, E, "samples", 4, gen)
    b = cache(mean, cov, E, "samples", 4, gen)
    assert not torch.equal(a[0], b[0])  # two draws
    per_state = np.stack([mean, -mean])
    hits = cache.hits
    cache(per_state, cov, E)
    cache(per_state, cov, E)
    assert cache.hits == hits
