"""Policy improvement (PIM): eq. (22) exactly on quadratic values, eqs. (51)-(52) with a parameterised
actor, and beside it the maximum variation condition (MVC, eqs. 37-39) that decides whether Algorithm 2
takes another PIM step.

* **Exact** (Algorithm 1 on linear dynamics): :func:`improve_policy` is the closed-form minimiser of
  eq. (22), :class:`ExactPIM` binds a problem, :func:`pim_step` is Algorithm 1's PIM step.
* **Parameterised** (Algorithm 2): :func:`actor_objective` is eq. (51) (gradient eq. 52 through the
  model), :func:`actor_step` one optimiser step on it.
* **MVC**: :func:`mvc_terms` is eqs. (38)-(39) on a batch from values of ``h`` (eq. 37,
  :func:`mixedrl.expectation.h_value`), shared with :func:`theory.mvc`; :func:`mvc_check` is
  Algorithm 2's decision from it, :class:`MVCResult` its outcome.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Any, Callable

import numpy as np
import scipy.linalg
import torch

from mixedrl.checks import as_vector
from mixedrl.compiled import constants
from mixedrl.expectation import h_value
from mixedrl.pev import check_hooks, run_mean
from mixedrl.schedule import Descent
from mixedrl.quadratic import AffinePolicy, LinearDynamics, QuadraticCost, QuadraticValue, check_problem

__all__ = ["improve_policy", "ExactPIM", "pim_step", "actor_objective", "actor_objective_at", "actor_step", "MVCResult", "MVCTerms", "mvc_terms", "mvc_check"]


# ----------------------------------------------------------------------------------------------------
# exact PIM on quadratic values (eq. 22)
# ----------------------------------------------------------------------------------------------------
def improve_policy(
    dynamics: LinearDynamics,
    cost: QuadraticCost,
    gamma: float,
    value: QuadraticValue,
    noise_mean: Any,
) -> AffinePolicy:
    """Implements eq. (22): exact PIM, the closed-form minimiser under the mixed model.

    .. math::
        \\pi^{k+1}(x) = \\arg\\min_u \\mathbb{E}_{\\hat\\xi_k}\\{ l(x', u) + \\gamma V^k(x') \\}
        = -L x - l_0,\\quad
        L = (R + B^T S B)^{-1} B^T S A,\\quad
        l_0 = (R + B^T S B)^{-1} B^T (S \\hat\\mu_k + \\gamma p),

    with ``S = Q + gamma P`` from ``V^k = x^T P x + 2 p^T x + c``.

    Parameters
    ----------
    dynamics : LinearDynamics
        A (n, n), B (n, m).
    cost : QuadraticCost
        Q (n, n), R (m, m).
    gamma : float
        Discount factor in (0, 1).
    value : QuadraticValue
        ``V^k``: P (n, n), p (n,), c.
    noise_mean : ndarray, shape (n,)
        ``mu_hat_k``.

    Returns
    -------
    AffinePolicy
        ``pi^{k+1}``: L (m, n), l0 (m,).

    Raises
    ------
    ValueError
        Shapes do not match, gamma not in (0, 1), or ``R + B^T S B`` is not positive definite (the
        objective is then not strictly convex in ``u``).

    Notes
    -----
    The objective is ``u^T (R + B^T S B) u + 2 u^T B^T (S (A x + mu_hat) + gamma p) + const`` plus the
    term ``tr(S K_hat)``, which does not depend on ``u``: the noise covariance does not enter PIM.
    """
    g = check_problem(dynamics, cost, gamma)
    n = dynamics.n
    if value.P.shape != (n, n):
        raise ValueError(f"value: P shape {value.P.shape} does not match n = {n}")
    mu = as_vector(noise_mean, "noise_mean", n)
    A, B, Q, R = dynamics.A, dynamics.B, cost.Q, cost.R
    S = Q + g * value.P
    H = R + B.T @ S @ B
    try:
        chol = scipy.linalg.cho_factor(0.5 * (H + H.T))
    except np.linalg.LinAlgError:
        raise ValueError("value: R + B^T (Q + gamma P) B is not positive definite") from None
    # L = (R + B^T S B)^-1 B^T S A
    L = scipy.linalg.cho_solve(chol, B.T @ S @ A)
    # l0 = (R + B^T S B)^-1 B^T (S mu_hat + gamma p)
    l0 = scipy.linalg.cho_solve(chol, B.T @ (S @ mu + g * value.p))
    return AffinePolicy(L, l0)


@dataclass(frozen=True)
class ExactPIM:
    """PIM step (eq. 22) bound to a linear-quadratic problem: ``pim(value, noise) -> AffinePolicy``."""

    dynamics: LinearDynamics
    cost: QuadraticCost
    gamma: float

    def __call__(self, value: QuadraticValue, noise: Any) -> AffinePolicy:
        """``pi^{k+1}`` greedy w.r.t. ``value`` under ``N(noise.mean, .)`` (:func:`improve_policy`)."""
        return improve_policy(self.dynamics, self.cost, self.gamma, value, noise.mean)


def pim_step(improve: Callable[[Any, Any], Any], value: Any, noise: Any) -> Any:
    """Implements eq. (22): policy improvement under the mixed model.

    .. math:: \\pi^{k+1}(x) = \\arg\\min_u \\mathbb{E}_{\\hat\\xi_k}\\{ l(x', u) + \\gamma V^k(x') \\}

    Parameters
    ----------
    improve : callable
        ``improve(value, noise) -> policy``, e.g. :class:`ExactPIM`.
    value, noise : object
        ``V^k``; the noise source, with ``.mean`` (n,) and ``.cov`` (n, n).

    Returns
    -------
    object
        ``pi^{k+1}``.

    Raises
    ------
    ValueError
        Propagated from ``improve``.
    """
    return improve(value, noise)


# ----------------------------------------------------------------------------------------------------
# parameterised PIM (eqs. 51-52)
# ----------------------------------------------------------------------------------------------------
def actor_objective(task: Any, critic: torch.nn.Module, actor: torch.nn.Module, s: torch.Tensor,
                    offsets: torch.Tensor, weights: torch.Tensor, relative_offset: float | None = None,
                    runs: int = 1) -> torch.Tensor:
    """Implements eqs. (51)-(52): the PIM objective, differentiated through the model ``f``.

    .. math::

        J_{\\rm actor} = \\mathbb{E}_{\\hat\\xi}\\{ l(x', u_\\theta) + \\gamma V^k(x') \\},
        \\qquad x' \\sim N(f(x, u_\\theta) + \\hat\\mu, \\hat K), \\qquad u_\\theta = \\pi(x; \\theta).

    Parameters
    ----------
    task : Task
        Model ``f`` (differentiable), utility, ``gamma``.
    critic : torch.nn.Module
        ``V^k`` (not updated by this objective).
    actor : torch.nn.Module
        ``pi(x; theta)``.
    s : torch.Tensor, shape (B, state_dim)
        Batch of states.
    offsets, weights : torch.Tensor
        Quadrature of ``xi_hat_k``, shapes ``(P, state_dim)`` and ``(P,)``.
    relative_offset : float or None, optional
        ``None`` (the paper's batch mean), or ``c > 0``: state ``x`` is weighted by
        ``rho(x) = 1 / (V^k(x) + c)`` (normalised to batch mean 1, no gradient;
        :mod:`mixedrl.departures.state_weights`). A positive weight per state does not move the minimiser
        of ``h`` at any state, only which states the batch gradient favours.
    runs : int, optional
        ``R >= 1``: the batch holds ``R`` runs' batches one after the other (stacked networks,
        :mod:`mixedrl.algorithms.batched`); the objective (and ``rho``'s normalisation) is per run.

    Returns
    -------
    torch.Tensor, shape () or (R,)
        Batch mean of ``h(x, pi(x; theta), xi_hat_k)`` (weighted by ``rho`` in the relative form),
        divided by ``value_scale``; one per run when ``runs > 1``.

    Notes
    -----
    Eq. (52) writes the gradient as a score-function term plus a pathwise term. With the
    reparameterisation ``x' = f(x, u_theta) + xi_hat`` (``xi_hat`` independent of ``theta``) both are the
    single pathwise gradient that autograd computes here, ``E{(dl/dx' + gamma dV/dx') df/du + dl/du}
    du/dtheta``.
    """
    relative_offset, runs = check_hooks(relative_offset, runs, s.shape[0])
    return _actor_objective(task, critic, actor, s, offsets, weights, relative_offset, runs)


def _actor_objective(task: Any, critic: Callable[..., torch.Tensor], actor: Callable[..., torch.Tensor],
                     s: torch.Tensor, offsets: torch.Tensor, weights: torch.Tensor, relative_offset: float | None,
                     runs: int) -> torch.Tensor:
    """:func:`actor_objective` on checked arguments (pure tensor arithmetic: the hot path, compiled by
    :mod:`mixedrl.compiled`)."""
    obs = task.observe(s)
    u = actor(obs)
    scale = float(getattr(task, "value_scale", 1.0))
    # J_actor = mean_x h(x, pi(x; theta), xi_hat_k)   (eq. 37)
    h = h_value(task, critic, s, u, offsets, weights)
    if relative_offset is None:
        return run_mean(h, runs) / scale
    with torch.no_grad():
        # rho(x) = 1 / (V^k(x) + c), normalised to batch mean 1 (per run)
        rho = 1.0 / (critic(obs).reshape(h.shape) + relative_offset)
        rho = rho / (rho.mean() if runs == 1 else run_mean(rho, runs).repeat_interleave(h.shape[0] // runs))
    return run_mean(rho * h, runs) / scale


def actor_objective_at(params: tuple[torch.Tensor, ...], s: torch.Tensor, offsets: torch.Tensor,
                       weights: torch.Tensor, *, task: Any, critic: Callable[..., torch.Tensor], actor: Any,
                       relative_offset: float | None = None, runs: int = 1) -> torch.Tensor:
    """Eqs. (51)-(52) as a pure loss of the actor's parameters (:mod:`mixedrl.compiled`): :func:`actor_objective`
    of the actor at ``params``, the critic ``V^k`` frozen, the arguments already checked by :func:`actor_step`."""
    from mixedrl.compiled import network_at

    return _actor_objective(task, critic, network_at(actor, params), s, offsets, weights, relative_offset, runs)


def actor_step(task: Any, critic: Callable[..., torch.Tensor], actor: Callable[..., torch.Tensor],
               optimizer: torch.optim.Optimizer | Descent, s: torch.Tensor, offsets: torch.Tensor,
               weights: torch.Tensor, grad_clip: float | None = None, relative_offset: float | None = None, *,
               runs: int = 1, active: list[int] | None = None) -> torch.Tensor:
    """Implements eqs. (51)-(52): PIM, one gradient step of the actor under ``xi_hat_k`` (of one run or of
    ``R`` runs at once: the step of :func:`mixedrl.algorithms.algorithm2.iteration`).

    .. math:: \\theta^{k+1} = \\theta^k - \\beta\\, \\partial J_{\\rm actor} / \\partial \\theta

    Parameters
    ----------
    task : Task
    critic : torch.nn.Module or callable
        ``V^k``, frozen during the step (``R`` runs: :meth:`mixedrl.algorithms.batched.StackedNetwork.frozen`).
    actor : torch.nn.Module or StackedNetwork
        ``pi(x; theta)``, updated in place.
    optimizer : torch.optim.Optimizer or Descent
        One run: the optimiser over the actor's parameters (learning rate ``beta``); ``R`` runs: their
        :class:`mixedrl.schedule.Descent`.
    s : torch.Tensor, shape (R B, state_dim)
        The batch of states (float32).
    offsets, weights : torch.Tensor
        Quadrature of ``xi_hat_k`` (see :func:`mixedrl.pev.critic_step`).
    grad_clip : float, optional
        Largest gradient norm (with an optimizer).
    relative_offset : float or None, optional
        Departure hook *state weights*; see :func:`actor_objective`.
    runs : int, optional
        ``R``.
    active : list of int, optional
        The runs that step (default all).

    Returns
    -------
    torch.Tensor, shape () or (R,)
        The actor objective before the step, detached.

    Notes
    -----
    Adam with gradient clipping (:mod:`mixedrl.departures.schedule`); the paper writes plain gradient descent.
    """
    step = optimizer if isinstance(optimizer, Descent) else Descent.single(actor, optimizer, grad_clip)
    relative_offset, runs = check_hooks(relative_offset, runs, s.shape[0])
    # theta^{k+1} = theta^k - beta dJ_actor/dtheta   (Adam, per run; eager, or one compiled step with
    # algorithm.compile)
    loss = partial(actor_objective_at, task=task, critic=critic, actor=actor, relative_offset=relative_offset,
                   runs=runs)
    key = ("pim", id(task), id(critic), id(actor), relative_offset, runs)
    with constants(critic):  # V^k is read, not trained
        return step.minimise(loss, (s, offsets, weights), active, key)


# ----------------------------------------------------------------------------------------------------
# the maximum variation condition (eqs. 37-39)
# ----------------------------------------------------------------------------------------------------


@dataclass
class MVCResult:
    """Outcome of the MVC check (eqs. 38-39) on a batch.

    Attributes
    ----------
    held : bool
        Whether the condition held in the configured sense (batch mean or every state).
    fraction : float
        Fraction of states where it held pointwise.
    lhs_mean : float
        Batch mean of ``h(x, u^{k+1}, xi_{k+1}) - h(x, u^{k+1}, xi_k)`` (the effect of the IBE update).
    e_mean : float
        Batch mean of ``e_k(x) = h(x, u^k, xi_k) - h(x, u^{k+1}, xi_k)`` (the PIM improvement).
    e_nonnegative : float
        Fraction of states with ``e_k(x) >= 0``.
    """

    held: bool
    fraction: float
    lhs_mean: float
    e_mean: float
    e_nonnegative: float


@dataclass(frozen=True)
class MVCTerms:
    """Both sides of eq. (38) on a batch (:func:`mvc_terms`), in float64.

    Attributes
    ----------
    variation : numpy.ndarray or torch.Tensor, shape (B,)
        ``h(x, u^{k+1}, xi_{k+1}) - h(x, u^{k+1}, xi_k)``, the left side.
    e : numpy.ndarray or torch.Tensor, shape (B,)
        ``e_k(x) = h(x, u^k, xi_k) - h(x, u^{k+1}, xi_k)`` of eq. (39), the right side.
    pointwise : numpy.ndarray or torch.Tensor of bool, shape (B,)
        Where ``variation <= e`` (plus the tolerance, if one was given).
    held_on_mean : bool
        ``mean(variation) <= mean(e)`` (plus the mean tolerance): the batch form (EQUATIONS.md point 12).
    """

    variation: Any
    e: Any
    pointwise: Any
    held_on_mean: bool


def _float64(a: Any) -> Any:
    return a.double() if isinstance(a, torch.Tensor) else np.asarray(a, dtype=np.float64)


def mvc_terms(h_new_next: Any, h_new_cur: Any, h_old_cur: Any, tolerance: Any = None) -> MVCTerms:
    """Implements eqs. (38)-(39): the maximum variation condition from three values of ``h`` (eq. 37).

    .. math::

        h(x, u^{k+1}, \\hat\\xi_{k+1}) - h(x, u^{k+1}, \\hat\\xi_k) \\le e_k(x),
        \\qquad e_k(x) = h(x, u^k, \\hat\\xi_k) - h(x, u^{k+1}, \\hat\\xi_k).

    The differences are taken in the inputs' dtype, then converted to float64 (numpy arrays or torch
    tensors alike).

    Parameters
    ----------
    h_new_next : numpy.ndarray or torch.Tensor, shape (B,)
        ``h(x, u^{k+1}, xi_hat_{k+1})``.
    h_new_cur : numpy.ndarray or torch.Tensor, shape (B,)
        ``h(x, u^{k+1}, xi_hat_k)``.
    h_old_cur : numpy.ndarray or torch.Tensor, shape (B,)
        ``h(x, u^k, xi_hat_k)``.
    tolerance : numpy.ndarray, shape (B,), optional
        Rounding tolerance added to the right side (the checks of :mod:`theory`); none by default.

    Returns
    -------
    MVCTerms

    Raises
    ------
    ValueError
        The three inputs are not of one shape (B,).
    """
    if not (h_new_next.shape == h_new_cur.shape == h_old_cur.shape) or h_new_next.ndim != 1:
        raise ValueError(f"h_new_next: expected three (B,) tensors, got {tuple(h_new_next.shape)}, "
                         f"{tuple(h_new_cur.shape)}, {tuple(h_old_cur.shape)}")
    # lhs = h(x, u^{k+1}, xi_{k+1}) - h(x, u^{k+1}, xi_k)   (eq. 38)
    lhs = _float64(h_new_next - h_new_cur)
    # e_k(x) = h(x, u^k, xi_k) - h(x, u^{k+1}, xi_k)   (eq. 39)
    e = _float64(h_old_cur - h_new_cur)
    if tolerance is None:
        # lhs <= e_k(x)   (eq. 38)
        return MVCTerms(lhs, e, lhs <= e, bool(lhs.mean() <= e.mean()))
    return MVCTerms(lhs, e, lhs <= e + tolerance, bool(lhs.mean() <= e.mean() + float(tolerance.mean())))


def mvc_check(h_new_next: torch.Tensor, h_new_cur: torch.Tensor, h_old_cur: torch.Tensor, mode: str = "mean"
              ) -> MVCResult:
    """The maximum variation condition (eqs. 38-39, :func:`mvc_terms`) on a batch, as Algorithm 2 decides it.

    Parameters
    ----------
    h_new_next, h_new_cur, h_old_cur : torch.Tensor, shape (B,)
        As in :func:`mvc_terms`.
    mode : {"mean", "all"}
        ``"mean"``: the inequality between batch means; ``"all"``: at every state (EQUATIONS.md point 12).

    Returns
    -------
    MVCResult

    Raises
    ------
    ValueError
        Shapes differ, or ``mode`` unknown.
    """
    t = mvc_terms(h_new_next, h_new_cur, h_old_cur)
    if mode not in ("mean", "all"):
        raise ValueError(f"mode: expected 'mean' or 'all', got {mode!r}")
    held = t.held_on_mean if mode == "mean" else bool(t.pointwise.all())
    return MVCResult(held=held, fraction=float(t.pointwise.double().mean()), lhs_mean=float(t.variation.mean()),
                     e_mean=float(t.e.mean()), e_nonnegative=float((t.e >= 0).double().mean()))
