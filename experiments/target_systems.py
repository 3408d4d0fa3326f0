"""The two never-tuned TARGET systems of issue 42, written before any learner was measured on them.

Issue 42 measures the default learner, near an equilibrium, on the shipped pendulum, the linear test bed and
two systems nobody tuned on. These are those two. They are written the way a user writes a task from
``docs/tutorial.rst`` (a :class:`mixedrl.tasks.Task` subclass with an :class:`~mixedrl.tasks.Equilibrium`),
and they are used for the final measurement only (seeds 0-9): every choice of the learner is made on
:mod:`experiments.tuning_systems` with seeds 100 and up. ``experiments/studies/learner_targets.toml`` lists
the whole target set.

* :class:`CubicSpring`: a mass on a hardening (cubic) spring with viscous damping, positioned by a force
  ``|u| <= 3`` N against an unknown constant force (true 0.6 N, prior 0): the "own system" of the issue.
* :class:`HangingPendulum`: a lightly damped pendulum held at the bottom against an unknown constant torque
  that needs three quarters of the actuator's bound (true 1.5 N m, ``|u| <= 2`` N m, prior 0).

Import with the repository root on ``sys.path``: ``from experiments.target_systems import TARGET_SYSTEMS``.
"""

from __future__ import annotations

import numpy as np
import torch

from experiments.tuning_systems import _OriginTask
from mixedrl.tasks import Task

__all__ = ["CubicSpring", "HangingPendulum", "TARGET_SYSTEMS"]


class _BoxTask(_OriginTask):
    """Shared by both (the tuning systems' template, :class:`experiments.tuning_systems._OriginTask`): the
    state observed as it is, starts uniform in ``[-init, init]`` (also ``obs_scale``), the origin with
    ``u* = 0`` as the equilibrium; the cost is ``sum_i w_i s'_i^2 + r u^2``."""

    state_dim = obs_dim = 2
    action_dim = noise_dim = 1
    gamma = 0.97
    r: float

    def cost(self, s_next: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return (s_next**2 * self._w.to(s_next.dtype)).sum(-1) + self.r * (u**2).sum(-1)


class CubicSpring(_BoxTask):
    """A mass ``m`` on a hardening spring ``k x + k3 x^3`` with viscous damping ``c v``, driven by a force
    ``u`` [N], ``|u| <= 3``, against an unknown constant force ``F_d`` (true 0.6 N, prior 0, std 0.5 N).

    State ``s = [x, v]``: position from the rest point [m] and velocity [m/s]. Semi-implicit Euler, ``dt``:

    .. math::

        v' = v + \\frac{dt}{m}\\big(u - k x - k_3 x^3 - c v\\big) + \\xi, \\qquad x' = x + dt\\, v'_{\\text{model}},
        \\qquad \\xi = \\frac{dt}{m} F_d,

    written as ``x' = f(x, u) + E xi`` with ``E = [dt, 1]^T`` (the force reaches the position through the
    updated velocity: a full-column-rank ``E`` that is not a 0/1 selection). Cost
    ``l(s', u) = 4 x'^2 + 0.1 v'^2 + 0.05 u^2``; ``gamma = 0.97``.
    """

    def __init__(self, dt: float = 0.05, mass: float = 1.0, stiffness: float = 1.0, cubic: float = 2.0,
                 damping: float = 0.3, force_bound: float = 3.0, force_bias: float = 0.6, force_std: float = 0.1,
                 prior_force_std: float = 0.5) -> None:
        self.dt, self.mass, self.k, self.k3, self.c = dt, mass, stiffness, cubic, damping
        k = dt / mass
        self.noise_matrix = torch.tensor([[dt], [1.0]])
        self.prior_mean, self.prior_cov = np.zeros(1), np.array([[(k * prior_force_std) ** 2]])
        self.true_mean, self.true_cov = np.array([k * force_bias]), np.array([[(k * force_std) ** 2]])
        self.action_bound = torch.tensor([force_bound])
        self.init = (1.0, 1.0)
        self.obs_scale = torch.tensor(self.init)
        self.value_scale = 3.0
        self.r = 0.05
        self._w = torch.tensor([4.0, 0.1], dtype=torch.float64)

    def f(self, s: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        x, v = s[:, 0], s[:, 1]
        v_next = v + self.dt / self.mass * (u[:, 0] - self.k * x - self.k3 * x**3 - self.c * v)
        return torch.stack([x + self.dt * v_next, v_next], dim=1)

    def is_terminal(self, s: torch.Tensor) -> torch.Tensor:
        """Not finite, or beyond the stroke: ``|x| > 4`` m."""
        return ~torch.isfinite(s).all(dim=-1) | (s[:, 0].abs() > 4.0)


class HangingPendulum(_BoxTask):
    """A pendulum (mass ``m`` at length ``l``, damping ``b``) held at the bottom by a torque ``u`` [N m],
    ``|u| <= 2``, against an unknown constant torque ``tau`` (true 1.5 N m, three quarters of the bound;
    prior 0, std 1 N m).

    State ``s = [theta, omega]``: angle from the bottom [rad] and rate [rad/s]. Forward Euler of
    ``m l^2 theta'' = -m g l sin(theta) - b theta' + u + tau``:

    .. math::

        \\theta' = \\theta + dt\\, \\omega, \\qquad
        \\omega' = \\omega + \\frac{dt}{m l^2}\\big(u - m g l \\sin\\theta - b\\, \\omega\\big) + \\xi,
        \\qquad \\xi = \\frac{dt}{m l^2} \\tau,

    ``E = [0, 1]^T``. Cost ``l(s', u) = theta'^2 + 0.05 omega'^2 + 0.02 u^2``; ``gamma = 0.97``. Unopposed,
    the torque holds the pendulum at ``asin(tau / (m g l)) = 0.31`` rad; the LQR with the prior's (zero)
    feed-forward leaves a visible part of that offset, the LQR with the true feed-forward none.
    """

    def __init__(self, dt: float = 0.05, gravity: float = 9.81, length: float = 0.5, mass: float = 1.0,
                 damping: float = 0.05, torque_bound: float = 2.0, torque_bias: float = 1.5, torque_std: float = 0.2,
                 prior_torque_std: float = 1.0) -> None:
        self.dt, self.g, self.length, self.mass, self.b = dt, gravity, length, mass, damping
        inertia = mass * length**2
        k = dt / inertia
        self.noise_matrix = torch.tensor([[0.0], [1.0]])
        self.prior_mean, self.prior_cov = np.zeros(1), np.array([[(k * prior_torque_std) ** 2]])
        self.true_mean, self.true_cov = np.array([k * torque_bias]), np.array([[(k * torque_std) ** 2]])
        self.action_bound = torch.tensor([torque_bound])
        self.init = (0.5, 1.0)
        self.obs_scale = torch.tensor(self.init)
        self.value_scale = 1.0
        self.r = 0.02
        self._w = torch.tensor([1.0, 0.05], dtype=torch.float64)

    def f(self, s: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        th, om = s[:, 0], s[:, 1]
        inertia = self.mass * self.length**2
        acc = (u[:, 0] - self.mass * self.g * self.length * torch.sin(th) - self.b * om) / inertia
        return torch.stack([th + self.dt * om, om + self.dt * acc], dim=1)

    def is_terminal(self, s: torch.Tensor) -> torch.Tensor:
        """Not finite, or swung over: ``|theta| > pi / 2``."""
        return ~torch.isfinite(s).all(dim=-1) | (s[:, 0].abs() > np.pi / 2)


#: The never-tuned target systems by name (constructors with their default parameters).
TARGET_SYSTEMS: dict[str, type[Task]] = {"cubic_spring": CubicSpring, "hanging_pendulum": HangingPendulum}
