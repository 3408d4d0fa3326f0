"""Algorithm 2: mixed RL with a parameterised critic and actor and the adaptive GPI (AGPI) loop.

One outer iteration ``k`` of :class:`AGPI` (see :meth:`AGPI.iteration`) is

1. **data**: the ``batch_size`` copies of the *true* environment take one step under the current policy
   ``pi^k``; their states are the batch ``x`` of this iteration and their transitions give residuals
   ``xi^D`` (eq. 10);
2. **PEV** (eqs. 49-50): one semi-gradient step of the critic ``V(x; w)`` under ``xi_hat_k``;
3. **PIM** (eqs. 51-52): one gradient step of the actor ``pi(x; theta)`` under ``xi_hat_k``, gradients
   through the model ``f``;
4. **IBE** (eq. 20): the noise source absorbs the residuals: ``xi_hat_k -> xi_hat_{k+1}``;
5. **MVC loop** (eqs. 37-39): while the maximum variation condition fails on the batch, one more PIM step
   (``j <- j + 1``), until it holds or ``j = j_max``;
6. the stopping test ``|V^{k+1} - V^k| <= eps`` and ``|pi^{k+1} - pi^k| <= eps``.

The noise source is the only difference between mixed RL (an IBE posterior), model-driven RL (the fixed
prior, eq. 55) and the oracle (the fixed true noise): one algorithm, three noise sources
(:func:`make_noise_source`).

Expectations over ``xi_hat ~ N(mu_hat, K_hat)`` use **sigma points** by default
(:func:`expectation_nodes`, ``rule="sigma"``): the ``2r`` spherical-cubature points
``mu_hat +- sqrt(r lambda_i) v_i`` in the range of ``K_hat`` (rank ``r``), equal weights; exact for
polynomials of degree <= 3 in ``xi``, deterministic, and as cheap as it gets for the vehicle's rank-1
noise (2 points). Reparameterised samples (``rule="samples"``) are available. Because the noise is
additive, ``f(x, u)`` is computed once per state and only ``l`` and ``V`` are evaluated at the nodes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from mixedrl.config import TrainConfig
from mixedrl.algorithms.model_data import ModelStateSampler
from mixedrl.ibe import UnknownCovarianceIBE
from mixedrl.noise import GaussianNoise
from mixedrl.networks import Actor, AffineActor, Critic, QuadraticCritic
from mixedrl.tasks import Task

__all__ = [
    "AGPI",
    "expectation_nodes",
    "critic_loss",
    "actor_objective",
    "h_value",
    "mvc_check",
    "MVCResult",
    "make_noise_source",
]

logger = logging.getLogger(__name__)


# ----------------------------------------------------------------------------------------------------
# noise sources: IBE posterior (mixed), prior (model, eq. 55), truth (oracle)
# ----------------------------------------------------------------------------------------------------
def make_noise_source(method: str, task: Task, recursion: str = "exact") -> Any:
    """The noise distribution Algorithm 2 plans with, by method.

    Parameters
    ----------
    method : {"mixed", "model", "oracle"}
        ``"mixed"``: :class:`mixedrl.ibe.UnknownCovarianceIBE` started at the prior ``(mu_M, K_M)``
        (Algorithm 2's initialisation, Case 2 of the IBE: mean and covariance unknown);
        ``"model"``: the prior ``N(mu_M, K_M)`` held fixed (eq. 55); ``"oracle"``: the true ``N(mu, K)``.
    task : Task
        Supplies ``prior_mean``, ``prior_cov``, ``true_mean``, ``true_cov``.
    recursion : {"exact", "paper"}
        Recursion of the IBE (mixed only).

    Returns
    -------
    object
        With ``.mean`` (noise_dim,), ``.cov`` (noise_dim, noise_dim), ``.update(xi)``, ``.count``,
        ``state_dict()`` and ``load_state_dict()``; the fixed sources
        (:class:`mixedrl.noise.GaussianNoise`) have no ``update``.

    Raises
    ------
    ValueError
        ``method`` unknown.
    """
    if method == "mixed":
        return UnknownCovarianceIBE(task.prior_mean, task.prior_cov, recursion=recursion)
    if method == "model":
        return GaussianNoise(task.prior_mean, task.prior_cov)
    if method == "oracle":
        return GaussianNoise(task.true_mean, task.true_cov)
    raise ValueError(f"method: expected 'mixed', 'model' or 'oracle', got {method!r}")


# ----------------------------------------------------------------------------------------------------
# the expectation over xi_hat
# ----------------------------------------------------------------------------------------------------
#: Eigenvalues of ``K_hat`` below this fraction of the largest are treated as 0 by the sigma points.
RANK_RTOL = 1e-6


def expectation_nodes(mean: np.ndarray, cov: np.ndarray, noise_matrix: torch.Tensor, rule: str = "sigma",
                      n_samples: int = 4, generator: torch.Generator | None = None,
                      dtype: torch.dtype = torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """Nodes and weights of the expectation over ``xi_hat ~ N(mu_hat, K_hat)`` in eqs. (49) and (51).

    Implements the integral of eq. (51),

    .. math::

        \\mathbb{E}_{\\hat\\xi}\\, g(f(x, u) + E \\hat\\xi) \\approx \\sum_i w_i\\, g(f(x, u) + d_i),
        \\qquad d_i = E\\, \\hat\\xi_i,

    with the spherical-cubature sigma points (``rule="sigma"``)

    .. math::

        \\hat\\xi_{\\pm i} = \\hat\\mu \\pm \\sqrt{r \\lambda_i}\\, v_i, \\quad w = \\frac{1}{2r},
        \\qquad \\hat K = \\sum_{i=1}^r \\lambda_i v_i v_i^\\top,

    or ``n_samples`` reparameterised draws ``mu_hat + K_hat^{1/2} eps`` (``rule="samples"``, weights
    ``1/n``).

    Parameters
    ----------
    mean : numpy.ndarray, shape (noise_dim,)
        ``mu_hat``.
    cov : numpy.ndarray, shape (noise_dim, noise_dim)
        ``K_hat``, symmetric positive semi-definite (may be singular).
    noise_matrix : torch.Tensor, shape (state_dim, noise_dim)
        ``E``, how the noise enters the state.
    rule : {"sigma", "samples"}
        Quadrature rule.
    n_samples : int
        Number of draws for ``rule="samples"``.
    generator : torch.Generator, optional
        Required for ``rule="samples"``.
    dtype : torch.dtype
        Dtype of the returned tensors.

    Returns
    -------
    offsets : torch.Tensor
        ``d_i = E xi_hat_i``, shape ``(P, state_dim)``.
    weights : torch.Tensor
        Quadrature weights summing to 1, shape ``(P,)``.

    Raises
    ------
    ValueError
        Shapes inconsistent, non-finite input, unknown ``rule``, or ``rule="samples"`` without generator.

    Notes
    -----
    The sigma rule integrates every polynomial of degree <= 3 in ``xi`` exactly; here ``l`` is quadratic
    in ``x'`` so the cost term is exact and only the critic's higher-order terms are approximated.
    Directions with ``lambda_i < 1e-6 lambda_max`` are dropped (the vehicle prior's ``1e-20`` entries):
    the error this makes is at most ``sum(dropped lambda) * max|Hessian| / 2``. If ``K_hat = 0`` the rule
    reduces to the single point ``mu_hat``.
    """
    mean = np.asarray(mean, dtype=np.float64)
    cov = np.asarray(cov, dtype=np.float64)
    n = mean.shape[0] if mean.ndim == 1 else -1
    if mean.ndim != 1 or cov.shape != (n, n) or noise_matrix.shape[-1] != n:
        raise ValueError(f"mean: shapes mean {mean.shape}, cov {cov.shape}, noise_matrix "
                         f"{tuple(noise_matrix.shape)} are inconsistent")
    if not (np.isfinite(mean).all() and np.isfinite(cov).all()):
        raise ValueError("mean: mean or cov contains NaN or inf")
    lam, vec = np.linalg.eigh(0.5 * (cov + cov.T))
    lam = np.clip(lam, 0.0, None)
    if rule == "sigma":
        keep = lam > RANK_RTOL * lam.max() if lam.max() > 0 else np.zeros_like(lam, dtype=bool)
        r = int(keep.sum())
        if r == 0:
            xi = mean[None, :]
        else:
            # xi_{+-i} = mu_hat +- sqrt(r lambda_i) v_i
            spread = (vec[:, keep] * np.sqrt(r * lam[keep])).T
            xi = np.concatenate([mean + spread, mean - spread], axis=0)
        xi_t = torch.as_tensor(xi, dtype=torch.float64)
    elif rule == "samples":
        if generator is None:
            raise ValueError("generator: required for rule='samples'")
        eps = torch.randn(n_samples, n, generator=generator, dtype=torch.float64)
        root = torch.as_tensor(vec * np.sqrt(lam), dtype=torch.float64)
        # xi = mu_hat + K_hat^{1/2} eps   (reparameterisation)
        xi_t = torch.as_tensor(mean) + eps @ root.T
    else:
        raise ValueError(f"rule: expected 'sigma' or 'samples', got {rule!r}")
    offsets = (xi_t @ noise_matrix.to(torch.float64).T).to(dtype)
    weights = torch.full((offsets.shape[0],), 1.0 / offsets.shape[0], dtype=dtype)
    return offsets, weights


def _next_state_terms(task: Task, critic: torch.nn.Module, s: torch.Tensor, u: torch.Tensor,
                      offsets: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """``sum_i w_i [l(f(s,u) + d_i, u) + gamma V(f(s,u) + d_i)]`` per state, shape (B,)."""
    s_mean = task.f(s, u)  # f(x, u), once per state: the noise is additive
    P = offsets.shape[0]
    s_next = (s_mean.unsqueeze(0) + offsets[:, None, :]).reshape(P * s.shape[0], -1)
    u_rep = u.unsqueeze(0).expand(P, *u.shape).reshape(P * u.shape[0], -1)
    # l(x', u) + gamma V(x'), x' = f(x, u) + xi_hat
    target = task.cost(s_next, u_rep) + task.gamma * critic(task.observe(s_next))
    return weights @ target.reshape(P, s.shape[0])


def h_value(task: Task, critic: torch.nn.Module, s: torch.Tensor, u: torch.Tensor, offsets: torch.Tensor,
            weights: torch.Tensor) -> torch.Tensor:
    """Implements eq. (37): the expected cumulative cost of action ``u`` under a noise distribution.

    .. math::

        h(x, u, \\hat\\xi) = \\mathbb{E}_{\\hat\\xi}\\{ l(x', u) + \\gamma V^k(x') \\},
        \\qquad x' = f(x, u) + \\hat\\xi.

    Parameters
    ----------
    task : Task
        The model ``f``, the utility ``l``, ``gamma``.
    critic : torch.nn.Module
        ``V^k``, maps observations (N, obs_dim) to (N,).
    s : torch.Tensor, shape (B, state_dim)
        States ``x``.
    u : torch.Tensor, shape (B, action_dim)
        Actions.
    offsets, weights : torch.Tensor
        Quadrature of the noise distribution (:func:`expectation_nodes`), shapes ``(P, state_dim)`` and
        ``(P,)``.

    Returns
    -------
    torch.Tensor, shape (B,)
        ``h`` per state (differentiable in ``u`` and in the critic's weights).

    Raises
    ------
    ValueError
        If the batch sizes of ``s`` and ``u`` differ.
    """
    if s.shape[0] != u.shape[0]:
        raise ValueError(f"u: batch size {u.shape[0]} differs from s's {s.shape[0]}")
    return _next_state_terms(task, critic, s, u, offsets, weights)


def critic_loss(task: Task, critic: torch.nn.Module, s: torch.Tensor, u: torch.Tensor, offsets: torch.Tensor,
                weights: torch.Tensor) -> torch.Tensor:
    """Implements eqs. (49)-(50): the PEV loss whose gradient is the critic's semi-gradient.

    .. math::

        J_{\\rm critic} = \\mathbb{E}_{\\hat\\xi}\\Big\\{\\tfrac12 \\big(l(x', u_\\theta)
            + \\gamma V^k(x'; w) - V^k(x; w)\\big)^2\\Big\\},
        \\qquad
        \\frac{\\partial J_{\\rm critic}}{\\partial w}
            = \\big(V^k(x; w) - \\mathbb{E}\\,V_{\\rm target}\\big)\\,\\frac{\\partial V^k(x; w)}{\\partial w}.

    Parameters
    ----------
    task : Task
        Model and utility.
    critic : torch.nn.Module
        ``V(x; w)``.
    s : torch.Tensor, shape (B, state_dim)
        Batch of states.
    u : torch.Tensor, shape (B, action_dim)
        ``u_theta = pi(x; theta)`` (detached: PEV does not move the actor).
    offsets, weights : torch.Tensor
        Quadrature of ``xi_hat_k`` (:func:`expectation_nodes`), shapes ``(P, state_dim)`` and ``(P,)``.

    Returns
    -------
    torch.Tensor, shape ()
        ``mean_x 1/2 (V(x; w) - E V_target)^2``; its gradient in ``w`` is the semi-gradient of eq. (50),
        averaged over the batch.

    Raises
    ------
    ValueError
        If the batch sizes of ``s`` and ``u`` differ.

    Notes
    -----
    *Semi-gradient*: ``V_target`` is computed without gradient (``torch.no_grad``), as eq. (50) says.
    The expectation is moved inside the square: ``E{(T - V)^2}/2`` and ``(E T - V)^2/2`` differ by the
    variance of ``T``, which does not depend on ``w`` through the semi-gradient, so both give the same
    gradient. The loss is divided by ``value_scale^2`` so that its size does not depend on the units of
    the cost.
    """
    if s.shape[0] != u.shape[0]:
        raise ValueError(f"u: batch size {u.shape[0]} differs from s's {s.shape[0]}")
    with torch.no_grad():
        # V_target = l(x', u_theta) + gamma V^k(x'),  x' = f(x, u_theta) + xi_hat
        target = _next_state_terms(task, critic, s, u, offsets, weights)
    value = critic(task.observe(s))
    scale = float(getattr(task, "value_scale", 1.0))
    return 0.5 * ((value - target) / scale).pow(2).mean()


def actor_objective(task: Task, critic: torch.nn.Module, actor: torch.nn.Module, s: torch.Tensor,
                    offsets: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Implements eqs. (51)-(52): the PIM objective, differentiated through the model ``f``.

    .. math::

        J_{\\rm actor} = \\mathbb{E}_{\\hat\\xi}\\{ l(x', u_\\theta) + \\gamma V^k(x') \\},
        \\qquad x' \\sim N(f(x, u_\\theta) + \\hat\\mu, \\hat K), \\qquad u_\\theta = \\pi(x; \\theta).

    Parameters
    ----------
    task : Task
        Model ``f`` (differentiable), utility, ``gamma``.
    critic : torch.nn.Module
        ``V^k`` (its weights are not updated by this objective).
    actor : torch.nn.Module
        ``pi(x; theta)``.
    s : torch.Tensor, shape (B, state_dim)
        Batch of states.
    offsets, weights : torch.Tensor
        Quadrature of ``xi_hat_k``, shapes ``(P, state_dim)`` and ``(P,)``.

    Returns
    -------
    torch.Tensor, shape ()
        Batch mean of ``h(x, pi(x; theta), xi_hat_k)``, divided by ``value_scale``.

    Notes
    -----
    Eq. (52) writes the gradient as a score-function term plus a pathwise term. With the
    reparameterisation ``x' = f(x, u_theta) + xi_hat`` (``xi_hat`` independent of ``theta``) both are the
    single pathwise gradient that autograd computes here, ``E{(dl/dx' + gamma dV/dx') df/du + dl/du}
    du/dtheta``.
    """
    u = actor(task.observe(s))
    scale = float(getattr(task, "value_scale", 1.0))
    return _next_state_terms(task, critic, s, u, offsets, weights).mean() / scale


@dataclass
class MVCResult:
    """Outcome of the MVC check (eqs. 38-39) on a batch.

    Attributes
    ----------
    held : bool
        Whether the condition held in the configured sense (batch mean or every state).
    fraction : float
        Fraction of states where it held pointwise.
    lhs_mean : float
        Batch mean of ``h(x, u^{k+1}, xi_{k+1}) - h(x, u^{k+1}, xi_k)`` (the effect of the IBE update).
    e_mean : float
        Batch mean of ``e_k(x) = h(x, u^k, xi_k) - h(x, u^{k+1}, xi_k)`` (the PIM improvement).
    e_nonnegative : float
        Fraction of states with ``e_k(x) >= 0``.
    """

    held: bool
    fraction: float
    lhs_mean: float
    e_mean: float
    e_nonnegative: float


def mvc_check(h_new_next: torch.Tensor, h_new_cur: torch.Tensor, h_old_cur: torch.Tensor, mode: str = "mean"
              ) -> MVCResult:
    """Implements eqs. (38)-(39): the maximum variation condition on a batch of states.

    .. math::

        h(x, u^{k+1}, \\hat\\xi_{k+1}) - h(x, u^{k+1}, \\hat\\xi_k) \\le e_k(x),
        \\qquad e_k(x) = h(x, u^k, \\hat\\xi_k) - h(x, u^{k+1}, \\hat\\xi_k).

    Parameters
    ----------
    h_new_next : torch.Tensor, shape (B,)
        ``h(x, u^{k+1}, xi_hat_{k+1})``.
    h_new_cur : torch.Tensor, shape (B,)
        ``h(x, u^{k+1}, xi_hat_k)``.
    h_old_cur : torch.Tensor, shape (B,)
        ``h(x, u^k, xi_hat_k)``.
    mode : {"mean", "all"}
        ``"mean"``: the inequality between batch means; ``"all"``: at every state (EQUATIONS.md point 12).

    Returns
    -------
    MVCResult

    Raises
    ------
    ValueError
        Shapes differ, or ``mode`` unknown.
    """
    if not (h_new_next.shape == h_new_cur.shape == h_old_cur.shape) or h_new_next.ndim != 1:
        raise ValueError(f"h_new_next: expected three (B,) tensors, got {tuple(h_new_next.shape)}, "
                         f"{tuple(h_new_cur.shape)}, {tuple(h_old_cur.shape)}")
    # lhs = h(x, u^{k+1}, xi_{k+1}) - h(x, u^{k+1}, xi_k)
    lhs = (h_new_next - h_new_cur).double()
    # e_k(x) = h(x, u^k, xi_k) - h(x, u^{k+1}, xi_k)
    e = (h_old_cur - h_new_cur).double()
    pointwise = lhs <= e
    if mode == "mean":
        held = bool(lhs.mean() <= e.mean())
    elif mode == "all":
        held = bool(pointwise.all())
    else:
        raise ValueError(f"mode: expected 'mean' or 'all', got {mode!r}")
    return MVCResult(held=held, fraction=float(pointwise.double().mean()), lhs_mean=float(lhs.mean()),
                     e_mean=float(e.mean()), e_nonnegative=float((e >= 0).double().mean()))


# ----------------------------------------------------------------------------------------------------
# Algorithm 2
# ----------------------------------------------------------------------------------------------------
def build_networks(task: Task, config: TrainConfig, generator: torch.Generator, architecture: str = "mlp"
                   ) -> tuple[torch.nn.Module, torch.nn.Module]:
    """Critic ``V(x; w)`` and actor ``pi(x; theta)`` of eq. (48) for ``task``.

    ``architecture="mlp"``: :class:`~mixedrl.networks.Critic` and :class:`~mixedrl.networks.Actor`
    (the same for every method); ``"quadratic"``: the exact LQ classes
    :class:`~mixedrl.networks.QuadraticCritic` and :class:`~mixedrl.networks.AffineActor`.
    """
    if architecture == "quadratic":
        return (QuadraticCritic(task.obs_dim, generator), AffineActor(task.obs_dim, task.action_dim, generator))
    if architecture != "mlp":
        raise ValueError(f"architecture: expected 'mlp' or 'quadratic', got {architecture!r}")
    critic = Critic(task.obs_dim, config.hidden_sizes, config.activation, generator, task.obs_scale,
                    task.value_scale, config.value_output)
    actor = Actor(task.obs_dim, task.action_dim, config.hidden_sizes, config.activation, generator,
                  task.action_bound, task.obs_scale)
    return critic, actor


def _lr_factor(config: TrainConfig, k: int) -> float:
    """Linear decay from 1 to ``lr_decay_to`` over the budget."""
    frac = min(1.0, k / max(1, config.iterations - 1))
    return 1.0 - (1.0 - config.lr_decay_to) * frac


class AGPI:
    """Algorithm 2 (mixed RL with parameterised value and policy, AGPI with the MVC inner loop).

    Parameters
    ----------
    task : Task
        The system (model ``f``, utility, true environment, prior).
    config : TrainConfig
        ``method`` in ``{"mixed", "model", "oracle"}`` selects the noise source.
    architecture : {"mlp", "quadratic"}, optional
        Function classes (see :func:`build_networks`).
    noise_source : object, optional
        Overrides :func:`make_noise_source` (anything with the IBE's face).

    Raises
    ------
    ValueError
        ``config.method`` is ``"ddpg"`` (use :class:`~mixedrl.algorithms.ddpg.DDPG`).

    Notes
    -----
    Order inside one iteration (see the module docstring): the paper's loop is IBE -> PEV -> PIM -> MVC.
    The MVC of eq. (38) needs ``xi_hat_{k+1}``, the estimate *after* the next IBE update, so the IBE
    update is moved between PIM and the MVC loop (a cyclic shift of the paper's loop: PEV and PIM of
    iteration ``k`` use ``xi_hat_k``, the MVC compares ``xi_hat_k`` with ``xi_hat_{k+1}``). The
    transitions feeding the IBE are collected under ``pi^k`` at the start of the iteration.
    The extra PIM steps of the inner loop use ``xi_hat_k`` (the distribution eq. 39 measures the
    improvement with).
    """

    def __init__(self, task: Task, config: TrainConfig, architecture: str = "mlp", noise_source: Any = None
                 ) -> None:
        if config.method == "ddpg":
            raise ValueError("config: method 'ddpg' is not Algorithm 2; use mixedrl.algorithms.ddpg.DDPG")
        self.task = task
        self.config = config
        self.architecture = architecture
        self.generator = torch.Generator().manual_seed(config.seed)
        self.critic, self.actor = build_networks(task, config, self.generator, architecture)
        self.critic_opt = torch.optim.Adam(self.critic.parameters(), lr=config.critic_lr)
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=config.actor_lr)
        self.noise = noise_source if noise_source is not None else make_noise_source(
            config.method, task, config.ibe_recursion)
        self.k = 0
        self.states = task.sample_initial(config.batch_size, self.generator)
        # desynchronised episode clocks, so the copies do not all reset at the same iteration
        self.steps = torch.randint(0, config.horizon, (config.batch_size,), generator=self.generator)
        self.stop_count = 0
        self.stopped = False
        self.last_batch: torch.Tensor | None = None
        # state_source="model": the batch comes from rollouts of the planning model (model_data.py)
        self.sampler = ModelStateSampler(task, config, self.generator) if config.state_source == "model" else None

    # -------------------------------------------------------------------------------------- helpers
    @property
    def policy(self) -> torch.nn.Module:
        """The actor ``pi(x; theta)`` as a module on observations."""
        return self.actor

    def _nodes(self, mean: np.ndarray, cov: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        return expectation_nodes(mean, cov, self.task.noise_matrix, self.config.expectation,
                                 self.config.noise_samples, self.generator)

    def _set_lr(self) -> None:
        factor = _lr_factor(self.config, self.k)
        for group in self.critic_opt.param_groups:
            group["lr"] = self.config.critic_lr * factor
        for group in self.actor_opt.param_groups:
            group["lr"] = self.config.actor_lr * factor

    def _clip(self, module: torch.nn.Module) -> float:
        return float(torch.nn.utils.clip_grad_norm_(module.parameters(), self.config.grad_clip))

    # -------------------------------------------------------------------------------------- the steps
    def collect(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Step the true environment copies once under ``pi^k``; return (states, residuals).

        With ``state_source="model"`` the batch is a step of the planning-model rollouts instead and the
        residuals come from the true drives of :class:`~mixedrl.algorithms.model_data.ModelStateSampler`.

        Returns
        -------
        states : torch.Tensor, shape (B, state_dim)
            The batch ``x`` of this iteration (float32), the states before the step.
        residuals : torch.Tensor, shape (M, noise_dim)
            Finite residuals ``xi^D`` of eq. (10) (float64).
        """
        if self.sampler is not None:
            return self.sampler.collect(self.actor, self.noise, self.k)
        task = self.task
        s = self.states
        with torch.no_grad():
            u = self.actor(task.observe(s.float())).double()
            s_next = task.true_step(s, u, self.generator)
            xi = task.residuals(s, u, s_next)
        xi = xi[torch.isfinite(xi).all(dim=-1)]
        self.steps += 1
        done = task.is_terminal(s_next) | (self.steps >= self.config.horizon)
        if bool(done.any()):
            n_done = int(done.sum())
            s_next = s_next.clone()
            s_next[done] = task.sample_initial(n_done, self.generator)
            self.steps[done] = 0
        self.states = s_next
        return s.float(), xi

    @property
    def true_transitions(self) -> int:
        """True-environment transitions used so far (``batch_size`` per iteration for ``state_source="true"``)."""
        return self.sampler.true_transitions if self.sampler is not None else self.k * self.config.batch_size

    def pev(self, s: torch.Tensor, offsets: torch.Tensor, weights: torch.Tensor) -> float:
        """Implements eqs. (49)-(50): PEV, one semi-gradient step of the critic under ``xi_hat_k``.

        .. math:: w^{k+1} = w^k - \\alpha\\, \\partial J_{\\rm critic} / \\partial w

        Parameters
        ----------
        s : torch.Tensor, shape (B, state_dim)
            The batch of states (float32).
        offsets, weights : torch.Tensor
            Quadrature of ``xi_hat_k``, shapes ``(P, state_dim)`` and ``(P,)``.

        Returns
        -------
        float
            The critic loss before the step.

        Notes
        -----
        The step is Adam's (learning rate ``alpha = critic_lr``, decayed linearly), with the gradient norm
        clipped at ``grad_clip``; the paper writes plain gradient descent.
        """
        with torch.no_grad():
            u = self.actor(self.task.observe(s))
        loss = critic_loss(self.task, self.critic, s, u, offsets, weights)
        self.critic_opt.zero_grad(set_to_none=True)
        loss.backward()
        self._clip(self.critic)
        # w^{k+1} = w^k - alpha dJ_critic/dw   (Adam)
        self.critic_opt.step()
        return float(loss.detach())

    def pim(self, s: torch.Tensor, offsets: torch.Tensor, weights: torch.Tensor) -> float:
        """Implements eqs. (51)-(52): PIM, one gradient step of the actor under ``xi_hat_k``.

        .. math:: \\theta^{k+1} = \\theta^k - \\beta\\, \\partial J_{\\rm actor} / \\partial \\theta

        Parameters
        ----------
        s : torch.Tensor, shape (B, state_dim)
            The batch of states (float32).
        offsets, weights : torch.Tensor
            Quadrature of ``xi_hat_k``, shapes ``(P, state_dim)`` and ``(P,)``.

        Returns
        -------
        float
            The actor objective before the step.

        Notes
        -----
        Adam (``beta = actor_lr``, decayed linearly) with gradient clipping, as for the critic. The
        critic's weights are frozen during the step (``requires_grad=False``), so only ``theta`` moves.
        """
        for p in self.critic.parameters():
            p.requires_grad_(False)
        try:
            obj = actor_objective(self.task, self.critic, self.actor, s, offsets, weights)
            self.actor_opt.zero_grad(set_to_none=True)
            obj.backward()
            self._clip(self.actor)
            # theta^{k+1} = theta^k - beta dJ_actor/dtheta   (Adam)
            self.actor_opt.step()
        finally:
            for p in self.critic.parameters():
                p.requires_grad_(True)
        return float(obj.detach())

    def ibe(self, residuals: torch.Tensor) -> None:
        """Implements eq. (20): the IBE update ``[mu_k, K_k] = IBE(mu_{k-1}, K_{k-1}, xi^D_k)`` (eq. 13).

        Parameters
        ----------
        residuals : torch.Tensor, shape (M, noise_dim)
            The residuals of eq. (10) collected this iteration (float64).

        Notes
        -----
        The fixed sources (model-driven RL, oracle) have no ``update``: for them this is a no-op.
        """
        if residuals.shape[0] > 0 and hasattr(self.noise, "update"):
            self.noise.update(residuals.numpy())

    def iteration(self) -> dict[str, float]:
        """Implements Algorithm 2, one outer iteration ``k``: data, PEV, PIM, IBE, MVC loop, stopping test.

        Returns
        -------
        dict
            This iteration's metrics (namespaced keys, see :mod:`mixedrl.runs`).

        Notes
        -----
        See the class Notes for the order of the steps and :func:`mvc_check` for the batch form of the MVC.
        """
        cfg, task = self.config, self.task
        self._set_lr()
        s, residuals = self.collect()
        mean_k, cov_k = np.array(self.noise.mean, dtype=np.float64), np.array(self.noise.cov, dtype=np.float64)
        offsets_k, weights_k = self._nodes(mean_k, cov_k)
        obs = task.observe(s)
        with torch.no_grad():
            v_before = self.critic(obs)
            u_old = self.actor(obs)
        # PEV with xi_hat_k
        critic_loss_value = self.pev(s, offsets_k, weights_k)
        # PIM with xi_hat_k
        actor_obj = self.pim(s, offsets_k, weights_k)
        # IBE: xi_hat_k -> xi_hat_{k+1}
        self.ibe(residuals)
        offsets_next, weights_next = self._nodes(np.array(self.noise.mean, dtype=np.float64),
                                                 np.array(self.noise.cov, dtype=np.float64))
        # AGPI inner loop: repeat PIM until the MVC holds or j = j_max
        with torch.no_grad():
            h_old_cur = h_value(task, self.critic, s, u_old, offsets_k, weights_k)
        j = 0
        while True:
            with torch.no_grad():
                u_new = self.actor(obs)
                h_new_cur = h_value(task, self.critic, s, u_new, offsets_k, weights_k)
                h_new_next = h_value(task, self.critic, s, u_new, offsets_next, weights_next)
            mvc = mvc_check(h_new_next, h_new_cur, h_old_cur, cfg.mvc_check)
            if mvc.held or j >= cfg.j_max:
                break
            self.pim(s, offsets_k, weights_k)
            j += 1
        # stopping test: |V^{k+1} - V^k| <= eps and |pi^{k+1} - pi^k| <= eps on the batch
        with torch.no_grad():
            dv = float((self.critic(obs) - v_before).abs().mean() / (v_before.abs().mean() + 1e-12))
            dpi = float(((u_new - u_old) / self.actor_bound_tensor()).abs().mean())
        if cfg.stop_epsilon > 0 and dv <= cfg.stop_epsilon and dpi <= cfg.stop_epsilon:
            self.stop_count += 1
        else:
            self.stop_count = 0
        self.stopped = cfg.stop_epsilon > 0 and self.stop_count >= cfg.stop_patience
        self.k += 1
        metrics = {
            "train/critic_loss": critic_loss_value,
            "train/actor_objective": actor_obj,
            "train/value_mean": float(v_before.mean()),
            "train/value_change": dv,
            "train/policy_change": dpi,
            "mvc/held": float(mvc.held),
            "mvc/fraction_states": mvc.fraction,
            "mvc/lhs_mean": mvc.lhs_mean,
            "mvc/e_mean": mvc.e_mean,
            "mvc/e_nonnegative": mvc.e_nonnegative,
            "mvc/inner_steps": float(j),
        }
        metrics["data/true_transitions"] = float(self.true_transitions)
        metrics.update(self.noise_metrics())
        if residuals.shape[0] > 0:
            batch_mean = residuals.mean(dim=0).numpy()
            for key in [k for k in metrics if k.startswith("ibe/mean_") and k[9:].isdigit()]:
                metrics[f"ibe/batch_mean_{key[9:]}"] = float(batch_mean[int(key[9:])])
        self.last_batch = s
        return metrics

    def noise_moments(self) -> tuple[np.ndarray, np.ndarray]:
        """Copies of the current ``(mu_hat, K_hat)``, shapes (noise_dim,), (noise_dim, noise_dim)."""
        return np.array(self.noise.mean, dtype=np.float64), np.array(self.noise.cov, dtype=np.float64)

    def actor_bound_tensor(self) -> torch.Tensor:
        bound = getattr(self.actor, "action_bound", None)
        return bound if bound is not None else torch.ones(self.task.action_dim)

    def noise_metrics(self) -> dict[str, float]:
        """IBE mean and covariance (components of the noise subspace), and errors against the truth."""
        mean = np.asarray(self.noise.mean, dtype=np.float64)
        cov = np.asarray(self.noise.cov, dtype=np.float64)
        out: dict[str, float] = {}
        for i in range(mean.shape[0]):
            if self.task.true_cov[i, i] > 0 or self.task.prior_cov[i, i] > 1e-12 or self.task.true_mean[i] != 0:
                out[f"ibe/mean_{i}"] = float(mean[i])
                out[f"ibe/cov_{i}{i}"] = float(cov[i, i])
        err = np.abs(mean - self.task.true_mean)
        scale = np.maximum(np.abs(self.task.true_mean), 1e-12)
        out["ibe/mean_error"] = float(np.max(err))
        out["ibe/mean_rel_error"] = float(np.max(np.where(np.abs(self.task.true_mean) > 0, err / scale, 0.0)))
        out["ibe/count"] = float(getattr(self.noise, "count", 0))
        return out

    def evaluate(self, seeds: list[int]) -> dict[str, Any]:
        """Evaluate the current policy on the task (see :meth:`Task.evaluate`)."""
        return self.task.evaluate(self.actor, seeds)

    # -------------------------------------------------------------------------------------- checkpoints
    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue exactly: weights, optimisers, generator, env states, IBE, counters."""
        return {
            "k": self.k,
            "critic": self.critic.state_dict(),
            "actor": self.actor.state_dict(),
            "critic_opt": self.critic_opt.state_dict(),
            "actor_opt": self.actor_opt.state_dict(),
            "generator": self.generator.get_state(),
            "states": self.states.clone(),
            "steps": self.steps.clone(),
            "noise": self.noise.state_dict(),
            "stop_count": self.stop_count,
            "stopped": self.stopped,
            **({"sampler": self.sampler.state_dict()} if self.sampler is not None else {}),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`.

        Raises
        ------
        ValueError
            A key is missing or a tensor has the wrong shape (message starts with ``state``).
        """
        missing = {"k", "critic", "actor", "critic_opt", "actor_opt", "generator", "states", "steps", "noise",
                   "stop_count", "stopped"} - set(state)
        if self.sampler is not None and "sampler" not in state:
            missing.add("sampler")
        if missing:
            raise ValueError(f"state: missing keys {sorted(missing)}")
        if tuple(state["states"].shape) != tuple(self.states.shape):
            raise ValueError(f"state: states have shape {tuple(state['states'].shape)}, expected "
                             f"{tuple(self.states.shape)}")
        if self.sampler is not None:
            self.sampler.load_state_dict(state["sampler"])
        try:
            self.critic.load_state_dict(state["critic"])
            self.actor.load_state_dict(state["actor"])
            self.critic_opt.load_state_dict(state["critic_opt"])
            self.actor_opt.load_state_dict(state["actor_opt"])
        except (RuntimeError, KeyError) as exc:
            raise ValueError(f"state: weights do not match the networks ({exc})") from None
        self.generator.set_state(state["generator"])
        self.states = state["states"].clone()
        self.steps = state["steps"].clone()
        self.noise.load_state_dict(state["noise"])
        self.k = int(state["k"])
        self.stop_count = int(state["stop_count"])
        self.stopped = bool(state["stopped"])

