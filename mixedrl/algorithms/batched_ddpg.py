"""Many DDPG runs as one computation: :class:`BatchedDDPG`.

``R`` runs of the data-driven baseline (:class:`~mixedrl.algorithms.ddpg.DDPG`) that share
:data:`~mixedrl.algorithms.batched.DDPG_SHARED_FIELDS` are trained together. Each run keeps its environment
copies, replay buffer, generator, Adam states, schedule, budget, counters, checkpoints and run directory;
what is shared is the arithmetic of the updates:

* the critics, the actors and their target networks are stacked
  (:class:`~mixedrl.algorithms.batched.StackedNetwork`) and each run's modules are rebound to views of the
  stacked tensors, so they keep working alone (exploration, evaluation, saving, the soft target updates);
* each run draws its minibatch from its own buffer; the ``R`` minibatches are concatenated (run ``r`` in rows
  ``r B .. (r + 1) B - 1``) and the TD targets and losses are evaluated once, one loss per run;
* each run takes its own clipped Adam step (:func:`mixedrl.schedule.descend`) and its own soft target update.

A run's data (:meth:`~mixedrl.algorithms.ddpg.DDPG.explore`) come from its own modules and generator in the
order of the run alone. An inactive run (budget reached) draws nothing, takes no step and keeps its targets
and counters. ``R = 1`` is :meth:`~mixedrl.algorithms.ddpg.DDPG.iteration` on the run's own modules;
reproducibility as for Algorithm 2 (docs/algorithm2.rst, "DDPG batches").
"""

from __future__ import annotations

from functools import partial
from typing import Any, Callable, Sequence

import torch

from mixedrl.algorithms.batched import DDPG_SHARED_FIELDS, BatchedRuns, StackedNetwork
from mixedrl.compiled import constants, network_at
from mixedrl.pev import run_mean

__all__ = ["BatchedDDPG", "critic_loss_at", "actor_loss_at"]


def critic_loss_at(params: Sequence[torch.Tensor], obs: torch.Tensor, act: torch.Tensor, cost: torch.Tensor,
                   next_obs: torch.Tensor, terminal: torch.Tensor, *, task: Any, critic: Any,
                   critic_target: Callable[..., torch.Tensor], actor_target: Callable[..., torch.Tensor],
                   runs: int) -> tuple[torch.Tensor, torch.Tensor]:
    """:meth:`BatchedDDPG.critic_step`'s loss with the critic at ``params``, as a pure function
    (:mod:`mixedrl.compiled`): ``(J_Q, Q(x, u))``, the second detached (the step's aux)."""
    with torch.no_grad():
        # y = l + gamma (1 - terminal) Q'(x', pi'(x'))
        target = cost + task.gamma * (1.0 - terminal) * critic_target(next_obs, actor_target(next_obs))
    q = network_at(critic, params)(obs, act)
    return 0.5 * run_mean(((q - target) / float(task.value_scale)).pow(2), runs), q.detach()


def actor_loss_at(params: Sequence[torch.Tensor], obs: torch.Tensor, *, task: Any, critic: Callable[..., torch.Tensor],
                  actor: Any, runs: int) -> torch.Tensor:
    """:meth:`BatchedDDPG.actor_step`'s objective ``J_pi = mean_B Q(x, pi(x; theta)) / s`` with the actor at
    ``params`` (the critic read, not trained), as a pure function (:mod:`mixedrl.compiled`)."""
    return run_mean(critic(obs, network_at(actor, params)(obs)), runs) / float(task.value_scale)

#: A member of a batch: a :class:`mixedrl.algorithms.ddpg.DDPG` run (not imported: ddpg imports this module).
DDPG = Any


class BatchedDDPG(BatchedRuns):
    """DDPG for ``R`` runs at once (see the module docstring).

    Parameters
    ----------
    members : sequence of DDPG
        The runs (built, possibly restored from checkpoints). They must share the task and
        :data:`~mixedrl.algorithms.batched.DDPG_SHARED_FIELDS`; for ``R >= 2`` the batch rebinds their
        networks' parameters (critic, actor and both targets) to views of stacked tensors.

    Raises
    ------
    ValueError
        No runs, a run that is not a :class:`~mixedrl.algorithms.ddpg.DDPG`, runs that differ in the task or
        a shared field, or the same run twice.
    """

    #: What a DDPG run has and an Algorithm-2 run has not (checked instead of the class, see :data:`DDPG`).
    kind, interface = "DDPG", ("explore", "finish_iteration", "buffer", "critic_target", "actor_target", "critic_opt",
                               "actor_opt")
    shared = DDPG_SHARED_FIELDS

    def __init__(self, members: Sequence[DDPG]) -> None:
        super().__init__(members)
        self.critic_target = StackedNetwork([m.critic_target for m in self.members], self.batch)
        self.actor_target = StackedNetwork([m.actor_target for m in self.members], self.batch)
        self._filler: tuple[torch.Tensor, ...] | None = None

    def _placeholder(self) -> tuple[torch.Tensor, ...]:
        """A minibatch for a run that does not iterate: zeros that fill its rows (its results are unused)."""
        if self._filler is None:
            b, task = self.batch, self.task
            self._filler = (torch.zeros(b, task.obs_dim), torch.zeros(b, task.action_dim), torch.zeros(b),
                            torch.zeros(b, task.obs_dim), torch.zeros(b))
        return self._filler

    def _join(self, batches: list[tuple[torch.Tensor, ...]]) -> tuple[torch.Tensor, ...]:
        """The runs' minibatches as one: each field concatenated, run ``r`` in rows ``r B .. (r + 1) B - 1``."""
        if self.runs == 1:
            return batches[0]
        return tuple(torch.cat(field) for field in zip(*batches))

    def critic_step(self, obs: torch.Tensor, act: torch.Tensor, cost: torch.Tensor, next_obs: torch.Tensor,
                    terminal: torch.Tensor, active: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
        """One TD step of every active run's critic toward its targets (its own clipped Adam step).

        .. math::
            y = l + \\gamma (1 - d)\\, Q'(x', \\pi'(x')), \\qquad
            J_Q(w) = \\tfrac12\\, \\mathrm{mean}_B \\big((Q(x, u; w) - y) / s\\big)^2

        with ``Q'``, ``pi'`` the run's target networks, ``d`` the terminal flag and ``s`` the task's
        ``value_scale``.

        Parameters
        ----------
        obs, next_obs : torch.Tensor, shape (R B, obs_dim)
        act : torch.Tensor, shape (R B, action_dim)
        cost, terminal : torch.Tensor, shape (R B,)
            The runs' minibatches, run ``r`` in rows ``r B .. (r + 1) B - 1``.
        active : list of int
            The runs that step.

        Returns
        -------
        loss : torch.Tensor
            ``J_Q`` before the step, shape () for one run, (R,) for ``R`` runs.
        q : torch.Tensor, shape (R B,)
            ``Q(x, u)`` before the step (no gradient).
        """
        # w <- w - alpha dJ_Q/dw   (Adam, per run; eager, or one compiled step with algorithm.compile)
        loss = partial(critic_loss_at, task=self.task, critic=self.critic, critic_target=self.critic_target,
                       actor_target=self.actor_target, runs=self.runs)
        return self.critic_descent.minimise(loss, (obs, act, cost, next_obs, terminal), active, key="ddpg_critic")

    def actor_step(self, obs: torch.Tensor, active: list[int]) -> torch.Tensor:
        """One deterministic-policy-gradient step of every active run's actor, critics frozen.

        .. math:: J_\\pi(\\theta) = \\mathrm{mean}_B\\, Q(x, \\pi(x; \\theta)) / s

        (minimised: ``Q`` is a cost-to-go). ``obs`` as in :meth:`critic_step`; returns ``J_pi`` before the
        step, shape () or (R,).
        """
        critic = self.critic.frozen()
        loss = partial(actor_loss_at, task=self.task, critic=critic, actor=self.actor, runs=self.runs)
        with constants(critic):  # Q is read, not trained
            # minimise Q(x, pi(x)), the cost-to-go of the deterministic policy:
            # theta <- theta - beta dJ_pi/dtheta   (Adam, per run)
            return self.actor_descent.minimise(loss, (obs,), active, key="ddpg_actor")

    def iteration(self, active: Sequence[bool] | None = None) -> list[dict[str, float] | None]:
        """One DDPG iteration of every active run (see :meth:`~mixedrl.algorithms.ddpg.DDPG.iteration`): its
        environment steps and minibatch (:meth:`~mixedrl.algorithms.ddpg.DDPG.explore`), :meth:`critic_step`,
        :meth:`actor_step`, its soft target updates (:meth:`~mixedrl.algorithms.ddpg.DDPG.finish_iteration`).

        Parameters
        ----------
        active : sequence of bool, optional
            Which runs iterate (default: all). An inactive run draws nothing, takes no step, keeps its
            targets and counters and returns ``None``.

        Returns
        -------
        list
            Per run its metrics row (the keys of :meth:`~mixedrl.algorithms.ddpg.DDPG.iteration`), or ``None``
            if inactive.

        Raises
        ------
        ValueError
            ``active`` does not hold one flag per run.
        """
        flags, on = self.active_runs(active)
        if not on:
            return [None] * self.runs
        costs: dict[int, float] = {}
        batches: list[tuple[torch.Tensor, ...]] = []
        for r, m in enumerate(self.members):
            if flags[r]:
                costs[r], minibatch = m.explore()
                batches.append(minibatch)
            else:
                batches.append(self._placeholder())
        obs, act, cost, next_obs, terminal = self._join(batches)
        critic_loss, q = self.critic_step(obs, act, cost, next_obs, terminal, on)
        actor_loss = self.actor_step(obs, on)
        critic_losses = critic_loss.reshape(-1).tolist()
        actor_losses = actor_loss.reshape(-1).tolist()
        rows: list[dict[str, float] | None] = [None] * self.runs
        for r in on:
            value_mean = float(q.mean()) if self.runs == 1 else float(q[r * self.batch:(r + 1) * self.batch].mean())
            rows[r] = self.members[r].finish_iteration(critic_losses[r], actor_losses[r], value_mean, costs[r])
        return rows
