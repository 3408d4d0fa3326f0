"""The linear-quadratic test bed of Algorithm 2: :class:`LinearTask`.

A small linear system with mean-shifted Gaussian noise and a quadratic utility, held as a
:class:`mixedrl.lq.LQProblem`, whose optimum (:func:`mixedrl.lq.optimal_solution`) is known in closed form.
Built by ``make_task("linear")`` or from a :class:`mixedrl.config.LinearTaskConfig`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from mixedrl.checks import check_number
from mixedrl.config import LinearTaskConfig
from mixedrl.lq import LQProblem
from mixedrl.task_base import Equilibrium, Task

__all__ = ["LinearTask"]


def _default_problem(A: Any, B: Any, Q: Any, R: Any, gamma: float, true_mean: Any, true_cov: Any,
                     prior_mean: Any, prior_cov: Any) -> LQProblem:
    """The :class:`LinearTask` defaults (a sampled double integrator, the noise on the velocity) for what is
    not given; errors name :class:`LinearTask`'s arguments."""
    dt = 0.1
    A = np.array([[1.0, dt], [0.0, 1.0]]) if A is None else np.asarray(A, dtype=np.float64)
    B = np.array([[0.5 * dt * dt], [dt]]) if B is None else np.asarray(B, dtype=np.float64)
    if B.ndim != 2:
        raise ValueError(f"B: expected shape (n, m), got {B.shape}")
    n, m = B.shape
    if A.shape != (n, n):
        raise ValueError(f"A: expected shape ({n}, {n}), got {A.shape}")
    try:
        return LQProblem(
            A=A, B=B, Q=np.eye(n) if Q is None else Q, R=0.1 * np.eye(m) if R is None else R, gamma=gamma,
            noise_mean=np.r_[np.zeros(n - 1), 0.5] if true_mean is None else true_mean,
            noise_cov=np.diag(np.r_[np.zeros(n - 1), 0.01]) if true_cov is None else true_cov,
            prior_mean=np.zeros(n) if prior_mean is None else prior_mean,
            prior_cov=0.01 * np.eye(n) if prior_cov is None else prior_cov)
    except ValueError as exc:
        name, _, rest = str(exc).partition(":")
        name = {"noise_mean": "true_mean", "noise_cov": "true_cov"}.get(name, name)  # LinearTask's names
        raise ValueError(f"{name}:{rest}") from None


class LinearTask(Task):
    """A small linear-quadratic system with mean-shifted noise: the generic test bed of Algorithm 2.

    .. math::

        s' = A s + B u + \\xi, \\quad \\xi \\sim N(\\mu, K), \\qquad l(s', u) = s'^\\top Q s' + u^\\top R u,

    whose optimum is affine, ``u = -L s - l0``, with value ``s^T P s + 2 p^T s + c`` (EQUATIONS.md, last
    section). The default is a sampled double integrator (``dt = 0.1``) with the disturbance on the
    velocity, a prior mean of 0 and a true mean of 0.5.

    Parameters
    ----------
    A, B, Q, R : array_like, optional
        System and cost matrices, shapes (n, n), (n, m), (n, n), (m, m).
    gamma : float, optional
        Discount factor.
    true_mean, true_cov, prior_mean, prior_cov : array_like, optional
        True noise and the designer's prior (eq. 8), shapes (n,), (n, n).
    init_box : float, optional
        Initial states are uniform in ``[-init_box, init_box]^n``.
    action_bound : float, optional
        Bound of the MLP actor's output.
    problem : mixedrl.lq.LQProblem, optional
        The problem itself, instead of the matrices and moments (:meth:`from_problem`).

    Attributes
    ----------
    problem : mixedrl.lq.LQProblem
        The LQ problem (``true_mean``, ``true_cov`` are its ``noise_mean``, ``noise_cov``); ``A``, ``B``,
        ``Q``, ``R``, ``gamma`` and the moments are its arrays.

    Raises
    ------
    ValueError
        On inconsistent shapes, a covariance that is not symmetric PSD, ``R`` not positive definite,
        ``(A, B)`` not stabilisable (:class:`mixedrl.lq.LQProblem`), or ``problem`` given with matrices.
    """

    name = "linear"
    #: :meth:`evaluate`: 64 starts, 100 steps (the horizon also of an evaluation on a plant).
    eval_horizon = 100
    evaluates_on_plant = True
    counts_evaluation_transitions = True

    def __init__(self, A: Any = None, B: Any = None, Q: Any = None, R: Any = None, gamma: float = 0.9,
                 true_mean: Any = None, true_cov: Any = None, prior_mean: Any = None, prior_cov: Any = None,
                 init_box: float = 1.0, action_bound: float = 10.0, *, problem: LQProblem | None = None) -> None:
        if problem is None:
            problem = _default_problem(A, B, Q, R, gamma, true_mean, true_cov, prior_mean, prior_cov)
        elif not isinstance(problem, LQProblem):
            raise ValueError(f"problem: expected an LQProblem, got {type(problem).__name__}")
        elif any(v is not None for v in (A, B, Q, R, true_mean, true_cov, prior_mean, prior_cov)):
            raise ValueError("problem: given together with matrices or moments (pass one or the other)")
        self.problem = problem
        n, m = problem.n, problem.m
        self.A, self.B, self.Q, self.R = problem.A, problem.B, problem.Q, problem.R
        self.state_dim = self.obs_dim = self.noise_dim = n
        self.action_dim = m
        self.gamma = problem.gamma
        self.true_mean, self.true_cov = problem.noise_mean, problem.noise_cov
        self.prior_mean, self.prior_cov = problem.prior_mean, problem.prior_cov
        self.noise_matrix = torch.eye(n)
        self.init_box = check_number(init_box, "init_box", positive=True)
        self.action_bound = torch.full((m,), check_number(action_bound, "action_bound", positive=True))
        self.obs_scale = torch.ones(n)
        #: ``(A^T, B^T, Q, R)`` as tensors of each dtype :meth:`f` and :meth:`cost` see.
        self._mats = {dtype: tuple(torch.tensor(M, dtype=dtype) for M in (self.A.T, self.B.T, self.Q, self.R))
                      for dtype in (torch.float32, torch.float64)}

    @classmethod
    def from_problem(cls, problem: LQProblem, init_box: float = 1.0, action_bound: float = 10.0) -> "LinearTask":
        """The task of an :class:`mixedrl.lq.LQProblem` (held as :attr:`problem`)."""
        return cls(init_box=init_box, action_bound=action_bound, problem=problem)

    @classmethod
    def from_config(cls, config: LinearTaskConfig) -> "LinearTask":
        """Build the task of a :class:`mixedrl.config.LinearTaskConfig`, on its problem.

        Raises
        ------
        ValueError
            ``task.disturbance.law`` is not ``"gaussian"`` (the only law this task simulates).
        """
        law = config.disturbance.law
        if law != "gaussian":
            raise ValueError(f"task.disturbance.law: the linear task simulates only 'gaussian', got {law!r}")
        return cls.from_problem(config.problem(), init_box=config.init_box, action_bound=config.action_bound)

    def equilibrium(self) -> Equilibrium:
        """The origin ``s* = 0``, ``u* = 0`` (the linearisation is the task itself, ``E = I``)."""
        return Equilibrium(state=np.zeros(self.state_dim), action=np.zeros(self.action_dim))

    def f(self, s: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        # x' = A x + B u (deterministic part)
        return s @ self._mats[s.dtype][0] + u @ self._mats[s.dtype][1]

    def observe(self, s: torch.Tensor) -> torch.Tensor:
        return s

    def cost(self, s_next: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        # l(x', u) = x'^T Q x' + u^T R u  (next-state convention, eq. 2)
        Q, R = self._mats[s_next.dtype][2:]
        return torch.einsum("bi,ij,bj->b", s_next, Q, s_next) + torch.einsum("bi,ij,bj->b", u, R, u)

    def sample_initial(self, n: int, generator: torch.Generator) -> torch.Tensor:
        return (2.0 * torch.rand(n, self.state_dim, generator=generator, dtype=torch.float64) - 1.0) * self.init_box

    def is_terminal(self, s: torch.Tensor) -> torch.Tensor:
        return ~torch.isfinite(s).all(dim=-1) | (s.abs() > 20.0 * self.init_box).any(dim=-1)

    def mean_features(self, s: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Case-3 features ``g(x, u) = [1, x]`` (a mean affine in the state), (B, 1 + n) float64."""
        s = s.to(torch.float64)
        return torch.cat([torch.ones(s.shape[0], 1, dtype=torch.float64), s], dim=1)

    def evaluate(self, policy: torch.nn.Module, seeds: list[int], horizon: int | None = None) -> dict[str, Any]:
        """Discounted cost of 100-step rollouts (``horizon``) from 64 seeded starts, averaged over ``seeds``.

        Counts its steps in :attr:`evaluation_transitions`; with a plant attached, returns
        :attr:`plant_evaluate`'s evaluation instead.
        """
        if self.plant_evaluate is not None:  # on the task's plant, or none
            return self.plant_evaluate(policy, seeds, horizon)
        horizon = int(self.eval_horizon if horizon is None else horizon)
        n = int(self.eval_starts)
        self.evaluation_transitions += n * horizon * len(seeds)
        costs = []
        for seed in seeds:
            gen = torch.Generator().manual_seed(int(seed))
            s = self.sample_initial(n, gen)
            total = torch.zeros(n, dtype=torch.float64)
            with torch.no_grad():
                for t in range(horizon):
                    u = policy(s.float()).double()
                    s_next = self.true_step(s, u, gen)
                    total += self.gamma**t * self.cost(s_next, u)
                    s = s_next
            costs.append(float(total.mean()))
        return {"cost": float(np.mean(costs))}
