"""Departure hook *rollouts*: PEV and PIM on ``H``-step rollouts of the planning model (SHAC / value expansion).

The paper's PEV (eqs. 49-50) and PIM (eqs. 51-52) look one model step ahead: the critic's target is
``l(x', u) + gamma V(x')`` and the actor's gradient goes through one step of ``f``. With
``algorithm.rollout_horizon = H > 0`` both are replaced, for mixed RL, model-driven RL and the oracle alike
(the noise source ``xi_hat_k`` is the only difference between them), by the short-horizon analytic policy
gradient of SHAC (Xu et al., ICLR 2022) and the model-based value expansion of Feinberg et al. (2018):

* from the batch states ``x_0`` the actor is rolled ``H`` steps through the differentiable model,
  ``x_{t+1} = f(x_t, pi(x_t; theta)) + E xi_t``, the ``xi_t ~ N(mu_hat_k, K_hat_k)`` drawn reparameterised
  from the run's own generator (:func:`noise_draws`, :func:`rollout`);
* **PIM**: the actor's loss is the discounted cost of the rollout plus the frozen target critic at its end,
  ``sum_{t<H} gamma^t l(x_{t+1}, u_t) + gamma^H V_target(x_H)``, differentiated through the model
  (:func:`actor_loss`);
* **PEV**: the critic is fitted at every state of the same rollout (detached) to the ``lambda``-returns
  ``G_t = l_t + gamma ((1 - lambda) V_target(x_{t+1}) + lambda G_{t+1})``, ``G_{H-1} = l_{H-1} + gamma
  V_target(x_H)`` (:func:`lambda_returns`, :func:`critic_loss`), ``V_target`` the averaged critic of
  ``algorithm.critic_target`` when that is on, else the critic itself without gradient;
* one actor-then-critic update per iteration (:func:`update`); the MVC loop's extra PIM steps are rollout
  actor steps (:func:`improve`);
* optionally the rollouts' discount ramps linearly from ``algorithm.rollout_discount_start`` to the task's
  ``gamma`` over the first ``algorithm.rollout_discount_ramp`` of the budget (:func:`discount`).

With ``H = 1`` and ``lambda = 0`` the losses are the paper's one-step objective and target with one noise
draw in place of the quadrature (``tests/test_rollout.py``). The state weights of
:mod:`~mixedrl.departures.state_weights` apply as in the paper's losses. The losses are pure functions of
tensors (no numpy, no data-dependent Python branches), so with ``algorithm.compile`` on each step is one
compiled graph (:func:`actor_loss_at`, :func:`critic_loss_at`; the noise draws stay eager, in the same
order). Every function takes ``runs`` for ``R >= 1`` stacked runs and returns one loss per run.

Config key ``algorithm.rollout_horizon``: default 16 (with ``rollout_lambda`` 0.95, ``rollout_discount_start``
0.95), the paper's 0 (one-step PEV and PIM). Measured effect: docs/algorithm2.rst and
``experiments/results/learner_tuning/table.md``; a run takes about 1.5-2 times the one-step learner's time.
"""

from __future__ import annotations

from functools import partial
from typing import Any, Callable, Sequence

import numpy as np
import torch

from mixedrl.compiled import constants, network_at
from mixedrl.config import PAPER_SETTINGS
from mixedrl.departures import anchor, region
from mixedrl.gaussian import psd_factor
from mixedrl.pev import run_mean

NAME = "rollout"
KEY = "algorithm.rollout_horizon"
PAPER = PAPER_SETTINGS["algorithm"]["rollout_horizon"]

__all__ = ["NAME", "KEY", "PAPER", "active", "discount", "noise_draws", "rollout", "actor_loss", "actor_loss_at",
           "lambda_returns", "critic_loss", "critic_loss_at", "update", "improve"]

Network = Callable[[torch.Tensor], torch.Tensor]


def active(config: Any) -> bool:
    """Whether PEV and PIM work on ``H``-step model rollouts (``algorithm.rollout_horizon > 0``; Algorithm 2
    only, DDPG learns from its replay buffer)."""
    return config.algorithm.rollout_horizon != PAPER and config.method != "ddpg"


def discount(config: Any, k: int, gamma: float) -> float:
    """The rollouts' discount at iteration ``k``: ``gamma`` (the task's), or, with
    ``algorithm.rollout_discount_start = g0 > 0``, ``g0`` ramped linearly to ``gamma`` over the first
    ``rollout_discount_ramp * iterations`` iterations."""
    algo = config.algorithm
    start = algo.rollout_discount_start
    length = algo.rollout_discount_ramp * algo.iterations
    if start <= 0 or length <= 0:
        return float(gamma)
    return float(start + (gamma - start) * min(1.0, k / length))


def noise_draws(mean: np.ndarray, cov: np.ndarray, noise_matrix: torch.Tensor, horizon: int, batch: int,
                generator: torch.Generator, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Reparameterised draws ``E xi_t``, ``xi_t = mu_hat + K_hat^{1/2} z_t``, ``z_t ~ N(0, I)`` from ``generator``.

    Parameters
    ----------
    mean : numpy.ndarray
        ``mu_hat``, shape (noise_dim,), or (batch, noise_dim) per state (a state-dependent source).
    cov : numpy.ndarray, shape (noise_dim, noise_dim)
        ``K_hat`` (symmetric PSD, may be singular: its symmetric square root is used).
    noise_matrix : torch.Tensor, shape (state_dim, noise_dim)
        ``E``.
    horizon, batch : int
        ``H`` steps of ``batch`` states.
    generator : torch.Generator
        The run's generator (``H * batch * noise_dim`` standard normals are drawn from it).
    dtype : torch.dtype
        Of the result.

    Returns
    -------
    torch.Tensor, shape (H, batch, state_dim)
    """
    mean_t = torch.as_tensor(np.asarray(mean, dtype=np.float64))
    root = torch.as_tensor(psd_factor(np.asarray(cov, dtype=np.float64)))  # root root^T = K, also when singular
    z = torch.randn(horizon, batch, root.shape[0], generator=generator, dtype=torch.float64)
    xi = mean_t + z @ root.T
    return (xi @ noise_matrix.double().T).to(dtype)


def rollout(task: Any, actor: Network, s: torch.Tensor, draws: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Roll the actor ``H`` steps through the model: ``x_{t+1} = f(x_t, pi(x_t)) + E xi_t``.

    Parameters
    ----------
    task : Task
        ``f`` (differentiable), ``cost``, ``observe``.
    actor : callable
        ``pi`` on observations.
    s : torch.Tensor, shape (B, state_dim)
        ``x_0``.
    draws : torch.Tensor, shape (H, B, state_dim)
        ``E xi_t`` (:func:`noise_draws`).

    Returns
    -------
    states : torch.Tensor, shape (H + 1, B, state_dim)
        ``x_0 .. x_H``, differentiable in the actor's parameters.
    costs : torch.Tensor, shape (H, B)
        ``l(x_{t+1}, u_t)``.
    """
    if torch.compiler.is_compiling():
        return _scanned(task, actor, s, draws)
    states, costs = [s], []
    x = s
    for d in draws:
        u = actor(task.observe(x))
        x = task.f(x, u) + d
        costs.append(task.cost(x, u).reshape(-1))
        states.append(x)
    return torch.stack(states), torch.stack(costs)


def _scanned(task: Any, actor: Network, s: torch.Tensor, draws: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`rollout`'s recursion as one ``scan`` (``torch._higher_order_ops.scan``), the form it is compiled in:
    the graph holds one step and its backward, not ``H`` unrolled copies (the default's 16 steps compile in
    about a third of the unrolled time). The same arithmetic; the clones keep the step's outputs from
    aliasing its inputs, which ``scan`` refuses."""
    from torch._higher_order_ops.scan import scan

    def step(x: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        u = actor(task.observe(x))
        x_next = task.f(x, u) + d
        return x_next.clone(), (x_next.clone(), task.cost(x_next, u).reshape(-1).clone())

    _, (states, costs) = scan(step, s, draws)
    return torch.cat([s.unsqueeze(0), states]), costs


def _discounts(gamma: torch.Tensor, steps: int) -> torch.Tensor:
    """``gamma^t`` for ``t = 0 .. steps``, shape (steps + 1, B), from the per-row discount ``gamma`` (B,)."""
    t = torch.arange(steps + 1, dtype=gamma.dtype).reshape(-1, 1)
    return gamma.reshape(1, -1) ** t


def actor_loss(task: Any, value_target: Network, states: torch.Tensor, costs: torch.Tensor, gamma: torch.Tensor,
               runs: int = 1, relative_offset: float | None = None) -> torch.Tensor:
    """PIM on a rollout: ``J = mean_x0 [sum_{t<H} gamma^t l(x_{t+1}, u_t) + gamma^H V_target(x_H)] / value_scale``.

    Parameters
    ----------
    task : Task
        ``observe``, ``value_scale``.
    value_target : callable
        The frozen critic ``V_target`` on observations.
    states, costs : torch.Tensor
        :func:`rollout`'s, shapes (H + 1, B, state_dim) and (H, B), differentiable.
    gamma : torch.Tensor, shape (B,)
        The discount of each row.
    runs : int
        ``R`` stacked runs (run ``r`` in rows ``r B/R ..``): one loss per run.
    relative_offset : float or None
        ``c`` of the relative state weights: each start weighted by ``1 / (V_target(x_0) + c)`` (mean 1 per run,
        no gradient); ``None``: the plain mean.

    Returns
    -------
    torch.Tensor, shape () or (R,)
    """
    horizon = costs.shape[0]
    disc = _discounts(gamma.to(costs.dtype), horizon)
    tail = value_target(task.observe(states[-1])).reshape(-1).to(costs.dtype)
    total = (disc[:-1] * costs).sum(dim=0) + disc[-1] * tail
    scale = float(getattr(task, "value_scale", 1.0))
    if relative_offset is None:
        return run_mean(total, runs) / scale
    rho = 1.0 / (value_target(task.observe(states[0])).reshape(-1).detach().to(costs.dtype) + relative_offset)
    rho = rho / run_mean(rho, runs).reshape(-1).repeat_interleave(rho.shape[0] // runs)
    return run_mean(rho * total, runs) / scale


def lambda_returns(costs: torch.Tensor, next_values: torch.Tensor, gamma: torch.Tensor, lam: float) -> torch.Tensor:
    """``lambda``-returns along a rollout (TD(lambda) targets, as in SHAC and Dreamer).

    .. math::

        G_{H-1} = l_{H-1} + \\gamma V(x_H), \\qquad
        G_t = l_t + \\gamma\\big((1 - \\lambda) V(x_{t+1}) + \\lambda G_{t+1}\\big).

    Parameters
    ----------
    costs : torch.Tensor, shape (H, B)
        ``l_t = l(x_{t+1}, u_t)``.
    next_values : torch.Tensor, shape (H, B)
        ``V(x_{t+1})``, ``t = 0 .. H - 1``.
    gamma : torch.Tensor, shape (B,)
    lam : float
        ``lambda`` in [0, 1]: 0 = one-step targets, 1 = the ``H``-step return with the critic at the end.

    Returns
    -------
    torch.Tensor, shape (H, B)
        ``G_t`` for the states ``x_0 .. x_{H-1}``.
    """
    g = gamma.to(costs.dtype)
    out = []
    ret = next_values[-1]
    for t in range(costs.shape[0] - 1, -1, -1):
        ret = costs[t] + g * ((1.0 - lam) * next_values[t] + lam * ret)
        out.append(ret)
    return torch.stack(out[::-1])


def critic_loss(task: Any, critic: Network, states: torch.Tensor, targets: torch.Tensor, runs: int = 1,
                relative_offset: float | None = None) -> torch.Tensor:
    """PEV on a rollout: ``1/2 mean_t,x (V(x_t) - G_t)^2`` (divided by ``value_scale^2``, or the relative error
    ``(V - G) / (|G| + c)`` squared).

    Parameters
    ----------
    task : Task
    critic : callable
        ``V(x; w)`` on observations (trained).
    states : torch.Tensor, shape (H, B, state_dim)
        ``x_0 .. x_{H-1}`` (detached).
    targets : torch.Tensor, shape (H, B)
        :func:`lambda_returns` (no gradient).
    runs : int
    relative_offset : float or None

    Returns
    -------
    torch.Tensor, shape () or (R,)
    """
    horizon, batch = targets.shape
    value = critic(task.observe(states.reshape(horizon * batch, -1))).reshape(horizon, batch).to(targets.dtype)
    if relative_offset is None:
        err = (value - targets) / float(getattr(task, "value_scale", 1.0))
    else:
        err = (value - targets) / (targets.abs() + relative_offset)
    return 0.5 * run_mean(err.pow(2), runs)


def actor_loss_at(params: Sequence[torch.Tensor], s: torch.Tensor, draws: torch.Tensor, gamma: torch.Tensor, *,
                  task: Any, actor: Any, value_target: Network, runs: int = 1,
                  relative_offset: float | None = None) -> torch.Tensor:
    """:func:`actor_loss` of the rollout from ``s`` under ``draws`` with the actor at ``params``: the pure loss the
    compiled step differentiates (:meth:`mixedrl.schedule.Descent.minimise`, ``algorithm.compile``), with the
    rollout ``(states, costs)`` as its ``aux`` (detached: the critic's data)."""
    states, costs = rollout(task, network_at(actor, params), s, draws)
    return actor_loss(task, value_target, states, costs, gamma, runs, relative_offset), (states.detach(), costs.detach())


def critic_loss_at(params: Sequence[torch.Tensor], states: torch.Tensor, targets: torch.Tensor, *, task: Any,
                   critic: Any, runs: int = 1, relative_offset: float | None = None) -> torch.Tensor:
    """:func:`critic_loss` with the critic at ``params`` (the pure loss of the compiled step)."""
    return critic_loss(task, network_at(critic, params), states, targets, runs, relative_offset)


# ----------------------------------------------------------------------------------------------------
# the hooks of the loop (mixedrl.algorithms.algorithm2.iteration)
# ----------------------------------------------------------------------------------------------------
def _draws(engine: Any, moments: Sequence[tuple[np.ndarray, np.ndarray] | None], s: torch.Tensor) -> torch.Tensor:
    """Each active run's draws from its own generator on its rows; an inactive run's rows get zeros."""
    horizon = engine.members[0].config.algorithm.rollout_horizon
    parts = []
    for r, m in enumerate(engine.members):
        rows = s[engine.rows(r)]
        if moments[r] is None:
            parts.append(torch.zeros(horizon, rows.shape[0], rows.shape[1], dtype=s.dtype))
        else:
            parts.append(noise_draws(*moments[r], engine.task.noise_matrix, horizon, rows.shape[0], m.generator,
                                     s.dtype))
    return torch.cat(parts, dim=1)


def _gamma(engine: Any, s: torch.Tensor) -> torch.Tensor:
    """The discount of every row (each run's :func:`discount` at its iteration)."""
    parts = [torch.full((s[engine.rows(r)].shape[0],), discount(m.config, m.k, float(engine.task.gamma)),
                        dtype=s.dtype) for r, m in enumerate(engine.members)]
    return torch.cat(parts)


def _target(engine: Any) -> Network:
    """``V_target``: the stacked target critic, or the critic without gradient."""
    return engine.critic_target if engine.critic_target is not None else engine.critic.frozen()


def improve(engine: Any, s: torch.Tensor, moments: Sequence[tuple[np.ndarray, np.ndarray] | None],
            active_runs: list[int], relative_offset: float | None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor,
                                                                             torch.Tensor]:
    """PIM hook: one actor step of each active run on a fresh rollout (:func:`actor_loss`).

    Returns
    -------
    objective : torch.Tensor, shape () or (R,)
        The actor loss before the step, detached.
    states, costs, gamma : torch.Tensor
        The rollout (detached) and the rows' discount, for :func:`update`'s critic fit.
    """
    gamma = _gamma(engine, s)
    # only the runs that step draw (a run's stream does not depend on its neighbours' MVC outcomes)
    own = [mo if r in active_runs else None for r, mo in enumerate(moments)]
    draws = _draws(engine, own, s)
    # eager, or one compiled step with algorithm.compile; the rollout the critic is fitted on is the step's own
    # (its aux: the actor before the step, the same draws)
    target = _target(engine)
    loss = partial(actor_loss_at, task=engine.task, actor=engine.actor, value_target=target,
                   runs=engine.runs, relative_offset=relative_offset)
    with constants(target):  # V_target is read, not trained
        obj, (states, costs) = engine.actor_descent.minimise(loss, (s, draws, gamma), active_runs,
                                                             key=("rollout_pim", engine.runs, relative_offset))
    return obj, states, costs, gamma


def update(engine: Any, s: torch.Tensor, moments: Sequence[tuple[np.ndarray, np.ndarray] | None],
           active_runs: list[int], relative_offset: float | None) -> tuple[torch.Tensor, torch.Tensor]:
    """PEV and PIM hook: an actor step (:func:`improve`) and a critic step on the ``lambda``-returns of the same
    rollout (:func:`lambda_returns`, :func:`critic_loss`).

    Parameters
    ----------
    engine : BatchedAGPI
        The runs (stacked networks, descents, target critic, :meth:`rows`).
    s : torch.Tensor, shape (R B, state_dim)
        The batch.
    moments : sequence
        Per run its planning moments ``(mean, cov)`` of ``xi_hat_k``, ``None`` for an inactive run.
    active_runs : list of int
        The runs that step.
    relative_offset : float or None
        The state-weights hook.

    Returns
    -------
    critic_losses, actor_objectives : torch.Tensor, shape () or (R,)
        Before the steps.
    """
    algo = engine.members[0].config.algorithm
    target = _target(engine)
    obj, states, costs, gamma = improve(engine, s, moments, active_runs, relative_offset)
    with torch.no_grad():
        horizon, batch = costs.shape
        next_values = target(engine.task.observe(states[1:].reshape(horizon * batch, -1))).reshape(horizon, batch)
        targets = lambda_returns(costs, next_values, gamma, algo.rollout_lambda)
    # the critic at its parameters: eagerly, or one compiled step with algorithm.compile
    pure = partial(critic_loss_at, task=engine.task, critic=engine.critic, runs=engine.runs,
                   relative_offset=relative_offset)
    loss = engine.critic_descent.minimise(pure, (states[:-1], targets), active_runs,
                                          key=("rollout_pev", engine.runs, relative_offset))
    region.remember(engine, states[-1], active_runs)  # departure hook: the end states the next starts carry over
    anchor.remember(engine, states, active_runs)  # departure hook: the observations the actors were trained on
    return loss, obj
