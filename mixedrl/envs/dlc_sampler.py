"""The double lane change's course sampler (``sampler.name = "dlc_course"``): its options
(:class:`CourseSampler`) and its code (:class:`CourseStateSampler`), registered with the task.

A departure from the paper, which does not say how its states were drawn (the hook *sampler*,
:mod:`mixedrl.departures.sampler`; docs/model_based.rst), applied identically to every method.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import torch

from mixedrl.checks import check_fraction, check_nonnegative_int, check_number, check_positive_int
from mixedrl.config import MODEL_COURSE_STARTS, ModelRolloutsSampler, register_sampler
from mixedrl.samplers import ModelStateSampler, course_length, course_starts, has_course

__all__ = ["CourseSampler", "CourseStateSampler"]


@dataclass
class CourseSampler(ModelRolloutsSampler):
    """``sampler.name = "dlc_course"``: the course design of the double lane change (a task with a
    course; docs/model_based.rst). Model rollouts as :class:`ModelRolloutsSampler`, of two kinds:

    * *course* copies (a fraction ``course_fraction`` of the batch) drive the course, from iteration
      ``course_start`` on, for ``course_horizon`` steps, restarting as ``course_starts`` says, and are
      *kicked* (``kick_prob`` per step, ``kick_scale`` times ``obs_scale``) so that the batch spreads
      around the course trajectory;
    * *wide* copies restart from the training distribution every ``algorithm.horizon`` steps.

    The true-data copies of mixed RL start at the course start and restart after ``true_horizon`` steps.
    Dotted keys: ``sampler.<field>``.
    """

    NAME: ClassVar[str] = "dlc_course"

    name: str = "dlc_course"
    """Always ``"dlc_course"`` for this class."""

    box: float = 3.0
    """A rollout restarts when a component of its observation exceeds ``box`` times ``obs_scale``."""

    true_horizon: int = 2000
    """Steps after which a true-data copy restarts at the course start (2000 = the whole course)."""

    course_fraction: float = 0.75
    """Fraction of the batch's rollouts that drive the course (the rest are wide copies)."""

    course_start: int = 500
    """Iteration from which the course copies drive the course; before it they restart from the wide
    distribution like the others."""

    course_starts: str = "along"
    """Where a course copy restarts: ``"start"``, at ``X = 0`` after its horizon (driving on past the
    course's end); ``"along"``, on the reference at ``X ~ U(0, course_length)``, also at the course's
    end; ``"loop"``, at ``X = 0``, also at the course's end."""

    course_horizon: int = 2000
    """Steps after which a course copy restarts (2000 = the whole double lane change)."""

    kick_prob: float = 0.01
    """Probability per step that a course copy is kicked: a uniform random offset of ``kick_scale *
    obs_scale_i`` on each noise component is added to its state."""

    kick_scale: float = 1.0
    """Size of a kick, in units of the task's ``obs_scale``."""

    def __post_init__(self) -> None:
        super().__post_init__()
        w = "sampler"
        check_fraction(self.course_fraction, f"{w}.course_fraction")
        check_fraction(self.kick_prob, f"{w}.kick_prob")
        self.course_start = check_nonnegative_int(self.course_start, f"{w}.course_start")
        if self.course_starts not in MODEL_COURSE_STARTS:
            raise ValueError(f"{w}.course_starts: expected one of {MODEL_COURSE_STARTS}, got {self.course_starts!r}")
        self.course_horizon = check_positive_int(self.course_horizon, f"{w}.course_horizon")
        check_number(self.kick_scale, f"{w}.kick_scale", nonneg=True)


class CourseStateSampler(ModelStateSampler):
    """The code of ``sampler.name = "dlc_course"`` (:class:`CourseSampler`): the hooks of
    :class:`~mixedrl.samplers.ModelStateSampler` for course copies, their restarts and their kicks."""

    @staticmethod
    def check_task(task: Any, config: Any) -> None:
        """Refuse a task without a course (an error naming ``sampler.name``)."""
        if not has_course(task):
            raise ValueError(f"sampler.name: {config.sampler.name!r} needs a task with a course (a model with "
                             f"initial_states and a course_length); task {type(task).__name__} has none")

    def __init__(self, task: Any, config: Any, generator: torch.Generator) -> None:
        super().__init__(task, config, generator)
        self.along = self.options.course_starts == "along"
        #: course copies restart when they pass the course's end ("along", "loop")
        self.end_restart = self.options.course_starts in ("along", "loop")
        self.course_length = course_length(task)
        self._on_course = torch.zeros_like(self.course)

    def copy_horizons(self, batch: int) -> torch.Tensor:
        """Course copies: ``course_horizon``; wide copies: ``algorithm.horizon``. Sets :attr:`course` (the
        course copies)."""
        opts = self.options
        self.course = torch.arange(batch) < int(round(opts.course_fraction * batch))
        return torch.where(self.course, opts.course_horizon, self.config.algorithm.horizon)

    def on_course(self) -> torch.Tensor:
        """The copies that drive the course at the current iteration: the course copies from iteration
        ``course_start`` on; shape (B,), bool."""
        return self.course & (self.k >= self.options.course_start)

    def expired(self, s_next: torch.Tensor) -> torch.Tensor:
        """Clock past the copy's horizon (a course copy's only once it drives the course), or a course copy
        past the course's end (``"along"``, ``"loop"``; the state's last entry is ``X``)."""
        on_course = self._on_course = self.on_course()
        horizons = torch.where(on_course, self.horizons, self.config.algorithm.horizon)
        done = self.steps >= horizons
        if self.end_restart:  # a course copy past the course's end
            done = done | (on_course & (s_next[:, -1] >= self.course_length))
        return done

    def restart(self, done: torch.Tensor) -> None:
        """Course copies on the course restart at the course start (or along it), wide ones wide."""
        course = done & self._on_course
        wide = done & ~course
        if bool(course.any()):
            self.states[course] = course_starts(self.task, int(course.sum()), self.generator, self.along)
        if bool(wide.any()):
            self.states[wide] = self.task.sample_initial(int(wide.sum()), self.generator)
        self.steps[done] = 0
        self.restarts += int(done.sum())

    def after_step(self, done: torch.Tensor) -> None:
        """Kick the course copies that did not restart: a uniform offset ``kick_scale * obs_scale * U(-1, 1)``
        (through ``E``), each with probability ``kick_prob``."""
        cfg, task, n = self.options, self.task, self.states.shape[0]
        if cfg.kick_prob <= 0:
            return
        hit = ~done & self.course & (torch.rand(n, generator=self.generator, dtype=torch.float64) < cfg.kick_prob)
        width = cfg.kick_scale * task.obs_scale.to(torch.float64)[: task.noise_dim]
        offset = width * (2.0 * torch.rand(n, task.noise_dim, generator=self.generator, dtype=torch.float64) - 1.0)
        self.states[hit] += (offset @ task.noise_matrix.to(torch.float64).T)[hit]


register_sampler(CourseSampler, tasks=("dlc",), implementation=CourseStateSampler)
