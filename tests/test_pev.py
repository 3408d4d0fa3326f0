"""PEV (mixedrl.pev): eq. (21) exactly on quadratic values, against a rollout that charges the cost on the
next state (eq. 2); the critic loss of eqs. (49)-(50) against its target written out by hand."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mixedrl.expectation import expectation_nodes
from mixedrl.pev import ExactPEV, bellman_backup, critic_loss, critic_step, evaluate_policy, pev_step
from mixedrl.quadratic import AffinePolicy, LinearDynamics, QuadraticCost
from mixedrl.tasks import LinearTask


def rollout_value(A, B, Q, R, g, L, l0, mu, K, x0, steps=700):
    """sum_t gamma^t E l(x_{t+1}, u_t), l(x', u) = x'^T Q x' + u^T R u, by propagating mean and covariance."""
    m, S = x0.copy(), np.zeros_like(A)
    total = 0.0
    for t in range(steps):
        u_mean = -L @ m - l0
        cov_u = L @ S @ L.T
        m_next = A @ m + B @ u_mean + mu
        S_next = (A - B @ L) @ S @ (A - B @ L).T + K
        # E l(x_{t+1}, u_t): charged on the NEXT state (eq. 2)
        total += g**t * (m_next @ Q @ m_next + np.trace(Q @ S_next) + u_mean @ R @ u_mean + np.trace(R @ cov_u))
        m, S = m_next, S_next
    return total


def test_exact_pev_equals_the_discounted_next_state_cost() -> None:
    A = np.array([[1.0, 0.1], [0.0, 1.0]])
    B = np.array([[0.005], [0.1]])
    Q, R, g = np.diag([1.0, 0.5]), np.array([[0.1]]), 0.9
    L, l0 = np.array([[2.0, 3.0]]), np.array([0.4])
    mu, K = np.array([0.05, -0.3]), np.array([[0.02, 0.005], [0.005, 0.01]])
    V = evaluate_policy(LinearDynamics(A, B), QuadraticCost(Q, R), g, AffinePolicy(L, l0), mu, K)
    for x0 in (np.array([1.0, -2.0]), np.array([0.0, 0.0]), np.array([-3.0, 0.5])):
        assert float(V(x0[None])[0]) == pytest.approx(rollout_value(A, B, Q, R, g, L, l0, mu, K, x0), rel=1e-10)
    # the fixed point of one exact sweep (eq. 31) is the PEV solution
    T = bellman_backup(LinearDynamics(A, B), QuadraticCost(Q, R), g, AffinePolicy(L, l0), V, mu, K)
    assert T.distance(V) < 1e-10
    pev = ExactPEV(LinearDynamics(A, B), QuadraticCost(Q, R), g)

    class Noise:
        mean, cov = mu, K

    assert pev_step(pev, AffinePolicy(L, l0), Noise()).distance(V) == 0.0


def test_critic_loss_target_is_the_next_state_cost() -> None:
    """With V = 0 the critic's target is E l(x', u): the loss is mean (E l(x', u))^2 / 2, x' = f(x, u) + xi."""
    task = LinearTask()
    critic = torch.nn.Linear(2, 1, dtype=torch.float64)
    torch.nn.init.zeros_(critic.weight)
    torch.nn.init.zeros_(critic.bias)
    V = lambda z: critic(z)[:, 0]  # noqa: E731
    s = torch.tensor([[1.0, -0.5], [0.2, 0.8], [-1.0, 0.0]], dtype=torch.float64)
    u = torch.tensor([[0.5], [-0.2], [1.0]], dtype=torch.float64)
    mu = np.array([0.0, 0.5])
    d, w = expectation_nodes(mu, np.zeros((2, 2)), task.noise_matrix, "sigma", dtype=torch.float64)
    x_next = task.f(s, u) + torch.tensor(mu)
    target = task.cost(x_next, u)
    loss = critic_loss(task, V, s, u, d, w)
    assert float(loss.detach()) == pytest.approx(float(0.5 * (target**2).mean()), rel=1e-14)


def test_critic_step_moves_the_critic_only() -> None:
    task = LinearTask()
    critic = torch.nn.Linear(2, 1)
    actor = torch.nn.Linear(2, 1)
    V = torch.nn.Sequential(critic, torch.nn.Flatten(0))
    opt = torch.optim.SGD(V.parameters(), lr=0.01)
    s = torch.randn(8, 2, generator=torch.Generator().manual_seed(0))
    d, w = expectation_nodes(np.array([0.0, 0.5]), 0.01 * np.eye(2), task.noise_matrix)
    actor_before = [p.clone() for p in actor.parameters()]
    critic_before = [p.clone() for p in critic.parameters()]
    loss = critic_step(task, V, actor, opt, s, d, w, grad_clip=10.0)
    assert np.isfinite(loss)
    assert all(torch.equal(a, b) for a, b in zip(actor_before, actor.parameters()))
    assert not all(torch.equal(a, b) for a, b in zip(critic_before, critic.parameters()))


def test_relative_critic_loss_weights_each_state_by_its_target() -> None:
    """batch_weighting="relative": mean of ((V - T) / (|T| + c))^2 / 2, computed here from the targets."""
    task = LinearTask()
    V = lambda z: torch.full((z.shape[0],), 0.3, dtype=torch.float64)  # noqa: E731
    s = torch.tensor([[1.0, -0.5], [0.2, 0.8], [-3.0, 2.0]], dtype=torch.float64)
    u = torch.tensor([[0.5], [-0.2], [1.0]], dtype=torch.float64)
    mu = np.array([0.0, 0.5])
    d, w = expectation_nodes(mu, np.zeros((2, 2)), task.noise_matrix, "sigma", dtype=torch.float64)
    x_next = task.f(s, u) + torch.tensor(mu)
    target = task.cost(x_next, u) + task.gamma * 0.3
    c = 0.7
    expected = 0.5 * (((0.3 - target) / (target.abs() + c)) ** 2).mean()
    assert float(critic_loss(task, V, s, u, d, w, relative_offset=c)) == pytest.approx(float(expected), rel=1e-14)
    # a huge offset makes every weight 1 / c^2: the plain loss divided by c^2
    plain = critic_loss(task, V, s, u, d, w)
    big = 1e9
    assert float(critic_loss(task, V, s, u, d, w, relative_offset=big)) * big**2 == pytest.approx(float(plain),
                                                                                                   rel=1e-6)
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="relative_offset"):
            critic_loss(task, V, s, u, d, w, relative_offset=bad)


def test_h_at_the_exact_value_of_an_affine_policy_is_that_value() -> None:
    """Eq. (37) against eq. (21): for an affine policy and its exact value V, h(x, pi(x), xi_hat) (the
    quadrature of the noise) is V(x) at every x, to the precision of V's linear solves."""
    from mixedrl.expectation import h_value
    from mixedrl.pim import improve_policy

    task = LinearTask()
    mu, K = np.array([0.1, 0.5]), np.array([[0.02, 0.005], [0.005, 0.03]])
    dyn, cost = LinearDynamics(task.A, task.B), QuadraticCost(task.Q, task.R)
    policy = improve_policy(dyn, cost, task.gamma, evaluate_policy(dyn, cost, task.gamma,
                            AffinePolicy(np.zeros((1, 2)), np.zeros(1)), mu, K), mu)
    V = evaluate_policy(dyn, cost, task.gamma, policy, mu, K)
    P, p, c = (torch.tensor(a) for a in (V.P, V.p, V.c))
    L, l0 = torch.tensor(policy.L), torch.tensor(policy.l0)

    def critic(z: torch.Tensor) -> torch.Tensor:
        return torch.einsum("bi,ij,bj->b", z, P, z) + 2.0 * z @ p + c

    def actor(z: torch.Tensor) -> torch.Tensor:
        return -(z @ L.T) - l0

    s = torch.tensor([[1.0, -0.5], [0.2, 0.8], [-1.0, 0.3], [0.0, 0.0]], dtype=torch.float64)
    d, w = expectation_nodes(mu, K, task.noise_matrix, "sigma", dtype=torch.float64)
    residual = float((h_value(task, critic, s, actor(s), d, w) - critic(s)).abs().max())
    assert residual < 1e-8 * float(critic(s).abs().max())
    # the test can tell: another policy's value is not a fixed point of this policy's h
    assert float((h_value(task, critic, s, 0.5 * actor(s), d, w) - critic(s)).abs().max()) > 1e-3
