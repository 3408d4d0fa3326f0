"""The nominal physics of Pendulum-v1 (state ``[theta, theta_dot]``, the angle not wrapped) and
MountainCarContinuous-v0 (``[position, velocity]``) in torch, as a designer's model ``f`` (equal to the envs'
``step`` up to float32 rounding); the ``E`` of a force added after their action clip (what
:class:`mixedrl.plant.DisturbedEnv` adds); and the two as :class:`~mixedrl.tasks.Task` objects
(docs/gym_benchmark.rst)."""

from __future__ import annotations

import math

import numpy as np
import torch

from mixedrl.task_base import Task

__all__ = ["MountainCarTask", "PendulumV1Task", "angle_normalize", "mountain_car_noise_matrix", "mountain_car_step",
           "pendulum_noise_matrix", "pendulum_v1_step"]


def angle_normalize(theta: torch.Tensor) -> torch.Tensor:
    """The angle wrapped into ``[-pi, pi)``, as Gymnasium's pendulum does for its cost."""
    return torch.remainder(theta + math.pi, 2 * math.pi) - math.pi


def pendulum_v1_step(s: torch.Tensor, u: torch.Tensor, g: float = 10.0, m: float = 1.0, l: float = 1.0,
                     dt: float = 0.05, max_speed: float = 8.0, max_torque: float = 2.0) -> torch.Tensor:
    """One step of Pendulum-v1, batched and differentiable: ``s`` (B, 2), ``u`` (B, 1) -> (B, 2).

    .. math::

        \\dot\\theta' = \\mathrm{clip}\\big(\\dot\\theta + (\\tfrac{3g}{2l}\\sin\\theta + \\tfrac{3}{ml^2}
        \\mathrm{clip}(u, \\pm u_{max}))\\,dt,\\ \\pm\\omega_{max}\\big), \\qquad \\theta' = \\theta + \\dot\\theta' dt
    """
    th, thdot = s[:, 0], s[:, 1]
    torque = torch.clamp(u[:, 0], -max_torque, max_torque)
    new_thdot = torch.clamp(thdot + (3 * g / (2 * l) * torch.sin(th) + 3.0 / (m * l**2) * torque) * dt,
                            -max_speed, max_speed)
    return torch.stack([th + new_thdot * dt, new_thdot], dim=-1)


def pendulum_noise_matrix(dt: float = 0.05, m: float = 1.0, l: float = 1.0) -> torch.Tensor:
    """``E`` (2, 1) float64 of a torque added after the clip of Pendulum-v1: ``3/(m l^2) [dt^2, dt]^T``."""
    c = 3.0 / (m * l**2)
    return torch.tensor([[c * dt * dt], [c * dt]], dtype=torch.float64)


def mountain_car_step(s: torch.Tensor, u: torch.Tensor, power: float = 0.0015, max_speed: float = 0.07,
                      min_position: float = -1.2, max_position: float = 0.6) -> torch.Tensor:
    """One step of MountainCarContinuous-v0, batched: ``s`` (B, 2), ``u`` (B, 1) -> (B, 2).

    ``v' = clip(v + power clip(u, -1, 1) - 0.0025 cos(3 p), +-max_speed)``, ``p' = clip(p + v')``, and
    ``v' = 0`` where the car stands at the left wall moving left.
    """
    p, v = s[:, 0], s[:, 1]
    force = torch.clamp(u[:, 0], -1.0, 1.0)
    v = torch.clamp(v + force * power - 0.0025 * torch.cos(3 * p), -max_speed, max_speed)
    p = torch.clamp(p + v, min_position, max_position)
    v = torch.where((p == min_position) & (v < 0), torch.zeros_like(v), v)
    return torch.stack([p, v], dim=-1)


def mountain_car_noise_matrix(power: float = 0.0015) -> torch.Tensor:
    """``E`` (2, 1) float64 of a force added after the clip of MountainCarContinuous-v0: ``power [1, 1]^T``."""
    return torch.tensor([[power], [power]], dtype=torch.float64)


class PendulumV1Task(Task):
    """Gymnasium's Pendulum-v1 as a task: the model is the env's own step, the uncertainty an unmodelled
    torque ``xi ~ N(mu, K)`` added after the actuator clip (eq. 1 with ``E`` of
    :func:`pendulum_noise_matrix`).

    Parameters
    ----------
    torque_mean, torque_std : float
        The simulated plant's torque (``true_mean``, ``true_cov``; what the oracle and
        ``plant_evaluation = "simulated"`` use; a real plant has its own).
    prior_mean, prior_std : float
        The designer's prior on the torque (eq. 8).
    gamma : float
        The discount.

    Notes
    -----
    The utility is Gymnasium's, ``angle_normalize(theta)^2 + 0.1 theta_dot^2 + 0.001 u^2``, charged on the
    next state (eq. 2; the env charges the current one). ``action_limit`` is the env's ``max_torque``.
    With a ``saturation_margin`` (a bias entering before the clip) :meth:`saturated` also drops the
    transitions near the env's speed clip.
    """

    state_dim, obs_dim, action_dim, noise_dim = 2, 3, 1, 1
    eval_horizon = 200

    def __init__(self, torque_mean: float = 0.0, torque_std: float = 0.05, prior_mean: float = 0.0,
                 prior_std: float = 1.0, gamma: float = 0.97) -> None:
        self.gamma = float(gamma)
        self.noise_matrix = pendulum_noise_matrix()
        self.prior_mean, self.prior_cov = np.array([prior_mean], float), np.array([[prior_std**2]], float)
        self.true_mean, self.true_cov = np.array([torque_mean], float), np.array([[torque_std**2]], float)
        self.action_bound = torch.tensor([2.0])
        self.action_limit = torch.tensor([2.0])
        self.obs_scale = torch.tensor([1.0, 1.0, 8.0])
        self.value_scale = 50.0

    def f(self, s: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return pendulum_v1_step(s, u.to(s.dtype))

    def observe(self, s: torch.Tensor) -> torch.Tensor:
        return torch.stack([torch.cos(s[:, 0]), torch.sin(s[:, 0]), s[:, 1]], dim=-1)

    def cost(self, s_next: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        torque = torch.clamp(u[:, 0], -2.0, 2.0)
        return angle_normalize(s_next[:, 0]) ** 2 + 0.1 * s_next[:, 1] ** 2 + 0.001 * torque**2

    def state_error(self, s: torch.Tensor) -> torch.Tensor:
        """The error the evaluation reports: ``[angle_normalize(theta), theta_dot]`` (the angle from upright,
        wrapped into ``[-pi, pi)``, as the cost sees it; the state's angle is not wrapped)."""
        return torch.stack([angle_normalize(s[:, 0]), s[:, 1]], dim=-1)

    def saturated(self, s: torch.Tensor, u: torch.Tensor) -> torch.Tensor | None:
        """:meth:`Task.saturated`, plus (with a ``saturation_margin``) the rows whose rate the model brings
        within ``E_rate * margin`` of the env's speed clip."""
        rows = super().saturated(s, u)
        margin = float(torch.as_tensor(self.saturation_margin).max())
        if rows is None or margin <= 0:
            return rows
        with torch.no_grad():
            rate = self.f(s, u)[:, 1]
        return rows | (rate.abs() > 8.0 - float(self.noise_matrix[1, 0]) * margin)

    def sample_initial(self, n: int, generator: torch.Generator) -> torch.Tensor:
        high = torch.tensor([math.pi, 1.0], dtype=torch.float64)
        return (2 * torch.rand(n, 2, generator=generator, dtype=torch.float64) - 1) * high

    def sample_region(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """The env's whole state region (``algorithm.rollout_region``): ``theta in [-pi, pi]``,
        ``theta_dot in [-8, 8]``."""
        high = torch.tensor([math.pi, 8.0], dtype=torch.float64)
        return (2 * torch.rand(n, 2, generator=generator, dtype=torch.float64) - 1) * high


class MountainCarTask(Task):
    """MountainCarContinuous-v0 as a task: the model is the env's own step
    (:func:`mixedrl.envs.gym_models.mountain_car_step`), the uncertainty a force ``xi ~ N(mu, K)`` (action
    units) added after the actuator clip (``E = power [1, 1]^T``, :func:`mountain_car_noise_matrix`).

    The designer's cost (the env's reward is sparse) is the energy the car still lacks to stand at the
    flag, ``max(0, E_goal - E(s')) / (E_goal - E_min)`` with ``E(p, v) = 0.0025 / 3 sin(3 p) + v^2 / 2``,
    plus ``0.001 u^2``; a state past the flag (``p >= 0.45``) is terminal. The evaluation reports the
    env's own return.
    """

    state_dim, obs_dim, action_dim, noise_dim = 2, 2, 1, 1
    eval_horizon = 999
    goal = 0.45

    def __init__(self, force_mean: float = 0.0, force_std: float = 0.1, prior_mean: float = 0.0,
                 prior_std: float = 1.0, gamma: float = 0.99) -> None:
        self.gamma = float(gamma)
        self.noise_matrix = mountain_car_noise_matrix()
        self.prior_mean, self.prior_cov = np.array([prior_mean], float), np.array([[prior_std**2]], float)
        self.true_mean, self.true_cov = np.array([force_mean], float), np.array([[force_std**2]], float)
        self.action_bound = torch.tensor([1.0])
        self.action_limit = torch.tensor([1.0])
        self.obs_scale = torch.tensor([1.2, 0.07])
        self.value_scale = 30.0
        self.e_goal = self.energy(torch.tensor([[self.goal, 0.0]], dtype=torch.float64))[0].item()
        self.e_min = self.energy(torch.tensor([[-math.pi / 6, 0.0]], dtype=torch.float64))[0].item()

    @staticmethod
    def energy(s: torch.Tensor) -> torch.Tensor:
        return 0.0025 / 3 * torch.sin(3 * s[:, 0]) + 0.5 * s[:, 1] ** 2

    def f(self, s: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return mountain_car_step(s, u.to(s.dtype))

    def observe(self, s: torch.Tensor) -> torch.Tensor:
        return s

    def cost(self, s_next: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        force = torch.clamp(u[:, 0], -1.0, 1.0)
        lack = torch.clamp(self.e_goal - self.energy(s_next), min=0.0) / (self.e_goal - self.e_min)
        return lack.to(s_next.dtype) + 0.001 * force.to(s_next.dtype) ** 2

    def is_terminal(self, s: torch.Tensor) -> torch.Tensor:
        return super().is_terminal(s) | (s[:, 0] >= self.goal)

    def sample_initial(self, n: int, generator: torch.Generator) -> torch.Tensor:
        lo = torch.tensor([-1.2, -0.07], dtype=torch.float64)
        hi = torch.tensor([0.5, 0.07], dtype=torch.float64)
        return lo + (hi - lo) * torch.rand(n, 2, generator=generator, dtype=torch.float64)
