"""Algorithm 2: a run's state (:class:`AGPI`) -- task, config, generator, networks, optimisers, noise source,
sampler, counters, checkpoint format -- and its networks (:func:`build_networks`).

The loop itself, one outer iteration ``k`` (data, PEV eqs. 49-50, PIM eqs. 51-52, IBE eq. 20, the MVC loop
eqs. 37-39, the stopping test), is :func:`mixedrl.algorithms.algorithm2.iteration`, for a run alone
(:meth:`AGPI.iteration`, ``R = 1``) and for many runs at once (:class:`mixedrl.algorithms.batched.BatchedAGPI`).
Its PEV and PIM steps are :func:`mixedrl.pev.critic_step` and :func:`mixedrl.pim.actor_step`, which
:meth:`AGPI.pev` and :meth:`AGPI.pim` call too. The departures from the paper plug into the loop's named
hooks (:mod:`mixedrl.departures`); ``TrainConfig.preset("paper")`` switches them all off.

The noise source is the only difference between mixed RL (an IBE posterior), model-driven RL (the fixed
prior, eq. 55) and the oracle (the fixed true noise): :func:`mixedrl.noise.make_noise_source`. A
state-dependent source (Case 3, :class:`mixedrl.ibe.StateDependentIBE`) is planned with per-state nodes.
Expectations over ``xi_hat ~ N(mu_hat, K_hat)`` use sigma points by default
(:func:`mixedrl.expectation.expectation_nodes`; docs/expectation.rst); because the noise is additive,
``f(x, u)`` is computed once per state and only ``l`` and ``V`` are evaluated at the nodes (``h`` of eq. 37,
:func:`mixedrl.expectation.h_value`).

``critic_loss``, ``actor_objective``, ``h_value``, ``expectation_nodes``, ``mvc_check``, ``MVCResult`` and
``make_noise_source`` are re-exported here.
"""

from __future__ import annotations

import logging
from functools import cached_property
from typing import Any

import numpy as np
import torch
from torch.optim.swa_utils import AveragedModel

from mixedrl.config import TrainConfig
from mixedrl.algorithms import algorithm2
from mixedrl.samplers import SAMPLER_CLASSES
from mixedrl.departures import actor_output, anchor, calibration, critic_target, state_weights
from mixedrl.expectation import NodeCache, expectation_nodes, h_value
from mixedrl.networks import Actor, AffineActor, ClippedActor, Critic, QuadraticCritic
from mixedrl.noise import make_noise_source
from mixedrl.plant import check_plant_sampler
from mixedrl.pev import critic_loss, critic_step
from mixedrl.pim import MVCResult, actor_objective, actor_step, mvc_check
from mixedrl.schedule import resolve_budget
from mixedrl.task_base import Task, check_task

__all__ = [
    "AGPI",
    "build_networks",
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
# Algorithm 2
# ----------------------------------------------------------------------------------------------------
def build_networks(task: Task, config: TrainConfig, generator: torch.Generator, architecture: str = "mlp"
                   ) -> tuple[torch.nn.Module, torch.nn.Module]:
    """Critic ``V(x; w)`` and actor ``pi(x; theta)`` of eq. (48) for ``task``.

    ``architecture="mlp"``: :class:`~mixedrl.networks.Critic` and :class:`~mixedrl.networks.Actor`
    (the same for every method); ``"quadratic"``: the exact LQ
    classes :class:`~mixedrl.networks.QuadraticCritic` and :class:`~mixedrl.networks.AffineActor`.
    """
    if architecture == "quadratic":
        return (QuadraticCritic(task.obs_dim, generator), AffineActor(task.obs_dim, task.action_dim, generator))
    if architecture != "mlp":
        raise ValueError(f"architecture: expected 'mlp' or 'quadratic', got {architecture!r}")
    critic = Critic(task.obs_dim, config.algorithm.hidden_sizes, config.algorithm.activation, generator, task.obs_scale,
                    task.value_scale, config.algorithm.value_output)
    args = (task.obs_dim, task.action_dim, config.algorithm.hidden_sizes, config.algorithm.activation, generator,
            task.action_bound, task.obs_scale)
    # departure hook (actor_output): the clipped actor with a straight-through gradient for its parameters
    actor: torch.nn.Module = ClippedActor(*args) if actor_output.active(config) else Actor(*args)
    return critic, actor


class AGPI:
    """Algorithm 2 (mixed RL with parameterised value and policy, AGPI with the MVC inner loop).

    Parameters
    ----------
    task : Task
        The system (model ``f``, utility, true environment, prior).
    config : TrainConfig
        ``method`` in ``{"mixed", "model", "oracle"}`` selects the noise source (``ibe_case`` the IBE's
        Case for mixed RL).
    architecture : {"mlp", "quadratic"}, optional
        Function classes (see :func:`build_networks`).
    noise_source : NoiseSource or StateDependentNoiseSource, optional
        Overrides :func:`mixedrl.noise.make_noise_source` (any object of the protocols of
        :mod:`mixedrl.noise`: ``learns``, ``state_dependent``, ``mean`` or ``mean_at``, ``cov``,
        ``update``, ``state_dict``/``load_state_dict``).

    Raises
    ------
    ValueError
        ``config.method`` is ``"ddpg"`` (use :class:`~mixedrl.algorithms.ddpg.DDPG`).

    Notes
    -----
    The order of the steps inside one iteration (the IBE update between PIM and the MVC loop, a cyclic
    shift of the paper's loop) is explained in :mod:`mixedrl.algorithms.algorithm2`.
    """

    def __init__(self, task: Task, config: TrainConfig, architecture: str = "mlp", noise_source: Any = None
                 ) -> None:
        if config.method == "ddpg":
            raise ValueError("config: method 'ddpg' is not Algorithm 2; use mixedrl.algorithms.ddpg.DDPG")
        check_task(task)
        self.task = task
        # self.config is the resolved config (what config.json holds): a global task's budget is region_budget
        # times longer (schedule.resolve_budget)
        config, self.region_budget = resolve_budget(config, task)
        self.config = config
        self.architecture = architecture
        self.generator = torch.Generator().manual_seed(config.seed)
        # algorithm.feedforward "lq_ss" / "lq_handover" ("auto" resolved by anchor.resolve) need an equilibrium
        feedforward = self.feedforward = anchor.resolve(config, task)
        self._linearisation = None if feedforward == "learned" else anchor.linearisation(task, feedforward)
        self.critic, self.actor = build_networks(task, config, self.generator, architecture)
        self.critic_opt = torch.optim.Adam(self.critic.parameters(), lr=config.algorithm.critic_lr)
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=config.algorithm.actor_lr)
        # Case 1 / 2 / 3 of the IBE (config.algorithm.ibe_case; mixed RL only)
        self.noise = noise_source if noise_source is not None else make_noise_source(
            config.method, task, config.algorithm.ibe_recursion, covariance="unknown" if config.algorithm.ibe_case == 2 else "known",
            state_dependent=config.algorithm.ibe_case == 3)
        #: The quadrature of xi_hat, recomputed only when its moments change (algorithm2.nodes).
        self.node_cache = NodeCache()
        self.k = 0
        self.states = task.sample_initial(config.algorithm.batch_size, self.generator)
        # desynchronised episode clocks, so the copies do not all reset at the same iteration
        self.steps = torch.randint(0, config.algorithm.horizon, (config.algorithm.batch_size,), generator=self.generator)
        self.stop_count = 0
        self.stopped = False
        self.last_batch: torch.Tensor | None = None
        #: States and actions (float64) of the last finite residuals, for a state-dependent IBE.
        self.transitions: tuple[torch.Tensor, torch.Tensor] | None = None
        # the sampler chosen by config.sampler.name makes the batch (model_data.py); None = the true copies
        sampler_class = SAMPLER_CLASSES.get(config.sampler.name)
        check_plant_sampler(task, config)
        if config.sampler.name not in SAMPLER_CLASSES:
            raise ValueError(f"config: sampler.name {config.sampler.name!r} has no implementation "
                             f"(known: {sorted(SAMPLER_CLASSES)})")
        if sampler_class is not None:
            sampler_class.check_task(task, config)
        self.sampler = sampler_class(task, config, self.generator) if sampler_class is not None else None
        #: The target critic ``V(x; w_bar)`` of PEV (:mod:`mixedrl.departures.critic_target`), else ``None``
        #: (eq. 50: the critic itself).
        self.critic_target: AveragedModel | None = critic_target.make(self.critic, config)
        #: End states of the last rollouts that the next iteration's region starts carry over
        #: (:mod:`mixedrl.departures.region`), else ``None``; part of the checkpoint once set.
        self.region_carry: torch.Tensor | None = None
        #: The box of the observations the actor was trained on in the second half of the budget, shape
        #: (2, obs_dim): low and high (:func:`mixedrl.departures.anchor.remember`), recorded on a task that
        #: declares an equilibrium whatever ``algorithm.feedforward`` deploys (``"lq_handover"`` hands over
        #: outside it, so a finished run can be evaluated either way); ``None`` before any; in the checkpoint.
        self.trained_box: torch.Tensor | None = None
        self.records_box = task.equilibrium() is not None

    # -------------------------------------------------------------------------------------- helpers
    @property
    def relative_offset(self) -> float | None:
        """``batch_weight_offset * value_scale`` if ``batch_weighting == "relative"``, else ``None`` (the plain
        batch mean): :func:`mixedrl.departures.state_weights.offset`."""
        return state_weights.offset(self.config, getattr(self.task, "value_scale", 1.0))

    @property
    def learned_policy(self) -> torch.nn.Module:
        """The learned policy: the actor ``pi(x; theta)`` (before a feed-forward of :attr:`policy`)."""
        return self.actor

    @property
    def policy(self) -> torch.nn.Module:
        """The run's policy on observations (what is evaluated and deployed): the :attr:`learned_policy`, or,
        with :attr:`feedforward` ``"lq_ss"``, that policy shifted to the discounted LQ optimum's action at its
        steady state (:func:`mixedrl.departures.anchor.feedforward_policy`); with ``"lq_handover"`` the latter,
        handed over to the optimum outside :attr:`trained_box`
        (:func:`mixedrl.departures.anchor.handover_policy`); either shift calibrated with
        ``algorithm.feedforward_calibration`` (:func:`mixedrl.departures.calibration.deployed_policy`)."""
        if self.feedforward == "learned":
            return self.learned_policy
        return calibration.deployed_policy(self, self.learned_policy, self._linearisation, self.feedforward)

    def nodes(self, mean: np.ndarray, cov: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """Quadrature of ``N(mean, cov)`` with this run's rule: :func:`mixedrl.algorithms.algorithm2.nodes`."""
        return algorithm2.nodes(self, mean, cov)

    def planning_moments(self, s: torch.Tensor, u: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        """The moments of ``xi_hat_k`` that PEV and PIM plan with on the batch ``s`` (``u = pi^k(s)``), copies:
        :func:`mixedrl.algorithms.algorithm2.planning_moments`."""
        return algorithm2.planning_moments(self, s, u)

    # -------------------------------------------------------------------------------------- the steps
    def collect(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Step the true environment copies once under ``pi^k``; return (states, residuals).

        With a model-rollout sampler (``sampler.name`` not ``"true_copies"``) the batch is a step of the
        planning-model rollouts instead and the residuals come from the sampler's true drives.

        Returns
        -------
        states : torch.Tensor, shape (B, state_dim)
            The batch ``x`` of this iteration (float32), the states before the step.
        residuals : torch.Tensor, shape (M, noise_dim)
            Finite residuals ``xi^D`` of eq. (10) (float64); their states and actions are kept in
            :attr:`transitions` (for a state-dependent IBE).
        """
        if self.sampler is not None:
            s, xi = self.sampler.collect(self.actor, self.noise, self.k)
            self.transitions = self.sampler.transitions
            return s, xi
        task = self.task
        s = self.states
        with torch.no_grad():
            u = self.actor(task.observe(s.float())).double()
            s_next = task.true_step(s, u, self.generator)
            xi = task.residuals(s, u, s_next)
        finite = torch.isfinite(xi).all(dim=-1)
        xi = xi[finite]
        self.transitions = (s[finite], u[finite])
        self.steps += 1
        done = task.is_terminal(s_next) | (self.steps >= self.config.algorithm.horizon)
        if bool(done.any()):
            n_done = int(done.sum())
            s_next = s_next.clone()
            s_next[done] = task.sample_initial(n_done, self.generator)
            self.steps[done] = 0
        self.states = s_next
        return s.float(), xi

    @property
    def true_transitions(self) -> int:
        """True-environment transitions used so far (``batch_size`` per iteration for ``sampler.name = "true_copies"``)."""
        return self.sampler.true_transitions if self.sampler is not None else self.k * self.config.algorithm.batch_size

    def pev(self, s: torch.Tensor, offsets: torch.Tensor, weights: torch.Tensor) -> float:
        """Implements eqs. (49)-(50): PEV, one semi-gradient step of this run's critic under ``xi_hat_k``
        (:func:`mixedrl.pev.critic_step` with this run's departure hooks). Returns the loss before the step.

        .. math:: w^{k+1} = w^k - \\alpha\\, \\partial J_{\\rm critic} / \\partial w
        """
        target = None if self.critic_target is None else self.critic_target.module
        return float(critic_step(self.task, self.critic, self.actor, self.critic_opt, s, offsets, weights,
                                 self.config.algorithm.grad_clip, self.relative_offset, target_critic=target))

    def pim(self, s: torch.Tensor, offsets: torch.Tensor, weights: torch.Tensor) -> float:
        """Implements eqs. (51)-(52): PIM, one gradient step of this run's actor under ``xi_hat_k``
        (:func:`mixedrl.pim.actor_step`). Returns the actor objective before the step.

        .. math:: \\theta^{k+1} = \\theta^k - \\beta\\, \\partial J_{\\rm actor} / \\partial \\theta
        """
        return float(actor_step(self.task, self.critic, self.actor, self.actor_opt, s, offsets, weights,
                                self.config.algorithm.grad_clip, self.relative_offset))

    def ibe(self, residuals: torch.Tensor) -> None:
        """Implements eq. (20): the IBE update of this run's noise source (:func:`mixedrl.algorithms.algorithm2.ibe`)."""
        algorithm2.ibe(self.noise, residuals, self.transitions)

    def iteration(self) -> dict[str, float]:
        """Implements Algorithm 2, one outer iteration ``k``: data, PEV, PIM, IBE, MVC loop, stopping test
        (:func:`mixedrl.algorithms.algorithm2.iteration` with this run alone, ``R = 1``).

        Returns
        -------
        dict
            This iteration's metrics (namespaced keys, see :mod:`mixedrl.runs`).
        """
        return self.engine.iteration()[0]

    @cached_property
    def engine(self) -> Any:
        """This run alone as a batch: the :class:`mixedrl.algorithms.batched.BatchedAGPI` of ``[self]``
        that :meth:`iteration` runs (built on first use)."""
        from mixedrl.algorithms.batched import BatchedAGPI

        return BatchedAGPI([self])

    def noise_moments(self) -> tuple[np.ndarray, np.ndarray]:
        """Copies of the current ``(mu_hat, K_hat)``, shapes (noise_dim,), (noise_dim, noise_dim).

        For a state-dependent source the mean is the average of ``phi(x, pi(x))`` over the last batch
        (the current environment states before the first iteration).
        """
        if self.noise.state_dependent:
            s = self.last_batch if self.last_batch is not None else self.states.float()
            with torch.no_grad():
                u = self.actor(self.task.observe(s))
            mean, cov = self.planning_moments(s, u)
            return mean.mean(axis=0), cov
        return np.array(self.noise.mean, dtype=np.float64), np.array(self.noise.cov, dtype=np.float64)

    def actor_bound_tensor(self) -> torch.Tensor:
        """The actor's action bound (ones if it has none), shape (action_dim,)."""
        bound = getattr(self.actor, "action_bound", None)
        return bound if bound is not None else torch.ones(self.task.action_dim)

    def noise_metrics(self) -> dict[str, float]:
        """IBE mean and covariance (components of the noise subspace), and errors against the truth."""
        mean, cov = self.noise_moments()
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
        return self.task.evaluate(self.policy, seeds)

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
            "evaluation_transitions": self.task.evaluation_transitions,
            **{key: part.state_dict() for key, part in self.plug_ins().items()},
            # departures.region's carried end states, once there are any (a fresh trainer has none)
            **({"region_carry": self.region_carry.clone()} if self.region_carry is not None else {}),
            # departures.anchor's box of the trained observations, once there is one
            **({"trained_box": self.trained_box.clone()} if self.trained_box is not None else {}),
        }

    def plug_ins(self) -> dict[str, Any]:
        """The run's parts that departures add, by checkpoint key: ``sampler`` (a model-rollout sampler),
        ``critic_target`` (target values); only those the run has."""
        parts = {"sampler": self.sampler, "critic_target": self.critic_target}
        return {key: part for key, part in parts.items() if part is not None}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`.

        Raises
        ------
        ValueError
            A key is missing or a tensor has the wrong shape (message starts with ``state``).
        """
        missing = {"k", "critic", "actor", "critic_opt", "actor_opt", "generator", "states", "steps", "noise",
                   "stop_count", "stopped"} - set(state)
        missing |= set(self.plug_ins()) - set(state)
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
            for key, part in self.plug_ins().items():
                if key != "sampler":  # the averages (the sampler is restored above)
                    part.load_state_dict(state[key])
        except (RuntimeError, KeyError) as exc:
            raise ValueError(f"state: weights do not match the networks ({exc})") from None
        self.generator.set_state(state["generator"])
        self.states = state["states"].clone()
        self.steps = state["steps"].clone()
        self.noise.load_state_dict(state["noise"])
        self.k = int(state["k"])
        self.stop_count = int(state["stop_count"])
        self.stopped = bool(state["stopped"])
        self.task.evaluation_transitions = int(state.get("evaluation_transitions", 0))
        carry = state.get("region_carry")
        self.region_carry = None if carry is None else carry.clone()
        box = state.get("trained_box")
        self.trained_box = None if box is None else box.clone()

