"""Held-out TUNING systems for the learner work of issue 42: written the way a user writes a task from
``docs/tutorial.rst`` (a :class:`mixedrl.tasks.Task` subclass, an :class:`~mixedrl.tasks.Equilibrium`),
never shipped in the package and never a target.

Issue 42 asks that every choice of the learner be made on held-out seeds and on systems that are not the
targets (the shipped pendulum, the linear test bed and two never-tuned systems). These are those tuning
systems; the targets and their seeds 0-9 are left for the final measurement. Use seeds 100 and up here.

* :class:`CartFriction`: a cart positioned by a force, with viscous and smooth Coulomb (``tanh``) friction
  and an unknown constant force (a slope, a cable): state (position error, velocity).
* :class:`TwoTank`: two cascaded tanks with Torricelli (``sqrt``) outflows, a pump into the upper tank and
  an unknown constant inflow into the lower one; the lower level is held at a setpoint.

Each has a differentiable torch ``f``, a quadratic cost with its minimum at the equilibrium, an action
bound, ``E``, a prior with mean 0 against a true mean large enough that the prior's discounted LQR holds a
visibly worse steady offset than the LQR with the true feed-forward (:func:`lqr_reference`).

Import with the repository root on ``sys.path``: ``from experiments.tuning_systems import TUNING_SYSTEMS``.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mixedrl.precision import lq_reference
from mixedrl.tasks import Equilibrium, Task

_ANALYSIS = Path(__file__).resolve().parent / "analysis"
if str(_ANALYSIS) not in sys.path:
    sys.path.insert(0, str(_ANALYSIS))
from precision_study import LQRPolicy  # noqa: E402  (the discounted LQR with a mean's feed-forward, as a policy)

__all__ = ["CartFriction", "TwoTank", "SwingUp", "SwingUpEquilibrium", "SwingUpBias",
           "CartNoisy", "CartDrift", "CartDrift3", "CartDriftBias", "TUNING_SYSTEMS", "GLOBAL_TUNING_SYSTEMS", "LQRPolicy", "lqr_reference"]


class _OriginTask(Task):
    """What both systems share: the state is observed as it is, training (and evaluation) starts are uniform
    in the box ``[-init, init]`` (``init``, also ``obs_scale``), and the equilibrium is the origin with
    ``u* = 0``."""

    init: tuple[float, float]

    def observe(self, s: torch.Tensor) -> torch.Tensor:
        return s

    def sample_initial(self, n: int, generator: torch.Generator) -> torch.Tensor:
        box = torch.tensor(self.init, dtype=torch.float64)
        return (2.0 * torch.rand(n, 2, generator=generator, dtype=torch.float64) - 1.0) * box

    def equilibrium(self) -> Equilibrium:
        return Equilibrium(state=np.zeros(2), action=np.zeros(1))


class CartFriction(_OriginTask):
    """A cart of mass ``m`` driven by a force ``u`` [N], ``|u| <= 5``, with viscous friction ``c v`` and smooth
    Coulomb friction ``F_c tanh(v / v_s)``, against an unknown constant force ``F_d`` (true 1.5 N, prior 0).

    State ``s = [e, v]``: position error from the setpoint [m] and velocity [m/s]. Forward Euler, ``dt``:

    .. math::

        e' = e + dt\\, v, \\qquad v' = v + \\frac{dt}{m}\\big(u - c v - F_c \\tanh(v / v_s)\\big) + \\xi,
        \\qquad \\xi = \\frac{dt}{m} F_d .

    ``E = [0, 1]^T``. Cost ``l(s', u) = e'^2 + 0.1 v'^2 + 0.01 u^2``; ``gamma = 0.97``. Equilibrium: the origin,
    ``u* = 0`` (the smooth friction is zero at ``v = 0``, so a constant force is not held by friction: the
    controller must cancel it). The ``tanh`` makes the damping near rest 16 times that at speed (``c + F_c / v_s = 3.2``
    against ``c = 0.2`` N s/m): the linearisation holds only for ``|v| << v_s = 0.1`` m/s.
    """

    state_dim = obs_dim = 2
    action_dim = noise_dim = 1
    gamma = 0.97

    def __init__(self, dt: float = 0.05, mass: float = 1.0, viscous: float = 0.2, coulomb: float = 0.3,
                 v_smooth: float = 0.1, force_bound: float = 5.0, force_bias: float = 1.5, force_std: float = 0.2,
                 prior_force_std: float = 0.5) -> None:
        self.dt, self.mass, self.viscous, self.coulomb, self.v_smooth = dt, mass, viscous, coulomb, v_smooth
        k = dt / mass  # xi per N
        self.xi_per_force = k
        self.noise_matrix = torch.tensor([[0.0], [1.0]])
        self.prior_mean, self.prior_cov = np.zeros(1), np.array([[(k * prior_force_std) ** 2]])
        self.true_mean, self.true_cov = np.array([k * force_bias]), np.array([[(k * force_std) ** 2]])
        self.action_bound = torch.tensor([force_bound])
        self.init = (0.5, 0.5)
        self.obs_scale = torch.tensor(self.init)
        self.value_scale = 1.0
        self._w = torch.tensor([1.0, 0.1], dtype=torch.float64)

    def f(self, s: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        e, v = s[:, 0], s[:, 1]
        friction = self.viscous * v + self.coulomb * torch.tanh(v / self.v_smooth)
        return torch.stack([e + self.dt * v, v + self.dt / self.mass * (u[:, 0] - friction)], dim=1)

    def cost(self, s_next: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return (s_next**2 * self._w.to(s_next.dtype)).sum(-1) + 0.01 * (u**2).sum(-1)

    def is_terminal(self, s: torch.Tensor) -> torch.Tensor:
        """Not finite, or off the track: ``|e| > 3`` m."""
        return ~torch.isfinite(s).all(dim=-1) | (s[:, 0].abs() > 3.0)


class TwoTank(_OriginTask):
    """Two cascaded tanks (area 1), Torricelli outflows ``q_i = c sqrt(h_i)``, a pump ``q* + u`` into the upper
    tank (``|u| <= 0.5 = q*``, so the pump never runs backwards) and an unknown constant inflow ``q_d`` into
    the lower one (true 0.06, 12% of the nominal flow; prior 0). The lower level is held at ``h* = 1``.

    State ``s = [h1 - h*, h2 - h*]`` (deviations from the setpoint, both tanks at ``h* = 1`` when ``q_d = 0``).
    Forward Euler, ``dt = 0.5`` s, with ``sqrt`` of a smooth positive part ``h+ = (h + sqrt(h^2 + 1e-4)) / 2``
    (differentiable, a drained tank has no outflow):

    .. math::

        h_1' = h_1 + dt\\,(q^* + u - c\\sqrt{h_1^+}), \\qquad h_2' = h_2 + dt\\,(c\\sqrt{h_1^+} - c\\sqrt{h_2^+}) + \\xi,
        \\qquad \\xi = dt\\, q_d,

    ``c = 0.5``, ``q* = c sqrt(1+) ~ 0.5``. ``E = [0, 1]^T``. Cost ``l(s', u) = 10 (h_2' - h^*)^2 + 0.5 (h_1' - h^*)^2
    + 0.5 u^2``; ``gamma = 0.97``. The equilibrium is the setpoint with ``u* = 0``. Holding ``h_2`` at the setpoint
    against ``q_d`` needs ``h_1 = ((q* - q_d) / c)^2 = 0.77``, far from the linearisation's ``h_1 = 1``: the
    ``sqrt`` is felt at the steady state itself.
    """

    state_dim = obs_dim = 2
    action_dim = noise_dim = 1
    gamma = 0.97

    def __init__(self, dt: float = 0.5, outflow: float = 0.5, setpoint: float = 1.0, inflow_bias: float = 0.06,
                 inflow_std: float = 0.02, prior_inflow_std: float = 0.05) -> None:
        self.dt, self.c, self.h_star = dt, outflow, setpoint
        self.q_star = float(self._outflow(torch.tensor([setpoint], dtype=torch.float64))[0])
        self.noise_matrix = torch.tensor([[0.0], [1.0]])
        self.prior_mean, self.prior_cov = np.zeros(1), np.array([[(dt * prior_inflow_std) ** 2]])
        self.true_mean, self.true_cov = np.array([dt * inflow_bias]), np.array([[(dt * inflow_std) ** 2]])
        self.action_bound = torch.tensor([0.5])
        self.init = (0.3, 0.3)
        self.obs_scale = torch.tensor(self.init)
        self.value_scale = 3.0
        self._w = torch.tensor([0.5, 10.0], dtype=torch.float64)

    def _outflow(self, h: torch.Tensor) -> torch.Tensor:
        return self.c * torch.sqrt(0.5 * (h + torch.sqrt(h * h + 1e-4)))

    def f(self, s: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        h1, h2 = s[:, 0] + self.h_star, s[:, 1] + self.h_star
        q1, q2 = self._outflow(h1), self._outflow(h2)
        h1n = h1 + self.dt * (self.q_star + u[:, 0] - q1)
        h2n = h2 + self.dt * (q1 - q2)
        return torch.stack([h1n - self.h_star, h2n - self.h_star], dim=1)

    def cost(self, s_next: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return (s_next**2 * self._w.to(s_next.dtype)).sum(-1) + 0.5 * (u**2).sum(-1)

    def is_terminal(self, s: torch.Tensor) -> torch.Tensor:
        """Not finite, or a tank empty or overflowing: a level outside ``(0, 2 h*)``."""
        return ~torch.isfinite(s).all(dim=-1) | (s.abs() > self.h_star).any(dim=-1)


class SwingUp(Task):
    r"""A GLOBAL tuning system: a pendulum swung up from anywhere and balanced upright, written for issue 42's
    global learner (not Pendulum-v1: another mass, length, torque bound and cost), with an unknown constant
    torque ``tau_d`` (true 0.6 N m, prior 0) added after the actuator clip.

    State ``s = [theta, theta_dot]``, ``theta = 0`` upright. Semi-implicit Euler, ``dt = 0.05``:

    .. math::

        \dot\theta' = \operatorname{clip}\Big(\dot\theta + dt\big(\tfrac{3 g}{2 l} \sin\theta
            + \tfrac{3}{m l^2} \operatorname{clip}(u, \pm \bar u)\big), \pm 8\Big) + \xi, \qquad
        \theta' = \theta + dt\, \dot\theta' + dt\, \xi, \qquad \xi = dt \tfrac{3}{m l^2} \tau_d,

    ``m = 0.8``, ``l = 1.2``, ``g = 9.81``, ``u_bar = 2.5`` (the torque cannot hold the pendulum level: it must
    swing up). Cost ``l(s', u) = wrap(theta')^2 + 0.1 theta_dot'^2 + 0.002 u^2``, ``gamma = 0.99``. Observation
    ``(cos theta, sin theta, theta_dot)``. Starts uniform in ``theta in [-pi, pi]``, ``theta_dot in [-1, 1]``.
    The measure is the undiscounted return (minus the cost) of 200-step episodes from seeded starts
    (:meth:`evaluate_return`).
    """

    state_dim, obs_dim, action_dim, noise_dim = 2, 3, 1, 1
    gamma = 0.99
    eval_horizon = 200

    def __init__(self, mass: float = 0.8, length: float = 1.2, torque_bound: float = 2.5, torque_bias: float = 0.6,
                 torque_std: float = 0.05, prior_torque_std: float = 1.0, dt: float = 0.05) -> None:
        self.dt, self.mass, self.length, self.g = dt, mass, length, 9.81
        c = 3.0 / (mass * length**2)
        self.noise_matrix = torch.tensor([[c * dt * dt], [c * dt]], dtype=torch.float64)
        self.prior_mean, self.prior_cov = np.zeros(1), np.array([[prior_torque_std**2]])
        self.true_mean, self.true_cov = np.array([torque_bias]), np.array([[torque_std**2]])
        self.action_bound = torch.tensor([torque_bound])
        self.obs_scale = torch.tensor([1.0, 1.0, 8.0])
        self.value_scale = 50.0

    def f(self, s: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        th, thdot = s[:, 0], s[:, 1]
        bound = float(self.action_bound[0])
        torque = torch.clamp(u[:, 0].to(s.dtype), -bound, bound)
        acc = 3 * self.g / (2 * self.length) * torch.sin(th) + 3.0 / (self.mass * self.length**2) * torque
        thdot_n = torch.clamp(thdot + self.dt * acc, -8.0, 8.0)
        return torch.stack([th + self.dt * thdot_n, thdot_n], dim=1)

    def observe(self, s: torch.Tensor) -> torch.Tensor:
        return torch.stack([torch.cos(s[:, 0]), torch.sin(s[:, 0]), s[:, 1]], dim=-1)

    def cost(self, s_next: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        wrapped = torch.remainder(s_next[:, 0] + np.pi, 2 * np.pi) - np.pi
        return wrapped**2 + 0.1 * s_next[:, 1] ** 2 + 0.002 * (u**2).sum(-1)

    def sample_initial(self, n: int, generator: torch.Generator) -> torch.Tensor:
        high = torch.tensor([np.pi, 1.0], dtype=torch.float64)
        return (2 * torch.rand(n, 2, generator=generator, dtype=torch.float64) - 1) * high

    def sample_region(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """The whole state region (``algorithm.rollout_region``): ``theta in [-pi, pi]``, ``theta_dot in [-8, 8]``."""
        high = torch.tensor([np.pi, 8.0], dtype=torch.float64)
        return (2 * torch.rand(n, 2, generator=generator, dtype=torch.float64) - 1) * high

    def evaluate_return(self, policy: torch.nn.Module, episodes: int = 20, seed: int = 1000) -> dict[str, float]:
        """Undiscounted returns (minus the summed cost) of ``episodes`` 200-step episodes of the true plant
        (the model plus the true torque and its noise) from starts drawn with ``seed``: mean, IQM, min."""
        gen = torch.Generator().manual_seed(seed)
        s = self.sample_initial(episodes, gen)
        total = torch.zeros(episodes, dtype=torch.float64)
        with torch.no_grad():
            for _ in range(self.eval_horizon):
                u = policy(self.observe(s).float()).double()
                s = self.true_step(s, u, gen)
                total -= self.cost(s, u)
        r = np.sort(total.numpy())
        q = len(r) // 4
        return {"mean": float(r.mean()), "iqm": float(r[q:len(r) - q].mean()), "min": float(r[0])}


class CartNoisy(CartFriction):
    """:class:`CartFriction` with a force noise five times as large (std 1.0 N beside the 1.5 N bias; the prior
    zero-mean with std 1.0 N): the noise keeps the velocity in a cloud about half the feed-forward's width
    (``algorithm.feedforward_width`` 0.25 of ``obs_scale``; the cart's is a tenth), as on the linear test bed."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**{"force_std": 1.0, "prior_force_std": 1.0, **kwargs})


class CartDrift(CartFriction):
    """:class:`CartFriction` whose training (and evaluation) starts lie in a smaller box (``box``: 0.1 m and
    0.1 m/s by default, a fifth of the cart's; ``obs_scale`` kept at 0.5): the prior LQR's rest point under the
    true force (about 0.195 m) lies outside the states a run trains from, as the prior's rest point (2.93) lies
    outside the linear test bed's box (1). :class:`CartDrift3` matches the test bed's ratio of the two (3)."""

    def __init__(self, box: float = 0.1, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.init = (box, box)


class CartDrift3(CartDrift):
    """:class:`CartDrift` with the box at 0.065: the prior LQR's rest point at three times the box, as on the
    linear test bed."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**{"box": 0.065, **kwargs})


class CartDriftBias(CartDrift):
    """:class:`CartDrift` (box 0.1) with twice the force (true 3 N, 60% of the 5 N bound; the linear test bed's
    needs half its bound): the action that holds the cart is about four times what the prior's LQR takes at the
    box's edge (the test bed's: 3.5 times), so an actor must extrapolate far beyond what it was trained on."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**{"force_bias": 3.0, **kwargs})


#: The tuning systems by name (constructors with their default parameters).
TUNING_SYSTEMS: dict[str, type[Task]] = {"cart_friction": CartFriction, "two_tank": TwoTank, "cart_noisy": CartNoisy,
                                         "cart_drift": CartDrift, "cart_drift3": CartDrift3,
                                         "cart_drift_bias": CartDriftBias}
#: The global tuning systems by name (no equilibrium to compare with an LQR: measured by their return).
class SwingUpEquilibrium(SwingUp):
    """:class:`SwingUp` that declares its upright rest point (``theta = 0``, ``u = 0``; the model's), so that
    ``algorithm.feedforward = "lq_ss"`` (``"auto"``) shifts its policy: the check that a shift at the top leaves a
    global swing-up intact."""

    def equilibrium(self) -> Equilibrium:
        return Equilibrium(state=np.zeros(2), action=np.zeros(1))


class SwingUpBias(SwingUp):
    """:class:`SwingUp` with a torque twice as large (true 1.2 N m, about half the 2.5 N m bound; prior 0): a
    second global tuning system, where the unmodelled torque takes half the actuator's authority on one side."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**{"torque_bias": 1.2, **kwargs})


GLOBAL_TUNING_SYSTEMS: dict[str, type[Task]] = {"swing_up": SwingUp, "swing_up_eq": SwingUpEquilibrium,
                                                "swing_up_bias": SwingUpBias}


def lqr_reference(task: Task) -> dict[str, Any]:
    """The discounted LQR on the task's linearisation with the true and with the prior's feed-forward
    (:func:`mixedrl.precision.lq_reference`): gain, action at the equilibrium, the steady state it holds
    on the linearisation under the true mean, and the closed loop's spectral radius."""
    lin = task.linearisation()
    out: dict[str, Any] = {}
    for name, mean in (("true_mean", task.true_mean), ("prior_mean", task.prior_mean)):
        ref = lq_reference(lin, mean)
        L, l0 = ref.solution.gain, ref.solution.offset
        x_ss = np.linalg.solve(np.eye(lin.A.shape[0]) - lin.A + lin.B @ L, lin.E @ task.true_mean - lin.B @ l0)
        out[name] = {"gain": (-L).tolist(), "action_at_equilibrium": ref.action.tolist(),
                     "steady_state_true_mean": x_ss.tolist()}
    ref = lq_reference(lin, task.true_mean)
    out["closed_loop_spectral_radius"] = float(np.max(np.abs(np.linalg.eigvals(lin.A - lin.B @ ref.solution.gain))))
    return out
