"""Policy evaluation (PEV): eq. (21) exactly on quadratic values, eqs. (49)-(50) with a parameterised critic.

* **Exact** (Algorithm 1 on linear dynamics, :mod:`mixedrl.quadratic` types): :func:`evaluate_policy`
  solves eq. (21) for an affine policy, :func:`bellman_backup` is one sweep of it (eq. 31),
  :class:`ExactPEV` binds a problem, and :func:`pev_step` is Algorithm 1's PEV step for any
  representation.
* **Parameterised** (Algorithm 2): :func:`critic_loss` is the loss of eq. (49) whose gradient is the
  semi-gradient of eq. (50); :func:`critic_step` takes one optimiser step on it.

Both charge the utility on the **next** state (eq. 2) and take the expectation over the mixed model's
noise ``xi_hat_k`` (exactly for quadratics, by the quadrature of :mod:`mixedrl.expectation` otherwise).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Any, Callable

import numpy as np
import torch

from mixedrl.checks import as_vector, check_covariance, check_number, check_positive_int
from mixedrl.expectation import h_value
from mixedrl.schedule import Descent
from mixedrl.quadratic import AffinePolicy, LinearDynamics, QuadraticCost, QuadraticValue, check_problem, lyapunov_solve

__all__ = ["evaluate_policy", "bellman_backup", "ExactPEV", "pev_step", "critic_loss", "critic_loss_at", "critic_step", "run_mean", "check_runs"]


# ----------------------------------------------------------------------------------------------------
# exact PEV on quadratic values (eq. 21)
# ----------------------------------------------------------------------------------------------------
def evaluate_policy(
    dynamics: LinearDynamics,
    cost: QuadraticCost,
    gamma: float,
    policy: AffinePolicy,
    noise_mean: Any,
    noise_cov: Any,
) -> QuadraticValue:
    """Implements eq. (21): exact PEV of an affine policy under the mixed model ``N(mu_hat, K_hat)``.

    .. math::
        V^k(x) = \\mathbb{E}_{\\hat\\xi_k}\\{ l(x', \\pi^k(x)) + \\gamma V^k(x') \\},\\quad
        x' = A x + B \\pi^k(x) + \\hat\\xi_k,\\ \\hat\\xi_k \\sim N(\\hat\\mu_k, \\hat K_k).

    With ``A_c = A - B L``, ``d = mu_hat - B l0``, ``S = Q + gamma P`` and ``V = x^T P x + 2 p^T x + c``,
    matching the quadratic, linear and constant terms gives

    .. math::
        P &= \\gamma A_c^T P A_c + A_c^T Q A_c + L^T R L \\\\
        (I - \\gamma A_c^T)\\, p &= A_c^T S d + L^T R\\, l_0 \\\\
        (1 - \\gamma)\\, c &= d^T S d + \\operatorname{tr}(S \\hat K) + l_0^T R\\, l_0 + 2 \\gamma\\, p^T d .

    Parameters
    ----------
    dynamics : LinearDynamics
        ``f(x, u) = A x + B u``, A (n, n), B (n, m).
    cost : QuadraticCost
        Q (n, n), R (m, m); utility on the next state (eq. 2).
    gamma : float
        Discount factor in (0, 1).
    policy : AffinePolicy
        L (m, n), l0 (m,).
    noise_mean : ndarray, shape (n,)
        ``mu_hat_k``.
    noise_cov : ndarray, shape (n, n)
        ``K_hat_k`` (symmetric PSD).

    Returns
    -------
    QuadraticValue
        ``V^k`` with P (n, n), p (n,), c.

    Raises
    ------
    ValueError
        Shapes do not match, gamma not in (0, 1), the covariance is not symmetric PSD, or the policy is
        not stabilising for the discounted problem (spectral radius of ``sqrt(gamma) A_c`` >= 1, so
        eq. 21 has no finite solution).

    Notes
    -----
    The expectation over ``xi_hat`` is exact (no sampling): ``E V(x') = V(E x') + tr(P K_hat)``.
    The quadratic term is a discrete Lyapunov equation in ``sqrt(gamma) A_c`` solved by
    :func:`lyapunov_solve`; the linear term is a linear system with matrix ``I - gamma A_c^T``,
    non-singular because ``rho(gamma A_c) < sqrt(gamma) < 1``.
    """
    g = check_problem(dynamics, cost, gamma)
    n, m = dynamics.n, dynamics.m
    if policy.L.shape != (m, n):
        raise ValueError(f"policy: gain shape {policy.L.shape} does not match (m, n) = ({m}, {n})")
    mu = as_vector(noise_mean, "noise_mean", n)
    K = check_covariance(noise_cov, "noise_cov", n)
    A, B, Q, R = dynamics.A, dynamics.B, cost.Q, cost.R
    L, l0 = policy.L, policy.l0
    Ac = A - B @ L
    rho = float(np.max(np.abs(np.linalg.eigvals(np.sqrt(g) * Ac))))
    if rho >= 1.0:
        raise ValueError(
            f"policy: not stabilising for the discounted problem (spectral radius of sqrt(gamma)(A - B L) = {rho:.6g} >= 1)"
        )
    # P = gamma A_c^T P A_c + A_c^T Q A_c + L^T R L   (quadratic terms of eq. 21)
    P = lyapunov_solve(np.sqrt(g) * Ac, Ac.T @ Q @ Ac + L.T @ R @ L)
    S = Q + g * P
    d = mu - B @ l0
    # (I - gamma A_c^T) p = A_c^T S d + L^T R l0   (linear terms of eq. 21)
    p = np.linalg.solve(np.eye(n) - g * Ac.T, Ac.T @ S @ d + L.T @ R @ l0)
    # (1 - gamma) c = d^T S d + tr(S K) + l0^T R l0 + 2 gamma p^T d   (constant terms of eq. 21)
    c = (d @ S @ d + float(np.sum(S * K)) + l0 @ R @ l0 + 2.0 * g * p @ d) / (1.0 - g)
    return QuadraticValue(P, p, c)


def bellman_backup(
    dynamics: LinearDynamics,
    cost: QuadraticCost,
    gamma: float,
    policy: AffinePolicy,
    value: QuadraticValue,
    noise_mean: Any,
    noise_cov: Any,
) -> QuadraticValue:
    """Implements eq. (31): one PEV sweep ``V_1(x) = E_xi{ l(x', pi(x)) + gamma V(x') }``, exactly.

    .. math::
        (T^{\\pi} V)(x) = \\mathbb{E}_{\\hat\\xi}\\{ l(x', \\pi(x)) + \\gamma V(x') \\}
        = h(x, \\pi(x), \\hat\\xi)\\quad\\text{(eq. 37)}

    With ``S = Q + gamma P``, ``A_c = A - B L``, ``d = mu - B l0`` the result is
    ``P_1 = A_c^T S A_c + L^T R L``, ``p_1 = A_c^T (S d + gamma p) + L^T R l0``,
    ``c_1 = d^T S d + tr(S K) + l0^T R l0 + 2 gamma p^T d + gamma c``.

    Parameters
    ----------
    dynamics : LinearDynamics
    cost : QuadraticCost
    gamma : float
    policy : AffinePolicy
        L (m, n), l0 (m,).
    value : QuadraticValue
        P (n, n), p (n,), c.
    noise_mean : ndarray, shape (n,)
    noise_cov : ndarray, shape (n, n)

    Returns
    -------
    QuadraticValue

    Raises
    ------
    ValueError
        Shapes do not match, gamma outside (0, 1), covariance not symmetric PSD.

    Notes
    -----
    The fixed point of this map is :func:`evaluate_policy`; the theory checks use it to check the MVC
    (eq. 38) and the value decrease (eq. 29) for *all* x at once.
    """
    g = check_problem(dynamics, cost, gamma)
    n, m = dynamics.n, dynamics.m
    if policy.L.shape != (m, n) or value.P.shape != (n, n):
        raise ValueError("policy: shapes of policy/value do not match the dynamics")
    mu = as_vector(noise_mean, "noise_mean", n)
    K = check_covariance(noise_cov, "noise_cov", n)
    A, B, Q, R = dynamics.A, dynamics.B, cost.Q, cost.R
    L, l0 = policy.L, policy.l0
    Ac = A - B @ L
    S = Q + g * value.P
    d = mu - B @ l0
    P1 = Ac.T @ S @ Ac + L.T @ R @ L
    p1 = Ac.T @ (S @ d + g * value.p) + L.T @ R @ l0
    c1 = d @ S @ d + float(np.sum(S * K)) + l0 @ R @ l0 + 2.0 * g * value.p @ d + g * value.c
    return QuadraticValue(P1, p1, c1)


@dataclass(frozen=True)
class ExactPEV:
    """PEV step (eq. 21) bound to a linear-quadratic problem: ``pev(policy, noise) -> QuadraticValue``
    (``noise`` has ``.mean`` (n,) and ``.cov`` (n, n))."""

    dynamics: LinearDynamics
    cost: QuadraticCost
    gamma: float

    def __call__(self, policy: AffinePolicy, noise: Any) -> QuadraticValue:
        """``V^k`` of ``policy`` under ``N(noise.mean, noise.cov)`` (:func:`evaluate_policy`)."""
        return evaluate_policy(self.dynamics, self.cost, self.gamma, policy, noise.mean, noise.cov)


def pev_step(evaluate: Callable[[Any, Any], Any], policy: Any, noise: Any) -> Any:
    """Implements eq. (21): policy evaluation of ``pi^k`` under the mixed model ``N(mu_hat_k, K_hat_k)``.

    .. math:: V^k(x) = \\mathbb{E}_{\\hat\\xi_k}\\{ l(x', \\pi^k(x)) + \\gamma V^k(x') \\}

    Parameters
    ----------
    evaluate : callable
        ``evaluate(policy, noise) -> value``, e.g. :class:`ExactPEV`.
    policy, noise : object
        ``pi^k``; the noise source, with ``.mean`` (n,) and ``.cov`` (n, n).

    Returns
    -------
    object
        ``V^k``.

    Raises
    ------
    ValueError
        Propagated from ``evaluate`` (e.g. a policy that does not stabilise the discounted problem).
    """
    return evaluate(policy, noise)


# ----------------------------------------------------------------------------------------------------
# parameterised PEV (eqs. 49-50)
# ----------------------------------------------------------------------------------------------------
def critic_loss(task: Any, critic: torch.nn.Module, s: torch.Tensor, u: torch.Tensor, offsets: torch.Tensor,
                weights: torch.Tensor, relative_offset: float | None = None, runs: int = 1,
                target_critic: Callable[[torch.Tensor], torch.Tensor] | None = None) -> torch.Tensor:
    """Implements eqs. (49)-(50): the PEV loss whose gradient is the critic's semi-gradient.

    .. math::

        J_{\\rm critic} = \\mathbb{E}_{\\hat\\xi}\\Big\\{\\tfrac12 \\big(l(x', u_\\theta)
            + \\gamma V^k(x'; w) - V^k(x; w)\\big)^2\\Big\\},
        \\qquad
        \\frac{\\partial J_{\\rm critic}}{\\partial w}
            = \\big(V^k(x; w) - \\mathbb{E}\\,V_{\\rm target}\\big)\\,\\frac{\\partial V^k(x; w)}{\\partial w}.

    Parameters
    ----------
    task : Task
    critic : torch.nn.Module
        ``V(x; w)``.
    s : torch.Tensor, shape (B, state_dim)
        Batch of states.
    u : torch.Tensor, shape (B, action_dim)
        ``u_theta = pi(x; theta)`` (detached: PEV does not move the actor).
    offsets, weights : torch.Tensor
        Quadrature of ``xi_hat_k`` (:func:`mixedrl.expectation.expectation_nodes`), shapes
        ``(P, state_dim)`` (or ``(P, B, state_dim)``, per state) and ``(P,)``.
    relative_offset : float or None, optional
        ``None`` (the paper's batch mean), or ``c > 0``: the *relative* TD error
        ``(V - E V_target) / (|E V_target| + c)`` is squared instead (:mod:`mixedrl.departures.state_weights`).
    runs : int, optional
        ``R >= 1``: ``s`` holds ``R`` runs' batches one after the other, ``(R B, n)``, ``critic`` is their
        stacked network (:mod:`mixedrl.algorithms.batched`); the loss is taken per run.
    target_critic : callable, optional
        ``V(x; w_bar)``, the network inside ``V_target`` (:mod:`mixedrl.departures.critic_target`);
        ``None`` (eq. 50): ``critic`` itself.

    Returns
    -------
    torch.Tensor, shape () or (R,)
        ``mean_x 1/2 (V(x; w) - E V_target)^2`` (or its relative form), one per run when ``runs > 1``;
        its gradient in ``w`` is the semi-gradient of eq. (50), averaged over the batch.

    Raises
    ------
    ValueError
        If the batch sizes of ``s`` and ``u`` differ, or ``runs`` does not divide them.

    Notes
    -----
    *Semi-gradient*: ``V_target`` is computed without gradient, as eq. (50) says. The expectation is moved
    inside the square: ``E{(T - V)^2}/2`` and ``(E T - V)^2/2`` differ by the variance of ``T``, which does
    not depend on ``w`` through the semi-gradient, so both give the same gradient. The loss is divided by
    ``value_scale^2`` so that its size does not depend on the units of the cost.
    """
    if s.shape[0] != u.shape[0]:
        raise ValueError(f"u: batch size {u.shape[0]} differs from s's {s.shape[0]}")
    relative_offset, runs = check_hooks(relative_offset, runs, s.shape[0])
    return _critic_loss(task, critic, s, u, offsets, weights, relative_offset, runs, target_critic)


def _critic_loss(task: Any, critic: Callable[..., torch.Tensor], s: torch.Tensor, u: torch.Tensor,
                 offsets: torch.Tensor, weights: torch.Tensor, relative_offset: float | None, runs: int,
                 target_critic: Callable[[torch.Tensor], torch.Tensor] | None) -> torch.Tensor:
    """:func:`critic_loss` on checked arguments (pure tensor arithmetic: the hot path, compiled by
    :mod:`mixedrl.compiled`)."""
    with torch.no_grad():
        # V_target = l(x', u_theta) + gamma V^k(x'),  x' = f(x, u_theta) + xi_hat   (h of eq. 37; V(x'; w_bar) of
        # the target critic instead of V^k(x'; w) when one is given)
        target = h_value(task, critic if target_critic is None else target_critic, s, u, offsets, weights)
    value = critic(task.observe(s))
    if relative_offset is not None:
        # relative TD error: a per-state weight 1 / (|E V_target| + c)^2 of the squared error
        return 0.5 * run_mean(((value - target) / (target.abs() + relative_offset)).pow(2), runs)
    scale = float(getattr(task, "value_scale", 1.0))
    return 0.5 * run_mean(((value - target) / scale).pow(2), runs)


def critic_loss_at(params: tuple[torch.Tensor, ...], s: torch.Tensor, offsets: torch.Tensor, weights: torch.Tensor, *,
                   task: Any, critic: Any, actor: Callable[..., torch.Tensor], relative_offset: float | None = None,
                   runs: int = 1, target_critic: Callable[[torch.Tensor], torch.Tensor] | None = None) -> torch.Tensor:
    """Eqs. (49)-(50) as a pure loss of the critic's parameters (:mod:`mixedrl.compiled`): :func:`critic_loss`
    of the critic at ``params`` on ``u = pi(x)`` (no gradient), the arguments already checked by
    :func:`critic_step`."""
    from mixedrl.compiled import network_at

    with torch.no_grad():
        u = actor(task.observe(s))
    return _critic_loss(task, network_at(critic, params), s, u, offsets, weights, relative_offset, runs,
                        target_critic)


def check_runs(runs: int, batch: int) -> int:
    """Return ``runs`` if it is an integer ``>= 1`` that divides ``batch``; else a ``ValueError`` naming ``runs``."""
    runs = check_positive_int(runs, "runs")
    if batch % runs:
        raise ValueError(f"runs: {runs} does not divide the batch of {batch} states")
    return runs


def check_hooks(relative_offset: float | None, runs: int, batch: int) -> tuple[float | None, int]:
    """The hooks of a loss, checked: ``relative_offset`` (``None`` or ``> 0``), ``runs`` (:func:`check_runs`)."""
    if relative_offset is not None:
        relative_offset = check_number(relative_offset, "relative_offset", positive=True)
    return relative_offset, check_runs(runs, batch)


def run_mean(values: torch.Tensor, runs: int = 1) -> torch.Tensor:
    """The batch mean of per-state ``values`` (..., B): a scalar, or one mean per run (R,) when ``runs = R > 1``
    (the states of run ``r`` are rows ``r B' .. (r + 1) B' - 1`` of the last axis, ``B' = B / R``; any leading
    axes, e.g. the steps of a rollout, are averaged with them)."""
    if runs == 1:
        return values.mean()
    return values.reshape(*values.shape[:-1], runs, -1).transpose(0, -2).reshape(runs, -1).mean(dim=1)


def critic_step(task: Any, critic: Callable[..., torch.Tensor], actor: Callable[..., torch.Tensor],
                optimizer: torch.optim.Optimizer | Descent, s: torch.Tensor, offsets: torch.Tensor,
                weights: torch.Tensor, grad_clip: float | None = None, relative_offset: float | None = None,
                target_critic: Callable[[torch.Tensor], torch.Tensor] | None = None, *,
                runs: int = 1, active: list[int] | None = None) -> torch.Tensor:
    """Implements eqs. (49)-(50): PEV, one semi-gradient step of the critic under ``xi_hat_k`` (of one run
    or of ``R`` runs at once: the step of :func:`mixedrl.algorithms.algorithm2.iteration`).

    .. math:: w^{k+1} = w^k - \\alpha\\, \\partial J_{\\rm critic} / \\partial w

    Parameters
    ----------
    task : Task
    critic : torch.nn.Module or StackedNetwork
        ``V(x; w)``, updated in place.
    actor : torch.nn.Module or StackedNetwork
        ``pi(x; theta)`` (not moved: ``u_theta`` is computed without gradient).
    optimizer : torch.optim.Optimizer or Descent
        One run: the optimiser over the critic's parameters (learning rate ``alpha``); ``R`` runs: their
        :class:`mixedrl.schedule.Descent` (each run's optimiser and clip).
    s : torch.Tensor, shape (R B, state_dim)
        The batch of states (float32), run ``r``'s in rows ``r B .. (r + 1) B - 1``.
    offsets, weights : torch.Tensor
        Quadrature of ``xi_hat_k``, shapes ``(P, state_dim)`` (or ``(P, R B, state_dim)``) and ``(P,)``
        (or ``(P, R B)``).
    grad_clip : float, optional
        Largest gradient norm (with an optimizer; a ``Descent`` holds its own).
    relative_offset, target_critic : optional
        Departure hooks *state weights* and *target values*; see :func:`critic_loss`.
    runs : int, optional
        ``R``.
    active : list of int, optional
        The runs that step (default all).

    Returns
    -------
    torch.Tensor, shape () or (R,)
        The critic loss before the step, detached.

    Notes
    -----
    The step is Adam's (:mod:`mixedrl.departures.schedule`), with the gradient norm clipped at ``grad_clip``;
    the paper writes plain gradient descent.
    """
    step = optimizer if isinstance(optimizer, Descent) else Descent.single(critic, optimizer, grad_clip)
    relative_offset, runs = check_hooks(relative_offset, runs, s.shape[0])
    # w^{k+1} = w^k - alpha dJ_critic/dw   (Adam, per run; eager, or one compiled step with algorithm.compile)
    loss = partial(critic_loss_at, task=task, critic=critic, actor=actor, relative_offset=relative_offset,
                   runs=runs, target_critic=target_critic)
    key = ("pev", id(task), id(critic), id(actor), id(target_critic), relative_offset, runs)
    return step.minimise(loss, (s, offsets, weights), active, key)
