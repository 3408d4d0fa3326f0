"""The interface between the learning algorithms and a controlled system: :class:`Task`.

Algorithm 2 (:mod:`mixedrl.algorithms.agpi`) and DDPG (:mod:`mixedrl.algorithms.ddpg`) see a system
only through this small interface, so they run unchanged on the double lane change
(:class:`DoubleLaneChangeTask`, Section VI of the paper) and on any user system (:class:`LinearTask`, and
the tutorial). :func:`task_from_config` builds either from the run's task configuration
(:class:`mixedrl.config.DoubleLaneChangeTaskConfig`, :class:`mixedrl.config.LinearTaskConfig`), and
any task registered by name with :func:`register_task` (the pendulum of :mod:`mixedrl.envs.pendulum`,
registered when :mod:`mixedrl` is imported).

The double lane change's experiment lives here with its task: the options of its course sampler
(:class:`CourseSampler`, ``sampler.name = "dlc_course"``) and its preset (:data:`DLC_EXPERIMENT`), which
this module registers with :mod:`mixedrl.config` (importing :mod:`mixedrl` imports this module).

The true system is eq. (1) with the noise entering through a fixed matrix ``E``:

.. math::

    s_{t+1} = f(s_t, u_t) + E\\, \\xi_t, \\qquad \\xi_t \\sim N(\\mu, K),

where ``s`` is the simulator state (``state_dim``), ``xi`` the additive uncertainty of the paper
(``noise_dim``; for the vehicle the five components of eq. 53) and ``E`` (``state_dim x noise_dim``) a
selection matrix. The residual of eq. (10) is ``xi = E^T (s' - f(s, u))``. The policy and the critic see
the observation ``observe(s)``; the utility is charged on the next state, ``l(s', u)`` (eq. 2).
"""

from __future__ import annotations

import abc
import math
from dataclasses import dataclass, field
from typing import Any, Callable, ClassVar

import numpy as np
import torch

from mixedrl.checks import (as_vector, check_covariance, check_fraction, check_nonnegative_int, check_number,
                            check_positive_int)
from mixedrl.config import (MODEL_COURSE_STARTS, DoubleLaneChangeTaskConfig, LinearTaskConfig, ModelRolloutsSampler,
                            TaskConfig, register_preset, register_sampler, task_config)
from mixedrl.config import register_task as register_task_config
from mixedrl.envs import DoubleLaneChangeModel, evaluate_tracking, make_config
from mixedrl.gaussian import sample_gaussian
from mixedrl.lq import LQProblem

__all__ = ["Task", "LinearTask", "DoubleLaneChangeTask", "CourseSampler", "DLC_EXPERIMENT", "Equilibrium",
           "Linearisation", "check_task", "make_task", "register_task", "task_from_config"]



#: Largest ``|f(s*, u*) - s*|`` and ``|grad l|`` (relative to the state's and the cost's scale) accepted at an
#: equilibrium by :meth:`Task.linearisation` (float64 round-off of the model and the cost).
EQUILIBRIUM_ATOL = 1e-9


@dataclass(frozen=True)
class Equilibrium:
    """A rest point of the noise-free model: ``f(state, action) = state`` (:meth:`Task.equilibrium`).

    Attributes
    ----------
    state : numpy.ndarray, shape (state_dim,)
        ``s*``, float64.
    action : numpy.ndarray, shape (action_dim,)
        ``u*``, float64.
    """

    state: np.ndarray
    action: np.ndarray


@dataclass(frozen=True)
class Linearisation:
    """The discounted LQ problem of a task at an equilibrium (:meth:`Task.linearisation`).

    In the coordinates ``x`` of the linearisation (``x = s - s*`` unless the task says otherwise) and
    ``v = u - u*``,

    .. math:: x' = A x + B v + E \\xi, \\qquad l(x', v) = x'^\\top Q x' + v^\\top R v,\\qquad \\gamma,

    the next-state convention of eq. (2) (EQUATIONS.md, last section). The item access ``lin["A"]``
    (keys ``A``, ``B``, ``Q``, ``R``, ``E``, ``gamma``) is kept for the callers of the former dict of
    :meth:`mixedrl.envs.pendulum.PendulumTask.linearisation`.

    Attributes
    ----------
    A : numpy.ndarray, shape (n, n)
    B : numpy.ndarray, shape (n, action_dim)
    Q : numpy.ndarray, shape (n, n)
        Symmetric PSD.
    R : numpy.ndarray, shape (action_dim, action_dim)
        Symmetric positive definite.
    E : numpy.ndarray, shape (n, noise_dim)
        How the noise ``xi`` enters ``x``.
    gamma : float
        The task's discount.
    state : numpy.ndarray, shape (state_dim,)
        The task state at ``x = 0`` (``s*``).
    action : numpy.ndarray, shape (action_dim,)
        ``u*``.
    embed : callable, optional
        ``x`` (B, n) torch float64 -> task states (B, state_dim); default ``s* + x`` (then ``n = state_dim``).
    """

    A: np.ndarray
    B: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    E: np.ndarray
    gamma: float
    state: np.ndarray
    action: np.ndarray
    embed: Callable[[torch.Tensor], torch.Tensor] | None = field(default=None, compare=False)

    _KEYS = ("A", "B", "Q", "R", "E", "gamma")

    def __getitem__(self, key: str) -> Any:
        if key not in self._KEYS:
            raise KeyError(f"key: expected one of {list(self._KEYS)}, got {key!r}")
        return getattr(self, key)

    def to_state(self, x: torch.Tensor) -> torch.Tensor:
        """Task states of the coordinates ``x`` (B, n) -> (B, state_dim), float64 (differentiable)."""
        if self.embed is not None:
            return self.embed(x)
        return torch.as_tensor(self.state, dtype=torch.float64) + x


def _cost_hessian(cost: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], x0: torch.Tensor, u0: torch.Tensor,
                  name: str, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """``Q = l_xx / 2``, ``R = l_uu / 2`` of a batched cost ``l(x', u)`` at ``(x0, u0)`` (float64, ``torch.func``),
    after checking that the gradient and the cross term ``l_xu`` vanish there (see :meth:`Task.linearisation`)."""
    n = x0.shape[0]

    def stage(z: torch.Tensor) -> torch.Tensor:
        return cost(z[None, :n], z[None, n:])[0]

    z0 = torch.cat([x0, u0])
    grad = torch.func.jacrev(stage)(z0)
    H = torch.func.hessian(stage)(z0)
    H = 0.5 * (H + H.T)
    cost_scale = 1.0 + float(H.abs().max()) * scale
    if float(grad.abs().max()) > EQUILIBRIUM_ATOL * cost_scale:
        raise ValueError(f"cost: {name}.cost has a nonzero gradient {grad.tolist()} at the equilibrium (the LQ "
                         f"yardstick needs the cost's minimum there)")
    if float(H[:n, n:].abs().max()) > EQUILIBRIUM_ATOL * cost_scale:
        raise ValueError(f"cost: {name}.cost couples the next state and the action at the equilibrium (the LQ form "
                         f"l = x'^T Q x' + u^T R u has no cross term)")
    return 0.5 * H[:n, :n].numpy(), 0.5 * H[n:, n:].numpy()


class Task(abc.ABC):
    """A controlled system with a known deterministic part ``f`` and additive Gaussian noise (eq. 1).

    Subclasses set the attributes below in ``__init__`` and implement the abstract methods. Every
    tensor method is batched over the first dimension and differentiable in torch.

    Attributes
    ----------
    state_dim, obs_dim, action_dim, noise_dim : int
        Sizes of ``s``, ``observe(s)``, ``u`` and ``xi``.
    gamma : float
        Discount factor of eq. (2).
    noise_matrix : torch.Tensor, shape (state_dim, noise_dim)
        ``E``: a 0/1 selection matrix, how ``xi`` enters the state.
    prior_mean, prior_cov : numpy.ndarray, shapes (noise_dim,), (noise_dim, noise_dim)
        The designer's prior ``mu_M``, ``K_M`` (eq. 8).
    true_mean, true_cov : numpy.ndarray, shapes (noise_dim,), (noise_dim, noise_dim)
        The true noise (used only by the true environment and by the oracle baseline).
    action_bound : torch.Tensor, shape (action_dim,)
        Symmetric bounds of the actor's output.
    obs_scale : torch.Tensor, shape (obs_dim,)
        Typical magnitude of each observation component (the networks divide by it).
    value_scale : float
        Typical magnitude of the value (the critic's output is multiplied by it).
    true_mean_varies : bool
        Whether the true noise mean depends on the state (:meth:`true_mean_at`); ``False`` by default.
    name : str
        The task's name in a run's results (``results["task"]``); the class name unless the subclass sets it.
    eval_horizon : int
        Steps of each rollout of the default :meth:`evaluate` (200 unless the subclass sets it).
    eval_starts : int
        Start states per evaluation seed of the default :meth:`evaluate` (64 unless the subclass sets it).
    """

    state_dim: int
    obs_dim: int
    action_dim: int
    noise_dim: int
    gamma: float
    noise_matrix: torch.Tensor
    prior_mean: np.ndarray
    prior_cov: np.ndarray
    true_mean: np.ndarray
    true_cov: np.ndarray
    action_bound: torch.Tensor
    obs_scale: torch.Tensor
    value_scale: float = 1.0
    true_mean_varies: bool = False
    name: str
    eval_horizon: int = 200
    eval_starts: int = 64

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "name" not in cls.__dict__:
            cls.name = cls.__name__

    @abc.abstractmethod
    def f(self, s: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Deterministic part of the dynamics; ``s`` (B, state_dim), ``u`` (B, action_dim) -> (B, state_dim)."""

    @abc.abstractmethod
    def observe(self, s: torch.Tensor) -> torch.Tensor:
        """Observation of the policy and the critic; (B, state_dim) -> (B, obs_dim)."""

    @abc.abstractmethod
    def cost(self, s_next: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Utility ``l(s', u)`` charged on the next state (eq. 2); returns (B,)."""

    @abc.abstractmethod
    def sample_initial(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """``n`` initial states of the training environments, float64, (n, state_dim)."""

    def is_terminal(self, s: torch.Tensor) -> torch.Tensor:
        """Boolean (B,): the episode of this copy ends (left the domain, course finished, not finite)."""
        return ~torch.isfinite(s).all(dim=-1)

    def equilibrium(self) -> Equilibrium | None:
        """A rest point ``f(s*, u*) = s*`` of the noise-free model where the precision yardstick
        (:mod:`mixedrl.precision`) is taken; ``None`` here (a task without one has no ``policy_gap``).

        Subclasses with an equilibrium override it (:class:`LinearTask`, the pendulum: the origin;
        :class:`DoubleLaneChangeTask`: on the reference at the desired speed).
        """
        return None

    def linearisation(self) -> Linearisation | None:
        """The discounted LQ problem at :meth:`equilibrium` (``None`` without one).

        By default ``x = s - s*``, ``v = u - u*`` and

        .. math::

            A = \\frac{\\partial f}{\\partial s}(s^*, u^*),\\quad B = \\frac{\\partial f}{\\partial u}(s^*, u^*),\\quad
            Q = \\tfrac12 \\frac{\\partial^2 l}{\\partial s'^2},\\quad R = \\tfrac12 \\frac{\\partial^2 l}{\\partial u^2}
            \\ \\text{at } (s', u) = (s^*, u^*),\\qquad E = \\text{noise\\_matrix},

        from :func:`torch.func.jacrev` and :func:`torch.func.hessian` of :meth:`f` and :meth:`cost` in
        float64 (exact for a linear ``f`` and a quadratic ``l``, the second-order model otherwise).

        Returns
        -------
        Linearisation or None

        Raises
        ------
        ValueError
            ``f(s*, u*) != s*`` (not a rest point), the cost's gradient at ``(s*, u*)`` is not zero (the
            equilibrium is not the cost's minimum: the LQ problem would need linear terms), or its Hessian
            couples ``s'`` and ``u`` (the LQ form has no cross term); the message names ``equilibrium`` or
            ``cost``.
        """
        eq = self.equilibrium()
        if eq is None:
            return None
        s0 = torch.as_tensor(np.asarray(eq.state, dtype=np.float64))
        u0 = torch.as_tensor(np.asarray(eq.action, dtype=np.float64))
        name = type(self).__name__

        def step(s: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
            return self.f(s[None], u[None])[0]

        with torch.no_grad():
            drift = float((step(s0, u0) - s0).abs().max())
        scale = 1.0 + float(s0.abs().max())
        if drift > EQUILIBRIUM_ATOL * scale:
            raise ValueError(f"equilibrium: {name}.f(state, action) differs from state by {drift:.3g} (not a rest "
                             f"point of the model; override {name}.linearisation)")
        A, B = torch.func.jacrev(step, argnums=(0, 1))(s0, u0)
        Q, R = _cost_hessian(lambda x, u: self.cost(x, u), s0, u0, name, scale)
        return Linearisation(A=A.numpy(), B=B.numpy(), Q=Q, R=R, E=self.noise_matrix.double().numpy(),
                             gamma=float(self.gamma),
                             state=s0.numpy(), action=u0.numpy())

    def true_step(self, s: torch.Tensor, u: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """One step of the *true* environment, eq. (1): ``f(s, u) + E xi``, ``xi ~ N(true_mean, true_cov)``.

        Parameters
        ----------
        s : torch.Tensor, shape (B, state_dim)
            States (float64).
        u : torch.Tensor, shape (B, action_dim)
            Actions.
        generator : torch.Generator
            Source of the noise.

        Returns
        -------
        torch.Tensor, shape (B, state_dim)
            Next states, dtype of ``s``.
        """
        xi = sample_gaussian(self.true_mean, self.true_cov, s.shape[0], generator).to(s.dtype)
        return self.f(s, u.to(s.dtype)) + xi @ self.noise_matrix.to(s.dtype).T

    def true_mean_at(self, s: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """The true noise mean at each state, (B, noise_dim) float64: ``true_mean`` on every row here
        (subclasses whose mean depends on the state override it and set ``true_mean_varies``)."""
        return torch.as_tensor(self.true_mean, dtype=torch.float64).expand(s.shape[0], -1).clone()

    def mean_features(self, s: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Features ``g(x, u)`` of the Case-3 mean ``phi = W^T g`` (eq. 19, :class:`mixedrl.ibe.LinearFeatureIBE`),
        (B, p) float64, the first column the constant 1.

        Raises
        ------
        NotImplementedError
            The task defines no features (subclasses implement them).
        """
        raise NotImplementedError(f"{type(self).__name__}.mean_features is not implemented (Case 3 of the IBE "
                                  f"needs it)")

    def residuals(self, s: torch.Tensor, u: torch.Tensor, s_next: torch.Tensor) -> torch.Tensor:
        """Eq. (10) in noise coordinates: ``xi = E^T (s' - f(s, u))``, (B, noise_dim)."""
        with torch.no_grad():
            return (s_next - self.f(s, u.to(s.dtype))) @ self.noise_matrix.to(s.dtype)

    def evaluate(self, policy: torch.nn.Module, seeds: list[int], horizon: int | None = None) -> dict[str, Any]:
        """Seeded rollouts of the *true* environment (:meth:`true_step`) under ``policy`` from fixed starts.

        For each seed, a generator seeded with it draws :attr:`eval_starts` start states from
        :meth:`sample_initial` and then the noise of ``horizon`` steps; the action is
        ``policy(observe(s))`` (float32 observations, as in training). A copy that reaches a terminal state
        (:meth:`is_terminal`) stops: no cost, no state counted from then on. Subclasses with a
        task-specific evaluation (a course, a reference trajectory) override this method.

        Parameters
        ----------
        policy : torch.nn.Module
            The actor: observations (B, obs_dim) float32 -> actions (B, action_dim).
        seeds : list of int
            One set of starts and one noise realisation per seed.
        horizon : int, optional
            Steps per rollout; :attr:`eval_horizon` by default.

        Returns
        -------
        dict
            Means over the seeds and starts:

            - ``"cost"``: discounted cost ``sum_t gamma^t l(s_{t+1}, u_t)`` of a rollout;
            - ``"mean_abs_state"``: ``|s|`` averaged over the second half of the rollout and the state's
              components (the steady offset from the origin, with the noise's spread);
            - ``"mean_abs_state_<i>"``, ``"mean_state_<i>"``: per state component ``i``, ``|s_i|`` and the
              signed ``s_i`` over the second half (the latter is the steady offset a constant bias leaves);
            - ``"terminated_fraction"``: rollouts that reached a terminal state.

        Raises
        ------
        ValueError
            ``seeds`` empty, or ``horizon`` not a positive integer.
        """
        horizon = self.eval_horizon if horizon is None else horizon
        horizon = check_positive_int(horizon, "horizon")
        if len(seeds) == 0:
            raise ValueError("seeds: expected at least one evaluation seed, got none")
        n, half = int(self.eval_starts), int(horizon) // 2
        costs, terminated, abs_sums, sums, counts = [], [], [], [], []
        with torch.no_grad():
            for seed in seeds:
                gen = torch.Generator().manual_seed(int(seed))
                s = self.sample_initial(n, gen).to(torch.float64)
                alive = torch.ones(n, dtype=torch.bool)
                total = torch.zeros(n, dtype=torch.float64)
                abs_sum = torch.zeros(self.state_dim, dtype=torch.float64)
                signed_sum = torch.zeros(self.state_dim, dtype=torch.float64)
                count = 0.0
                for t in range(int(horizon)):
                    u = policy(self.observe(s.float())).double()
                    s_next = self.true_step(s, u, gen)
                    step_cost = self.cost(s_next, u).double()
                    total += torch.where(alive, self.gamma**t * step_cost, torch.zeros_like(total))
                    alive = alive & ~self.is_terminal(s_next)
                    s = torch.where(alive[:, None], s_next, s)
                    if t >= half:
                        kept = s[alive]
                        abs_sum += kept.abs().sum(dim=0)
                        signed_sum += kept.sum(dim=0)
                        count += kept.shape[0]
                costs.append(float(total.mean()))
                terminated.append(float((~alive).double().mean()))
                abs_sums.append(abs_sum)
                sums.append(signed_sum)
                counts.append(count)
        count = max(sum(counts), 1.0)
        mean_abs = (torch.stack(abs_sums).sum(dim=0) / count).tolist()
        mean = (torch.stack(sums).sum(dim=0) / count).tolist()
        out: dict[str, Any] = {"cost": float(np.mean(costs)), "mean_abs_state": float(np.mean(mean_abs)),
                               "terminated_fraction": float(np.mean(terminated))}
        out.update({f"mean_abs_state_{i}": v for i, v in enumerate(mean_abs)})
        out.update({f"mean_state_{i}": v for i, v in enumerate(mean)})
        return out


def _check_output(value: Any, task: Task, fn: str, shape: tuple[int, ...], dtype: torch.dtype | None) -> None:
    """Raise ``ValueError`` naming ``Task.fn`` unless ``value`` is a finite float tensor of ``shape`` (``dtype``)."""
    where = f"{type(task).__name__}.{fn}"
    if not isinstance(value, torch.Tensor):
        raise ValueError(f"{where}: expected a torch.Tensor of shape {shape}, returned {type(value).__name__}")
    if tuple(value.shape) != shape:
        raise ValueError(f"{where}: expected shape {shape}, returned shape {tuple(value.shape)}")
    if not value.is_floating_point() or (dtype is not None and value.dtype != dtype):
        expected = "a floating dtype" if dtype is None else str(dtype)
        raise ValueError(f"{where}: expected dtype {expected}, returned {value.dtype}")
    if not bool(torch.isfinite(value).all()):
        raise ValueError(f"{where}: returned NaN or inf values (on states from sample_initial, zero actions)")


def check_task(task: Task, batch: int = 3) -> None:
    """Check a task's sizes and its functions' outputs once, with errors that name the function.

    Calls :meth:`Task.sample_initial` (own generator, seed 0), :meth:`Task.observe`, :meth:`Task.f` and
    :meth:`Task.cost` on ``batch`` states with zero and bound actions, in float32 and float64 (training uses
    both); nothing of the task or of a trainer's random streams is touched.

    Parameters
    ----------
    task : Task
        The task to check.
    batch : int, optional
        Number of states to probe with.

    Raises
    ------
    ValueError
        A size attribute is not a positive integer, an array attribute has the wrong shape, or a function
        returns the wrong shape, dtype or non-finite values; the message names the task class, the
        attribute or function (``cost``, ``f``, ...), the expected and the returned shape.
    """
    name = type(task).__name__
    for attr in ("state_dim", "obs_dim", "action_dim", "noise_dim"):
        check_positive_int(getattr(task, attr, None), f"{name}.{attr}")
    n, m, o, d = task.state_dim, task.action_dim, task.obs_dim, task.noise_dim
    gamma = getattr(task, "gamma", None)
    if not isinstance(gamma, (float, int, np.floating)) or not 0.0 < float(gamma) < 1.0:
        raise ValueError(f"{name}.gamma: expected a discount factor in (0, 1), got {gamma!r}")
    for attr, shape in (("noise_matrix", (n, d)), ("prior_mean", (d,)), ("prior_cov", (d, d)),
                        ("true_mean", (d,)), ("true_cov", (d, d)), ("action_bound", (m,)), ("obs_scale", (o,))):
        v = getattr(task, attr, None)
        if v is None:
            raise ValueError(f"{name}.{attr}: not set (expected shape {shape})")
        arr = np.asarray(v.detach() if isinstance(v, torch.Tensor) else v, dtype=np.float64)
        if arr.shape != shape:
            raise ValueError(f"{name}.{attr}: expected shape {shape}, got shape {arr.shape}")
        if not np.isfinite(arr).all():
            raise ValueError(f"{name}.{attr}: contains NaN or inf")
        if attr in ("action_bound", "obs_scale") and not (arr > 0).all():
            raise ValueError(f"{name}.{attr}: expected positive values, got {arr.tolist()}")
    s = task.sample_initial(batch, torch.Generator().manual_seed(0))
    _check_output(s, task, "sample_initial", (batch, n), torch.float64)
    bound = torch.as_tensor(task.action_bound, dtype=torch.float64)
    for dtype in (torch.float32, torch.float64):
        x = s.to(dtype)
        _check_output(task.observe(x), task, "observe", (batch, o), None)
        for u in (torch.zeros(batch, m, dtype=dtype), bound.to(dtype).expand(batch, m).clone()):
            u.requires_grad_(True)
            s_next = task.f(x, u)
            _check_output(s_next, task, "f", (batch, n), dtype)
            if not s_next.requires_grad:
                raise ValueError(f"{name}.f: the output does not depend differentiably on u (a detached or "
                                 f"numpy computation?); the policy improvement differentiates through f")
            _check_output(task.cost(s_next, u), task, "cost", (batch,), None)


#: :class:`LinearTask`'s names of the :class:`mixedrl.lq.LQProblem` fields it calls otherwise.
_TASK_KEYS = {"noise_mean": "true_mean", "noise_cov": "true_cov"}


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
        raise ValueError(f"{_TASK_KEYS.get(name, name)}:{rest}") from None


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
        The LQ problem in its one representation (``true_mean`` is its ``noise_mean``, ``true_cov`` its
        ``noise_cov``); ``A``, ``B``, ``Q``, ``R``, ``gamma`` and the moments are its arrays. Its optimum
        is :func:`mixedrl.lq.optimal_solution`.

    Raises
    ------
    ValueError
        On inconsistent shapes, a covariance that is not symmetric PSD, ``R`` not positive definite,
        ``(A, B)`` not stabilisable (:class:`mixedrl.lq.LQProblem`), or ``problem`` given with matrices.
    """

    name = "linear"

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
        # views of the problem's arrays (the same objects)
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
        self.value_scale = 1.0
        A, B = self.A, self.B
        self._At = {torch.float32: torch.tensor(A.T, dtype=torch.float32), torch.float64: torch.tensor(A.T)}
        self._Bt = {torch.float32: torch.tensor(B.T, dtype=torch.float32), torch.float64: torch.tensor(B.T)}
        self._Q = {torch.float32: torch.tensor(self.Q, dtype=torch.float32), torch.float64: torch.tensor(self.Q)}
        self._R = {torch.float32: torch.tensor(self.R, dtype=torch.float32), torch.float64: torch.tensor(self.R)}

    @classmethod
    def from_problem(cls, problem: LQProblem, init_box: float = 1.0, action_bound: float = 10.0) -> "LinearTask":
        """The task of an :class:`mixedrl.lq.LQProblem` (held as :attr:`problem`)."""
        return cls(init_box=init_box, action_bound=action_bound, problem=problem)

    @classmethod
    def from_config(cls, config: LinearTaskConfig) -> "LinearTask":
        """Build the task of a :class:`mixedrl.config.LinearTaskConfig` (``task.*`` of a run's config), on
        its problem (:meth:`mixedrl.config.LinearTaskConfig.problem`).

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
        """The origin ``s* = 0``, ``u* = 0`` (the linearisation is the task itself: ``A``, ``B``, ``Q``, ``R``, ``E = I``)."""
        return Equilibrium(state=np.zeros(self.state_dim), action=np.zeros(self.action_dim))

    def f(self, s: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        # x' = A x + B u (deterministic part)
        return s @ self._At[s.dtype] + u @ self._Bt[s.dtype]

    def observe(self, s: torch.Tensor) -> torch.Tensor:
        return s

    def cost(self, s_next: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        # l(x', u) = x'^T Q x' + u^T R u  (next-state convention, eq. 2)
        Q, R = self._Q[s_next.dtype], self._R[s_next.dtype]
        return torch.einsum("bi,ij,bj->b", s_next, Q, s_next) + torch.einsum("bi,ij,bj->b", u, R, u)

    def sample_initial(self, n: int, generator: torch.Generator) -> torch.Tensor:
        return (2.0 * torch.rand(n, self.state_dim, generator=generator, dtype=torch.float64) - 1.0) * self.init_box

    def is_terminal(self, s: torch.Tensor) -> torch.Tensor:
        return ~torch.isfinite(s).all(dim=-1) | (s.abs() > 20.0 * self.init_box).any(dim=-1)

    def mean_features(self, s: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Case-3 features ``g(x, u) = [1, x]`` (a mean affine in the state), (B, 1 + n) float64."""
        s = s.to(torch.float64)
        return torch.cat([torch.ones(s.shape[0], 1, dtype=torch.float64), s], dim=1)

    def evaluate(self, policy: torch.nn.Module, seeds: list[int]) -> dict[str, Any]:
        """Discounted cost of 100-step rollouts from a fixed grid of starts, averaged over ``seeds``."""
        costs = []
        for seed in seeds:
            gen = torch.Generator().manual_seed(int(seed))
            s = self.sample_initial(64, gen)
            total = torch.zeros(64, dtype=torch.float64)
            with torch.no_grad():
                for t in range(100):
                    u = policy(s.float()).double()
                    s_next = self.true_step(s, u, gen)
                    total += self.gamma**t * self.cost(s_next, u)
                    s = s_next
            costs.append(float(total.mean()))
        return {"cost": float(np.mean(costs))}


#: Registered task name -> its :class:`Task` class (built by ``from_config``); :func:`register_task`.
_TASK_FACTORIES: dict[str, type] = {}


def register_task(task_cls: type, config_cls: type) -> type:
    """Register a named task: its :class:`Task` class and its configuration dataclass.

    ``config_cls`` is registered with :func:`mixedrl.config.register_task` (its ``name`` default is the
    task's name, which must equal ``task_cls.name``); :func:`task_from_config` and :func:`make_task` then
    build ``task_cls.from_config(config)``, so a run, a ``--set task.name=...`` override and a sweep
    specification can name the task.

    Raises
    ------
    ValueError
        ``task_cls`` is not a :class:`Task` subclass with a ``from_config`` class method, or its ``name``
        is not ``config_cls``'s (and the errors of :func:`mixedrl.config.register_task`).
    """
    if not (isinstance(task_cls, type) and issubclass(task_cls, Task) and hasattr(task_cls, "from_config")):
        raise ValueError(f"task_cls: expected a Task subclass with a from_config class method, got {task_cls!r}")
    register_task_config(config_cls)
    name = config_cls().name
    if getattr(task_cls, "name", None) != name:
        raise ValueError(f"task_cls: its name {getattr(task_cls, 'name', None)!r} is not the configuration's {name!r}")
    _TASK_FACTORIES[name] = task_cls
    return task_cls


def make_task(name: str, **kwargs: Any) -> Task:
    """Build a task by name: ``"dlc"`` (:class:`DoubleLaneChangeTask`), ``"linear"`` (:class:`LinearTask`)
    or a registered one (:func:`register_task`), with constructor arguments ``kwargs``.

    Raises
    ------
    ValueError
        ``name`` unknown (the message lists the known names).
    """
    if name == "linear":
        return LinearTask(**kwargs)
    if name == "dlc":
        return DoubleLaneChangeTask(**kwargs)
    if name in _TASK_FACTORIES:
        return _TASK_FACTORIES[name](**kwargs)
    raise ValueError(f"name: expected one of {('dlc', 'linear', *_TASK_FACTORIES)}, got {name!r}")


def task_from_config(config: TaskConfig | dict[str, Any] | str) -> Task:
    """Build the task of a run's task configuration (``TrainConfig.task``).

    Parameters
    ----------
    config : DoubleLaneChangeTaskConfig, LinearTaskConfig, a registered configuration, dict or str
        The configuration, or anything :func:`mixedrl.config.task_config` accepts (a name, a nested dict).

    Returns
    -------
    Task
        :class:`DoubleLaneChangeTask`, :class:`LinearTask` or the registered task class of
        ``config.name`` (:func:`register_task`).

    Raises
    ------
    ValueError
        An invalid configuration (the message starts with the dotted field name), or an unknown task
        name (``task.name``, listing the known ones).
    """
    config = task_config(config)
    if isinstance(config, DoubleLaneChangeTaskConfig):
        return DoubleLaneChangeTask.from_config(config)
    if isinstance(config, LinearTaskConfig):
        return LinearTask.from_config(config)
    return _TASK_FACTORIES[config.name].from_config(config)


class DoubleLaneChangeTask(Task):
    """The double lane change of Section VI as a :class:`Task` (an adapter on :mod:`mixedrl.envs`).

    * state: the tracking state ``s = [v_y, r, v_x, phi, Y, X]`` of
      :class:`~mixedrl.envs.DoubleLaneChangeModel`; ``f`` = its ``step`` (eq. 53, forward Euler);
    * noise: the paper's five-component ``xi`` on ``x = [v_y, r, v_x, phi, y]`` (eq. 54), entering the
      first five state components (``E = [I_5; 0]``); the true noise is ``F_dis T / m`` on ``v_x``
      (component :attr:`noise_index`; ``T / m`` is :attr:`force_scale`) with ``F_dis ~ N(261, 32)`` by
      default (drawn by the model's ``sample_force``, so a configured road grade and law -- Gaussian,
      Student-t or two-point, :class:`mixedrl.envs.Disturbance` -- are honoured);
    * prior (eq. 55): ``mu_M = 150 T/m`` and ``K_M = (4 T/m)^2`` on ``v_x``, ``1e-20`` on the other four
      diagonal entries (EQUATIONS.md point 6: the paper's prior is read as acting on ``v_x``);
    * observation: :meth:`~mixedrl.envs.DoubleLaneChangeModel.observe` (the paper's relative state
      ``[v_y, r, v_x - 12, e_phi, e_y]`` by default); utility: eq. (54) on the next state, discount
      :attr:`gamma` (0.99 by default);
    * training states: :meth:`~mixedrl.envs.DoubleLaneChangeModel.reset_states` (anywhere on the
      course); evaluation: :func:`mixedrl.envs.evaluate_tracking` (one full course from the reference
      start, per seed).

    Its configuration is one object, :class:`~mixedrl.envs.dlc_config.DoubleLaneChangeTaskConfig` (the
    run's ``task.*`` settings, :meth:`from_config`), which the model and the environments take as it is:
    the environment's fields and the discount and prior. The constructor builds it from keywords.

    Parameters
    ----------
    prior_force_mean : float, optional
        The designer's prior mean force [N] (paper: 150).
    prior_force_std : float, optional
        Prior standard deviation ``sqrt(K_M)`` in force units [N] (paper: 4).
    gamma : float, optional
        Discount factor of eq. (2) (default 0.99).
    **config
        Any other field of :class:`~mixedrl.envs.dlc_config.DoubleLaneChangeTaskConfig` (e.g.
        ``disturbance``, ``cost`` -- or the flat ``q_speed``, ... --, ``preview_distances``,
        ``train_half_widths``; nested ones also as dicts, :func:`mixedrl.envs.make_config`).

    Attributes
    ----------
    config : DoubleLaneChangeTaskConfig
        The task's configuration (also ``model.config``).
    noise_index : int
        Component of ``xi`` (and of the state) the disturbance acts on: ``v_x`` (2).
    force_scale : float
        ``T / m`` [s/kg]: ``xi = force_scale * F_dis`` (eq. 54); see :meth:`force_to_xi`,
        :meth:`xi_to_force`.
    true_mean_varies : bool
        ``True`` on a road grade (``grade_amplitude != 0``): the true mean is :meth:`true_mean_at`.
    mean_harmonics : int
        Harmonics ``H`` of the Fourier series along the course that Case 3 of the IBE fits
        (:meth:`mean_features`; 8).

    Raises
    ------
    ValueError
        ``prior_force_std`` not positive, ``gamma`` not in (0, 1), or an invalid environment override.
    """

    name = "dlc"

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
        self.noise_matrix = torch.zeros(self.state_dim, self.noise_dim)
        self.noise_matrix[:5, :5] = torch.eye(5)
        self.prior_mean = np.zeros(5)
        self.prior_mean[vx] = cfg.prior_force_mean * scale
        self.prior_cov = np.diag(np.full(5, 1e-20))
        self.prior_cov[vx, vx] = (cfg.prior_force_std * scale) ** 2
        self.true_mean = np.zeros(5)
        self.true_mean[vx] = cfg.disturbance.mean * scale
        self.true_cov = np.zeros((5, 5))
        self.true_cov[vx, vx] = cfg.disturbance.variance * scale**2
        self.true_mean_varies = cfg.disturbance.grade_amplitude != 0.0
        self.action_bound = torch.tensor(self.model.action_bound, dtype=torch.float32)
        scales = [0.3, 0.2, 0.5, 0.1, 0.5] + [2.0] * (self.obs_dim - 5) if cfg.obs_scale is None else cfg.obs_scale
        self.obs_scale = torch.tensor(scales, dtype=torch.float32)
        self.value_scale = 1.0

    @classmethod
    def from_config(cls, config: DoubleLaneChangeTaskConfig) -> "DoubleLaneChangeTask":
        """Build the task of a :class:`~mixedrl.envs.dlc_config.DoubleLaneChangeTaskConfig` (``task.*`` of a
        run's config), which is also the environment's configuration (``self.config``, ``self.model.config``).

        Every law of :data:`mixedrl.config.DISTURBANCE_LAWS` is simulated (``task.disturbance.law``,
        ``task.disturbance.dof``); the task's ``true_mean`` / ``true_cov`` are the law's mean and variance
        (the same for every law), so the oracle plans with the Gaussian of the true moments.

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

        with ``L`` the course length (120 m) and ``H`` = :attr:`mean_harmonics` (8: wavelengths down to
        15 m). A road grade's mean force ``mean - m g sin(theta(X))`` is represented exactly when its
        wavelength is ``L / k`` for some ``k <= H`` (up to the ``sin(theta)`` nonlinearity, third order
        in the grade), approximately otherwise.
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
        ``u* = 0`` -- the origin of the tracking errors (the observation is 0 without preview).

        It is a rest point of the errors on a straight road (eq. 53 at ``v_y = r = 0``, ``delta = a_x = 0``), not
        of the six-component state (``X`` advances): :meth:`linearisation` is taken on the paper's state.
        """
        cfg = self.model.config
        X0 = torch.zeros((), dtype=torch.float64)
        heading, lateral = float(cfg.reference.heading(X0)), float(cfg.reference.lateral(X0))
        return Equilibrium(state=np.array([0.0, 0.0, cfg.v_des, heading, lateral, 0.0]), action=np.zeros(2))

    def linearisation(self) -> Linearisation:
        """The discounted LQ problem of the tracking errors at :meth:`equilibrium` (the LQR reference's problem).

        Coordinates: the paper's relative state ``x = [v_y, r, v_x - v_des, e_phi, e_y]`` (eq. 53), ``v = u``;
        ``A``, ``B`` are the Jacobians of the shared ``f`` (:class:`~mixedrl.envs.VehicleDynamics`) at
        ``[0, 0, v_des, 0, 0]`` on a straight road (as :func:`validation.nmpc.linearise_straight`), ``Q``,
        ``R`` half the Hessian of eq. (54) (``T diag(0, 0, q_speed, 0, q_lateral)``, ``T diag(r_steer, r_accel)``),
        ``E = I_5`` (the noise's five components are those of ``x``). ``x`` embeds into the task state at
        ``X = 0``: ``s = [x_0, x_1, v_des + x_2, psi_ref(0) + x_3, Y_ref(0) + x_4, 0]``.
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

        Q, R = _cost_hessian(lambda x, u: self.model.cost(embed(x), u), torch.zeros(5, dtype=torch.float64), u0,
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
        # s' = f(s, u) + xi e_vx,  xi = F_dis T / m  (eq. 54): the environments' one true step
        return self.model.true_step(s, u.to(s.dtype), generator)

    def evaluate(self, policy: torch.nn.Module, seeds: list[int], keep_trajectory: bool = False
                 ) -> dict[str, Any]:
        """Table I metrics averaged over one full course per seed (:func:`mixedrl.envs.evaluate_tracking`).

        Returns ``lateral_mae`` [m], ``speed_mae`` [m/s], ``lateral_max``, ``speed_max``, ``cost`` (total
        eq. 54 cost of the course), ``terminated`` (fraction of runs that left the road); with
        ``keep_trajectory`` also ``trajectories`` (the :class:`~mixedrl.envs.TrackingResult` objects).
        """
        runs = [evaluate_tracking(policy, self.model.config, seed=int(seed)) for seed in seeds]
        out: dict[str, Any] = {
            "lateral_mae": float(np.mean([r.mean_abs_lateral_error for r in runs])),
            "speed_mae": float(np.mean([r.mean_abs_speed_error for r in runs])),
            "lateral_max": float(np.mean([r.max_abs_lateral_error for r in runs])),
            "speed_max": float(np.mean([r.max_abs_speed_error for r in runs])),
            "cost": float(np.mean([r.total_cost for r in runs])),
            "terminated": float(np.mean([r.terminated for r in runs])),
        }
        if keep_trajectory:
            out["trajectories"] = runs
        return out


# ----------------------------------------------------------------------------------------------------
# the double lane change's experiment: its course sampler and its preset, registered here
# ----------------------------------------------------------------------------------------------------
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
    """Where a course copy restarts once ``course_start`` has passed: ``"start"`` = at the course start
    (``X = 0``), not at the course's end (a copy drives on past it until its horizon); ``"along"`` = on
    the reference at a point drawn uniformly along the course (``X ~ U(0, course_length)``), also when it
    passes the course's end; ``"loop"`` = at the course start, also when it passes the course's end."""

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


register_sampler(CourseSampler, tasks=("dlc",))

#: The double lane change's experiment configuration (the reproduction of Table I, ``mixedrl reproduce``):
#: the shared settings (learning rates, their decay, ``horizon``, ``value_output``, ``batch_size``, the
#: budget) were chosen by a small search on mixed-RL runs of the double lane change (seeds 0-2) and then
#: applied unchanged to every method; the course sampler and the relative batch weighting are the
#: departures docs/algorithm2.rst lists.
DLC_EXPERIMENT: dict[str, dict[str, Any]] = {
    "algorithm": {"lr_decay_iterations": 1500, "batch_weighting": "relative"},
    "sampler": {"name": CourseSampler.NAME},
}
register_preset("dlc", DLC_EXPERIMENT)
