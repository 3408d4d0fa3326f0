"""The double lane change of Section VI as a :class:`mixedrl.tasks.Task`: :class:`DoubleLaneChangeTask`.

Built by name (``make_task("dlc")``) or from a run's
:class:`~mixedrl.envs.dlc_config.DoubleLaneChangeTaskConfig`. This module registers the task's
configuration (``task.name = "dlc"``), its course sampler (:class:`CourseSampler`) and its preset
(:data:`DLC_EXPERIMENT`) with :mod:`mixedrl.config`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from mixedrl.config import register_builtin_task, register_preset
from mixedrl.envs.dlc_sampler import CourseSampler
from mixedrl.envs.dlc_config import CostWeights, DoubleLaneChangeTaskConfig, make_config
from mixedrl.envs.evaluation import TrackingResult, evaluate_courses
from mixedrl.envs.model import DoubleLaneChangeModel
from mixedrl.task_base import Equilibrium, Linearisation, Task, check_policies_and_seeds, cost_hessian

__all__ = ["DoubleLaneChangeTask", "CourseSampler", "DLC_EXPERIMENT"]


class DoubleLaneChangeTask(Task):
    """The double lane change of Section VI as a :class:`~mixedrl.tasks.Task` (an adapter on :mod:`mixedrl.envs`).

    * state: the tracking state ``s = [v_y, r, v_x, phi, Y, X]`` of
      :class:`~mixedrl.envs.DoubleLaneChangeModel`; ``f`` = its ``step`` (eq. 53, forward Euler);
    * noise: the paper's five-component ``xi`` on ``x = [v_y, r, v_x, phi, y]`` (eq. 54), entering the
      first five state components (``E = [I_5; 0]``); the true noise is ``F_dis T / m`` on ``v_x``
      (:attr:`noise_index`; ``T / m`` is :attr:`force_scale`) with ``F_dis ~ N(261, 32)`` by default
      (any law of :class:`mixedrl.envs.Disturbance`);
    * prior (eq. 55): ``mu_M = 150 T/m``, ``K_M = (4 T/m)^2`` on ``v_x``, ``1e-20`` on the others;
    * observation: :meth:`~mixedrl.envs.DoubleLaneChangeModel.observe`; utility: eq. (54) on the next
      state, discount :attr:`gamma`;
    * training states: :meth:`~mixedrl.envs.DoubleLaneChangeModel.reset_states`; evaluation:
      :func:`mixedrl.envs.evaluate_tracking`, one full course per seed.

    The constructor builds a :class:`~mixedrl.envs.dlc_config.DoubleLaneChangeTaskConfig` from keywords
    (:meth:`from_config` takes one).

    Parameters
    ----------
    prior_force_mean : float, optional
        The designer's prior mean force [N] (paper: 150).
    prior_force_std : float, optional
        Prior standard deviation ``sqrt(K_M)`` in force units [N] (paper: 4).
    gamma : float, optional
        Discount factor of eq. (2) (default 0.99).
    **config
        Any other field of :class:`~mixedrl.envs.dlc_config.DoubleLaneChangeTaskConfig` (nested ones
        also as dicts, :func:`mixedrl.envs.make_config`).

    Attributes
    ----------
    config : DoubleLaneChangeTaskConfig
        The task's configuration (also ``model.config``).
    noise_index : int
        Component of ``xi`` (and of the state) the disturbance acts on: ``v_x`` (2).
    force_scale : float
        ``T / m`` [s/kg]: ``xi = force_scale * F_dis`` (eq. 54).
    true_mean_varies : bool
        ``True`` on a road grade (``grade_amplitude != 0``): the true mean is :meth:`true_mean_at`.
    mean_harmonics : int
        Harmonics ``H`` of the Fourier series along the course that Case 3 of the IBE fits
        (:meth:`mean_features`; 8).
    lqr_reference : bool
        ``False``: the course is no equilibrium, so the LQR is not a run's yardstick (the NMPC
        references of ``validation/nmpc.py`` are).

    Raises
    ------
    ValueError
        ``prior_force_std`` not positive, ``gamma`` not in (0, 1), or an invalid environment override.
    """

    name = "dlc"
    lqr_reference = False
    evaluates_on_plant = True
    counts_evaluation_transitions = True

    def __init__(self, prior_force_mean: float = 150.0, prior_force_std: float = 4.0, gamma: float = 0.99,
                 **config: Any) -> None:
        self._setup(make_config(DoubleLaneChangeTaskConfig(), prior_force_mean=prior_force_mean,
                                prior_force_std=prior_force_std, gamma=gamma, **config))

    def _setup(self, cfg: DoubleLaneChangeTaskConfig) -> None:
        self.config = cfg
        self.model = DoubleLaneChangeModel(cfg)
        scale = cfg.dt / cfg.params.m  # T / m: force [N] -> xi [m/s]
        self.force_scale = scale
        self.state_dim, self.action_dim = self.model.state_dim, self.model.action_dim
        self.obs_dim, self.noise_dim = self.model.obs_dim, 5
        self.gamma = cfg.gamma
        vx = self.noise_index = self.model.noise_index
        self.noise_matrix = torch.eye(self.state_dim, self.noise_dim)  # E = [I_5; 0]
        on_vx = np.arange(5) == vx
        self.prior_mean = np.where(on_vx, cfg.prior_force_mean * scale, 0.0)
        self.prior_cov = np.diag(np.where(on_vx, (cfg.prior_force_std * scale) ** 2, 1e-20))
        self.true_mean = np.where(on_vx, cfg.disturbance.mean * scale, 0.0)
        self.true_cov = np.diag(np.where(on_vx, cfg.disturbance.variance * scale**2, 0.0))
        self.true_mean_varies = cfg.disturbance.grade_amplitude != 0.0
        self.action_bound = torch.tensor(self.model.action_bound, dtype=torch.float32)
        scales = [0.3, 0.2, 0.5, 0.1, 0.5] + [2.0] * (self.obs_dim - 5) if cfg.obs_scale is None else cfg.obs_scale
        self.obs_scale = torch.tensor(scales, dtype=torch.float32)
        self.value_scale = 1.0
        #: An evaluation on a plant drives one course (:func:`mixedrl.plant.evaluate_on_plant`).
        self.eval_horizon = cfg.max_steps

    @classmethod
    def from_config(cls, config: DoubleLaneChangeTaskConfig) -> "DoubleLaneChangeTask":
        """Build the task of a :class:`~mixedrl.envs.dlc_config.DoubleLaneChangeTaskConfig` (used as it is).

        The task's ``true_mean`` / ``true_cov`` are the law's mean and variance whatever the law, so the
        oracle plans with the Gaussian of the true moments.

        Raises
        ------
        ValueError
            ``config`` is not a :class:`~mixedrl.envs.dlc_config.DoubleLaneChangeTaskConfig`.
        """
        if not isinstance(config, DoubleLaneChangeTaskConfig):
            raise ValueError(f"config: expected a DoubleLaneChangeTaskConfig, got {type(config).__name__}")
        task = cls.__new__(cls)
        task._setup(config)  # the configuration itself, not a copy
        return task

    # harmonics of the Case-3 Fourier basis along the course (documented under Attributes)
    mean_harmonics: int = 8

    def true_mean_at(self, s: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """The true noise mean at each state (B, 5) float64: ``(mean - m g sin(theta(X))) T / m`` on ``v_x``
        (:meth:`mixedrl.envs.DoubleLaneChangeModel.xi_mean`), 0 elsewhere."""
        out = torch.zeros(s.shape[0], self.noise_dim, dtype=torch.float64)
        out[:, self.noise_index] = torch.as_tensor(self.model.xi_mean(s.to(torch.float64)), dtype=torch.float64)
        return out

    def mean_features(self, s: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Case-3 features (eq. 19): a Fourier series of the position ``X`` along the course, (B, 1 + 2H).

        .. math:: g(x, u) = \\big[1,\\ \\sin(2\\pi k X / L),\\ \\cos(2\\pi k X / L)\\big]_{k = 1..H}

        with ``L`` the course length and ``H`` = :attr:`mean_harmonics`. A road grade's mean force is
        represented exactly (up to third order in the grade) when its wavelength is ``L / k``, ``k <= H``.
        """
        X = s[:, 5].to(torch.float64)
        k = torch.arange(1, self.mean_harmonics + 1, dtype=torch.float64)
        angle = (2.0 * math.pi / self.model.config.course_length) * X[:, None] * k
        return torch.cat([torch.ones(s.shape[0], 1, dtype=torch.float64), torch.sin(angle), torch.cos(angle)], dim=1)

    def force_to_xi(self, force: Any) -> Any:
        """``xi = F_dis T / m`` [m/s] of a force [N] (eq. 54); floats, arrays or tensors."""
        return force * self.force_scale

    def xi_to_force(self, xi: Any) -> Any:
        """The force [N] whose noise on ``v_x`` is ``xi`` [m/s]: ``F_dis = xi m / T``."""
        return xi / self.force_scale

    def equilibrium(self) -> Equilibrium:
        """On the reference at the course start at the desired speed: ``s* = [0, 0, v_des, psi_ref(0), Y_ref(0), 0]``,
        ``u* = 0``, the origin of the tracking errors.

        A rest point of the errors on a straight road, not of the six-component state (``X`` advances).
        """
        cfg = self.model.config
        X0 = torch.zeros((), dtype=torch.float64)
        heading, lateral = float(cfg.reference.heading(X0)), float(cfg.reference.lateral(X0))
        return Equilibrium(state=np.array([0.0, 0.0, cfg.v_des, heading, lateral, 0.0]), action=np.zeros(2))

    def linearisation(self) -> Linearisation:
        """The discounted LQ problem of the tracking errors at :meth:`equilibrium` (the LQR reference's problem).

        Coordinates: ``x = [v_y, r, v_x - v_des, e_phi, e_y]``, ``v = u``; ``A``, ``B`` the Jacobians of
        ``f`` at ``[0, 0, v_des, 0, 0]`` on a straight road, ``Q``, ``R`` half the Hessian of eq. (54),
        ``E = I_5``. ``x`` embeds at ``X = 0``: ``s = [x_0, x_1, v_des + x_2, psi_ref(0) + x_3, Y_ref(0) + x_4, 0]``.
        """
        eq = self.equilibrium()
        cfg = self.model.config
        s0 = torch.as_tensor(eq.state)
        x0 = torch.tensor([0.0, 0.0, cfg.v_des, 0.0, 0.0], dtype=torch.float64)
        u0 = torch.zeros(2, dtype=torch.float64)
        A, B = torch.func.jacrev(lambda x, u: self.model.dynamics(x, u), argnums=(0, 1))(x0, u0)

        def embed(x: torch.Tensor) -> torch.Tensor:
            # s = s* + [x_0, x_1, x_2, x_3, x_4, 0]: the errors around the reference at X = 0
            return s0 + torch.cat([x, torch.zeros(x.shape[0], 1, dtype=x.dtype)], dim=1)

        Q, R = cost_hessian(lambda x, u: self.model.cost(embed(x), u), torch.zeros(5, dtype=torch.float64), u0,
                             type(self).__name__, 1.0 + cfg.v_des)
        return Linearisation(A=A.numpy(), B=B.numpy(), Q=Q, R=R, E=np.eye(5), gamma=self.gamma, state=eq.state,
                             action=eq.action, embed=embed)

    def f(self, s: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return self.model.step(s, u)

    def observe(self, s: torch.Tensor) -> torch.Tensor:
        return self.model.observe(s)

    def cost(self, s_next: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return self.model.cost(s_next, u)

    def sample_initial(self, n: int, generator: torch.Generator) -> torch.Tensor:
        return self.model.reset_states(n, generator, dtype=torch.float64)

    def is_terminal(self, s: torch.Tensor) -> torch.Tensor:
        return self.model.is_terminated(s)

    def true_step(self, s: torch.Tensor, u: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        # s' = f(s, u) + xi e_vx,  xi = F_dis T / m  (eq. 54)
        return self.model.true_step(s, u.to(s.dtype), generator)

    def evaluate(self, policy: torch.nn.Module, seeds: list[int], keep_trajectory: bool = False
                 ) -> dict[str, Any]:
        """Table I metrics averaged over one full course per seed (:func:`mixedrl.envs.evaluate_tracking`).

        Returns ``lateral_mae`` [m], ``speed_mae`` [m/s], ``lateral_max``, ``speed_max``, ``cost`` (total
        eq. 54 cost of the course), ``terminated`` (fraction of runs that left the road); with
        ``keep_trajectory`` also ``trajectories`` (the :class:`~mixedrl.envs.TrackingResult` objects).
        The courses are driven by :func:`mixedrl.envs.evaluate_courses` with ``exact=True`` (bit for bit
        :func:`~mixedrl.envs.evaluate_tracking`'s); their steps are added to :attr:`evaluation_transitions`.

        With a plant attached (:func:`mixedrl.plant.attach_plant`) the evaluation is
        :attr:`plant_evaluate`'s instead: one episode of at most a course per seed, without the Table I
        metrics.

        Raises
        ------
        ValueError
            ``seeds`` empty or not ints.
        """
        if self.plant_evaluate is not None:  # on the task's plant, or none
            return self.plant_evaluate(policy, seeds, None)
        runs = evaluate_courses([policy], self.model.config, seeds=[list(seeds)], exact=True)[0]
        self.evaluation_transitions += sum(r.n_steps for r in runs)
        return _course_metrics(runs, keep_trajectory)

    def evaluate_many(self, policies: list[torch.nn.Module], seeds: list[list[int]], *, exact: bool = False
                      ) -> list[dict[str, Any]]:
        """:meth:`evaluate` of several policies, each on its own seeds, in one lock-step drive
        (:func:`mixedrl.envs.evaluate_courses`).

        With ``exact=False`` (default) the metrics may differ from :meth:`evaluate`'s in the float32 last
        bits of the policy (docs/reproduction.rst); with ``exact=True`` they are bit-identical. Steps are
        counted as :meth:`Task.evaluate_many <mixedrl.tasks.Task.evaluate_many>` says; with a plant the
        policies are evaluated on it one after the other.

        Raises
        ------
        ValueError
            As :func:`mixedrl.envs.evaluate_courses` (e.g. ``seeds`` not one non-empty list per policy).
        """
        seeds = check_policies_and_seeds(policies, seeds)
        if self.plant_evaluate is not None:  # one policy after the other on the plant (or none)
            return super().evaluate_many(policies, seeds, exact=exact)
        runs = evaluate_courses(list(policies), self.model.config, seeds=seeds, exact=exact)
        self.last_evaluation_counts = [sum(r.n_steps for r in courses) for courses in runs]
        self.evaluation_transitions += sum(self.last_evaluation_counts)
        return [_course_metrics(r, False) for r in runs]


def _course_metrics(runs: list[TrackingResult], keep_trajectory: bool) -> dict[str, Any]:
    """The task's evaluation dict (:meth:`DoubleLaneChangeTask.evaluate`) of one policy's courses."""
    out: dict[str, Any] = {key: float(np.mean([getattr(r, attr) for r in runs])) for key, attr in (
        ("lateral_mae", "mean_abs_lateral_error"), ("speed_mae", "mean_abs_speed_error"),
        ("lateral_max", "max_abs_lateral_error"), ("speed_max", "max_abs_speed_error"), ("cost", "total_cost"),
        ("terminated", "terminated"))}
    if keep_trajectory:
        out["trajectories"] = runs
    return out


# the double lane change's configuration and preset, registered here
register_builtin_task(DoubleLaneChangeTaskConfig, DoubleLaneChangeTaskConfig.from_dict, CostWeights=CostWeights)

#: The double lane change's experiment configuration (the reproduction of Table I, ``mixedrl reproduce``),
#: applied to every method; the course sampler and the relative batch weighting are departures listed
#: on docs/algorithm2.rst.
DLC_EXPERIMENT: dict[str, dict[str, Any]] = {
    "algorithm": {"lr_decay_iterations": 1500, "batch_weighting": "relative"},
    "sampler": {"name": CourseSampler.NAME},
}
register_preset("dlc", DLC_EXPERIMENT)
