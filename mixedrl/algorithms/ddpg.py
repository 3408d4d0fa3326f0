"""The data-driven baseline of Section VI: DDPG (Lillicrap et al. 2015) on true-environment transitions.

DDPG never calls the model ``f`` for planning: it learns ``Q(x, u; w)`` and ``pi(x; theta)`` only from
transitions ``(x, u, l, x')`` of the true environment (:meth:`mixedrl.tasks.Task.true_step`), stored in
a replay buffer, with target networks and Gaussian exploration noise. Shared with Algorithm 2: the MLP class,
``algorithm.hidden_sizes``, ``algorithm.value_output``, the learning-rate decay (``algorithm.lr_decay_*``),
``algorithm.iterations``, ``algorithm.horizon``, the discount factor, the observation and the cost. DDPG has
its own ``ddpg.batch_size``, ``ddpg.activation``, ``ddpg.critic_lr``, ``ddpg.actor_lr`` and ``ddpg.grad_clip``
(not tuned). One iteration = ``ddpg.envs`` environment steps + one critic and one actor update (the unit in
which "iterations to converge" is counted for every method).
"""

from __future__ import annotations

import copy
from functools import cached_property
from typing import Any

import torch

from mixedrl.config import TrainConfig
from mixedrl.networks import Actor, QCritic
from mixedrl.plant import check_plant_sampler
from mixedrl.schedule import set_learning_rates
from mixedrl.task_base import Task, check_task

__all__ = ["DDPG", "ReplayBuffer"]


class ReplayBuffer:
    """Fixed-capacity ring buffer of transitions ``(obs, action, cost, next_obs, terminal)``.

    Parameters
    ----------
    capacity : int
        Maximum number of transitions.
    obs_dim, action_dim : int
        Sizes.
    """

    _FIELDS = ("obs", "action", "cost", "next_obs", "terminal")

    def __init__(self, capacity: int, obs_dim: int, action_dim: int) -> None:
        self.capacity = int(capacity)
        self.obs = torch.zeros(capacity, obs_dim)
        self.action = torch.zeros(capacity, action_dim)
        self.cost = torch.zeros(capacity)
        self.next_obs = torch.zeros(capacity, obs_dim)
        self.terminal = torch.zeros(capacity)
        self.pointer = 0
        self.size = 0

    def add(self, obs: torch.Tensor, action: torch.Tensor, cost: torch.Tensor, next_obs: torch.Tensor,
            terminal: torch.Tensor) -> None:
        """Append a batch of ``n`` transitions (shapes (n, obs_dim), (n, action_dim), (n,), (n, obs_dim), (n,))."""
        n = obs.shape[0]
        idx = (self.pointer + torch.arange(n)) % self.capacity
        for key, value in zip(self._FIELDS, (obs, action, cost, next_obs, terminal)):
            getattr(self, key)[idx] = value
        self.pointer = int((self.pointer + n) % self.capacity)
        self.size = int(min(self.size + n, self.capacity))

    def sample(self, n: int, generator: torch.Generator) -> tuple[torch.Tensor, ...]:
        """Uniformly sample ``n`` stored transitions with ``generator``."""
        if self.size == 0:
            raise ValueError("n: cannot sample from an empty replay buffer")
        idx = torch.randint(0, self.size, (n,), generator=generator)
        return tuple(getattr(self, key)[idx] for key in self._FIELDS)

    def state_dict(self) -> dict[str, Any]:
        """The stored transitions and the ring pointer (only the filled part)."""
        return {**{key: getattr(self, key)[:self.size].clone() for key in self._FIELDS}, "pointer": self.pointer,
                "size": self.size}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`."""
        n = int(state["size"])
        if n > self.capacity or state["obs"].shape[1:] != self.obs.shape[1:]:
            raise ValueError("state: replay buffer shapes do not match")
        for key in self._FIELDS:
            getattr(self, key)[:n] = state[key]
        self.pointer, self.size = int(state["pointer"]), n


class DDPG:
    """Deep deterministic policy gradient on the true environment (the paper's data-driven RL).

    Parameters
    ----------
    task : Task
        The true environment (``true_step``, ``cost``, ``observe``); ``f`` is used only inside
        ``true_step`` to simulate the environment, never for learning.
    config : TrainConfig
        ``method == "ddpg"``; the ``ddpg.*`` fields configure buffer, warm-up, targets, exploration, the
        minibatch size, the hidden activation, the learning rates and the gradient clip.

    Raises
    ------
    ValueError
        ``config.method`` is not ``"ddpg"``.
    """

    #: The deployed policy is the actor as trained (no noise model for an LQ feed-forward,
    #: :func:`mixedrl.departures.anchor.resolve`).
    feedforward = "learned"

    def __init__(self, task: Task, config: TrainConfig) -> None:
        if config.method != "ddpg":
            raise ValueError(f"config: method must be 'ddpg', got {config.method!r}")
        check_task(task)
        check_plant_sampler(task, config)
        self.task, self.config = task, config
        self.generator = torch.Generator().manual_seed(config.seed)
        g, own = self.generator, config.ddpg
        self.critic = QCritic(task.obs_dim, task.action_dim, config.algorithm.hidden_sizes, own.activation, g,
                              task.action_bound, task.obs_scale, task.value_scale, config.algorithm.value_output)
        self.actor = Actor(task.obs_dim, task.action_dim, config.algorithm.hidden_sizes, own.activation, g,
                           task.action_bound, task.obs_scale)
        self.critic_target = copy.deepcopy(self.critic)
        self.actor_target = copy.deepcopy(self.actor)
        for p in list(self.critic_target.parameters()) + list(self.actor_target.parameters()):
            p.requires_grad_(False)
        self.critic_opt = torch.optim.Adam(self.critic.parameters(), lr=own.critic_lr)
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=own.actor_lr)
        self.buffer = ReplayBuffer(config.ddpg.buffer_size, task.obs_dim, task.action_dim)
        self.states = task.sample_initial(config.ddpg.envs, g)
        # desynchronised episode clocks, so the copies do not all reset at the same iteration
        self.steps = torch.randint(0, config.algorithm.horizon, (config.ddpg.envs,), generator=g)
        self.k = 0
        self.stopped = False
        #: True-environment transitions taken so far (warm-up and exploration included), counted in :meth:`collect`
        #: (``None`` after loading a checkpoint that predates the counter).
        self.true_transitions: int | None = 0

    @property
    def policy(self) -> torch.nn.Module:
        return self.actor

    def collect(self) -> float:
        """One exploratory step of every environment copy into the buffer; returns the mean cost."""
        task, cfg = self.task, self.config
        s = self.states
        with torch.no_grad():
            obs = task.observe(s.float())
            # u = pi(x) + N(0, sigma^2), clipped to the action bounds
            noise = torch.randn(s.shape[0], task.action_dim, generator=self.generator) * (
                cfg.ddpg.noise_std * task.action_bound)
            u = torch.maximum(torch.minimum(self.actor(obs) + noise, task.action_bound), -task.action_bound)
            s_next = task.true_step(s, u.double(), self.generator)
            if self.true_transitions is not None:
                self.true_transitions += s.shape[0]
            cost = task.cost(s_next, u.double()).float()
            terminal = task.is_terminal(s_next)
            next_obs = task.observe(torch.where(terminal[:, None], s, s_next).float())
        ok = torch.isfinite(cost) & torch.isfinite(next_obs).all(dim=-1)
        self.buffer.add(obs[ok], u[ok], cost[ok], next_obs[ok], terminal[ok].float())
        self.steps += 1
        done = terminal | (self.steps >= cfg.algorithm.horizon)
        if bool(done.any()):
            s_next = s_next.clone()
            s_next[done] = task.sample_initial(int(done.sum()), self.generator)
            self.steps[done] = 0
        self.states = s_next
        return float(cost[ok].mean()) if bool(ok.any()) else float("nan")

    def _soft_update(self, target: torch.nn.Module, source: torch.nn.Module) -> None:
        tau = self.config.ddpg.tau
        with torch.no_grad():
            for pt, ps in zip(target.parameters(), source.parameters()):
                # w' <- tau w + (1 - tau) w'
                pt.mul_(1.0 - tau).add_(ps, alpha=tau)

    def explore(self) -> tuple[float, tuple[torch.Tensor, ...]]:
        """The data of iteration ``k``: this iteration's learning rates, one exploratory step of every
        environment copy (:meth:`collect`), more until the buffer holds ``ddpg.warmup`` transitions, then a
        minibatch drawn from the buffer with the run's generator.

        Returns
        -------
        mean_cost : float
            The mean cost of the first step (``train/env_cost``).
        minibatch : tuple of torch.Tensor
            ``(obs, action, cost, next_obs, terminal)``, shapes (B, obs_dim), (B, action_dim), (B,),
            (B, obs_dim), (B,) with ``B = ddpg.batch_size``.
        """
        cfg = self.config
        set_learning_rates(cfg, self.k, self.critic_opt, self.actor_opt)
        mean_cost = self.collect()
        while self.buffer.size < cfg.ddpg.warmup:
            self.collect()
        return mean_cost, self.buffer.sample(cfg.ddpg.batch_size, self.generator)

    def finish_iteration(self, critic_loss: float, actor_loss: float, value_mean: float,
                         mean_cost: float) -> dict[str, float]:
        """The end of iteration ``k`` (after the critic and the actor stepped): the soft target updates,
        ``k + 1``, and the metrics row (its losses and mean ``Q`` computed by the caller)."""
        self._soft_update(self.critic_target, self.critic)
        self._soft_update(self.actor_target, self.actor)
        self.k += 1
        count = self.true_transitions
        return {"train/critic_loss": critic_loss, "train/actor_loss": actor_loss, "train/value_mean": value_mean,
                "train/env_cost": mean_cost, "train/buffer_size": float(self.buffer.size),
                "data/true_transitions": float(count if count is not None else "nan")}

    def iteration(self) -> dict[str, float]:
        """One DDPG iteration: environment steps, one critic update, one actor update, target updates
        (:class:`mixedrl.algorithms.batched_ddpg.BatchedDDPG` with this run alone, ``R = 1``)."""
        return self.engine.iteration()[0]

    @cached_property
    def engine(self) -> Any:
        """This run alone as a batch: the :class:`mixedrl.algorithms.batched_ddpg.BatchedDDPG` of ``[self]``
        that :meth:`iteration` runs (built on first use)."""
        from mixedrl.algorithms.batched_ddpg import BatchedDDPG

        return BatchedDDPG([self])

    def evaluate(self, seeds: list[int]) -> dict[str, Any]:
        """Evaluate the deterministic actor (no exploration noise) on the task."""
        return self.task.evaluate(self.actor, seeds)

    def state_dict(self) -> dict[str, Any]:
        """Weights, targets, optimisers, generator, environment states, replay buffer, counter."""
        return {"k": self.k, "critic": self.critic.state_dict(), "actor": self.actor.state_dict(),
                "critic_target": self.critic_target.state_dict(), "actor_target": self.actor_target.state_dict(),
                "critic_opt": self.critic_opt.state_dict(), "actor_opt": self.actor_opt.state_dict(),
                "generator": self.generator.get_state(), "states": self.states.clone(),
                "steps": self.steps.clone(), "buffer": self.buffer.state_dict(),
                "true_transitions": self.true_transitions}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`.

        Raises
        ------
        ValueError
            Missing keys or mismatched shapes.
        """
        keys = {"k", "critic", "actor", "critic_target", "actor_target", "critic_opt", "actor_opt", "generator",
                "states", "steps", "buffer"}
        missing = keys - set(state)
        if missing:
            raise ValueError(f"state: missing keys {sorted(missing)}")
        try:
            for name in ("critic", "actor", "critic_target", "actor_target", "critic_opt", "actor_opt"):
                getattr(self, name).load_state_dict(state[name])
        except (RuntimeError, KeyError, ValueError) as exc:
            raise ValueError(f"state: weights do not match the networks ({exc})") from None
        self.generator.set_state(state["generator"])
        self.states, self.steps = state["states"].clone(), state["steps"].clone()
        self.buffer.load_state_dict(state["buffer"])
        self.k = int(state["k"])
        # a checkpoint written before the counter existed did not record it: unknown (None), not guessed
        count = state.get("true_transitions")
        self.true_transitions = None if count is None else int(count)
