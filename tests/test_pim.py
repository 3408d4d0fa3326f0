"""PIM (mixedrl.pim): eq. (22) exactly against a numerical minimiser of h (eq. 37, cost on the next state),
the actor objective of eq. (51) by hand, and the MVC beside it."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.optimize
import torch

from mixedrl.expectation import expectation_nodes
from mixedrl.pev import evaluate_policy
from mixedrl.pim import ExactPIM, actor_objective, improve_policy, pim_step
from mixedrl.quadratic import AffinePolicy, LinearDynamics, QuadraticCost
from mixedrl.tasks import LinearTask


def test_exact_pim_minimises_h_with_the_next_state_cost() -> None:
    A = np.array([[1.0, 0.1], [0.0, 1.0]])
    B = np.array([[0.005], [0.1]])
    Q, R, g = np.diag([1.0, 0.5]), np.array([[0.1]]), 0.9
    mu, K = np.array([0.05, -0.3]), 0.01 * np.eye(2)
    f, cost = LinearDynamics(A, B), QuadraticCost(Q, R)
    V = evaluate_policy(f, cost, g, AffinePolicy(np.array([[2.0, 3.0]]), np.array([0.4])), mu, K)
    pi = improve_policy(f, cost, g, V, mu)
    for x in (np.array([1.0, -2.0]), np.array([0.3, 0.7])):

        def h(u: np.ndarray) -> float:
            # h(x, u) = l(x', u) + gamma V(x') at x' = A x + B u + mu (+ tr terms independent of u)
            xn = A @ x + B @ u + mu
            return float(xn @ Q @ xn + u @ R @ u + g * V(xn[None])[0])

        best = scipy.optimize.minimize(h, np.zeros(1), method="BFGS", options={"gtol": 1e-12}).x
        np.testing.assert_allclose(pi(x[None])[0], best, rtol=1e-6, atol=1e-8)

    class Noise:
        mean, cov = mu, K

    assert pim_step(ExactPIM(f, cost, g), V, Noise()).distance(pi) == 0.0


def test_actor_objective_is_the_mean_next_state_cost_for_a_zero_critic() -> None:
    task = LinearTask()
    actor = torch.nn.Linear(2, 1, dtype=torch.float64)
    s = torch.tensor([[1.0, -0.5], [0.2, 0.8]], dtype=torch.float64)
    mu = np.array([0.1, 0.5])
    d, w = expectation_nodes(mu, np.zeros((2, 2)), task.noise_matrix, "sigma", dtype=torch.float64)
    zero = lambda z: torch.zeros(z.shape[0], dtype=torch.float64)  # noqa: E731
    u = actor(s)
    expected = task.cost(task.f(s, u) + torch.tensor(mu), u).mean()
    obj = actor_objective(task, zero, actor, s, d, w).detach()
    assert float(obj) == pytest.approx(float(expected.detach()), rel=1e-14)


def test_relative_actor_objective_weights_states_by_inverse_value() -> None:
    """batch_weighting="relative": sum_x rho(x) h(x) / B with rho = 1 / (V(x) + c) normalised to mean 1."""
    task = LinearTask()
    actor = torch.nn.Linear(2, 1, dtype=torch.float64)
    s = torch.tensor([[1.0, -0.5], [0.2, 0.8], [-2.0, 1.5]], dtype=torch.float64)
    mu = np.array([0.1, 0.5])
    d, w = expectation_nodes(mu, np.zeros((2, 2)), task.noise_matrix, "sigma", dtype=torch.float64)

    def critic(z: torch.Tensor) -> torch.Tensor:
        # V(x) = |x|^2 (a state-dependent value, so the weights differ between states)
        return (z**2).sum(-1)

    c = 1.0
    u = actor(s)
    x_next = task.f(s, u) + torch.tensor(mu)
    h = task.cost(x_next, u) + task.gamma * critic(x_next)
    rho = 1.0 / (critic(s) + c)
    expected = (rho / rho.mean() * h).mean()
    obj = actor_objective(task, critic, actor, s, d, w, relative_offset=c)
    assert float(obj.detach()) == pytest.approx(float(expected.detach()), rel=1e-12)
    assert float(obj.detach()) != pytest.approx(float(h.mean().detach()), rel=1e-3)
    # the weights carry no gradient: d obj / d theta = mean(rho_n * dh/dtheta)
    obj.backward()
    g_obj = actor.weight.grad.clone()
    actor.zero_grad()
    (rho.detach() / rho.detach().mean() * (task.cost(task.f(s, actor(s)) + torch.tensor(mu), actor(s))
                                           + task.gamma * critic(task.f(s, actor(s)) + torch.tensor(mu)))).mean().backward()
    assert torch.allclose(g_obj, actor.weight.grad, rtol=1e-12, atol=0)
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="relative_offset"):
            actor_objective(task, critic, actor, s, d, w, relative_offset=bad)


def test_mvc_terms_is_the_one_mvc_of_training_and_theory(monkeypatch: pytest.MonkeyPatch) -> None:
    """Eqs. (38)-(39) are computed once (mvc_terms): Algorithm 2's mvc_check and theory.mvc both call it,
    and mvc_check's figures are the float32 differences of eq. (38)/(39) taken to float64, bit for bit."""
    import theory.checks
    from mixedrl import pim

    g = torch.Generator().manual_seed(0)
    a, b, c = (torch.randn(64, generator=g) for _ in range(3))
    res = pim.mvc_check(a, b, c, "mean")
    lhs, e = (a - b).double(), (c - b).double()
    assert res.lhs_mean == float(lhs.mean()) and res.e_mean == float(e.mean())
    assert res.held == bool(lhs.mean() <= e.mean())
    assert res.fraction == float((lhs <= e).double().mean())
    calls: list[int] = []
    real = pim.mvc_terms

    def spy(*args: object, **kwargs: object) -> pim.MVCTerms:
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(pim, "mvc_terms", spy)
    monkeypatch.setattr(theory.checks, "mvc_terms", spy)
    pim.mvc_check(a, b, c)
    noise = type("N", (), {"mean": np.zeros(1), "cov": np.eye(1)})()
    rep = theory.checks.mvc(lambda z: z[:, 0] ** 2, lambda s: 0 * s, lambda s: -0.5 * s, lambda s, u: s + u,
                            lambda s, u: s[:, 0] ** 2 + u[:, 0] ** 2, 0.9, noise, noise, np.ones((4, 1)))
    assert calls == [1, 1]
    np.testing.assert_array_equal(rep.extra["variation"], 0.0)
