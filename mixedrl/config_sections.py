"""The sections of :class:`mixedrl.config.TrainConfig` besides the task: :class:`AlgorithmConfig`,
:class:`DDPGConfig`, :class:`RunConfig`, the samplers' options (:data:`SAMPLERS`, :func:`register_sampler`) and
the tasks' experiment configurations (:data:`PRESETS`, :func:`register_preset`).

:mod:`mixedrl.config` re-exports every public name of this module.
"""

from __future__ import annotations

import copy
import dataclasses
import os
from dataclasses import dataclass
from typing import Any, ClassVar, Union

from mixedrl.checks import check_fraction, check_int, check_nonnegative_int, check_number, check_positive_int
from mixedrl.config_tasks import (BATCH_WEIGHTINGS, COMPILE_MODES, FEEDFORWARDS, RETIRED_ACTOR_OUTPUTS,
                                   RETIRED_FEEDFORWARDS, build_section, check_choice)

__all__ = ["AlgorithmConfig", "DDPGConfig", "OPTIMISER_FIELDS", "RunConfig", "SamplerConfig", "TrueCopiesSampler",
           "ModelRolloutsSampler", "SAMPLERS", "PRESETS", "register_sampler", "register_preset", "sampler_config"]

# ---- sections of TrainConfig ----
#: The network and optimiser settings each of Algorithm 2 (``algorithm.<field>``) and DDPG (``ddpg.<field>``)
#: has its own of: minibatch size, hidden activation, the two Adam learning rates, the gradient clip.
OPTIMISER_FIELDS = ("batch_size", "activation", "critic_lr", "actor_lr", "grad_clip")


def _check_optimiser(section: Any, where: str) -> None:
    """Check the :data:`OPTIMISER_FIELDS` of ``section`` (an :class:`AlgorithmConfig` or a :class:`DDPGConfig`),
    naming ``<where>.<field>``."""
    section.batch_size = check_positive_int(section.batch_size, f"{where}.batch_size")
    check_choice(section.activation, f"{where}.activation", ("elu", "tanh", "relu"))
    for name in ("critic_lr", "actor_lr"):
        check_number(getattr(section, name), f"{where}.{name}", positive=True)
    check_number(section.grad_clip, f"{where}.grad_clip", positive=True, allow_inf=True)


@dataclass
class AlgorithmConfig:
    """The training algorithm: Algorithm 2 (mixed, model, oracle), and the network sizes, critic head and
    budget DDPG shares with it. Dotted keys: ``algorithm.<field>``.

    The :data:`OPTIMISER_FIELDS` are Algorithm 2's only (DDPG's: :class:`DDPGConfig`). The fields marked
    *Departure* depart from the paper's Algorithm 2; docs/algorithm2.rst gives each with the paper's value
    (:data:`mixedrl.config.PAPER_SETTINGS`), and docs/tuning.rst the measurements behind the defaults.
    """

    iterations: int = 800
    """Budget: number of outer iterations ``k`` (one PEV + PIM step of Algorithm 2, or one DDPG update); the
    same budget rule for every method, DDPG included (Algorithm 2 on a global task: :attr:`region_budget`)."""

    region_budget: int = 4
    """Budget factor >= 1 of Algorithm 2 on a task that declares a state region, at the same true transitions
    (:func:`mixedrl.schedule.resolve_budget`, docs/tuning.rst); 1 turns it off (the ``paper`` preset)."""

    batch_size: int = 128
    """Number of states of the PEV/PIM batch per iteration (Algorithm 2; made by the sampler). DDPG's
    replay minibatch is ``ddpg.batch_size``."""

    horizon: int = 60
    """Steps after which a training copy (true copy, model rollout, DDPG's environment copy) restarts from
    a fresh initial state; shared by every method."""

    hidden_sizes: tuple[int, ...] = (64, 64)
    """Hidden layer widths of the actor and the critic (shared by every method, DDPG included)."""

    activation: str = "tanh"
    """Hidden activation of Algorithm 2's MLPs: ``"elu"``, ``"tanh"`` or ``"relu"`` (DDPG's:
    ``ddpg.activation``)."""

    value_output: str = "square"
    """Output head of the critic, and of DDPG's Q-critic: ``"softplus"``, ``"square"`` (sum of
    squares) or ``"linear"``; see :class:`mixedrl.networks.Critic`."""

    critic_lr: float = 2e-3
    """Adam learning rate alpha of Algorithm 2's critic (eq. 50); DDPG's Q-critic has ``ddpg.critic_lr``."""

    actor_lr: float = 2e-3
    """Adam learning rate beta of Algorithm 2's actor (eq. 52); DDPG's actor has ``ddpg.actor_lr``."""

    lr_decay_to: float = 0.01
    """Departure (schedule): the learning rates decay linearly to ``lr_decay_to`` times their value, in
    (0, 1]; 1.0 = constant (the paper's). Over the budget, or ``lr_decay_iterations``; shared by every method
    (:func:`mixedrl.schedule.lr_factor`)."""

    lr_decay_iterations: int = 0
    """Length in iterations of the learning-rate decay of every method, after which the rates stay; 0 = the
    budget, also when the budget is shorter (:func:`mixedrl.schedule.lr_factor`)."""

    grad_clip: float = 1.0
    """Clip of the global gradient norm of each update of Algorithm 2 (``math.inf`` disables it)."""

    expectation: str = "sigma"
    """How the expectation over ``xi_hat ~ N(mu_hat, K_hat)`` in eqs. (49)-(52) is computed:
    ``"sigma"`` = deterministic spherical-cubature sigma points in the range of ``K_hat`` (2r points,
    exact for polynomials of degree <= 3 in ``xi``), ``"samples"`` = reparameterised Monte-Carlo samples."""

    noise_samples: int = 4
    """Number of reparameterised samples per state when ``expectation == "samples"``."""

    j_max: int = 1
    """Maximum number of extra PIM steps of the AGPI inner loop (Algorithm 2)."""

    mvc_check: str = "mean"
    """Where the MVC (eq. 38) is checked on the batch: ``"mean"`` (batch average of both sides) or
    ``"all"`` (every state)."""

    stop_epsilon: float = 0.0
    """Stopping test of Algorithm 2: stop when the mean absolute change of ``V`` and of ``pi`` on the
    batch both stay below ``stop_epsilon`` for ``stop_patience`` iterations; 0 disables it."""

    stop_patience: int = 100
    """Consecutive iterations the stopping test must hold."""

    ibe_recursion: str = "exact"
    """Recursion of the Case-2 IBE (``"exact"`` = eq. 17 recursively, ``"paper"`` = eq. 18)."""

    ibe_case: int = 2
    """Which IBE mixed RL plans with (:func:`mixedrl.noise.make_noise_source`): ``2`` = Case 2, mean and
    covariance unknown (eqs. 17-18); ``1`` = Case 1, covariance known (the true ``K``, eq. 16); ``3`` =
    Case 3, a state-dependent mean ``phi(x, u) = W^T g(x, u)`` on the task's features, covariance known
    (eq. 19, :class:`mixedrl.ibe.LinearFeatureIBE`). Only ``method = "mixed"`` reads it;
    ``ibe_recursion`` must be ``"exact"`` unless it is 2."""

    batch_weighting: str = "relative"
    """Departure (state weights): how PEV and PIM weight the batch's states (eqs. 50, 52): ``"uniform"`` (the
    paper's batch mean) or ``"relative"`` (the TD error relative to ``|V_target| + c``, PIM's states by
    ``1 / (V(x) + c)``; :func:`mixedrl.pev.critic_loss`, :func:`mixedrl.pim.actor_objective`)."""

    batch_weight_offset: float = 0.3
    """Departure (state weights): ``c`` of ``batch_weighting = "relative"``, > 0, in units of ``value_scale``."""

    critic_target: float = 0.8
    """Departure (target values): decay ``beta`` in [0, 1) of the target critic ``w_bar <- beta w_bar +
    (1 - beta) w`` that PEV's target takes (:func:`mixedrl.pev.critic_loss`); 0 = eq. (50) as written."""

    feedforward: str = "auto"
    """Departure (anchor): where the deployed policy takes its action at the task's equilibrium, training
    unchanged: ``"learned"`` (the paper's, the actor's own), ``"lq_ss"`` (shifted near the LQ optimum's steady
    state, :func:`mixedrl.departures.anchor.steady_anchor`), ``"lq_handover"`` (``"lq_ss"``, handed over to the
    LQ optimum outside the observations the actor was trained on, :class:`mixedrl.departures.anchor.HandoverPolicy`)
    or ``"auto"`` (:func:`mixedrl.departures.anchor.resolve`); docs/precision.rst. Retired (refused naming the
    commit that still runs each, :data:`mixedrl.config.RETIRED_FEEDFORWARDS`): ``"lq"`` (a constant shift to the
    optimum's action at the equilibrium; commit c44231f), ``"lq_train"``, ``"lq_affine"``, ``"lq_affine_ss"``
    (commit ee954d7)."""

    feedforward_width: float = 0.25
    """Departure (anchor): width ``rho`` >= 0 of the ``"lq_ss"`` shift (and of the hand-over), weighted by
    ``exp(-|(o - o_ss) / (rho obs_scale)|^2 / 2)``; 0 = a constant shift (docs/tuning.rst)."""

    feedforward_calibration: int = 1
    """Departure (anchor): Newton steps >= 0 that correct the ``"lq_ss"`` shift (and ``"lq_handover"``'s) so that
    the deployed closed loop's mean state in the planning model, under the run's own noise, is the LQ optimum's
    (:func:`mixedrl.departures.calibration.calibrate_shift`); 0 = the shift as :func:`~mixedrl.departures.anchor.steady_anchor`
    gives it (docs/precision.rst)."""

    compile: str = "off"
    """How the updates run, Algorithm 2's PEV and PIM steps and DDPG's critic and actor steps alike
    (:mod:`mixedrl.compiled`, docs/algorithm2.rst): ``"off"`` = eagerly (the reference), ``"on"`` = compiled by
    ``torch.compile``, ``"functional"`` = that step uncompiled."""

    rollout_horizon: int = 16
    """Departure (rollouts): model steps ``H`` >= 0 of the rollouts PEV and PIM work on
    (:mod:`mixedrl.departures.rollout`); 0 = the paper's one-step PEV and PIM (eqs. 49-52)."""

    rollout_lambda: float = 0.95
    """Departure (rollouts): ``lambda`` in [0, 1] of the critic's ``lambda``-returns (``rollout_horizon > 0``)."""

    rollout_discount_start: float = 0.95
    """Departure (rollouts): discount in [0, 1) at which the rollouts (``rollout_horizon > 0``) start, ramped
    linearly to the task's ``gamma`` over ``rollout_discount_ramp``; 0 = ``gamma`` throughout."""

    rollout_discount_ramp: float = 0.4
    """Departure (rollouts): fraction of the budget, in [0, 1], over which the discount ramps."""

    rollout_region: float = 0.5
    """Departure (region starts, :mod:`mixedrl.departures.region`): fraction in [0, 1] of the rollouts' start
    states drawn from the task's state region, the rest end states of earlier rollouts; 0 = the batch. Only
    with ``rollout_horizon > 0`` on a task that declares a region, not with ``ibe_case = 3``."""

    actor_output: str = "clip_inward"
    """Departure (actor output, :mod:`mixedrl.departures.actor_output`): how Algorithm 2's actor bounds its
    output: ``"tanh"`` (``u_bar tanh(MLP)``, the paper's) or ``"clip_inward"`` (``u_bar clip(MLP, -1, 1)``, the
    gradient passed straight through for the parameters only where the step moves a clipped output back inside).
    Retired: ``"clip"`` (straight through in both directions; commit c44231f still runs it,
    :data:`mixedrl.config.RETIRED_ACTOR_OUTPUTS`)."""

    def __post_init__(self) -> None:
        w = "algorithm"
        for name in ("iterations", "region_budget", "horizon", "noise_samples", "j_max", "stop_patience"):
            setattr(self, name, check_positive_int(getattr(self, name), f"{w}.{name}"))
        for name in ("lr_decay_iterations", "rollout_horizon", "feedforward_calibration"):
            setattr(self, name, check_nonnegative_int(getattr(self, name), f"{w}.{name}"))
        _check_optimiser(self, w)
        if isinstance(self.hidden_sizes, (str, bytes)) or not isinstance(self.hidden_sizes, (list, tuple)) \
                or not self.hidden_sizes:
            raise ValueError(f"{w}.hidden_sizes: expected positive widths, got {self.hidden_sizes!r}")
        self.hidden_sizes = tuple(check_positive_int(h, f"{w}.hidden_sizes") for h in self.hidden_sizes)
        for name, options in (("compile", COMPILE_MODES), ("value_output", ("softplus", "square", "linear")),
                              ("expectation", ("sigma", "samples")), ("mvc_check", ("mean", "all")),
                              ("ibe_recursion", ("exact", "paper")), ("batch_weighting", BATCH_WEIGHTINGS)):
            check_choice(getattr(self, name), f"{w}.{name}", options)
        check_choice(self.actor_output, f"{w}.actor_output", ("tanh", "clip_inward"), RETIRED_ACTOR_OUTPUTS)
        check_choice(self.feedforward, f"{w}.feedforward", FEEDFORWARDS, RETIRED_FEEDFORWARDS)
        self.feedforward_width = check_number(self.feedforward_width, f"{w}.feedforward_width", nonneg=True)
        self.batch_weight_offset = check_number(self.batch_weight_offset, f"{w}.batch_weight_offset", positive=True)
        check_number(self.stop_epsilon, f"{w}.stop_epsilon", nonneg=True)
        if check_int(self.ibe_case, f"{w}.ibe_case") not in (1, 2, 3):
            raise ValueError(f"{w}.ibe_case: expected 1, 2 or 3 (the IBE's Case), got {self.ibe_case!r}")
        if self.ibe_case != 2 and self.ibe_recursion != "exact":
            raise ValueError(f"{w}.ibe_recursion: 'paper' is eq. (18), a Case 2 recursion; "
                             f"{w}.ibe_case is {self.ibe_case}")
        check_fraction(self.lr_decay_to, f"{w}.lr_decay_to", low_open=True)
        for i, name in enumerate(("critic_target", "rollout_discount_start",  # below 1
                                  "rollout_lambda", "rollout_discount_ramp", "rollout_region")):
            check_fraction(getattr(self, name), f"{w}.{name}", high_open=i < 2)


@dataclass
class DDPGConfig:
    """The DDPG baseline's settings: replay buffer, target networks, exploration noise (textbook values, not
    tuned) and its own :data:`OPTIMISER_FIELDS`, independent of Algorithm 2's. Network sizes, critic head,
    budget, horizon and learning-rate decay are shared (``algorithm.<field>``). Dotted keys: ``ddpg.<field>``."""

    envs: int = 16
    """Parallel true-environment copies stepped once per iteration (transitions per iteration)."""

    buffer_size: int = 200_000
    """Replay buffer capacity (transitions)."""

    warmup: int = 2000
    """Transitions collected with exploration before the first update."""

    tau: float = 0.005
    """Polyak factor of the target networks, in (0, 1]."""

    noise_std: float = 0.2
    """Standard deviation of the Gaussian exploration noise, as a fraction of each action bound."""

    batch_size: int = 512
    """Replay minibatch size of each update (transitions)."""

    activation: str = "elu"
    """Hidden activation of the actor's and the Q-critic's MLPs: ``"elu"``, ``"tanh"`` or ``"relu"``."""

    critic_lr: float = 3e-3
    """Adam learning rate of the Q-critic (decayed by the shared ``algorithm.lr_decay_*`` rule)."""

    actor_lr: float = 3e-4
    """Adam learning rate of the actor (decayed by the shared ``algorithm.lr_decay_*`` rule)."""

    grad_clip: float = 10.0
    """Clip of the global gradient norm of each critic and actor update (``math.inf`` disables it)."""

    def __post_init__(self) -> None:
        self.envs = check_positive_int(self.envs, "ddpg.envs")
        self.buffer_size = check_positive_int(self.buffer_size, "ddpg.buffer_size")
        self.warmup = check_nonnegative_int(self.warmup, "ddpg.warmup")
        check_fraction(self.tau, "ddpg.tau", low_open=True)
        check_number(self.noise_std, "ddpg.noise_std", positive=True)
        _check_optimiser(self, "ddpg")


@dataclass
class RunConfig:
    """Bookkeeping of a run: evaluation, checkpoints, threads. Dotted keys: ``run.<field>``."""

    eval_every: int = 100
    """Evaluate the policy every ``eval_every`` iterations (:meth:`mixedrl.tasks.Task.evaluate`)."""

    eval_seeds: int = 2
    """Number of noise realisations averaged by each evaluation."""

    checkpoint_every: int = 500
    """Write an atomic checkpoint every ``checkpoint_every`` iterations (and at the end)."""

    num_threads: int = 1
    """``torch.set_num_threads`` for the run (fixed, so results do not depend on the machine)."""

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            setattr(self, f.name, check_positive_int(getattr(self, f.name), f"run.{f.name}"))
        cores = os.cpu_count()
        if cores is not None and self.num_threads > cores:
            raise ValueError(f"run.num_threads: {self.num_threads} threads, more than this machine's {cores} cores")


# ---- samplers: where Algorithm 2's PEV/PIM states come from ----
#: The registry of samplers: ``sampler.name`` -> its options class (:func:`register_sampler`), which carries
#: the tasks it needs (``TASKS``) and the class that makes Algorithm 2's batch (``IMPLEMENTATION``).
SAMPLERS: dict[str, type] = {}


def register_sampler(cls: type, tasks: tuple[str, ...] | None = None, implementation: type | None = None) -> type:
    """Register the options class ``cls`` of a sampler under ``cls.NAME``, with the task names it needs
    (``None``: any task; another task is an error naming ``sampler.name``) and its implementation (a
    :class:`mixedrl.samplers.ModelStateSampler` subclass; ``None``: the true copies)."""
    cls.TASKS, cls.IMPLEMENTATION = tasks, implementation
    SAMPLERS[cls.NAME] = cls
    return cls


@dataclass
class TrueCopiesSampler:
    """``sampler.name = "true_copies"``, the paper's: the batch is the states of ``algorithm.batch_size``
    true-environment copies, each stepped once per iteration and reset every ``algorithm.horizon`` steps;
    the IBE consumes their residuals. No options."""

    NAME: ClassVar[str] = "true_copies"

    name: str = "true_copies"
    """Always ``"true_copies"`` for this class."""


@dataclass
class ModelRolloutsSampler:
    """``sampler.name = "model_rollouts"`` (departure, docs/model_based.rst): the batch is
    ``algorithm.batch_size`` rollouts of the planning model, restarted from ``Task.sample_initial`` every
    ``algorithm.horizon`` steps; for mixed RL ``true_envs`` true copies collect the IBE's residuals
    (:class:`mixedrl.samplers.ModelStateSampler`). Dotted keys: ``sampler.<field>``."""

    NAME: ClassVar[str] = "model_rollouts"

    name: str = "model_rollouts"
    """Always ``"model_rollouts"`` for this class."""

    box: float = 3.0
    """A rollout restarts when a component of its observation exceeds ``box`` times the task's
    ``obs_scale`` (``math.inf`` disables it: the planning model may then drive a rollout anywhere)."""

    true_envs: int = 1
    """Mixed RL: true-environment copies driven at each collection."""

    true_steps: int = 20
    """Mixed RL: consecutive steps each true copy drives per collection."""

    true_every: int = 10
    """Mixed RL: iterations between collections (true transitions per iteration:
    ``true_envs * true_steps / true_every``)."""

    true_horizon: int = 200
    """Mixed RL: steps after which a true copy restarts at the task's episode start."""

    def __post_init__(self) -> None:
        w = "sampler"
        if self.name != self.NAME:
            raise ValueError(f"{w}.name: expected {self.NAME!r} for {type(self).__name__}, got {self.name!r}")
        check_number(self.box, f"{w}.box", positive=True, allow_inf=True)
        for name in ("true_envs", "true_steps", "true_every", "true_horizon"):
            setattr(self, name, check_positive_int(getattr(self, name), f"{w}.{name}"))


register_sampler(TrueCopiesSampler)
register_sampler(ModelRolloutsSampler)

#: The configuration of a run's sampler: one of the registered classes (:data:`SAMPLERS`), by ``name``.
SamplerConfig = Union[TrueCopiesSampler, ModelRolloutsSampler]


def sampler_config(value: Any, task: str | None = None) -> Any:
    """Build a sampler configuration from its name, a dict (``name`` selects the class, default
    ``"model_rollouts"``) or an options object (returned as is), checked against the task name ``task``.

    Raises
    ------
    ValueError
        Unknown sampler (``sampler.name``), unknown option (``config: unknown key(s) ['sampler.<key>']``),
        an invalid value, or a sampler the task cannot provide for (naming ``sampler.name`` and the task).
    """
    if isinstance(value, str):
        value = {"name": value}
    if isinstance(value, dict):
        name = check_choice(value.get("name", ModelRolloutsSampler.NAME), "sampler.name", tuple(SAMPLERS))
        value = build_section(SAMPLERS[name], {**value, "name": name}, "sampler")
    elif not any(type(value) is cls for cls in SAMPLERS.values()):
        raise ValueError(f"sampler: expected a sampler name {tuple(SAMPLERS)}, a dict or an options object, "
                         f"got {value!r}")
    needs = SAMPLERS[value.name].TASKS
    if task is not None and needs is not None and task not in needs:
        raise ValueError(f"sampler.name: {value.name!r} needs a task with a course ({', '.join(needs)}); "
                         f"task {task!r} has none")
    return value


# ---- presets: a task's experiment configuration ----
#: Task name -> section -> field values over the library defaults (:func:`register_preset`).
PRESETS: dict[str, dict[str, dict[str, Any]]] = {}


def register_preset(task: str, sections: dict[str, dict[str, Any]]) -> None:
    """Register the experiment configuration of the task ``task``: the values ``TrainConfig`` gives a
    section's missing fields when the run's task is ``task`` (``{"algorithm": {...}, "sampler": {...}}``)."""
    allowed = ["algorithm", "ddpg", "run", "sampler"]
    unknown = sorted(set(sections) - set(allowed))
    if unknown:
        raise ValueError(f"sections: unknown section(s) {unknown}; allowed: {allowed}")
    PRESETS[task] = copy.deepcopy(sections)
