"""Departure hook *anchor*, its calibration: the deployed shift corrected on the model's mean state.

``algorithm.feedforward_calibration = k`` (default 1; 0 = the shift of :func:`mixedrl.departures.anchor.steady_anchor`
alone): the ``"lq_ss"`` shift (and ``"lq_handover"``'s) is moved by ``k`` Newton steps so that the deployed closed
loop's mean state in the planning model, under the run's own noise, is the discounted LQ optimum's
(:func:`calibrate_shift`). :func:`deployed_policy` builds the deployed policy of :attr:`AGPI.policy
<mixedrl.algorithms.agpi.AGPI.policy>` with it. Training is unchanged. Measured effect: docs/precision.rst
(``experiments/results/offset_calibration``).
"""

from __future__ import annotations

import logging
from typing import Any, Sequence

import numpy as np
import scipy.linalg
import torch

from mixedrl.departures.anchor import (AffinePolicy, FeedForwardPolicy, LQReference, equilibrium_gain,
                                       feedforward_policy, handover_policy, lq_reference, own_noise)
from mixedrl.task_base import Linearisation, Task

__all__ = ["calibrate_shift", "deployed_policy", "CALIBRATION_COPIES", "CALIBRATION_HORIZON",
           "CALIBRATION_STEP"]

logger = logging.getLogger(__name__)

#: Model copies of the calibration's closed loops (:func:`calibrate_shift`).
CALIBRATION_COPIES = 256
#: Most steps of the calibration's closed loops: ``min(task.eval_horizon, CALIBRATION_HORIZON)`` (the evaluation
#: horizon of every system the calibration was chosen on; a course of 2,000 steps is not needed to see a rest point).
CALIBRATION_HORIZON = 200
#: Finite-difference step of the calibration's Jacobian, as a fraction of the action bound (of 1 where unbounded).
CALIBRATION_STEP = 1e-2
#: Mixed with the run's seed into the seed of the calibration's noise draws (a stream of its own).
_CALIBRATION_STREAM = 0x6361_6C69


def _model_means(task: Task, policies: Sequence[torch.nn.Module], start: torch.Tensor, noise: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """Closed loops of ``policies`` in the planning model ``f(s, u) + E xi`` from ``start``, each over the same
    noise ``noise`` (T, N, state_dim, already through ``E``): per policy the mean of ``task.state_error`` over the
    second half of the ``T`` steps and over the copies not yet terminal (as :meth:`Task.evaluate
    <mixedrl.task_base.Task.evaluate>` measures a steady offset), and its standard deviation there.

    Returns
    -------
    means, stds : torch.Tensor, shape (len(policies), error_dim), float64
        ``nan`` rows for a policy whose every copy terminated.
    """
    T, N = noise.shape[0], noise.shape[1]
    P, half = len(policies), T // 2
    s = start.reshape(N, -1).repeat(P, 1)
    alive = torch.ones(P * N, dtype=torch.bool)
    e0 = task.state_error(s[:1])
    total, square = torch.zeros(2, P, e0.shape[-1], dtype=torch.float64)
    count = torch.zeros(P, 1, dtype=torch.float64)
    with torch.no_grad():
        for t in range(T):
            obs = task.observe(s.float()).reshape(P, N, -1)
            u = torch.cat([pi(obs[i]) for i, pi in enumerate(policies)]).double()
            s_next = task.f(s, u) + noise[t].repeat(P, 1)
            alive = alive & ~task.is_terminal(s_next)
            s = torch.where(alive[:, None], s_next, s)
            if t >= half:
                e = torch.where(alive[:, None], task.state_error(s).double(), 0.0).reshape(P, N, -1)
                total += e.sum(1)
                square += (e ** 2).sum(1)
                count += alive.reshape(P, N).sum(1, keepdim=True)
    means = total / count  # nan where nothing survived
    stds = (square / count - means ** 2).clamp_min(0.0).sqrt()
    return means, stds


def _stationary_draws(trainer: Any, lin: Linearisation, ref: LQReference, cov: np.ndarray) -> np.ndarray:
    """:data:`CALIBRATION_COPIES` draws, in the linearisation's coordinates, of the optimum's stationary
    distribution there, ``N(x_ss, S)`` with ``S = A_c S A_c^T + E K E^T``, ``A_c = A - B L`` (the discrete Lyapunov
    equation, scipy), from the calibration's own stream; ``x_ss`` alone where ``A_c`` is not stable."""
    a_c = lin.A - lin.B @ ref.solution.gain
    n = a_c.shape[0]
    z = np.random.default_rng(_calibration_seed(trainer, 1)).standard_normal((CALIBRATION_COPIES, n))
    if np.max(np.abs(np.linalg.eigvals(a_c))) >= 1.0:
        return np.broadcast_to(ref.steady_state, (CALIBRATION_COPIES, n)).copy()
    S = scipy.linalg.solve_discrete_lyapunov(a_c, lin.E @ cov @ lin.E.T)
    vals, vecs = np.linalg.eigh((S + S.T) / 2)
    return ref.steady_state + z @ (vecs * np.sqrt(np.clip(vals, 0.0, None))).T


def _calibration_seed(trainer: Any, part: int) -> int:
    """The seed of the calibration's draws ``part`` (0: the noise, 1: the starts) for the run's seed."""
    return int(np.random.SeedSequence([int(trainer.config.seed), _CALIBRATION_STREAM, part]).generate_state(1)[0])


def calibrate_shift(trainer: Any, deploy: Any, reference: torch.nn.Module, start: torch.Tensor, mean: np.ndarray,
                    cov: np.ndarray, steps: int) -> torch.Tensor:
    r"""Implements ``algorithm.feedforward_calibration``: the correction ``delta`` of the deployed shift's action
    whose closed loop in the planning model rests, in the mean, where the LQ optimum's does.

    With ``e(delta)`` the mean of ``task.state_error`` over the second half of ``task.eval_horizon`` steps (at most
    :data:`CALIBRATION_HORIZON`) of
    :data:`CALIBRATION_COPIES` copies of ``f(s, u) + E xi``, ``xi ~ N(mean, cov)`` (the run's own noise), from
    the states ``start`` (drawn by :func:`deployed_policy` from the optimum's stationary distribution on the
    linearisation, so that the window sees the noise's full spread), under ``deploy(delta)``, and ``e_LQ`` the same under ``reference`` (the
    optimum's affine policy), each of ``steps`` Newton steps solves

    .. math:: \min_{\Delta}\ \big| W \big(e(\delta) - e_{LQ} + J \Delta\big) \big|^2,
        \qquad \delta \leftarrow \delta + \Delta

    with ``J`` the forward difference of ``e`` in each action (step :data:`CALIBRATION_STEP` of the bound) and
    ``W`` the inverse of the optimum's spread of each component. Every closed loop of a step runs over the same
    noise draws, seeded from the run's seed (a stream of their own: training's draws are untouched), so the
    differences are free of Monte-Carlo noise and a run's calibration is reproducible.

    Parameters
    ----------
    trainer : AGPI
        Has ``task`` and ``config`` (its seed).
    deploy : callable
        ``delta`` (action_dim,) float32 -> the deployed policy with the shift's action moved by ``delta``.
    reference : torch.nn.Module
        The optimum's policy on observations.
    start : torch.Tensor, shape (CALIBRATION_COPIES, state_dim)
        The states the copies start from (float64), the same for every policy.
    mean, cov : numpy.ndarray
        The noise moments, noise coordinates.
    steps : int
        Newton steps (> 0).

    Returns
    -------
    torch.Tensor, shape (action_dim,), float32
        ``delta``; zeros (with a warning) where the closed loops leave the task's states (every copy terminal).
    """
    task: Task = trainer.task
    m, d = int(task.action_dim), int(task.noise_dim)
    gen = torch.Generator().manual_seed(_calibration_seed(trainer, 0))
    horizon = min(int(task.eval_horizon), CALIBRATION_HORIZON)
    z = torch.randn(horizon, CALIBRATION_COPIES, d, generator=gen, dtype=torch.float64)
    vals, vecs = np.linalg.eigh(np.asarray(cov, dtype=np.float64).reshape(d, d))
    root = torch.as_tensor(vecs * np.sqrt(np.clip(vals, 0.0, None)), dtype=torch.float64)
    xi = torch.as_tensor(np.asarray(mean, dtype=np.float64).reshape(d)) + z @ root.T
    noise = xi @ task.noise_matrix.to(torch.float64).T
    bound = getattr(task, "action_bound", None)
    h = CALIBRATION_STEP * (torch.ones(m) if bound is None else torch.as_tensor(bound, dtype=torch.float32).reshape(m))
    delta = torch.zeros(m)
    for _ in range(steps):
        candidates = [reference, deploy(delta)] + [deploy(delta + h[j] * torch.eye(m)[j]) for j in range(m)]
        means, stds = _model_means(task, candidates, start, noise)
        if not bool(torch.isfinite(means).all()):
            logger.warning("algorithm.feedforward_calibration: a calibration closed loop left the task's states; "
                           "the shift is not corrected")
            return torch.zeros(m)
        J = (means[2:] - means[1]).T / h.double()  # (error_dim, m)
        w = 1.0 / stds[0].clamp_min(1e-9 * (1.0 + float(means[0].abs().max())))
        step = torch.linalg.lstsq(w[:, None] * J, -(w * (means[1] - means[0]))[:, None]).solution[:, 0]
        delta = delta + step.float()
    return delta


def deployed_policy(trainer: Any, policy: torch.nn.Module, lin: Linearisation, feedforward: str) -> torch.nn.Module:
    """The deployed policy of ``"lq_ss"`` or ``"lq_handover"`` (:func:`feedforward_policy`,
    :func:`handover_policy`), with the shift calibrated by :func:`calibrate_shift` when the run's
    ``algorithm.feedforward_calibration`` is positive. The calibration of the last call is kept on ``trainer``
    and reused while the actor's weights and the run's own noise are the same."""
    shifted = feedforward_policy(trainer, policy, lin)

    def deploy(delta: torch.Tensor | None) -> torch.nn.Module:
        moved = shifted if delta is None else FeedForwardPolicy(policy, shifted.observation[0], shifted.action + delta,
                                                                shifted.bound, shifted.width)
        return handover_policy(trainer, shifted, lin, moved) if feedforward == "lq_handover" else moved

    steps = trainer.config.algorithm.feedforward_calibration
    if steps == 0:
        return deploy(None)
    mean, cov = own_noise(trainer, lin, policy)
    key = (steps, tuple((id(p), p._version) for p in policy.parameters()), np.asarray(mean).tobytes(),
           np.asarray(cov).tobytes(), None if trainer.trained_box is None else trainer.trained_box.numpy().tobytes())
    cached = getattr(trainer, "_calibration", None)
    if cached is not None and cached[0] == key:
        return deploy(cached[1])
    ref = lq_reference(lin, mean, cov)
    start = lin.to_state(torch.as_tensor(_stationary_draws(trainer, lin, ref, np.asarray(cov)), dtype=torch.float64))
    reference = AffinePolicy(equilibrium_gain(trainer.task, lin), shifted.observation[0], shifted.action,
                             shifted.bound)
    delta = calibrate_shift(trainer, deploy, reference, start, np.asarray(mean), np.asarray(cov), steps)
    trainer._calibration = (key, delta)
    return deploy(delta)
