"""Where Algorithm 2's PEV/PIM states come from when it plans on the model: :class:`ModelStateSampler`
(a departure, :mod:`mixedrl.departures.sampler`; docs/model_based.rst).

With a model-rollout sampler (``sampler.name`` ``"model_rollouts"``, or a task's own: :data:`SAMPLER_CLASSES`)
the batch ``x`` of eqs. (49)-(52) is made of states of ``batch_size`` rollouts of the *planning* model

.. math::

    x_{t+1} = f(x_t, \\pi^k(x_t)) + E\\, \\hat\\xi_t, \\qquad \\hat\\xi_t \\sim N(\\hat\\mu_k, \\hat K_k),

driven by the current policy, with ``N(mu_hat_k, K_hat_k)`` the method's noise source (for a
state-dependent source, the mean at each rollout's state). The true environment only supplies the
residuals ``xi^D`` (eq. 10) the IBE consumes (``true_envs`` copies driven ``true_steps`` steps every
``true_every`` iterations); a fixed noise source (model-driven, oracle) uses no true transitions.

A rollout restarts after its horizon, at a terminal state, or when it leaves the box
``|observe(x)_i| <= box * obs_scale_i``. A task may register its own sampler: a subclass of
:class:`ModelStateSampler` overriding the hooks :meth:`~ModelStateSampler.check_task`,
:meth:`~ModelStateSampler.copy_horizons`, :meth:`~ModelStateSampler.expired`,
:meth:`~ModelStateSampler.restart` and :meth:`~ModelStateSampler.after_step`, registered with its options
class (:func:`mixedrl.config.register_sampler`; e.g. :mod:`mixedrl.envs.dlc_sampler`).
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np
import torch

from mixedrl.config import SAMPLERS, ModelRolloutsSampler, TrainConfig, register_sampler
from mixedrl.gaussian import sample_gaussian
from mixedrl.plant import plant_copies
from mixedrl.task_base import Task

__all__ = ["ModelStateSampler", "SAMPLER_CLASSES", "course_starts", "course_length", "has_course"]

#: The sampler's tensors in its :meth:`ModelStateSampler.state_dict`.
_TENSORS = ("states", "steps", "true_states", "true_steps")


def course_starts(task: Task, n: int, generator: torch.Generator, along: bool = False) -> torch.Tensor:
    """``n`` episode start states of ``task``, float64, shape (n, state_dim).

    A task with a course starts near its beginning (``task.model.initial_states``), or with ``along=True``
    at a point drawn uniformly along it; a task without one draws from ``sample_initial``.
    """
    model = getattr(task, "model", None)
    if model is not None and hasattr(model, "initial_states"):
        return model.initial_states(n, generator, dtype=torch.float64, along=along)
    return task.sample_initial(n, generator)


def has_course(task: Task) -> bool:
    """Whether ``task`` has a course (a model with ``initial_states`` and a finite ``course_length``)."""
    return hasattr(getattr(task, "model", None), "initial_states") and math.isfinite(course_length(task))


def course_length(task: Task) -> float:
    """The course length of ``task`` (``inf`` for a task without a course)."""
    config = getattr(getattr(task, "model", None), "config", None)
    return float(getattr(config, "course_length", math.inf))


class ModelStateSampler:
    """Rollouts of the planning model that supply Algorithm 2's batch, and the true-data collector.

    Parameters
    ----------
    task : Task
        Model ``f``, ``observe``, ``noise_matrix``, start distributions, the true environment.
    config : TrainConfig
        ``algorithm.batch_size``, ``algorithm.horizon`` and the sampler's options ``config.sampler``
        (:class:`~mixedrl.config.ModelRolloutsSampler` or a subclass).
    generator : torch.Generator
        The run's generator, the source of every draw of the sampler.

    Attributes
    ----------
    states : torch.Tensor, shape (B, state_dim)
        Current model-rollout states (float64), ``B = algorithm.batch_size``.
    true_transitions : int
        True-environment transitions used so far.
    transitions : tuple of torch.Tensor or None
        States and actions (float64) of the residuals of the last :meth:`true_drive` (for a
        state-dependent IBE, Case 3).
    """

    def __new__(cls, task: Task, config: TrainConfig, generator: torch.Generator) -> "ModelStateSampler":
        """``ModelStateSampler(task, config, generator)`` builds the class registered for
        ``config.sampler.name`` (:data:`SAMPLER_CLASSES`)."""
        registered = SAMPLER_CLASSES.get(getattr(config.sampler, "name", None))
        if cls is ModelStateSampler and isinstance(registered, type) and issubclass(registered, cls):
            cls = registered
        return super().__new__(cls)

    def __init__(self, task: Task, config: TrainConfig, generator: torch.Generator) -> None:
        opts = config.sampler
        if not isinstance(opts, ModelRolloutsSampler):
            raise ValueError(f"config: sampler.name is {opts.name!r}, not a model-rollout sampler")
        self.task, self.config, self.generator = task, config, generator
        #: The sampler's options (``config.sampler``).
        self.options = opts
        B = config.algorithm.batch_size
        #: Steps after which each copy restarts (:meth:`copy_horizons`).
        self.horizons = self.copy_horizons(B)
        # start anywhere in the wide distribution, with desynchronised clocks
        self.states = task.sample_initial(B, generator)
        self.steps = (torch.rand(B, generator=generator, dtype=torch.float64) * self.horizons).long()
        self.true_states = course_starts(task, opts.true_envs, generator)
        self.true_steps = torch.zeros(opts.true_envs, dtype=torch.long)
        self.true_transitions = 0
        self.transitions: tuple[torch.Tensor, torch.Tensor] | None = None
        self.restarts = 0
        self.k = 0
        self.box = float(opts.box) * task.obs_scale.to(torch.float64)
        #: The task's plant (:mod:`mixedrl.plant`) driven instead of the simulated true copies, or None.
        self.plant = plant_copies(task, config)

    # ------------------------------------------------------------------------------------ hooks of a task's sampler
    @staticmethod
    def check_task(task: Task, config: TrainConfig) -> None:
        """Refuse a task the sampler cannot serve (a ``ValueError`` naming ``sampler.name``): any task here."""

    def copy_horizons(self, batch: int) -> torch.Tensor:
        """The steps after which each of the ``batch`` copies restarts: ``algorithm.horizon`` for all; shape (B,)."""
        return torch.full((batch,), self.config.algorithm.horizon)

    def expired(self, s_next: torch.Tensor) -> torch.Tensor:
        """The copies whose rollout ends after this step besides terminal and out-of-box ones: clock past the
        horizon; shape (B,), bool."""
        return self.steps >= self.horizons

    def restart(self, done: torch.Tensor) -> None:
        """Restart the copies flagged in ``done`` (bool, (B,)) from ``task.sample_initial``."""
        self.states[done] = self.task.sample_initial(int(done.sum()), self.generator)
        self.steps[done] = 0
        self.restarts += int(done.sum())

    def after_step(self, done: torch.Tensor) -> None:
        """After the step and the restarts (``done``): nothing here."""

    # ------------------------------------------------------------------------------------ rollouts
    def _outside(self, s: torch.Tensor) -> torch.Tensor:
        if math.isinf(self.options.box):
            return torch.zeros(s.shape[0], dtype=torch.bool)
        obs = self.task.observe(s)
        return (obs.abs() > self.box[: obs.shape[-1]]).any(dim=-1)

    def model_step(self, actor: torch.nn.Module, mean: np.ndarray | Any, cov: np.ndarray) -> torch.Tensor:
        """Return the current batch and advance every rollout one step of the planning model.

        .. math:: x_{t+1} = f(x_t, \\pi(x_t)) + E \\hat\\xi_t, \\qquad \\hat\\xi_t \\sim N(\\hat\\mu, \\hat K)

        Parameters
        ----------
        actor : torch.nn.Module
            The current policy ``pi^k`` (on observations, float32).
        mean : numpy.ndarray, shape (noise_dim,), or callable
            The planning mean ``mu_hat_k``, or a state-dependent one ``mean(x, u)`` (float64 tensors
            ``(B, state_dim)``, ``(B, action_dim)`` -> ``(B, noise_dim)``).
        cov : numpy.ndarray, shape (noise_dim, noise_dim)
            The planning covariance ``K_hat_k``.

        Returns
        -------
        torch.Tensor, shape (B, state_dim)
            The batch ``x`` (float32): the states before the step (``B = algorithm.batch_size``).
        """
        task, s = self.task, self.states
        with torch.no_grad():
            u = actor(task.observe(s.float())).double()
            if callable(mean):  # xi_hat = mu_hat(x, u) + K_hat^(1/2) z
                xi = (sample_gaussian(np.zeros(cov.shape[0]), cov, s.shape[0], self.generator)
                      + mean(s.double(), u)).to(s.dtype)
            else:
                xi = sample_gaussian(mean, cov, s.shape[0], self.generator).to(s.dtype)
            # x' = f(x, pi(x)) + E xi_hat
            s_next = task.f(s, u) + xi @ task.noise_matrix.to(s.dtype).T
        self.steps += 1
        done = task.is_terminal(s_next) | self._outside(s_next) | self.expired(s_next)
        self.states = s_next.clone()
        if bool(done.any()):
            self.restart(done)
        self.after_step(done)
        return s.float()

    # ------------------------------------------------------------------------------------ true data
    def true_drive(self, actor: torch.nn.Module) -> torch.Tensor:
        """Drive the ``true_envs`` true copies ``true_steps`` steps under ``actor``; return the residuals.

        Returns
        -------
        torch.Tensor, shape (M, noise_dim)
            Finite residuals ``xi^D`` of eq. (10) (:meth:`Task.residuals`; clipped rows dropped), float64.
            Every step adds ``true_envs`` to :attr:`true_transitions`.
        """
        task, cfg = self.task, self.options
        out, states, actions = [], [], []
        for _ in range(cfg.true_steps):
            s = self.true_states if self.plant is None else self.plant.current(self.true_states)
            with torch.no_grad():
                u = actor(task.observe(s.float())).double()
                s_next = task.true_step(s, u, self.generator) if self.plant is None else self.plant.step(u)
                out.append(task.residuals(s, u, s_next))
            states.append(s)
            actions.append(u)
            self.true_transitions += s.shape[0]
            self.true_steps += 1
            done = task.is_terminal(s_next) | (self.true_steps >= cfg.true_horizon)
            if self.plant is not None:  # the plant's own episode end; its reset, not the model's starts
                done = done | self.plant.done
            s_next = s_next.clone()
            if bool(done.any()):
                s_next[done] = (course_starts(task, int(done.sum()), self.generator) if self.plant is None
                                else self.plant.reset(done))
                self.true_steps[done] = 0
            self.true_states = s_next
        xi = torch.cat(out, dim=0)
        finite = torch.isfinite(xi).all(dim=-1)
        self.transitions = (torch.cat(states, dim=0)[finite], torch.cat(actions, dim=0)[finite])
        return xi[finite]

    def collect(self, actor: torch.nn.Module, noise: Any, k: int) -> tuple[torch.Tensor, torch.Tensor]:
        """One iteration's data: the model batch, and true residuals if the noise source learns.

        Parameters
        ----------
        actor : torch.nn.Module
            ``pi^k``.
        noise : object
            The noise source (``.mean`` or, if ``state_dependent``, ``.mean_at(x, u)``; ``.cov``; an
            ``update`` method if it learns from data).
        k : int
            The iteration; true data is collected when ``k % true_every == 0``.

        Returns
        -------
        states : torch.Tensor, shape (B, state_dim)
            The batch (float32).
        residuals : torch.Tensor, shape (M, noise_dim)
            Residuals for the IBE (``M = 0`` for a fixed noise source or between collections).
        """
        mean = noise.mean_at if getattr(noise, "state_dependent", False) else np.array(noise.mean, dtype=np.float64)
        self.k = k
        s = self.model_step(actor, mean, np.array(noise.cov, dtype=np.float64))
        if hasattr(noise, "update") and k % self.options.true_every == 0:
            return s, self.true_drive(actor)
        return s, torch.zeros(0, self.task.noise_dim, dtype=torch.float64)

    # ------------------------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        """Rollout states and clocks, true-copy states and clocks, counters, and with a plant that has
        started episodes ``plant_episodes`` (so a resumed run continues the plant's episode seeds)."""
        state = {key: getattr(self, key).clone() for key in _TENSORS}
        state.update(true_transitions=self.true_transitions, restarts=self.restarts)
        if self.plant is not None and self.plant.episodes:
            state["plant_episodes"] = self.plant.episodes
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`.

        A state without ``plant_episodes`` restarts the plant's episode seeds at 0.

        Raises
        ------
        ValueError
            A key is missing, a tensor has the wrong shape or ``plant_episodes`` is not an integer >= 0
            (message starts with ``state``).
        """
        missing = {*_TENSORS, "true_transitions", "restarts"} - set(state)
        if missing:
            raise ValueError(f"state: sampler is missing keys {sorted(missing)}")
        episodes = state.get("plant_episodes", 0)
        if isinstance(episodes, bool) or not isinstance(episodes, (int, np.integer)) or episodes < 0:
            raise ValueError(f"state: sampler plant_episodes is {episodes!r}, expected an integer >= 0")
        for key in _TENSORS:
            if tuple(state[key].shape) != tuple(getattr(self, key).shape):
                raise ValueError(f"state: sampler {key} has shape {tuple(state[key].shape)}, expected "
                                 f"{tuple(getattr(self, key).shape)}")
        for key in _TENSORS:
            setattr(self, key, state[key].clone())
        self.true_transitions = int(state["true_transitions"])
        self.restarts = int(state["restarts"])
        if self.plant is not None:
            self.plant.episodes = int(episodes)


register_sampler(ModelRolloutsSampler, implementation=ModelStateSampler)


class _Implementations(Mapping):
    def __getitem__(self, name: str) -> type | None:
        return SAMPLERS[name].IMPLEMENTATION

    def __iter__(self) -> Iterator[str]:
        return iter(SAMPLERS)

    def __len__(self) -> int:
        return len(SAMPLERS)

    def __repr__(self) -> str:
        return repr(dict(self))


#: Sampler name -> the class that makes Algorithm 2's batch (``None``: the true copies of
#: :class:`mixedrl.algorithms.agpi.AGPI`), a read-only view of :data:`mixedrl.config.SAMPLERS`.
SAMPLER_CLASSES: Mapping[str, type | None] = _Implementations()
