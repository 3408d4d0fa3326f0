"""Where Algorithm 2's PEV/PIM states come from when it plans on the model: :class:`ModelStateSampler`.

With a model-rollout sampler (``TrainConfig.sampler.name`` ``"model_rollouts"`` or ``"dlc_course"``,
:data:`SAMPLER_CLASSES`) the batch ``x`` of eqs. (49)-(52) is made of states of
``batch_size`` rollouts of the *planning* model

.. math::

    x_{t+1} = f(x_t, \\pi^k(x_t)) + E\\, \\hat\\xi_t, \\qquad \\hat\\xi_t \\sim N(\\hat\\mu_k, \\hat K_k),

driven by the current policy, with ``N(mu_hat_k, K_hat_k)`` the method's noise source (the IBE posterior
for mixed RL, the prior for model-driven RL, the true law for the oracle; for a state-dependent source,
Case 3 of the IBE or the oracle on a road grade, the mean ``mu_hat_k(x_t, pi^k(x_t))`` of each rollout's
state). The true environment is used
only to collect the residuals ``xi^D`` (eq. 10) that the IBE consumes, at the rate the config sets
(``true_envs`` copies driven ``true_steps`` steps every ``true_every`` iterations); a fixed noise source
(model-driven, oracle) consumes no data, so those runs use **zero** true transitions.

With ``"model_rollouts"`` every rollout restarts from the task's training distribution
(:class:`mixedrl.config.ModelRolloutsSampler`). The double lane change's ``"dlc_course"``
(:class:`mixedrl.envs.dlc_task.CourseSampler`; a departure from the paper, which does not say how its states
were drawn; applied identically to every method) has two kinds of rollouts:

* *course* copies (a fraction ``course_fraction`` of the batch) drive the course from its start
  (the task's episode start) for ``course_horizon`` steps, so the batch holds the states the
  current policy visits on the job it is evaluated on; ``course_starts`` says whether they also
  restart when they pass the course's end (``"loop"``: at its start; ``"along"``: at a random point
  along it) or drive on beyond it (``"start"``);
* the course copies are *kicked* (``kick_prob`` per step): a random offset of the size of the
  task's ``obs_scale`` is added to the state and the policy has to recover, so the batch spreads around
  the course trajectory in every direction instead of lying on it;
* *wide* copies restart from the task's wide training distribution (``sample_initial``) every
  ``horizon`` steps, as the true-environment batch does, so large errors stay covered.

A rollout also restarts when it leaves the box ``|observe(x)_i| <= box * obs_scale_i``: outside it
the critic would be trained on states far from anything the policy has to handle (see
docs/model_based.rst).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from mixedrl.config import ModelRolloutsSampler, TrainConfig
from mixedrl.envs.dlc_task import CourseSampler
from mixedrl.gaussian import sample_gaussian
from mixedrl.plant import plant_copies
from mixedrl.tasks import Task

__all__ = ["ModelStateSampler", "SAMPLER_CLASSES", "course_starts", "has_course"]


def course_starts(task: Task, n: int, generator: torch.Generator, along: bool = False) -> torch.Tensor:
    """``n`` episode start states of ``task``, float64, shape (n, state_dim).

    The double lane change starts at the beginning of the course (``task.model.initial_states``, a small
    perturbation of the reference at ``X = 0``), or with ``along=True`` at a point drawn uniformly along
    the course (``X ~ U(0, course_length)``, the same perturbation); a task without a course starts from
    its training distribution (``sample_initial``).
    """
    model = getattr(task, "model", None)
    if model is not None and hasattr(model, "initial_states"):
        return model.initial_states(n, generator, dtype=torch.float64, along=along)
    return task.sample_initial(n, generator)


def has_course(task: Task) -> bool:
    """Whether ``task`` has a course (a model with ``initial_states`` and a finite ``course_length``)."""
    model = getattr(task, "model", None)
    return hasattr(model, "initial_states") and math.isfinite(_course_length(task))


def _course_length(task: Task) -> float:
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
        (:class:`~mixedrl.config.ModelRolloutsSampler` or :class:`~mixedrl.envs.dlc_task.CourseSampler`).
    generator : torch.Generator
        The run's generator (every draw of the sampler comes from it, so a run is reproducible and
        resumable).

    Attributes
    ----------
    states : torch.Tensor, shape (batch_size, state_dim)
        Current model-rollout states (float64).
    true_transitions : int
        True-environment transitions used so far.
    transitions : tuple of torch.Tensor or None
        States and actions (float64) of the residuals of the last :meth:`true_drive` (for a
        state-dependent IBE, Case 3).
    """

    def __init__(self, task: Task, config: TrainConfig, generator: torch.Generator) -> None:
        opts = config.sampler
        if not isinstance(opts, ModelRolloutsSampler):
            raise ValueError(f"config: sampler.name is {opts.name!r}, not a model-rollout sampler")
        self.task, self.config, self.generator = task, config, generator
        #: The sampler's options (``config.sampler``); a plain model-rollout sampler has no course copies.
        self.options = opts
        self.course_start = getattr(opts, "course_start", 0)
        self.kick_prob = getattr(opts, "kick_prob", 0.0)
        B = config.algorithm.batch_size
        n_course = int(round(getattr(opts, "course_fraction", 0.0) * B))
        #: True for the copies that drive the course from its start.
        self.course = torch.arange(B) < n_course
        #: The iteration from which each copy, if a course copy, drives the course: ``course_start`` for
        #: all (``course_ramp = 0``), or spread evenly over ``course_ramp`` iterations after it (copy ``i``
        #: of ``n`` course copies at ``course_start + floor(i course_ramp / n)``).
        self.switch = self.course_start + (torch.arange(B) * getattr(opts, "course_ramp", 0)) // max(n_course, 1)
        self.horizons = torch.where(self.course, getattr(opts, "course_horizon", 1), config.algorithm.horizon)
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
        starts = getattr(opts, "course_starts", "start")
        self.along = starts == "along"
        #: course copies restart when they pass the course's end ("along", "loop")
        self.end_restart = starts in ("along", "loop")
        self.course_length = _course_length(task)
        #: The task's plant (mixedrl.plant) driven instead of the simulated true copies, or None.
        self.plant = plant_copies(task, config)

    # ------------------------------------------------------------------------------------ rollouts
    def on_course(self) -> torch.Tensor:
        """The copies that drive the course at the current iteration: the course copies whose
        :attr:`switch` has passed (all of them from ``course_start + course_ramp`` on); shape (B,), bool."""
        return self.course & (self.k >= self.switch)

    def _restart(self, done: torch.Tensor, on_course: torch.Tensor) -> None:
        """Restart the copies flagged in ``done``: course copies (``on_course``, :meth:`on_course`) at the
        course start, wide ones wide."""
        course = done & on_course
        wide = done & ~course
        if bool(course.any()):
            self.states[course] = course_starts(self.task, int(course.sum()), self.generator, self.along)
        if bool(wide.any()):
            self.states[wide] = self.task.sample_initial(int(wide.sum()), self.generator)
        self.steps[done] = 0
        self.restarts += int(done.sum())

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
        torch.Tensor, shape (batch_size, state_dim)
            The batch ``x`` (float32): the states before the step.
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
        on_course = self.on_course()
        horizons = torch.where(on_course, self.horizons, self.config.algorithm.horizon)
        done = task.is_terminal(s_next) | self._outside(s_next) | (self.steps >= horizons)
        if self.end_restart:  # a course copy past the course's end
            done = done | (on_course & (s_next[:, -1] >= self.course_length))  # (the state's last entry is X)
        self.states = s_next.clone()
        if bool(done.any()):
            self._restart(done, on_course)
        if self.kick_prob > 0:
            self._kick(~done & self.course)
        return s.float()

    def _kick(self, eligible: torch.Tensor) -> None:
        """Add a uniform offset ``kick_scale * obs_scale * U(-1, 1)`` (through ``E``) to the eligible
        copies, each with probability ``kick_prob``."""
        cfg, task = self.options, self.task
        n = self.states.shape[0]
        hit = eligible & (torch.rand(n, generator=self.generator, dtype=torch.float64) < cfg.kick_prob)
        width = cfg.kick_scale * task.obs_scale.to(torch.float64)[: task.noise_dim]
        offset = width * (2.0 * torch.rand(n, task.noise_dim, generator=self.generator, dtype=torch.float64) - 1.0)
        self.states[hit] += (offset @ task.noise_matrix.to(torch.float64).T)[hit]

    # ------------------------------------------------------------------------------------ true data
    def true_drive(self, actor: torch.nn.Module) -> torch.Tensor:
        """Drive the ``true_envs`` true copies ``true_steps`` steps under ``actor``; return the residuals.

        Returns
        -------
        torch.Tensor, shape (M, noise_dim)
            Finite residuals ``xi^D`` of eq. (10) in noise coordinates (:meth:`Task.residuals`; rows the
            plant may have clipped are dropped), float64. Every step counts
            ``true_envs`` transitions in :attr:`true_transitions`.
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
        states : torch.Tensor, shape (batch_size, state_dim)
            The batch (float32).
        residuals : torch.Tensor, shape (M, noise_dim)
            Residuals for the IBE (``M = 0`` for a fixed noise source or between collections).
        """
        if getattr(noise, "state_dependent", False):
            mean = noise.mean_at
        else:
            mean = np.array(noise.mean, dtype=np.float64)
        cov = np.array(noise.cov, dtype=np.float64)
        self.k = k
        s = self.model_step(actor, mean, cov)
        if hasattr(noise, "update") and k % self.options.true_every == 0:
            return s, self.true_drive(actor)
        return s, torch.zeros(0, self.task.noise_dim, dtype=torch.float64)

    # ------------------------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        """Rollout states and clocks, true-copy states and clocks, counters."""
        return {"states": self.states.clone(), "steps": self.steps.clone(), "true_states": self.true_states.clone(),
                "true_steps": self.true_steps.clone(), "true_transitions": self.true_transitions,
                "restarts": self.restarts}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`.

        Raises
        ------
        ValueError
            A key is missing or a tensor has the wrong shape (message starts with ``state``).
        """
        missing = {"states", "steps", "true_states", "true_steps", "true_transitions", "restarts"} - set(state)
        if missing:
            raise ValueError(f"state: sampler is missing keys {sorted(missing)}")
        for key in ("states", "steps", "true_states", "true_steps"):
            if tuple(state[key].shape) != tuple(getattr(self, key).shape):
                raise ValueError(f"state: sampler {key} has shape {tuple(state[key].shape)}, expected "
                                 f"{tuple(getattr(self, key).shape)}")
        for key in ("states", "steps", "true_states", "true_steps"):
            setattr(self, key, state[key].clone())
        self.true_transitions = int(state["true_transitions"])
        self.restarts = int(state["restarts"])


#: Sampler name (``TrainConfig.sampler.name``, :data:`mixedrl.config.SAMPLERS`) -> the class that makes
#: Algorithm 2's batch; ``None`` = the true-environment copies of :class:`mixedrl.algorithms.agpi.AGPI`
#: itself (Algorithm 2 as the paper writes it). A new sampler registers its options class with
#: :func:`mixedrl.config.register_sampler` and its implementation here.
SAMPLER_CLASSES: dict[str, type | None] = {
    "true_copies": None,
    ModelRolloutsSampler.NAME: ModelStateSampler,
    CourseSampler.NAME: ModelStateSampler,
}
