"""The precision yardstick (docs/precision.rst): a learned policy at the equilibrium against the discounted LQ optimum.

For a task's linearisation at its equilibrium (:meth:`mixedrl.tasks.Task.linearisation`: ``x' = A x + B v + E xi``,
``v = u - u*``) and a noise mean ``mu``, the optimum (eqs. 6-7; :func:`mixedrl.lq.discounted_lq_optimum`) is

.. math:: v = -L x - l_0(E\\mu), \\qquad V^*(x) = x^T P x + 2 p^T x + c(E\\mu, E K E^T),

so at the equilibrium (``x = 0``) the optimal action is ``u* - l0`` and the optimal value is ``c``. Evaluation
only: nothing here touches a trainer's weights, generators or buffers.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np
import torch

from mixedrl.pev import evaluate_policy
from mixedrl.quadratic import AffinePolicy, LinearDynamics, QuadraticCost
from mixedrl.tasks import Linearisation, Task
from mixedrl.departures.anchor import (FeedForwardPolicy, LQReference, equilibrium_gain, equilibrium_observation,
                                      feedforward_action, feedforward_policy, lq_reference, noise_vector, own_noise,
                                      steady_anchor)

__all__ = ["LQReference", "lq_reference", "policy_gap", "run_policy_gap", "own_noise", "FeedForwardPolicy",
           "feedforward_policy", "equilibrium_observation", "equilibrium_gain", "steady_anchor",
           "feedforward_action", "gap_summary", "format_policy_gap", "VALUE_NOTE", "LQRPolicy", "run_references"]

#: What the ``value`` entries of :func:`policy_gap` compare (also in ``results.json``).
VALUE_NOTE = ("value: the critic at the equilibrium (V(x*), for DDPG Q(x*, pi(x*))) on the nonlinear model; "
              "optimum_value: c = V*(0) of the LQ optimum on the linearisation with the method's own N(mu, K); "
              "linearised_policy_value: the exact value at 0 on the same LQ problem of the policy's affine "
              "approximation at the equilibrium (action and Jacobian there); value_regret = "
              "linearised_policy_value - optimum_value >= 0. value vs optimum_value agree only as far as the "
              "linearisation holds and the critic's V(x*) is not an average over contexts it cannot see.")


def _true_mean(task: Task, lin: Linearisation) -> np.ndarray:
    """``task.true_mean_at`` the equilibrium ``(lin.state, lin.action)``, shape (noise_dim,)."""
    s_star = torch.as_tensor(np.asarray(lin.state, dtype=np.float64))[None]
    return task.true_mean_at(s_star, torch.as_tensor(np.asarray(lin.action, dtype=np.float64))[None])[0].numpy()


def policy_gap(task: Task, policy: torch.nn.Module, noise_mean: Any, noise_cov: Any = None, *,
               value: Callable[[torch.Tensor], torch.Tensor] | None = None, true_mean: Any = None,
               lin: Linearisation | None = None) -> dict[str, Any] | None:
    """Implements the precision yardstick: ``policy`` at the task's equilibrium against the LQ optimum.

    .. math::

        \\Delta u = \\pi(o(s^*)) - (u^* - l_0(E\\mu)), \\qquad
        \\Delta u_{true} = \\pi(o(s^*)) - (u^* - l_0(E\\mu_{true}))

    per action component, and the values of :data:`VALUE_NOTE`.

    Parameters
    ----------
    task : Task
        The task; its :meth:`~mixedrl.tasks.Task.linearisation` (or ``lin``) defines the equilibrium.
    policy : torch.nn.Module
        Observations (B, obs_dim) float32 -> actions (B, action_dim).
    noise_mean : array_like, shape (noise_dim,)
        The noise mean the policy was trained for (the method's own).
    noise_cov : array_like, shape (noise_dim, noise_dim), optional
        Its covariance (for the values' constant term); default 0.
    value : callable, optional
        Observations (B, obs_dim) float32 -> values (B,): the learned critic at the equilibrium.
    true_mean : array_like, shape (noise_dim,), optional
        The true noise mean at the equilibrium; default ``task.true_mean_at`` there.
    lin : Linearisation, optional
        Instead of ``task.linearisation()``.

    Returns
    -------
    dict or None
        ``None`` if the task has no equilibrium; else JSON-ready lists and floats:
        ``action``, ``optimum_action``, ``action_error``, ``optimum_action_true_mean``,
        ``action_error_true_mean`` (each (action_dim,)), ``max_abs_action_error``, ``gain`` (the policy's
        ``du/dx`` at ``x = 0``, (action_dim, n)), ``optimum_gain`` (``-L``), ``gain_error_rel``
        (``||gain + L|| / ||L||``, Frobenius), ``noise_mean``,
        ``true_mean``, ``optimum_steady_state`` (the optimum's ``x_ss``), ``state`` and ``observation`` at
        the equilibrium, ``value``, ``optimum_value``, ``linearised_policy_value``, ``value_regret``
        (``None`` where not available, e.g. a linearised policy that does not stabilise the LQ problem),
        ``value_note``.

    Raises
    ------
    ValueError
        As :func:`lq_reference`, or from :meth:`~mixedrl.tasks.Task.linearisation`.
    """
    lin = task.linearisation() if lin is None else lin
    if lin is None:
        return None
    d = lin.E.shape[1]
    mu = noise_vector(noise_mean, d, "noise_mean")
    K = np.zeros((d, d)) if noise_cov is None else np.asarray(noise_cov, dtype=np.float64)
    u_star = np.asarray(lin.action, dtype=np.float64)
    mu_true = noise_vector(_true_mean(task, lin) if true_mean is None else true_mean, d, "true_mean")
    own, truth = lq_reference(lin, mu, K), lq_reference(lin, mu_true)

    def act(x: torch.Tensor) -> torch.Tensor:
        """``x (n,) float64 -> pi(observe(s(x)))`` (m,) float64, with float32 observations as in training."""
        return policy(task.observe(lin.to_state(x[None].to(torch.float64)).float()))[0].double()

    x0 = torch.zeros(lin.A.shape[0], dtype=torch.float64)
    obs = task.observe(lin.to_state(x0[None]).float())
    with torch.no_grad():
        a = act(x0).numpy()
        v = None if value is None else float(value(obs)[0])
    # the policy's affine approximation at x = 0: v = (a - u*) + J x  ->  AffinePolicy(L = -J, l0 = u* - a)
    J = torch.func.jacrev(act)(x0).detach().numpy()
    try:
        lin_value = evaluate_policy(LinearDynamics(lin.A, lin.B), QuadraticCost(lin.Q, lin.R), lin.gamma,
                                    AffinePolicy(-J, u_star - a), lin.E @ mu, lin.E @ K @ lin.E.T)
        v_lin: float | None = float(lin_value.c)
    except ValueError:  # the linearised policy does not stabilise the discounted LQ problem
        v_lin = None
    c = float(own.solution.c)
    err, err_true = a - own.action, a - truth.action
    return {
        "noise_mean": mu.tolist(),
        "true_mean": mu_true.tolist(),
        "state": lin.state.tolist(),
        "observation": obs[0].double().tolist(),
        "action": a.tolist(),
        "optimum_action": own.action.tolist(),
        "action_error": err.tolist(),
        "optimum_action_true_mean": truth.action.tolist(),
        "action_error_true_mean": err_true.tolist(),
        "max_abs_action_error": float(np.max(np.abs(err))),
        "gain": J.tolist(),
        "optimum_gain": (-own.solution.gain).tolist(),
        "gain_error_rel": float(np.linalg.norm(J + own.solution.gain) / max(np.linalg.norm(own.solution.gain), 1e-300)),
        "optimum_steady_state": own.steady_state.tolist(),
        "value": v,
        "optimum_value": c if math.isfinite(c) else None,
        "linearised_policy_value": v_lin,
        "value_regret": None if v_lin is None else v_lin - c,
        "value_note": VALUE_NOTE,
    }


def _linearised(task: Task) -> tuple[Linearisation | None, str | None]:
    """``(task.linearisation(), None)``, or ``(None, reason)`` when the task has no equilibrium or its
    linearisation fails (a ``ValueError``, or a ``RuntimeError`` of autograd on a non-differentiable ``f``/``cost``)."""
    try:
        lin = task.linearisation()
    except (ValueError, RuntimeError) as exc:  # RuntimeError: f or cost not differentiable by torch.func
        return None, f"no linearisation at the equilibrium: {type(exc).__name__}: {exc}"
    if lin is None:
        return None, f"task {getattr(task, 'name', type(task).__name__)!r} defines no equilibrium (Task.equilibrium)"
    return lin, None


def run_policy_gap(trainer: Any, policy: torch.nn.Module | None = None) -> tuple[dict[str, Any] | None, str | None]:
    """:func:`policy_gap` of a trainer's policy for the method's own noise mean, or ``(None, reason)``.

    The method's own noise is that of :func:`own_noise` (DDPG, without a noise model: the true mean and
    covariance). The value is the critic at the equilibrium (DDPG's ``Q(x*, pi(x*))``).

    Parameters
    ----------
    trainer : AGPI or DDPG
        Anything with ``task``, ``policy`` and ``critic``.
    policy : torch.nn.Module, optional
        The policy to measure; default ``trainer.policy`` (what is evaluated: with ``algorithm.feedforward
        = "lq_ss"`` the shifted actor; pass ``trainer.learned_policy`` for the actor's own).

    Returns
    -------
    tuple
        ``(policy_gap dict, None)``, or ``(None, reason)`` when the task has no equilibrium, its
        linearisation fails (``ValueError``, or autograd's ``RuntimeError`` on a non-differentiable ``f`` or
        ``cost``) or the LQ problem at it has no solution. It does not raise for those, so a finished run
        always writes its results.
    """
    task: Task = trainer.task
    policy = trainer.policy if policy is None else policy
    lin, reason = _linearised(task)
    if lin is None:
        return None, reason
    critic = getattr(trainer, "critic", None)
    mean, cov = own_noise(trainer, lin, policy)
    ddpg = critic is not None and getattr(trainer, "noise", None) is None
    value = (lambda o: critic(o, policy(o))) if ddpg else critic  # DDPG's V(x*) = Q(x*, pi(x*))
    mean = _true_mean(task, lin) if mean is None else mean
    try:
        return policy_gap(task, policy, mean, cov, value=value, lin=lin), None
    except (ValueError, RuntimeError) as exc:
        return None, f"no LQ optimum at the equilibrium: {type(exc).__name__}: {exc}"


class LQRPolicy(torch.nn.Module):
    """The discounted LQR at the task's equilibrium with a noise mean's feed-forward, as a policy on observations.

    .. math:: u = \\operatorname{clip}\\big(u_{ff} + G\\,(o - o^*),\\ -\\bar u,\\ \\bar u\\big)

    with ``u_ff = u* - l0(E mu)`` the LQ optimum's action at the equilibrium for the mean ``mu``
    (:func:`lq_reference`) and ``G`` its gain in observation coordinates (:func:`equilibrium_gain`).

    Parameters
    ----------
    task : Task
        A task with an equilibrium (:meth:`~mixedrl.tasks.Task.linearisation` not ``None``).
    mean : array_like, shape (noise_dim,)
        The noise mean of the feed-forward.
    lin : Linearisation, optional
        Instead of ``task.linearisation()``.

    Raises
    ------
    ValueError
        If the task has no equilibrium, or as :func:`lq_reference`.
    """

    def __init__(self, task: Task, mean: Any, lin: Linearisation | None = None) -> None:
        super().__init__()
        lin = task.linearisation() if lin is None else lin
        if lin is None:
            raise ValueError(f"task: {getattr(task, 'name', type(task).__name__)!r} defines no equilibrium "
                             "(Task.equilibrium), so it has no LQR")
        self.register_buffer("u_ff", torch.as_tensor(lq_reference(lin, mean).action, dtype=torch.float32))
        self.register_buffer("gain", equilibrium_gain(task, lin).float())
        self.register_buffer("o_star", equilibrium_observation(task, lin))
        self.register_buffer("bound", torch.as_tensor(task.action_bound, dtype=torch.float32))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        u = self.u_ff + (obs - self.o_star) @ self.gain.T
        return torch.clamp(u, -self.bound, self.bound)


def run_references(trainer: Any, seeds: list[int]) -> tuple[dict[str, Any] | None, str | None]:
    """The yardstick of a run: the discounted LQR with the true mean's feed-forward (:class:`LQRPolicy`),
    evaluated like the run (its task, its evaluation seeds, :meth:`mixedrl.tasks.Task.evaluate`), so the run's
    evaluated cost can be read against it. The evaluation is simulated and not counted among the run's
    evaluation transitions.

    Returns
    -------
    tuple
        ``({"lqr_true_mean": {...}}, None)`` (the evaluation's numbers), or ``(None, reason)`` when the task
        has no equilibrium, declares the LQR no yardstick (``Task.lqr_reference`` false, as the double lane
        change, whose course is not an equilibrium), has a state-dependent true mean, is evaluated on a
        plant, or its LQ problem has no solution.
    """
    task: Task = trainer.task
    name = getattr(task, "name", type(task).__name__)
    if not getattr(task, "lqr_reference", True):
        return None, f"task {name!r} declares the LQR at its equilibrium no yardstick (Task.lqr_reference)"
    if getattr(task, "true_mean_varies", False):
        return None, f"task {name!r} has a state-dependent true mean: no constant feed-forward"
    if getattr(task, "plant_evaluation", "simulated") != "simulated":
        return None, "the run is evaluated on a plant: a reference would cost plant transitions"
    lin, reason = _linearised(task)
    if lin is None:
        return None, reason
    try:
        policy = LQRPolicy(task, task.true_mean, lin)
    except (ValueError, np.linalg.LinAlgError) as exc:
        return None, f"no discounted LQ optimum at the equilibrium: {type(exc).__name__}: {exc}"
    counted = (task.evaluation_transitions, task.last_evaluation_counts)
    try:
        ev = task.evaluate(policy, list(seeds))
    finally:  # the yardstick's steps are not the run's evaluation transitions
        task.evaluation_transitions, task.last_evaluation_counts = counted
    return {"lqr_true_mean": {k: float(v) for k, v in ev.items() if isinstance(v, (int, float, np.floating))}}, None


#: The entries of a ``policy_gap`` that the command line shows (:func:`gap_summary`).
SUMMARY_KEYS = ("action_error", "action_error_true_mean", "value_regret")


def gap_summary(gap: dict[str, Any] | None) -> dict[str, Any] | None:
    """The entries :data:`SUMMARY_KEYS` of a :func:`policy_gap` result (``None`` stays ``None``)."""
    return None if gap is None else {k: gap[k] for k in SUMMARY_KEYS}


def format_policy_gap(gap: dict[str, Any] | None, reason: str | None = None) -> str:
    """One line for the command line: the action error per component (own mean, true mean) and the regret."""
    if gap is None:
        return f"policy_gap: n/a ({reason or 'no equilibrium'})"
    own, true = (", ".join(f"{e:+.4g}" for e in gap[key]) for key in ("action_error", "action_error_true_mean"))
    tail = "" if gap["value_regret"] is None else f"; LQ value regret {gap['value_regret']:.3g}"
    return f"policy_gap: action - LQ optimum at the equilibrium [{own}] (own mean), [{true}] (true mean){tail}"
