"""The interface between the learning algorithms and a controlled system: :class:`Task` and :func:`check_task`.

Every task builds on this module, which imports none of them (the usual import is
``from mixedrl.tasks import Task``); :class:`Equilibrium`, :class:`Linearisation` and :func:`cost_hessian`
of :mod:`mixedrl.equilibrium` are re-exported here. The true system is eq. (1) with the noise entering
through a fixed matrix ``E``:

.. math::

    s_{t+1} = f(s_t, u_t) + E\\, \\xi_t, \\qquad \\xi_t \\sim N(\\mu, K),

where ``s`` is the simulator state (``state_dim``), ``xi`` the additive uncertainty (``noise_dim``) and
``E`` (``state_dim x noise_dim``) any matrix of full column rank. The residual of eq. (10) is the
least-squares ``xi`` of ``E xi = s' - f(s, u)``. The true system is simulated (:meth:`Task.true_step`)
unless the task has a plant (:mod:`mixedrl.plant`). The policy and the critic see ``observe(s)``; the
utility is charged on the next state, ``l(s', u)`` (eq. 2).
"""

from __future__ import annotations

import abc
import math
from typing import Any, Callable

import numpy as np
import torch

from mixedrl.checks import check_positive_int, check_seed_lists, check_task_types, probe_task
from mixedrl.equilibrium import EQUILIBRIUM_ATOL, Equilibrium, Linearisation, cost_hessian
from mixedrl.gaussian import sample_gaussian
from mixedrl.ibe.common import check_noise_matrix, noise_coordinates

__all__ = ["EQUILIBRIUM_ATOL", "Equilibrium", "Linearisation", "Task", "check_policies_and_seeds", "check_task",
           "cost_hessian"]


class Task(abc.ABC):
    """A controlled system with a known deterministic part ``f`` and additive Gaussian noise (eq. 1).

    Subclasses set the attributes below in ``__init__`` (those up to ``obs_scale`` are required, the others
    have defaults) and implement the abstract methods; :func:`check_task` checks them. Every tensor method
    is batched over the first dimension and differentiable in torch.

    Attributes
    ----------
    state_dim, obs_dim, action_dim, noise_dim : int
        Sizes of ``s``, ``observe(s)``, ``u`` and ``xi``.
    gamma : float
        Discount factor of eq. (2).
    noise_matrix : torch.Tensor, shape (state_dim, noise_dim)
        ``E``: how ``xi`` enters the state, of full column rank (e.g. a 0/1 selection or ``[dt^2, dt]^T``).
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
    lqr_reference : bool
        Whether the discounted LQR at the equilibrium is the yardstick of the task's runs
        (:func:`mixedrl.precision.run_references`); ``True`` by default.
    name : str
        The task's name in a run's results; the class name by default.
    eval_horizon, eval_starts : int
        Steps per rollout (200) and start states per seed (64) of the default :meth:`evaluate`.
    action_limit : torch.Tensor or None, shape (action_dim,)
        Where the plant clips the action (``None``: it does not); ``f`` must apply the same clip.
    saturation_margin : float or torch.Tensor
        Transitions with ``|u_i| > action_limit_i - saturation_margin_i`` are dropped from the IBE
        (:meth:`saturated`); 0 by default.
    plant : list of mixedrl.plant.CheckedPlant or None
        The true system (:func:`mixedrl.plant.attach_plant`); ``None``: simulated by :meth:`true_step`.
    plant_evaluation : str
        ``"simulated"`` (:meth:`evaluate` as below), ``"plant"`` or ``"none"``
        (:data:`mixedrl.plant.PLANT_EVALUATIONS`).
    plant_evaluate : callable or None
        ``(policy, seeds, horizon) -> dict``, what :meth:`evaluate` returns instead of its simulated
        rollouts (set by :func:`mixedrl.plant.attach_plant`).
    evaluation_transitions : int
        Plant (or simulated plant) transitions the evaluations have used.
    last_evaluation_counts : list of int or None
        Per policy, the evaluation transitions of the last :meth:`evaluate_many`.
    evaluates_on_plant, counts_evaluation_transitions : bool
        Whether :meth:`evaluate` honours :attr:`plant_evaluate` and adds its transitions to
        :attr:`evaluation_transitions`: True for the default :meth:`evaluate`, False for a subclass that
        overrides :meth:`evaluate` without setting them.
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
    lqr_reference: bool = True
    name: str
    eval_horizon: int = 200
    eval_starts: int = 64
    action_limit: torch.Tensor | None = None
    saturation_margin: Any = 0.0
    plant: Any = None
    plant_evaluation: str = "simulated"
    plant_evaluate: Callable[..., dict[str, Any]] | None = None
    evaluation_transitions: int = 0
    evaluates_on_plant: bool = True
    counts_evaluation_transitions: bool = True
    last_evaluation_counts: list[int] | None = None

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "name" not in cls.__dict__:
            cls.name = cls.__name__
        if "evaluate" in cls.__dict__:  # an own evaluate must declare these itself
            for flag in ("evaluates_on_plant", "counts_evaluation_transitions"):
                if flag not in cls.__dict__:
                    setattr(cls, flag, False)

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

    def sample_region(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """``n`` states drawn over the task's whole state region, float64, (n, state_dim), where the rollouts
        of ``algorithm.rollout_region`` start. A task declares a region by overriding this method.

        Raises
        ------
        NotImplementedError
            The task declares no state region.
        """
        raise NotImplementedError(f"{type(self).__name__} declares no state region (override sample_region)")

    @classmethod
    def declares_region(cls) -> bool:
        """Whether the task overrides :meth:`sample_region` with a state region of its own."""
        return cls.sample_region is not Task.sample_region

    def is_terminal(self, s: torch.Tensor) -> torch.Tensor:
        """Boolean (B,): the episode of this copy ends (left the domain, course finished, not finite)."""
        return ~torch.isfinite(s).all(dim=-1)

    def equilibrium(self) -> Equilibrium | None:
        """A rest point ``f(s*, u*) = s*`` of the noise-free model, where the precision yardstick
        (:mod:`mixedrl.precision`) is taken; ``None`` here. Subclasses with one override it."""
        return None

    def linearisation(self) -> Linearisation | None:
        """The discounted LQ problem at :meth:`equilibrium` (``None`` without one).

        By default ``x = s - s*``, ``v = u - u*`` and

        .. math::

            A = \\frac{\\partial f}{\\partial s}(s^*, u^*),\\quad B = \\frac{\\partial f}{\\partial u}(s^*, u^*),\\quad
            Q = \\tfrac12 \\frac{\\partial^2 l}{\\partial s'^2},\\quad
            R = \\tfrac12 \\frac{\\partial^2 l}{\\partial u^2}
            \\ \\text{at } (s', u) = (s^*, u^*),\\qquad E = \\text{noise\\_matrix},

        from :func:`torch.func.jacrev` and :func:`torch.func.hessian` of :meth:`f` and :meth:`cost` in float64.

        Returns
        -------
        Linearisation or None

        Raises
        ------
        ValueError
            ``f(s*, u*) != s*``, the cost's gradient at ``(s*, u*)`` is not zero, or its Hessian couples
            ``s'`` and ``u``; the message names ``equilibrium`` or ``cost``.
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
        Q, R = cost_hessian(lambda x, u: self.cost(x, u), s0, u0, name, scale)
        return Linearisation(A=A.numpy(), B=B.numpy(), Q=Q, R=R, E=self.noise_matrix.double().numpy(),
                             gamma=float(self.gamma), state=s0.numpy(), action=u0.numpy())

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
        """The true noise mean at each state, (B, noise_dim) float64: ``true_mean`` here (a subclass whose mean
        depends on the state overrides it and sets ``true_mean_varies``)."""
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
        """Eq. (10) in noise coordinates: the least-squares ``xi`` of ``E xi = s' - f(s, u)``, (B, noise_dim)
        (``E^T (s' - f)`` for a 0/1 selection; :func:`mixedrl.ibe.common.noise_coordinates`).

        Notes
        -----
        A departure from eq. (10): rows whose action the plant may have clipped (:meth:`saturated`) are
        NaN, so the callers drop them from the IBE.
        """
        with torch.no_grad():
            xi = noise_coordinates(s_next - self.f(s, u.to(s.dtype)), self.noise_matrix.to(s.dtype))
            clipped = self.saturated(s, u)
            return xi if clipped is None else xi.masked_fill(clipped[:, None], math.nan)

    def saturated(self, s: torch.Tensor, u: torch.Tensor) -> torch.Tensor | None:
        """Bool (B,): rows of ``(s, u)`` with ``|u_i| > action_limit_i - saturation_margin_i`` for some ``i``
        (the plant may have clipped them), or ``None`` without an :attr:`action_limit`. A task whose plant also
        clips states overrides it.

        The margin is 0 for a disturbance entering after the clip; one entering before it (an actuator bias
        ``b``) needs a margin covering ``|b|`` (e.g. the prior's mean plus three standard deviations).
        """
        if self.action_limit is None:
            return None
        limit = torch.as_tensor(self.action_limit, dtype=torch.float64)
        margin = torch.as_tensor(self.saturation_margin, dtype=torch.float64)
        return (u.double().abs() > limit - margin).any(dim=-1)

    def state_error(self, s: torch.Tensor) -> torch.Tensor:
        """The task's error measure of states ``s`` (B, state_dim) -> (B, k) float64, reported by the default
        :meth:`evaluate`: the state itself here. A task whose state is not an error (a wrapped angle)
        overrides it."""
        return s

    def evaluate(self, policy: torch.nn.Module, seeds: list[int], horizon: int | None = None) -> dict[str, Any]:
        """Seeded rollouts of the *true* environment (:meth:`true_step`) under ``policy`` from fixed starts.

        For each seed, a generator seeded with it draws :attr:`eval_starts` start states from
        :meth:`sample_initial` and then the noise; the action is ``policy(observe(s))`` (float32
        observations). A copy that reaches a terminal state stops: no cost, no state counted from then on.
        Every simulated step is added to :attr:`evaluation_transitions`. With :attr:`plant_evaluate` set
        it returns that instead. A subclass may override it (see :attr:`evaluates_on_plant`).

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
            - ``"mean_abs_state"``: ``|e|`` of the error measure ``e = state_error(s)``, averaged over the
              second half of the rollout and over its components;
            - ``"mean_abs_state_<i>"``, ``"mean_state_<i>"``: per component ``i``, ``|e_i|`` and the signed
              ``e_i`` over the second half;
            - ``"terminated_fraction"``: rollouts that reached a terminal state.

        Raises
        ------
        ValueError
            ``seeds`` empty, or ``horizon`` not a positive integer.
        """
        if self.plant_evaluate is not None:  # on the task's plant, or none (mixedrl.plant.attach_plant)
            return self.plant_evaluate(policy, seeds, horizon)
        horizon = check_positive_int(self.eval_horizon if horizon is None else horizon, "horizon")
        if len(seeds) == 0:
            raise ValueError("seeds: expected at least one evaluation seed, got none")
        n, half = int(self.eval_starts), horizon // 2
        self.evaluation_transitions += n * horizon * len(seeds)
        per_seed = []  # (cost, terminated fraction, sum |e|, sum e, count) of each seed
        with torch.no_grad():
            for seed in seeds:
                gen = torch.Generator().manual_seed(int(seed))
                s = self.sample_initial(n, gen).to(torch.float64)
                alive = torch.ones(n, dtype=torch.bool)
                total = torch.zeros(n, dtype=torch.float64)
                abs_sum, signed_sum = torch.zeros(2, self.state_error(s).shape[-1], dtype=torch.float64)
                count = 0.0
                for t in range(horizon):
                    u = policy(self.observe(s.float())).double()
                    s_next = self.true_step(s, u, gen)
                    total += torch.where(alive, self.gamma**t * self.cost(s_next, u).double(), torch.zeros_like(total))
                    alive = alive & ~self.is_terminal(s_next)
                    s = torch.where(alive[:, None], s_next, s)
                    if t >= half:
                        kept = self.state_error(s)[alive]
                        abs_sum += kept.abs().sum(dim=0)
                        signed_sum += kept.sum(dim=0)
                        count += kept.shape[0]
                per_seed.append((float(total.mean()), float((~alive).double().mean()), abs_sum, signed_sum, count))
        costs, terminated, abs_sums, sums, counts = zip(*per_seed)
        count = max(sum(counts), 1.0)
        mean_abs = (torch.stack(abs_sums).sum(dim=0) / count).tolist()
        mean = (torch.stack(sums).sum(dim=0) / count).tolist()
        out: dict[str, Any] = {"cost": float(np.mean(costs)), "mean_abs_state": float(np.mean(mean_abs)),
                               "terminated_fraction": float(np.mean(terminated))}
        out.update({f"mean_abs_state_{i}": v for i, v in enumerate(mean_abs)})
        out.update({f"mean_state_{i}": v for i, v in enumerate(mean)})
        return out

    def evaluate_many(self, policies: list[torch.nn.Module], seeds: list[list[int]], *, exact: bool = False
                      ) -> list[dict[str, Any]]:
        """:meth:`evaluate` of several policies, each on its own seeds: ``[evaluate(p, s) for p, s in ...]``.

        A task may override it to drive all the rollouts at once; this default is exact whatever ``exact``
        says. Each policy's evaluation transitions are left in :attr:`last_evaluation_counts`
        (:func:`mixedrl.plant.credit_evaluations` reads them).

        Parameters
        ----------
        policies : list of torch.nn.Module
            The runs' policies.
        seeds : list of list of int
            One non-empty list of evaluation seeds per policy.
        exact : bool, optional
            Whether each result must equal :meth:`evaluate`'s bit for bit (False allows a batched policy call).

        Returns
        -------
        list of dict
            Per policy, what :meth:`evaluate` returns.

        Raises
        ------
        ValueError
            ``policies`` not a list, or ``seeds`` not one non-empty list of ints per policy.
        """
        seeds = check_policies_and_seeds(policies, seeds)
        out, counts = [], []
        for policy, s in zip(policies, seeds):
            before = self.evaluation_transitions
            out.append(self.evaluate(policy, s))
            counts.append(self.evaluation_transitions - before)
        self.last_evaluation_counts = counts
        return out


def check_policies_and_seeds(policies: Any, seeds: Any) -> list[list[int]]:
    """``seeds`` as one list per policy (:func:`mixedrl.checks.check_seed_lists`), after checking that
    ``policies`` is a non-empty list.

    Raises
    ------
    ValueError
        Naming ``policies`` or ``seeds``.
    """
    if isinstance(policies, torch.nn.Module) or not isinstance(policies, (list, tuple)) or not policies:
        raise ValueError(f"policies: expected a non-empty list of policies, got {type(policies).__name__}")
    return check_seed_lists(seeds, len(policies))


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

    After :func:`mixedrl.checks.check_task_types` (sizes, array attributes), calls :meth:`Task.sample_initial`
    (own generator, seed 0), :meth:`Task.observe`, :meth:`Task.f` and :meth:`Task.cost` on ``batch`` states with
    zero and bound actions, in float32 and float64, then :func:`mixedrl.checks.probe_task`; no random stream of
    the task or a trainer is touched.

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
        returns the wrong shape, dtype or non-finite values; the message names the task class and the
        attribute or function.
    """
    check_task_types(task, probe=False)
    name, n, o, m = type(task).__name__, int(task.state_dim), int(task.obs_dim), int(task.action_dim)
    gamma = getattr(task, "gamma", None)
    if not isinstance(gamma, (float, int, np.floating)) or not 0.0 < float(gamma) < 1.0:
        raise ValueError(f"{name}.gamma: expected a discount factor in (0, 1), got {gamma!r}")
    check_noise_matrix(task.noise_matrix, f"{name}.noise_matrix", n)
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
    probe_task(task)
