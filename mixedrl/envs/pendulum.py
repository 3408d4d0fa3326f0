"""A second worked example beside the vehicle: the inverted pendulum with an unmodelled torque bias.

:class:`PendulumTask` is nonlinear, open-loop unstable and input-bounded; its true environment carries a
constant torque the designer's prior misses (docs/pendulum.rst). It is registered as
``task.name = "pendulum"`` with its configuration :class:`PendulumTaskConfig`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import torch

from mixedrl.checks import check_fields, check_number
from mixedrl.tasks import Equilibrium, Linearisation, Task, register_task

__all__ = ["PendulumTask", "PendulumTaskConfig"]

#: Parameters that must be finite and positive (the others: ``torque_bias``, ``prior_torque_bias``
#: finite, ``gamma`` in (0, 1)).
_POSITIVE = ("dt", "gravity", "length", "mass", "damping", "torque_bound", "torque_std", "prior_torque_std",
             "q_omega", "r", "init_angle", "init_rate", "value_scale")


def _check_parameters(values: dict[str, Any], where: str = "") -> None:
    """Check the pendulum's parameters; an error names the key (``where`` + its name)."""
    for name in _POSITIVE:
        check_number(values[name], where + name, positive=True)
    for name in ("torque_bias", "prior_torque_bias"):
        check_number(values[name], where + name)
    gamma = values["gamma"]
    if not 0.0 < gamma < 1.0:
        raise ValueError(f"{where}gamma: expected a number in (0, 1), got {gamma!r}")


class PendulumTask(Task):
    """Inverted pendulum held upright by a bounded torque against an unmodelled constant torque bias.

    State ``s = [theta, omega]``: angle from the upright [rad] (positive counter-clockwise) and angular
    rate [rad/s]; input ``u``: the torque at the pivot [N m], ``|u| <= torque_bound``. Forward Euler
    with step ``dt`` of ``m l^2 theta'' = m g l sin(theta) - b theta' + u + tau``:

    .. math::

        \\theta_{t+1} = \\theta_t + dt\\, \\omega_t, \\qquad
        \\omega_{t+1} = \\omega_t + \\frac{dt}{m l^2}\\big(m g l \\sin\\theta_t - b\\,\\omega_t + u_t\\big)
        + \\xi_t,

    with ``xi = dt tau / (m l^2)`` the disturbance torque ``tau ~ N(torque_bias, torque_std^2)`` in rate
    units: the noise enters the rate only (``noise_matrix = [[0], [1]]``). The model ``f`` (what mixed
    RL plans with) is the bracket without ``xi``; the designer's prior on ``tau`` is
    ``N(prior_torque_bias, prior_torque_std^2)`` (0 and 0.2 N m by default), so the true bias of 0.5 N m
    is unmodelled. The utility is charged on the next state (eq. 2):
    ``l(s', u) = theta'^2 + q_omega omega'^2 + r u^2``.

    Parameters
    ----------
    dt : float, optional
        Sampling time [s].
    gravity, length, mass, damping : float, optional
        ``g`` [m/s^2], ``l`` [m], ``m`` [kg], ``b`` [N m s].
    torque_bound : float, optional
        Bound of the input torque [N m] (the actor's output bound).
    torque_bias, torque_std : float, optional
        True disturbance torque: mean and standard deviation [N m].
    prior_torque_bias, prior_torque_std : float, optional
        The designer's prior on the disturbance torque [N m] (eq. 8).
    q_omega, r : float, optional
        Weights of ``omega'^2`` and ``u^2`` in the utility (``theta'^2`` has weight 1).
    gamma : float, optional
        Discount factor.
    init_angle, init_rate : float, optional
        Training (and evaluation) starts are uniform in ``[-init_angle, init_angle] x [-init_rate, init_rate]``.
    value_scale : float, optional
        Typical magnitude of the value (the critic's output scale).

    Raises
    ------
    ValueError
        A parameter is not a finite positive number (``torque_bias`` and ``prior_torque_bias``: finite),
        or ``gamma`` is outside (0, 1); the message names it.

    Notes
    -----
    ``obs_scale = (init_angle, init_rate)``; ``eval_horizon = 200`` steps (10 s at ``dt = 0.05``).
    """

    state_dim, obs_dim, action_dim, noise_dim = 2, 2, 1, 1
    name = "pendulum"

    def __init__(self, dt: float = 0.05, gravity: float = 9.81, length: float = 1.0, mass: float = 1.0,
                 damping: float = 0.1, torque_bound: float = 4.0, torque_bias: float = 0.5,
                 torque_std: float = 0.2, prior_torque_bias: float = 0.0, prior_torque_std: float = 0.2,
                 q_omega: float = 0.1, r: float = 0.01, gamma: float = 0.97, init_angle: float = 0.3,
                 init_rate: float = 0.3, value_scale: float = 1.0) -> None:
        _check_parameters(dict(locals()))
        self.dt, self.gravity, self.length, self.mass, self.damping = dt, gravity, length, mass, damping
        self.torque_bound, self.q_omega, self.r = float(torque_bound), float(q_omega), float(r)
        self.gamma = float(gamma)
        self.init_angle, self.init_rate = float(init_angle), float(init_rate)
        #: xi per N m of disturbance torque: ``dt / (m l^2)``.
        self.xi_per_torque = k = dt / (mass * length**2)
        self.noise_matrix = torch.tensor([[0.0], [1.0]])
        self.true_mean, self.true_cov = np.array([k * torque_bias]), np.array([[(k * torque_std) ** 2]])
        self.prior_mean, self.prior_cov = np.array([k * prior_torque_bias]), np.array([[(k * prior_torque_std) ** 2]])
        self.action_bound = torch.tensor([self.torque_bound])
        self.obs_scale = torch.tensor([self.init_angle, self.init_rate])
        self._weights = torch.tensor([1.0, self.q_omega], dtype=torch.float64)
        self.value_scale = float(value_scale)

    @classmethod
    def from_config(cls, config: "PendulumTaskConfig") -> "PendulumTask":
        """The pendulum of a run's task configuration (``TrainConfig.task`` with ``name = "pendulum"``)."""
        return cls(**{f.name: getattr(config, f.name) for f in fields(config) if f.name != "name"})

    def equilibrium(self) -> Equilibrium:
        """The upright rest point ``s* = [0, 0]``, ``u* = 0`` of the noise-free model."""
        return Equilibrium(state=np.zeros(2), action=np.zeros(1))

    def linearisation(self) -> Linearisation:
        """The discounted LQ problem at the upright equilibrium ``s = 0, u = 0``, written out by hand.

        Returns
        -------
        Linearisation
            ``A`` (2, 2), ``B`` (2, 1): Jacobians of :meth:`f` at the origin; ``Q = diag(1, q_omega)``,
            ``R = [[r]]`` (the utility is exactly quadratic, charged on the next state); ``E`` (2, 1), the
            noise matrix; ``gamma``. Item access (``lin["A"]``) works too.
        """
        k = self.xi_per_torque
        A = np.array([[1.0, self.dt], [k * self.mass * self.gravity * self.length, 1.0 - k * self.damping]])
        B = np.array([[0.0], [k]])
        eq = self.equilibrium()
        return Linearisation(A=A, B=B, Q=np.diag([1.0, self.q_omega]), R=np.array([[self.r]]),
                             E=self.noise_matrix.double().numpy(), gamma=self.gamma, state=eq.state,
                             action=eq.action)

    def torque_from_xi(self, xi: Any) -> Any:
        """Disturbance torque [N m] of a noise value (or IBE mean) ``xi`` [rad/s per step]."""
        return xi / self.xi_per_torque

    def f(self, s: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        theta, omega = s[:, 0], s[:, 1]
        k = self.xi_per_torque
        accel = self.mass * self.gravity * self.length * torch.sin(theta) - self.damping * omega + u[:, 0]
        return torch.stack([theta + self.dt * omega, omega + k * accel], dim=1)

    def observe(self, s: torch.Tensor) -> torch.Tensor:
        return s

    def cost(self, s_next: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return (s_next**2 * self._weights.to(s_next.dtype)).sum(dim=1) + self.r * (u**2).sum(dim=1)

    def sample_initial(self, n: int, generator: torch.Generator) -> torch.Tensor:
        box = torch.tensor([self.init_angle, self.init_rate], dtype=torch.float64)
        return (2.0 * torch.rand(n, 2, generator=generator, dtype=torch.float64) - 1.0) * box

    def is_terminal(self, s: torch.Tensor) -> torch.Tensor:
        """Not finite, or fallen: ``|theta| > pi / 2``."""
        return ~torch.isfinite(s).all(dim=-1) | (s[:, 0].abs() > 0.5 * math.pi)


@dataclass
class PendulumTaskConfig:
    """Configuration of :class:`PendulumTask` (``task.name = "pendulum"``): its constructor's arguments,
    with the same defaults and meaning (see :class:`PendulumTask`). Dotted keys: ``task.<field>``.

    Raises
    ------
    ValueError
        As :class:`PendulumTask`, the message naming the dotted key (``task.dt``, ``task.gamma``, ...).
    """

    name: str = "pendulum"
    dt: float = 0.05
    gravity: float = 9.81
    length: float = 1.0
    mass: float = 1.0
    damping: float = 0.1
    torque_bound: float = 4.0
    torque_bias: float = 0.5
    torque_std: float = 0.2
    prior_torque_bias: float = 0.0
    prior_torque_std: float = 0.2
    q_omega: float = 0.1
    r: float = 0.01
    gamma: float = 0.97
    init_angle: float = 0.3
    init_rate: float = 0.3
    value_scale: float = 1.0

    def __post_init__(self) -> None:
        if self.name != "pendulum":
            raise ValueError(f"task.name: expected 'pendulum' for PendulumTaskConfig, got {self.name!r}")
        check_fields(self, prefix="task.")
        _check_parameters(vars(self), "task.")


register_task(PendulumTask, PendulumTaskConfig)
