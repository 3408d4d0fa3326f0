"""Departure hook *anchor*: the deployed policy is anchored at the discounted LQ optimum of the equilibrium.

The paper's actor is an MLP ``pi(x; theta)`` (eq. 48) whose action at the task's equilibrium is whatever
training makes it (``"learned"``). This departure uses the discounted LQ optimum on the task's linearisation
(eqs. 6-7, :func:`lq_reference`) for the run's *own* noise moments (mixed RL: the IBE posterior; model-driven
RL: the prior; the oracle: the truth; :func:`own_noise`):

* ``"auto"``: ``"lq_handover"`` where the task declares an equilibrium, else ``"learned"`` (:func:`resolve`);
* ``"lq_ss"``: the deployed policy is the actor shifted to the optimum's action at the optimum's steady
  state for the own noise mean (:func:`feedforward_policy`);
* ``"lq_handover"``: ``"lq_ss"`` inside the box of observations the actor was trained on in the second half of
  its budget (:func:`remember`, :attr:`AGPI.trained_box <mixedrl.algorithms.agpi.AGPI.trained_box>`), handed
  over outside it to the optimum's affine policy (:class:`HandoverPolicy`): where the true system holds a
  state the planning model never visits (model-driven RL against an unmodelled mean), the actor's
  extrapolation is not trusted.

With ``algorithm.feedforward_calibration = k > 0`` (default 1) the ``"lq_ss"`` shift (and so ``"lq_handover"``'s) is
corrected by ``k`` Newton steps so that the deployed closed loop's mean state, simulated in the planning model
with the run's own noise, is the LQ optimum's (:mod:`mixedrl.departures.calibration`): the shift alone makes the two rest
at one point only to first order, and a curved actor under noise rests elsewhere.

Training is unchanged by every value. Config key ``algorithm.feedforward``: default ``"auto"``, the paper's
``"learned"``. Measured effect and the retired values: docs/algorithm2.rst, docs/precision.rst. Retired
(refused naming the commit that still runs each, :data:`mixedrl.config.RETIRED_FEEDFORWARDS`): ``"lq"``, the
actor shifted to the optimum's action at the equilibrium (commit c44231f); ``"lq_train"``, ``"lq_affine"``,
``"lq_affine_ss"``, actors anchored during training (commit ee954d7).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import torch

from mixedrl.config import PAPER_SETTINGS
from mixedrl.lq import LQSolution, discounted_lq_optimum
from mixedrl.task_base import Linearisation, Task

__all__ = ["NAME", "KEY", "PAPER", "active", "resolve", "LQReference", "lq_reference", "own_noise",
           "FeedForwardPolicy", "AffinePolicy", "HandoverPolicy", "feedforward_policy", "handover_policy", "equilibrium_observation",
           "equilibrium_gain", "feedforward_action", "steady_anchor", "remember"]

logger = logging.getLogger(__name__)

NAME = "anchor"
KEY = "algorithm.feedforward"
PAPER = PAPER_SETTINGS["algorithm"]["feedforward"]



def active(config: Any) -> bool:
    """Whether the run's policy is anchored at the LQ optimum (``algorithm.feedforward != "learned"``)."""
    return config.algorithm.feedforward != PAPER


def resolve(config: Any, task: Task) -> str:
    """The run's ``algorithm.feedforward`` with ``"auto"`` resolved: ``"lq_handover"`` for Algorithm 2 on a task
    that declares an equilibrium (:meth:`mixedrl.task_base.Task.equilibrium`) whose LQ problem solves and whose
    observations determine the linearisation's coordinates (:func:`equilibrium_gain`), ``"lq_ss"`` where only
    the latter fails, ``"learned"`` where the LQ problem fails (a failure is logged as a warning naming the
    reason) and for DDPG (no noise model to take the mean from); any other value as set."""
    value = config.algorithm.feedforward
    if value != "auto":
        return value
    if config.method == "ddpg" or task.equilibrium() is None:
        return "learned"
    try:
        lin = task.linearisation()
        lq_reference(lin, task.prior_mean, task.prior_cov)
    except (ValueError, np.linalg.LinAlgError) as err:
        logger.warning("algorithm.feedforward 'auto': no LQ problem at the task's equilibrium (%s: %s); the "
                       "learned feed-forward is deployed", type(err).__name__, err)
        return "learned"
    try:
        equilibrium_gain(task, lin)
    except ValueError as err:
        logger.warning("algorithm.feedforward 'auto': no hand-over to the LQ optimum (%s); 'lq_ss' is deployed", err)
        return "lq_ss"
    return "lq_handover"


@dataclass(frozen=True)
class LQReference:
    """The discounted LQ optimum at an equilibrium for one noise mean (:func:`lq_reference`).

    Attributes
    ----------
    solution : LQSolution
        ``L``, ``l0``, ``P``, ``p``, ``c``, ``S`` in the linearisation's coordinates.
    action : numpy.ndarray, shape (action_dim,)
        ``u* - l0``: the optimal action at the equilibrium.
    steady_state : numpy.ndarray, shape (n,)
        ``x_ss = (I - A + B L)^{-1} (E mu - B l0)``: the mean state the optimum holds under its own mean.
    steady_action : numpy.ndarray, shape (action_dim,)
        ``u* - L x_ss - l0``: its action there (the action that cancels the mean: ``B v_ss = -(A - I) x_ss - E mu``).
    """

    solution: LQSolution
    action: np.ndarray
    steady_state: np.ndarray
    steady_action: np.ndarray


def noise_vector(value: Any, size: int, name: str) -> np.ndarray:
    """``value`` as a vector of ``size`` finite floats (noise coordinates), else a ``ValueError`` naming ``name``."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (size,) or not np.isfinite(arr).all():
        raise ValueError(f"{name}: expected {size} finite numbers (noise coordinates), got shape {arr.shape}")
    return arr


def lq_reference(lin: Linearisation, noise_mean: Any, noise_cov: Any = None) -> LQReference:
    """Implements the discounted LQ optimum (eqs. 6-7) on a task's linearisation for a noise mean.

    .. math::

        v = -L x - l_0, \\qquad [L, l_0, P, p, c] = \\mathrm{LQ}(A, B, Q, R, \\gamma;\\ E\\mu, E K E^T),
        \\qquad x_{ss} = (I - A + B L)^{-1} (E\\mu - B l_0)

    (:func:`mixedrl.lq.discounted_lq_optimum`: the DARE with ``(sqrt(gamma) A, sqrt(gamma) B, Q,
    gamma R)`` and the feed-forward's linear system).

    Parameters
    ----------
    lin : Linearisation
        From :meth:`mixedrl.tasks.Task.linearisation`; ``A`` (n, n), ``B`` (n, m), ``E`` (n, d).
    noise_mean : array_like, shape (d,)
        The noise mean ``mu`` in noise coordinates.
    noise_cov : array_like, shape (d, d), optional
        The noise covariance ``K`` (only the constant ``c`` depends on it); default 0.

    Returns
    -------
    LQReference

    Raises
    ------
    ValueError
        ``noise_mean`` / ``noise_cov`` of the wrong shape or not finite, or the DARE has no stabilising
        solution (the message names ``Q``).
    """
    d = lin.E.shape[1]
    mu = noise_vector(noise_mean, d, "noise_mean")
    K = np.zeros((d, d)) if noise_cov is None else np.asarray(noise_cov, dtype=np.float64)
    if K.shape != (d, d) or not np.isfinite(K).all():
        raise ValueError(f"noise_cov: expected a finite ({d}, {d}) matrix, got shape {K.shape}")
    mean_x, cov_x = lin.E @ mu, lin.E @ K @ lin.E.T
    sol = discounted_lq_optimum(lin.A, lin.B, lin.Q, lin.R, lin.gamma, mean_x, cov_x)
    n = lin.A.shape[0]
    # x_ss = A x_ss + B (-L x_ss - l0) + E mu  =>  (I - A + B L) x_ss = E mu - B l0
    x_ss = np.linalg.solve(np.eye(n) - lin.A + lin.B @ sol.gain, mean_x - lin.B @ sol.offset)
    u_star = np.asarray(lin.action, dtype=np.float64)
    return LQReference(solution=sol, action=u_star - sol.offset, steady_state=x_ss,
                       steady_action=u_star - sol.gain @ x_ss - sol.offset)


def own_noise(trainer: Any, lin: Linearisation, policy: torch.nn.Module | None = None
              ) -> tuple[np.ndarray | None, np.ndarray]:
    """The noise moments a trainer planned with at the end, at the equilibrium of ``lin``.

    With a noise source (Algorithm 2: mixed, model, oracle) the planning moments
    (:meth:`~mixedrl.algorithms.agpi.AGPI.noise_moments`; for a state-dependent source
    :meth:`~mixedrl.algorithms.agpi.AGPI.planning_moments` at the equilibrium, with ``policy``'s action
    there, default the trainer's learned policy); without one (DDPG) ``(None, task.true_cov)``: the caller
    takes the true mean.

    Returns
    -------
    mean : numpy.ndarray, shape (noise_dim,), or None
    cov : numpy.ndarray, shape (noise_dim, noise_dim)
    """
    noise = getattr(trainer, "noise", None)
    if noise is None:
        return None, np.asarray(trainer.task.true_cov, dtype=np.float64)
    if getattr(noise, "state_dependent", False):
        policy = getattr(trainer, "learned_policy", trainer.policy) if policy is None else policy
        s = torch.as_tensor(np.asarray(lin.state, dtype=np.float64))[None].float()
        with torch.no_grad():
            m, cov = trainer.planning_moments(s, policy(trainer.task.observe(s)))
        return np.asarray(m[0], dtype=np.float64), np.asarray(cov, dtype=np.float64)
    return trainer.noise_moments()


class FeedForwardPolicy(torch.nn.Module):
    """A policy shifted by a constant so that it takes a given action at a given observation.

    .. math:: \\pi_{ff}(o) = \\operatorname{clip}\\big(\\pi(o) - \\pi(o^*) + u_{ff},\\ -\\bar u,\\ \\bar u\\big)

    with ``o*`` the anchor's observation (``"lq_ss"``: the LQ optimum's steady state's, :func:`steady_anchor`) and
    ``u_ff`` the action wanted there (:func:`feedforward_policy`). The shift is recomputed from ``policy`` at every
    call, so the wrapper follows the wrapped module's weights; it has no parameters of its own.

    Parameters
    ----------
    policy : torch.nn.Module
        Observations (B, obs_dim) float32 -> actions (B, action_dim).
    observation : torch.Tensor, shape (obs_dim,)
        ``o*``.
    action : torch.Tensor, shape (action_dim,)
        ``u_ff``.
    bound : torch.Tensor, shape (action_dim,), optional
        The action bound ``u_bar`` (the actor's); default none.
    width : torch.Tensor, shape (obs_dim,), optional
        With it the shift is local: multiplied by ``w(o) = exp(-|(o - o*) / width|^2 / 2)`` (1 at ``o*``, with
        zero slope there, so the action and the gain at ``o*`` are as above; far from ``o*`` the policy is
        ``policy``'s own). Default: the shift is constant.
    """

    def __init__(self, policy: torch.nn.Module, observation: torch.Tensor, action: torch.Tensor,
                 bound: torch.Tensor | None = None, width: torch.Tensor | None = None) -> None:
        super().__init__()
        self.policy = policy
        self.register_buffer("observation", torch.as_tensor(observation, dtype=torch.float32).reshape(1, -1).clone())
        self.register_buffer("action", torch.as_tensor(action, dtype=torch.float32).reshape(-1).clone())
        self.bound = None if bound is None else torch.as_tensor(bound, dtype=torch.float32)
        self.width = None if width is None else torch.as_tensor(width, dtype=torch.float32).reshape(-1)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        shift = self.action - self.policy(self.observation)[0]
        if self.width is not None:
            distance = (obs - self.observation[0]) / self.width  # obs batched (B, obs_dim) or one (obs_dim,)
            shift = shift * torch.exp(-0.5 * (distance ** 2).sum(-1, keepdim=True))
        u = self.policy(obs) + shift
        return u if self.bound is None else torch.maximum(torch.minimum(u, self.bound), -self.bound)


class AffinePolicy(torch.nn.Module):
    """The discounted LQ optimum's affine policy in observations, ``clip(u_a + G (o - o_a), -u_bar, u_bar)``
    (unclipped without ``bound``): :class:`HandoverPolicy`'s outer policy and the calibration's reference closed
    loop (:mod:`mixedrl.departures.calibration`)."""

    def __init__(self, gain: torch.Tensor, observation: torch.Tensor, action: torch.Tensor,
                 bound: torch.Tensor | None = None) -> None:
        super().__init__()
        f32 = dict(dtype=torch.float32)
        self.gain = torch.as_tensor(gain, **f32)
        self.observation = torch.as_tensor(observation, **f32).reshape(-1)
        self.action = torch.as_tensor(action, **f32).reshape(-1)
        self.bound = None if bound is None else torch.as_tensor(bound, **f32)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        u = self.action + (obs - self.observation) @ self.gain.T
        return u if self.bound is None else torch.maximum(torch.minimum(u, self.bound), -self.bound)


class HandoverPolicy(torch.nn.Module):
    """A policy inside a box of observations, handed over to an affine policy outside it (``"lq_handover"``).

    .. math::

        \\pi_h(o) = \\operatorname{clip}\\big(w(o)\\, \\pi(o) + (1 - w(o))\\, (u_a + G (o - o_a)),\\ -\\bar u,\\ \\bar u\\big),
        \\qquad w(o) = \\exp\\Big(-\\tfrac12 \\big|d(o) / \\rho\\big|^2\\Big)

    with ``d_i(o) = max(0, o_i - high_i) + max(0, low_i - o_i)`` the distance outside the box ``[low, high]``
    and the affine policy the discounted LQ optimum's ``u* - l0 - L x`` written in observations: ``G`` its gain
    (:func:`equilibrium_gain`), ``u_a`` its action at ``o_a`` (:func:`steady_anchor`). Inside the box the
    policy is ``pi``'s, exactly. ``width`` (``rho``) ``None``: ``w`` drops from 1 to 0 at the box's edge.

    Parameters
    ----------
    policy : torch.nn.Module
        Observations (B, obs_dim) or (obs_dim,) -> actions.
    low, high : torch.Tensor, shape (obs_dim,)
        The box.
    gain : torch.Tensor, shape (action_dim, obs_dim)
    observation : torch.Tensor, shape (obs_dim,)
    action : torch.Tensor, shape (action_dim,)
    width : torch.Tensor, shape (obs_dim,), optional
    bound : torch.Tensor, shape (action_dim,), optional
    """

    def __init__(self, policy: torch.nn.Module, low: torch.Tensor, high: torch.Tensor, gain: torch.Tensor,
                 observation: torch.Tensor, action: torch.Tensor, width: torch.Tensor | None = None,
                 bound: torch.Tensor | None = None) -> None:
        super().__init__()
        self.policy = policy
        f32 = dict(dtype=torch.float32)
        self.low, self.high = torch.as_tensor(low, **f32).reshape(-1), torch.as_tensor(high, **f32).reshape(-1)
        self.affine = AffinePolicy(gain, observation, action)
        self.width = None if width is None else torch.as_tensor(width, **f32).reshape(-1)
        self.bound = None if bound is None else torch.as_tensor(bound, **f32)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        u = self.policy(obs)
        distance = torch.relu(obs - self.high) + torch.relu(self.low - obs)
        outside = (distance > 0).any(-1, keepdim=True)
        if not bool(outside.any()):
            return u
        w = (torch.zeros_like(distance[..., :1]) if self.width is None
             else torch.exp(-0.5 * ((distance / self.width) ** 2).sum(-1, keepdim=True)))
        blend = w * u + (1.0 - w) * self.affine(obs)
        if self.bound is not None:
            blend = torch.maximum(torch.minimum(blend, self.bound), -self.bound)
        return torch.where(outside, blend, u)  # inside the box: pi's action, bit for bit


def feedforward_policy(trainer: Any, policy: torch.nn.Module, lin: Linearisation | None = None
                       ) -> FeedForwardPolicy:
    """``policy`` shifted, near the LQ optimum's steady state for the trainer's own noise mean, to the optimum's
    action there (``algorithm.feedforward = "lq_ss"``, :func:`steady_anchor`), within the run's
    ``algorithm.feedforward_width``.

    Parameters
    ----------
    trainer : AGPI
        Has ``task`` and a noise source.
    policy : torch.nn.Module
        The learned policy.
    lin : Linearisation, optional
        Instead of ``trainer.task.linearisation()``.

    Raises
    ------
    ValueError
        If the task has no equilibrium (naming ``algorithm.feedforward``), or as :func:`lq_reference`.
    """
    task: Task = trainer.task
    lin = linearisation(task, "lq_ss") if lin is None else lin
    obs, action = steady_anchor(trainer, lin, policy)
    rho = float(trainer.config.algorithm.feedforward_width)
    width = rho * task.obs_scale if rho > 0 else None
    bound = getattr(policy, "action_bound", None)
    return FeedForwardPolicy(policy, obs, action, bound, width)


def handover_policy(trainer: Any, shifted: FeedForwardPolicy, lin: Linearisation,
                    inside: torch.nn.Module | None = None) -> torch.nn.Module:
    """``"lq_handover"``'s deployed policy: ``inside`` (default ``shifted``, the ``"lq_ss"`` policy of
    :func:`feedforward_policy`) inside the run's :attr:`~mixedrl.algorithms.agpi.AGPI.trained_box`, handed over
    outside it to the discounted LQ optimum's affine policy through ``shifted``'s anchor, with ``shifted``'s width
    (:class:`HandoverPolicy`); ``inside`` itself while the run has no box (before its first iteration)."""
    inside = shifted if inside is None else inside
    box = trainer.trained_box
    if box is None:
        return inside
    return HandoverPolicy(inside, box[0], box[1], equilibrium_gain(trainer.task, lin), shifted.observation[0],
                          shifted.action, shifted.width, shifted.bound)


def remember(engine: Any, states: torch.Tensor, active_runs: Sequence[int]) -> None:
    """Hook of the loop: widen each active run's :attr:`trained_box` to the observations of the states its actor was
    trained on this iteration (the rollouts' states, or the batch of the one-step learner), on a task that declares
    an equilibrium (``run.records_box``), whatever the run deploys.

    The box covers the second half of the run's budget: at iteration ``k = iterations // 2`` it starts afresh
    (the early iterates' states, under a policy since trained away, do not count). Non-finite observations are
    left out.

    Parameters
    ----------
    engine : BatchedAGPI
        The runs (``members``, ``task``, :meth:`rows`).
    states : torch.Tensor, shape (..., R B, state_dim)
        The states, run ``r`` in ``engine.rows(r)`` of the second-to-last dimension.
    active_runs : sequence of int
    """
    if not engine.members[0].records_box:  # the runs share the task
        return
    with torch.no_grad():  # every run's rows observed in one call
        observed = engine.task.observe(states.reshape(-1, states.shape[-1])).float()
    observed = observed.reshape(*states.shape[:-1], observed.shape[-1])
    for r in active_runs:
        m = engine.members[r]
        obs = observed[..., engine.rows(r), :].reshape(-1, observed.shape[-1])
        obs = obs[torch.isfinite(obs).all(-1)]
        if obs.shape[0] == 0:
            continue
        low, high = obs.min(0).values, obs.max(0).values
        if m.trained_box is not None and m.k != m.config.algorithm.iterations // 2:
            low, high = torch.minimum(m.trained_box[0], low), torch.maximum(m.trained_box[1], high)
        m.trained_box = torch.stack([low, high])


def linearisation(task: Task, feedforward: str) -> Linearisation:
    """``task.linearisation()``, or a ``ValueError`` naming ``algorithm.feedforward`` (of value ``feedforward``)
    for a task without an equilibrium."""
    lin = task.linearisation()
    if lin is None:
        raise ValueError(f"algorithm.feedforward: {feedforward!r} needs a task with an equilibrium (Task.equilibrium); "
                         f"task {getattr(task, 'name', type(task).__name__)!r} defines none")
    return lin


def equilibrium_observation(task: Task, lin: Linearisation) -> torch.Tensor:
    """``o* = task.observe(s*)`` at the equilibrium of ``lin``, shape (obs_dim,) float32."""
    return task.observe(lin.to_state(torch.zeros(1, lin.A.shape[0], dtype=torch.float64)).float())[0]


def equilibrium_gain(task: Task, lin: Linearisation) -> torch.Tensor:
    """The LQ optimum's feedback gain in observation coordinates at the equilibrium (the LQR's,
    :class:`mixedrl.precision.LQRPolicy`).

    .. math:: G = -L\\, J_o^{+}, \\qquad J_o = \\frac{\\partial\\, o(s(x))}{\\partial x}\\Big|_{x=0}

    (``L`` of :func:`lq_reference`, which does not depend on the noise; ``J_o^+`` the pseudo-inverse), so
    a policy with ``du/do (o*) = G`` has ``du/dx (0) = G J_o = -L``: the optimum's gain, when the
    observation determines the coordinates to first order (``J_o`` of full column rank).

    Returns
    -------
    torch.Tensor, shape (action_dim, obs_dim), float64

    Raises
    ------
    ValueError
        If ``J_o`` is not of full column rank, or as :func:`lq_reference`.
    """
    n = lin.A.shape[0]
    J_o = torch.func.jacrev(lambda x: task.observe(lin.to_state(x[None]))[0])(
        torch.zeros(n, dtype=torch.float64)).detach().double().numpy()
    if np.linalg.matrix_rank(J_o) < n:
        raise ValueError(f"task: the LQ gain in observation coordinates needs observations that determine the "
                         f"linearisation's {n} coordinates at the equilibrium; d o / d x there has rank "
                         f"{np.linalg.matrix_rank(J_o)}")
    L = lq_reference(lin, np.zeros(lin.E.shape[1])).solution.gain
    return torch.as_tensor(-L @ np.linalg.pinv(J_o))


def feedforward_action(trainer: Any, lin: Linearisation, policy: torch.nn.Module | None = None) -> torch.Tensor:
    """The feed-forward ``u_ff = u* - l0(E mu)`` of :func:`lq_reference` for the trainer's own noise
    (:func:`own_noise`; ``policy`` as there), shape (action_dim,) float64.

    Raises
    ------
    ValueError
        If the trainer has no noise model (naming ``algorithm.feedforward``), or as :func:`lq_reference`.
    """
    return torch.as_tensor(_own_reference(trainer, lin, policy).action)


def _own_reference(trainer: Any, lin: Linearisation, policy: torch.nn.Module | None = None) -> LQReference:
    """:func:`lq_reference` for the trainer's own noise moments (:func:`own_noise`); an error naming
    ``algorithm.feedforward`` for a trainer without a noise model."""
    mean, cov = own_noise(trainer, lin, policy)
    if mean is None:
        raise ValueError("algorithm.feedforward: the LQ feed-forward needs the method's noise model; this trainer "
                         "has none")
    return lq_reference(lin, mean, cov)


def steady_anchor(trainer: Any, lin: Linearisation, policy: torch.nn.Module | None = None
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """The anchor of ``algorithm.feedforward = "lq_ss"``: the observation of the LQ optimum's steady state
    for the trainer's own noise (:func:`own_noise`; ``policy`` as there) and the optimum's action there
    (:attr:`LQReference.steady_state`, :attr:`LQReference.steady_action`).

    .. math:: o^* = o\\big(s(x_{ss})\\big), \\qquad u(o^*) = u^* - L x_{ss} - l_0

    The optimum's affine policy ``u* - l0 - L x`` takes this action at ``x_ss``: a policy shifted to it there
    (:func:`feedforward_policy`) rests where the optimum's closed loop does, to first order.

    Returns
    -------
    obs : torch.Tensor, shape (obs_dim,), float32
    action : torch.Tensor, shape (action_dim,), float64

    Raises
    ------
    ValueError
        As :func:`feedforward_action`.
    """
    ref = _own_reference(trainer, lin, policy)
    x_ss = torch.as_tensor(ref.steady_state, dtype=torch.float64)[None]
    obs = trainer.task.observe(lin.to_state(x_ss).float())[0]
    return obs, torch.as_tensor(ref.steady_action)
