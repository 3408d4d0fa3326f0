"""One typed, documented configuration object per training run, the experiment included.

:class:`TrainConfig` holds a run of Algorithm 2 (``method`` = ``mixed``, ``model``, ``oracle``) or of
the DDPG baseline (``method = "ddpg"``) in seven fields: ``method``, ``seed``, ``task`` (the experiment:
system, prior, true disturbance law, discount, cost weights, preview), ``algorithm``
(:class:`AlgorithmConfig`), ``sampler`` (where the PEV/PIM states come from, a registered options class
chosen by ``name``: :data:`SAMPLERS`), ``ddpg`` (:class:`DDPGConfig`) and ``run`` (:class:`RunConfig`).
It is saved as ``config.json`` beside the run's results; loading a dictionary with a key that is not a
field, at any level, is an error naming the dotted key.

The task configuration is one of two nested dataclasses, chosen by its ``name``:

* :class:`DoubleLaneChangeTaskConfig` (``name = "dlc"``, the paper's Section VI): the environment's own
  configuration (:mod:`mixedrl.envs.dlc_config`, re-exported here) with the discount and the prior, so
  every field of the environment is a ``task.<field>`` key, with the nested
  :class:`ForceDisturbanceConfig` (``task.disturbance``, the environment's
  :class:`~mixedrl.envs.disturbance.Disturbance`) and :class:`CostWeights` (``task.cost``);
* :class:`LinearTaskConfig` (``name = "linear"``, a small LQ system with a known optimum), with the
  nested :class:`GaussianNoiseConfig` (``task.disturbance``).

A section that is not given takes the task's experiment configuration (:data:`PRESETS`): the double
lane change registers :data:`mixedrl.envs.dlc_task.DLC_EXPERIMENT` (the reproduction of Table I: its
course sampler :class:`mixedrl.envs.dlc_task.CourseSampler`, the learning-rate decay over 1500
iterations, the relative batch weighting; both live with the task in :mod:`mixedrl.envs.dlc_task` and
stay importable from here and from :mod:`mixedrl.tasks`); any other task gets the library defaults of
the section classes (model rollouts from the task's start distribution restarted outside 3 x ``obs_scale``,
the decay tied to the budget, the relative batch weighting; docs/tuning.rst gives the measurement behind
them).

Dotted keys address nested fields, the same way on the command line, in :func:`apply_overrides` and in
sweep specifications::

    mixedrl train --method mixed --out runs/p300 --set task.prior_force_mean=300 algorithm.iterations=300
    mixedrl train --method mixed --out runs/true --set sampler.name=\\"true_copies\\"
    mixedrl train --method mixed --out runs/mine --config experiment.json   # nested JSON, like config.json

``"task": "dlc"`` (a task's name) stands for that task's defaults. The flat form of the first release
(45 top-level fields: ``iterations``, ``model_course_starts``, ``ddpg_tau`` ...) is refused with an error
naming the release that reads it (:data:`FLAT_FORM_RELEASE`).
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Union

import numpy as np

from mixedrl.checks import (as_matrix, as_vector, check_covariance, check_fraction, check_int,
                            check_nonnegative_int, check_number, check_positive_int, check_unknown_keys)
from mixedrl.envs.disturbance import DISTURBANCE_LAWS, Disturbance
from mixedrl.envs.dlc_config import CostWeights, DoubleLaneChangeTaskConfig
from mixedrl.lq import LQProblem

__all__ = [
    "TrainConfig",
    "AlgorithmConfig",
    "DDPGConfig",
    "RunConfig",
    "SamplerConfig",
    "TrueCopiesSampler",
    "ModelRolloutsSampler",
    "CourseSampler",
    "SAMPLERS",
    "PRESETS",
    "PAPER_SETTINGS",
    "CONFIG_PRESETS",
    "DLC_EXPERIMENT",
    "FLAT_FORM_RELEASE",
    "memory_lower_bounds",
    "machine_memory",
    "register_sampler",
    "register_preset",
    "sampler_config",
    "TaskConfig",
    "DoubleLaneChangeTaskConfig",
    "LinearTaskConfig",
    "ForceDisturbanceConfig",
    "GaussianNoiseConfig",
    "CostWeights",
    "task_config",
    "register_task",
    "task_names",
    "apply_overrides",
    "flatten_table",
    "METHODS",
    "TASKS",
    "DISTURBANCE_LAWS",
    "BATCH_WEIGHTINGS",
    "MODEL_COURSE_STARTS",
]

#: The four methods of the reproduction (mixed RL, model-driven RL, oracle, DDPG).
METHODS = ("mixed", "model", "oracle", "ddpg")
#: The built-in tasks: the double lane change (paper) and a small linear system. Tasks registered with
#: :func:`register_task` (the pendulum, a user's own) are listed by :func:`task_names`.
TASKS = ("dlc", "linear")
#: Where the course copies of the double lane change's sampler restart
#: (:attr:`mixedrl.envs.dlc_task.CourseSampler.course_starts`).
MODEL_COURSE_STARTS = ("start", "along", "loop")
#: How Algorithm 2 weights the states of its batch (``AlgorithmConfig.batch_weighting``).
BATCH_WEIGHTINGS = ("uniform", "relative")

#: Where the policy takes its action at the equilibrium (``algorithm.feedforward``).
FEEDFORWARDS = ("learned", "lq", "lq_train", "lq_affine", "lq_affine_ss")

#: The ``algorithm.feedforward`` values that change the actor's class during training.
ANCHORED_FEEDFORWARDS = ("lq_train", "lq_affine", "lq_affine_ss")
#: The ``algorithm.feedforward`` values whose actor has the LQ optimum's gain as its first-order part.
AFFINE_FEEDFORWARDS = ("lq_affine", "lq_affine_ss")


def _law(value: Any, name: str) -> str:
    if value not in DISTURBANCE_LAWS:
        raise ValueError(f"{name}: expected one of {DISTURBANCE_LAWS}, got {value!r}")
    return str(value)


def _jsonable(value: Any) -> Any:
    """Dataclasses to dicts, tuples to lists, recursively (what ``json.dumps`` writes)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, (tuple, list)):
        return [_jsonable(v) for v in value]
    return value


def _build(cls: type, data: Any, where: str) -> Any:
    """Instantiate the configuration dataclass ``cls`` from a JSON-like dict (or return an instance as is).

    ``where`` is the dotted path of ``data`` in the run's configuration (``"task"``, ...); unknown keys are
    reported with their full dotted name. Nested fields are passed on as given: each class's
    ``__post_init__`` builds its own nested configurations (with their dotted paths), after checking the
    fields they depend on.
    """
    if isinstance(data, cls):
        return data
    if not isinstance(data, dict):
        raise ValueError(f"{where}: expected a dict (a JSON object), got {data!r}")
    allowed = {f.name for f in dataclasses.fields(cls) if f.init}
    check_unknown_keys({f"{where}.{k}": v for k, v in data.items()}, {f"{where}.{k}" for k in allowed}, "config")
    return cls(**data)


# ----------------------------------------------------------------------------------------------------
# the double lane change (Section VI of the paper): its configuration is the environment's
# ----------------------------------------------------------------------------------------------------
#: The true longitudinal force ``F_dis`` of the double lane change (``task.disturbance``): the
#: environment's :class:`mixedrl.envs.disturbance.Disturbance` itself.
ForceDisturbanceConfig = Disturbance


def _gamma(value: Any) -> float:
    gamma = check_number(value, "task.gamma")
    if not 0.0 < gamma < 1.0:
        raise ValueError(f"task.gamma: expected a number in (0, 1), got {gamma!r}")
    return gamma


# ----------------------------------------------------------------------------------------------------
# the linear test bed
# ----------------------------------------------------------------------------------------------------
@dataclass
class GaussianNoiseConfig:
    """The true additive noise ``xi ~ N(mean, cov)`` of the linear task, in state coordinates.

    Dotted keys: ``task.disturbance.<field>``.
    """

    WHERE: ClassVar[str] = "task.disturbance"

    law: str = "gaussian"
    """Distribution of ``xi``; one of :data:`DISTURBANCE_LAWS` (the linear task simulates only
    ``"gaussian"``)."""

    mean: tuple[float, ...] = (0.0, 0.5)
    """Mean ``mu`` of ``xi``, shape (n,)."""

    cov: tuple[tuple[float, ...], ...] = ((0.0, 0.0), (0.0, 0.01))
    """Covariance ``K`` of ``xi`` (symmetric PSD), shape (n, n)."""

    def __post_init__(self) -> None:
        self.law = _law(self.law, f"{self.WHERE}.law")
        self.mean = tuple(as_vector(self.mean, f"{self.WHERE}.mean").tolist())
        cov = as_matrix(self.cov, f"{self.WHERE}.cov", (len(self.mean), len(self.mean)))
        self.cov = _rows(check_covariance(cov, f"{self.WHERE}.cov", len(self.mean)))


def _rows(matrix: np.ndarray) -> tuple[tuple[float, ...], ...]:
    return tuple(tuple(float(v) for v in row) for row in np.asarray(matrix))


@dataclass
class LinearTaskConfig:
    """The linear test bed :class:`mixedrl.linear_task.LinearTask`: ``s' = A s + B u + xi``, utility
    ``s'^T Q s' + u^T R u`` (a sampled double integrator, ``dt = 0.1``, the noise on the velocity, by
    default). Dotted keys: ``task.<field>``; ``n`` = ``A``'s size, ``m`` = ``B``'s columns.

    The JSON face of the LQ problem: it is validated by, and :meth:`problem` returns, the problem's one
    representation :class:`mixedrl.lq.LQProblem` (``(A, B)`` stabilisable, ``R`` positive definite);
    ``init_box``, ``action_bound`` and the law are what the learning task adds.
    """

    WHERE: ClassVar[str] = "task"

    name: str = "linear"
    """Always ``"linear"`` for this class (selects it when loading)."""

    gamma: float = 0.9
    """Discount factor of eq. (2), in (0, 1)."""

    A: tuple[tuple[float, ...], ...] = ((1.0, 0.1), (0.0, 1.0))
    """System matrix, shape (n, n)."""

    B: tuple[tuple[float, ...], ...] = ((0.5 * 0.1 * 0.1,), (0.1,))
    """Input matrix, shape (n, m)."""

    Q: tuple[tuple[float, ...], ...] = ((1.0, 0.0), (0.0, 1.0))
    """State weight of the utility (symmetric PSD), shape (n, n)."""

    R: tuple[tuple[float, ...], ...] = ((0.1,),)
    """Input weight of the utility (symmetric PSD), shape (m, m)."""

    prior_mean: tuple[float, ...] = (0.0, 0.0)
    """The designer's prior mean ``mu_M`` of ``xi`` (eq. 8), shape (n,)."""

    prior_cov: tuple[tuple[float, ...], ...] = ((0.01, 0.0), (0.0, 0.01))
    """The designer's prior covariance ``K_M`` (symmetric PSD), shape (n, n)."""

    disturbance: GaussianNoiseConfig = field(default_factory=GaussianNoiseConfig)
    """The true noise law (used by the true environment and the oracle only)."""

    init_box: float = 1.0
    """Initial states are uniform in ``[-init_box, init_box]^n``."""

    action_bound: float = 10.0
    """Bound of the MLP actor's output."""

    def __post_init__(self) -> None:
        if self.name != "linear":
            raise ValueError(f"task.name: expected 'linear' for LinearTaskConfig, got {self.name!r}")
        self.gamma = _gamma(self.gamma)
        dist = self.disturbance
        if not isinstance(dist, (dict, GaussianNoiseConfig)):
            raise ValueError(f"task.disturbance: expected a dict (a JSON object), got {dist!r}")
        mean, cov = (dist.get(k, getattr(GaussianNoiseConfig, k)) if isinstance(dist, dict) else getattr(dist, k)
                     for k in ("mean", "cov"))
        # the problem is validated once, by its one representation (the system's size decides which of
        # the noise's mean / cov is wrong)
        problem = _lq_problem(self, mean, cov)
        self.disturbance = _build(GaussianNoiseConfig, dist, "task.disturbance")
        for name in _problem_fields():  # the validated values, as JSON (tuples)
            value = getattr(problem, name)
            if isinstance(value, np.ndarray):
                value = _rows(value) if value.ndim == 2 else tuple(value.tolist())
            setattr(self, name, value)
        self.init_box = check_number(self.init_box, "task.init_box", positive=True)
        self.action_bound = check_number(self.action_bound, "task.action_bound", positive=True)


    def problem(self) -> LQProblem:
        """The LQ problem this configuration describes, in its one representation (:class:`mixedrl.lq.LQProblem`:
        the true noise ``disturbance.mean`` / ``disturbance.cov``, the prior, the matrices, ``gamma``)."""
        return _lq_problem(self, self.disturbance.mean, self.disturbance.cov)


#: Names of :class:`mixedrl.lq.LQProblem`'s fields that :class:`LinearTaskConfig` calls otherwise.
_PROBLEM_KEYS = {"noise_mean": "disturbance.mean", "noise_cov": "disturbance.cov"}


def _problem_fields() -> tuple[str, ...]:
    """:class:`mixedrl.lq.LQProblem`'s fields that :class:`LinearTaskConfig` holds under the same name (every
    field but the true noise, which is ``task.disturbance``)."""
    return tuple(f.name for f in dataclasses.fields(LQProblem) if f.name not in _PROBLEM_KEYS)


def _lq_problem(cfg: LinearTaskConfig, mean: Any, cov: Any) -> LQProblem:
    """:class:`mixedrl.lq.LQProblem` of ``cfg`` with the true noise ``N(mean, cov)``; its errors name the
    dotted key (``task.A``, ``task.disturbance.mean``, ...)."""
    try:
        return LQProblem(**{name: getattr(cfg, name) for name in _problem_fields()}, noise_mean=mean, noise_cov=cov)
    except ValueError as exc:
        name, _, rest = str(exc).partition(":")
        raise ValueError(f"task.{_PROBLEM_KEYS.get(name, name)}:{rest}") from None


#: The configuration of a run's task: one of the two built-in classes, or a class registered with
#: :func:`register_task`, selected by ``name``.
TaskConfig = Union[DoubleLaneChangeTaskConfig, LinearTaskConfig]
_TASK_CLASSES: dict[str, type] = {"dlc": DoubleLaneChangeTaskConfig, "linear": LinearTaskConfig}


def register_task(config_cls: type) -> type:
    """Register the configuration dataclass of a named task (usable as a decorator).

    The name is the default of the class's ``name`` field; ``TrainConfig(task={"name": ..., ...})``,
    ``--set task.name=...`` and a sweep specification's ``"task.name"`` then build ``config_cls`` from the
    other ``task.<field>`` values. The task object itself is built by
    :func:`mixedrl.tasks.register_task`'s factory (which calls this function).

    Parameters
    ----------
    config_cls : type
        A dataclass with a ``name`` field whose default is the task's name; its ``__post_init__`` checks
        the values (messages starting with the dotted key ``task.<field>``).

    Raises
    ------
    ValueError
        ``config_cls`` is not a dataclass with a string default for ``name``, or the name is a built-in
        task's.
    """
    fields = {f.name: f for f in dataclasses.fields(config_cls)} if dataclasses.is_dataclass(config_cls) else {}
    name = fields["name"].default if "name" in fields else None
    if not isinstance(name, str) or not name:
        raise ValueError(f"config_cls: expected a dataclass with a string default for 'name', got {config_cls!r}")
    if name in TASKS:
        raise ValueError(f"config_cls: the name {name!r} is a built-in task's")
    _TASK_CLASSES[name] = config_cls
    return config_cls


def task_names() -> tuple[str, ...]:
    """Names of the tasks a configuration can name: the built-in :data:`TASKS` and the registered ones."""
    return tuple(_TASK_CLASSES)


def task_config(value: Any = "dlc") -> TaskConfig:
    """Build a task configuration from its name, a JSON-like dict (``name`` selects the class, default
    ``"dlc"``; missing fields take that task's defaults) or a configuration object (returned as is).

    Raises
    ------
    ValueError
        Unknown task name (``task.name``, the message lists :func:`task_names`), unknown key (``config:
        unknown key(s) ['task.<key>']``, e.g. a double-lane-change field given to the linear task) or an
        invalid value (message starts with the dotted field name).
    """
    if isinstance(value, tuple(_TASK_CLASSES.values())):
        return value
    if isinstance(value, str):
        value = {"name": value}
    if not isinstance(value, dict):
        raise ValueError(f"task: expected a task name {task_names()} or a dict, got {value!r}")
    name = value.get("name", "dlc")
    if name not in _TASK_CLASSES:
        raise ValueError(f"task.name: expected one of {task_names()}, got {name!r}")
    if name == "dlc":
        return DoubleLaneChangeTaskConfig.from_dict({**value, "name": name}, where="task")
    return _build(_TASK_CLASSES[name], {**value, "name": name}, "task")


# ----------------------------------------------------------------------------------------------------
# sections of TrainConfig
# ----------------------------------------------------------------------------------------------------
def _choice(value: Any, name: str, options: tuple) -> Any:
    if value not in options:
        raise ValueError(f"{name}: expected one of {options}, got {value!r}")
    return value


@dataclass
class AlgorithmConfig:
    """The training algorithm shared by every method: Algorithm 2 (mixed, model, oracle) and the networks,
    optimiser and budget DDPG uses too. Dotted keys: ``algorithm.<field>``.

    ``batch_weighting``, ``batch_weight_offset`` and ``actor_average`` are tuning add-ons, departures from
    the paper's Algorithm 2 (docs/algorithm2.rst). ``batch_weighting`` defaults to ``"relative"``, measured
    over the pendulum and the linear test bed (``experiments/studies/custom_defaults.toml``, docs/tuning.rst); the paper's
    plain batch mean is ``"uniform"``. ``actor_average`` is off by default.
    """

    iterations: int = 1500
    """Budget: number of outer iterations ``k`` (one PEV + PIM step of Algorithm 2, or one DDPG update)."""

    batch_size: int = 512
    """Number of states of the PEV/PIM batch per iteration (Algorithm 2; made by the sampler), or the
    replay minibatch size (DDPG)."""

    horizon: int = 60
    """Steps after which a training copy (a true-environment copy or a model rollout started from the
    training distribution) is reset to a fresh initial state."""

    hidden_sizes: tuple[int, ...] = (64, 64)
    """Hidden layer widths of the actor and the critic (the same for every method)."""

    activation: str = "elu"
    """Hidden activation of the MLPs: ``"elu"``, ``"tanh"`` or ``"relu"``."""

    value_output: str = "square"
    """Output head of the critic (and of DDPG's Q-critic): ``"softplus"``, ``"square"`` (sum of squares)
    or ``"linear"``; see :class:`mixedrl.networks.Critic`."""

    critic_lr: float = 3e-3
    """Adam learning rate alpha of the critic (eq. 50), also DDPG's Q-critic."""

    actor_lr: float = 3e-4
    """Adam learning rate beta of the actor (eq. 52), also DDPG's actor."""

    lr_decay_to: float = 0.01
    """Learning rates decay linearly from their value to ``lr_decay_to`` times it over the budget
    (1.0 = constant), or over ``lr_decay_iterations`` iterations if that is set."""

    lr_decay_iterations: int = 0
    """Length of the learning-rate decay in iterations; after it the rates stay at ``lr_decay_to`` times
    their start. 0 (the default) = the budget (``iterations``), so the decay is tied to the budget; a
    budget shorter than the length decays over the budget (see :func:`mixedrl.schedule.lr_factor`)."""

    grad_clip: float = 10.0
    """Clip of the global gradient norm of each update (``math.inf`` disables it)."""

    expectation: str = "sigma"
    """How the expectation over ``xi_hat ~ N(mu_hat, K_hat)`` in eqs. (49)-(52) is computed:
    ``"sigma"`` = deterministic spherical-cubature sigma points in the range of ``K_hat`` (2r points,
    exact for polynomials of degree <= 3 in ``xi``), ``"samples"`` = reparameterised Monte-Carlo samples."""

    noise_samples: int = 4
    """Number of reparameterised samples per state when ``expectation == "samples"``."""

    j_max: int = 5
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
    """Departure (tuning add-on): how the states of the batch are weighted in PEV and PIM (eqs. 50 and
    52): ``"uniform"`` = the plain batch mean (the paper's); ``"relative"`` (the default) = each state by its relative
    error: PEV squares the relative TD error ``(V - V_target) / (|V_target| + c)`` and PIM weights state
    ``x`` by ``1 / (V(x) + c)`` (batch mean 1), ``c = batch_weight_offset``
    (:func:`mixedrl.pev.critic_loss`, :func:`mixedrl.pim.actor_objective`)."""

    batch_weight_offset: float = 1.0
    """Departure (tuning add-on): ``c`` of ``batch_weighting = "relative"``, in the units of the value."""

    actor_average: float = 0.0
    """Departure (tuning add-on): decay ``beta`` of an exponential moving average of the actor's weights,
    ``theta_bar <- beta theta_bar + (1 - beta) theta`` after every iteration (Polyak averaging). With
    ``beta > 0`` the *averaged* actor is the run's policy (evaluated, saved, deployed:
    :attr:`mixedrl.algorithms.agpi.AGPI.policy`), while the iterate keeps driving the training rollouts
    and the gradient steps. 0 (the default) = no averaging. The window is about ``1 / (1 - beta)``
    iterations."""

    critic_target: float = 0.0
    """Departure (precision add-on): decay ``beta`` of a target critic for PEV's target. 0 (the default) =
    eq. (50) as written: ``V_target = l(x', u) + gamma V^k(x'; w)`` with the critic being trained. ``beta > 0``:
    ``V_target`` takes ``V(x'; w_bar)`` instead, ``w_bar <- beta w_bar + (1 - beta) w`` after every iteration
    (an exponential moving average of the critic's weights, the target networks of DQN and DDPG;
    :func:`mixedrl.pev.critic_loss`), so the target moves slowly when the batch's distribution changes.
    PIM and the MVC keep the critic ``V^k(x; w)`` itself. The same for every method of Algorithm 2; the
    window is about ``1 / (1 - beta)`` iterations. DDPG has its own (``ddpg.tau``)."""

    bellman_steps: int = 1
    """Departure (precision add-on): model steps ``n`` of the Bellman operator in PEV and PIM. 1 (the
    default) = the one-step ``h`` of eq. (37), the paper's Algorithm 2. ``n > 1``: the critic's target
    and the actor's objective are the ``n``-step ``h_n`` on a rollout of the planning model under the
    actor, the noise at its mean for ``n - 1`` steps and ``V^k`` with the quadrature of ``xi_hat_k``
    after them (:func:`mixedrl.pev.h_steps`; the actor's gradient back-propagated through the rollout).
    The same for every method; the MVC (eq. 38) keeps the one-step ``h``."""

    feedforward: str = "learned"
    """Departure (precision add-on): where the run's policy takes its action at the task's equilibrium.
    ``"learned"`` (the default, the paper's) = the actor's own. ``"lq"`` = the actor shifted by a constant so
    that at the equilibrium it takes the discounted LQ optimum's action for the method's own noise mean,
    ``pi_ff(o) = pi(o) - pi(o(s*)) + u* - l0(E mu)`` (:class:`mixedrl.precision.FeedForwardPolicy`; the
    mean is the IBE posterior for mixed RL, the prior for model-driven RL, the truth for the oracle).
    Training is unchanged (the same bits); the shifted actor is what is evaluated and deployed
    (:attr:`mixedrl.algorithms.agpi.AGPI.policy`). ``"lq_train"`` = the same anchor as the actor's policy
    class *during training*: ``u(o) = u_bar tanh(MLP(o) - MLP(o*) + atanh(clip(u_ff / u_bar, -0.999, 0.999)))``
    (:class:`mixedrl.networks.AnchoredActor`; smooth, bounded, ``u(o*) = u_ff``), ``u_ff`` the LQ optimum's
    action for the run's current own noise moments, refreshed at the start of every iteration (before the
    data collection, PEV, PIM and the MVC use the actor); the trained actor is what is evaluated and
    deployed. A departure from the paper too, off by default, the same for mixed, model and oracle
    (only the noise moments differ); needs ``architecture="mlp"``; runs with ``"lq_train"`` and runs without
    it are trained in separate batches (:func:`mixedrl.algorithms.batched.batch_key`). Algorithm 2 only
    (DDPG has no noise model to take the mean from; it refuses every value but ``"learned"``), and only for
    a task with an equilibrium. ``"lq_affine"`` = ``"lq_train"`` with the LQ optimum's feedback gain too:
    ``u(o) = u_bar tanh(z* + G_z (o - o*) + MLP(o) - MLP(o*) - J_MLP(o*) (o - o*))``
    (:class:`mixedrl.networks.AffineAnchoredActor`), so the policy is the discounted LQ optimum's affine
    policy to first order at the equilibrium (``u(o*) = u_ff``, ``du/dx = -L``,
    :func:`mixedrl.precision.equilibrium_gain`) and training shapes only the terms of second and higher
    order; it needs observations that determine the linearisation's coordinates there. ``"lq_affine_ss"``
    = ``"lq_affine"`` expanded about the LQ optimum's steady state ``x_ss`` for the own noise mean instead
    of the equilibrium: ``o*`` = the observation of ``x_ss`` and ``u(o*)`` = the optimum's action there,
    both refreshed with the noise moments (:func:`mixedrl.precision.steady_anchor`), so the learned
    remainder vanishes, with its slope, where the closed loop comes to rest (with ``"lq_affine"`` it
    vanishes at the equilibrium, and at ``x_ss`` the remainder and the tanh's curvature shift the resting
    point)."""

    def __post_init__(self) -> None:
        w = "algorithm"
        for name in ("iterations", "batch_size", "horizon", "noise_samples", "j_max", "stop_patience",
                     "bellman_steps"):
            setattr(self, name, check_positive_int(getattr(self, name), f"{w}.{name}"))
        self.lr_decay_iterations = check_nonnegative_int(self.lr_decay_iterations, f"{w}.lr_decay_iterations")
        if isinstance(self.hidden_sizes, (str, bytes)) or not isinstance(self.hidden_sizes, (list, tuple)) \
                or not self.hidden_sizes:
            raise ValueError(f"{w}.hidden_sizes: expected positive widths, got {self.hidden_sizes!r}")
        self.hidden_sizes = tuple(check_positive_int(h, f"{w}.hidden_sizes") for h in self.hidden_sizes)
        _choice(self.activation, f"{w}.activation", ("elu", "tanh", "relu"))
        _choice(self.value_output, f"{w}.value_output", ("softplus", "square", "linear"))
        _choice(self.expectation, f"{w}.expectation", ("sigma", "samples"))
        _choice(self.mvc_check, f"{w}.mvc_check", ("mean", "all"))
        _choice(self.ibe_recursion, f"{w}.ibe_recursion", ("exact", "paper"))
        _choice(self.batch_weighting, f"{w}.batch_weighting", BATCH_WEIGHTINGS)
        _choice(self.feedforward, f"{w}.feedforward", FEEDFORWARDS)
        if check_int(self.ibe_case, f"{w}.ibe_case") not in (1, 2, 3):
            raise ValueError(f"{w}.ibe_case: expected 1, 2 or 3 (the IBE's Case), got {self.ibe_case!r}")
        if self.ibe_case != 2 and self.ibe_recursion != "exact":
            raise ValueError(f"{w}.ibe_recursion: 'paper' is eq. (18), a Case 2 recursion; "
                             f"{w}.ibe_case is {self.ibe_case}")
        for name in ("critic_lr", "actor_lr"):
            check_number(getattr(self, name), f"{w}.{name}", positive=True)
        check_number(self.grad_clip, f"{w}.grad_clip", positive=True, allow_inf=True)
        check_fraction(self.lr_decay_to, f"{w}.lr_decay_to", low_open=True)
        check_fraction(self.actor_average, f"{w}.actor_average", high_open=True)
        check_fraction(self.critic_target, f"{w}.critic_target", high_open=True)
        check_number(self.stop_epsilon, f"{w}.stop_epsilon", nonneg=True)
        self.batch_weight_offset = check_number(self.batch_weight_offset, f"{w}.batch_weight_offset", positive=True)


@dataclass
class DDPGConfig:
    """What DDPG has and the model-based methods do not (replay buffer, target networks, exploration
    noise; textbook values, not tuned). Dotted keys: ``ddpg.<field>``."""

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

    def __post_init__(self) -> None:
        self.envs = check_positive_int(self.envs, "ddpg.envs")
        self.buffer_size = check_positive_int(self.buffer_size, "ddpg.buffer_size")
        self.warmup = check_nonnegative_int(self.warmup, "ddpg.warmup")
        check_fraction(self.tau, "ddpg.tau", low_open=True)
        check_number(self.noise_std, "ddpg.noise_std", positive=True)


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


# ----------------------------------------------------------------------------------------------------
# samplers: where Algorithm 2's PEV/PIM states come from
# ----------------------------------------------------------------------------------------------------
#: Sampler name -> its options class (``sampler.name`` selects it); filled by :func:`register_sampler`.
SAMPLERS: dict[str, type] = {}
#: Sampler name -> the task names it works with (``None`` = any task).
_SAMPLER_TASKS: dict[str, tuple[str, ...] | None] = {}


def register_sampler(cls: type, tasks: tuple[str, ...] | None = None) -> type:
    """Register the options class ``cls`` of a sampler under ``cls.NAME`` (usable as a decorator).

    ``tasks`` names the task configurations the sampler needs (``None``: any task); choosing it with
    another task is an error naming ``sampler.name`` and the task. The algorithm that uses the sampler
    looks its implementation up by the same name (:data:`mixedrl.algorithms.model_data.SAMPLER_CLASSES`).
    """
    SAMPLERS[cls.NAME] = cls
    _SAMPLER_TASKS[cls.NAME] = tasks
    return cls


@dataclass
class TrueCopiesSampler:
    """``sampler.name = "true_copies"``: Algorithm 2 as the paper writes it. The batch is the current
    states of ``algorithm.batch_size`` copies of the true environment, each stepped once per iteration
    under the current policy and reset every ``algorithm.horizon`` steps (``batch_size`` true transitions
    per iteration); the IBE consumes their residuals. No options."""

    NAME: ClassVar[str] = "true_copies"

    name: str = "true_copies"
    """Always ``"true_copies"`` for this class."""


@dataclass
class ModelRolloutsSampler:
    """``sampler.name = "model_rollouts"``: the batch is ``algorithm.batch_size`` rollouts of the planning
    model ``f + E xi_hat`` under the method's noise source, restarted from the task's training
    distribution (``sample_initial``) every ``algorithm.horizon`` steps; for mixed RL ``true_envs`` copies
    of the true environment collect the IBE's residuals (model-driven RL and the oracle collect none).
    Dotted keys: ``sampler.<field>``."""

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

#: The configuration of a run's sampler: one of the registered classes (:data:`SAMPLERS`), by ``name``
#: (these two, or a task's own, such as the double lane change's :class:`mixedrl.envs.dlc_task.CourseSampler`).
SamplerConfig = Union[TrueCopiesSampler, ModelRolloutsSampler]


def sampler_config(value: Any, task: str | None = None) -> Any:
    """Build a sampler configuration from its name, a dict (``name`` selects the class, default
    ``"model_rollouts"``) or an options object (returned as is); ``task`` (a task name) is checked
    against what the sampler needs.

    Raises
    ------
    ValueError
        Unknown sampler (``sampler.name``), unknown option (``config: unknown key(s) ['sampler.<key>']``),
        an invalid value, or a sampler the task cannot provide for (naming ``sampler.name`` and the task).
    """
    if isinstance(value, str):
        value = {"name": value}
    if isinstance(value, dict):
        name = value.get("name", ModelRolloutsSampler.NAME)
        if name not in SAMPLERS:
            raise ValueError(f"sampler.name: expected one of {tuple(SAMPLERS)}, got {name!r}")
        value = _build(SAMPLERS[name], {**value, "name": name}, "sampler")
    elif not any(type(value) is cls for cls in SAMPLERS.values()):
        raise ValueError(f"sampler: expected a sampler name {tuple(SAMPLERS)}, a dict or an options object, "
                         f"got {value!r}")
    needs = _SAMPLER_TASKS.get(value.name)
    if task is not None and needs is not None and task not in needs:
        raise ValueError(f"sampler.name: {value.name!r} needs a task with a course ({', '.join(needs)}); "
                         f"task {task!r} has none")
    return value


# ----------------------------------------------------------------------------------------------------
# presets: a task's experiment configuration
# ----------------------------------------------------------------------------------------------------
#: Task name -> its experiment configuration: section -> field values that replace the library defaults
#: (a section not named keeps the library defaults). Filled by :func:`register_preset`.
PRESETS: dict[str, dict[str, dict[str, Any]]] = {}
_SECTIONS = ("algorithm", "sampler", "ddpg", "run")


def register_preset(task: str, sections: dict[str, dict[str, Any]]) -> None:
    """Register the experiment configuration of the task named ``task``: the values ``TrainConfig`` gives
    a section's missing fields when the run's task is ``task`` (``{"algorithm": {...}, "sampler": {...}}``)."""
    unknown = set(sections) - set(_SECTIONS)
    if unknown:
        raise ValueError(f"sections: unknown section(s) {sorted(unknown)}; allowed: {sorted(_SECTIONS)}")
    PRESETS[task] = copy.deepcopy(sections)


def __getattr__(name: str) -> Any:
    """``CourseSampler`` and ``DLC_EXPERIMENT``, which the double lane change registers
    (:mod:`mixedrl.envs.dlc_task`, imported with the package), stay readable here: the options class of its
    sampler (``SAMPLERS["dlc_course"]``) and its preset (``PRESETS["dlc"]``)."""
    if name == "CourseSampler" and "dlc_course" in SAMPLERS:
        return SAMPLERS["dlc_course"]
    if name == "DLC_EXPERIMENT" and "dlc" in PRESETS:
        return PRESETS["dlc"]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


# ----------------------------------------------------------------------------------------------------
# the flat configuration form (45 top-level fields) of the first release
# ----------------------------------------------------------------------------------------------------
#: The release that reads the flat configuration form (``config.json`` with 45 top-level fields, and the
#: flat keys ``iterations``, ``model_course_starts``, ``ddpg_tau`` ...).
FLAT_FORM_RELEASE = "mixedrl 0.1.0 at git commit b510485"


def _refuse_flat_form(keys: Any) -> None:
    """Raise naming :data:`FLAT_FORM_RELEASE` if a top-level key of a configuration is one of the flat
    form's: a field of ``algorithm`` or ``run`` (``iterations``), ``ddpg_<field>``, ``state_source``, a
    sampler option (``model_*``, ``true_*``) or ``train_half_widths``."""
    fields = {f.name for cls in (AlgorithmConfig, RunConfig) for f in dataclasses.fields(cls)}
    fields |= {f"ddpg_{f.name}" for f in dataclasses.fields(DDPGConfig)} | {"state_source", "train_half_widths"}
    flat = sorted(k for k in keys if k in fields or str(k).startswith(("model_", "true_")))
    if flat:
        raise ValueError(f"config: {flat} at the top level is the flat form, read by {FLAT_FORM_RELEASE}; this "
                         f"release reads the sections (algorithm.iterations, sampler.course_starts, ...)")


def flatten_table(table: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Flatten nested TOML tables into dotted keys: ``{"a": {"b": 1}}`` -> ``{"a.b": 1}``.

    TOML turns ``a.b = 1`` into a nested table; a quoted ``"a.b" = 1`` stays one key. Both end up as
    ``"a.b"``. Lists and scalars are leaves.
    """
    out: dict[str, Any] = {}
    for key, value in table.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flatten_table(value, prefix=f"{name}."))
        else:
            out[name] = value
    return out


def apply_overrides(data: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    """Return a copy of the config dict ``data`` with dotted-key ``overrides`` applied.

    ``{"task.prior_force_mean": 300}`` sets ``data["task"]["prior_force_mean"]``; a plain key replaces a
    top-level value. Intermediate levels are created as dicts when missing; a string ``task`` (a name,
    ``"dlc"``) is first expanded to ``{"name": "dlc"}``. Keys are not checked here: building the config
    (:meth:`TrainConfig.from_dict`) reports unknown ones with their dotted name.

    Parameters
    ----------
    data : dict
        A config dict (``TrainConfig.to_dict()``, a parsed ``config.json``, or a partial dict).
    overrides : dict
        Dotted keys to values (JSON-like).

    Returns
    -------
    dict
        A new dict; ``data`` is not modified.

    Raises
    ------
    ValueError
        An empty key segment (``"task..gamma"``) or a dotted key that descends into a value that is not a
        dict (``"seed.x"``), naming the key.

    Examples
    --------
    >>> from mixedrl.config import apply_overrides
    >>> apply_overrides({"seed": 1, "task": "dlc"}, {"task.prior_force_mean": 300, "seed": 2})
    {'seed': 2, 'task': {'name': 'dlc', 'prior_force_mean': 300}}
    >>> apply_overrides({}, {"algorithm.iterations": 300})
    {'algorithm': {'iterations': 300}}
    """
    if not isinstance(data, dict):
        raise ValueError(f"data: expected a dict, got {type(data).__name__}")
    out = copy.deepcopy(data)
    for key, value in overrides.items():
        parts = str(key).split(".")
        if any(not p for p in parts):
            raise ValueError(f"{key}: empty segment in a dotted key")
        node = out
        for i, part in enumerate(parts[:-1]):
            child = node.get(part)
            if child is None:
                child = node[part] = {}
            elif isinstance(child, str) and part in ("task", "sampler") and i == 0:
                child = node[part] = {"name": child}
            elif not isinstance(child, dict):
                raise ValueError(f"{key}: {'.'.join(parts[:i + 1])} is {child!r}, not a nested configuration")
            node = child
        node[parts[-1]] = copy.deepcopy(value)
    return out


_SECTION_CLASSES: dict[str, type] = {"algorithm": AlgorithmConfig, "ddpg": DDPGConfig, "run": RunConfig}


def machine_memory() -> int | None:
    """The machine's physical memory in bytes (``None`` where the system does not report it)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, OSError, ValueError):
        return None


def memory_lower_bounds(config: TrainConfig) -> dict[str, int]:
    """Lower bounds, in bytes, of the memory a run of ``config`` allocates, by the key that sets it.

    Every bound takes the smallest task (one observation, one action: the task's own sizes only add), so
    a configuration above the machine's memory cannot run on it:

    * ``algorithm.hidden_sizes``: the actor and the critic, each at least ``P = sum_i (h_{i-1} + 1) h_i
      + h_last + 1`` parameters (``h_0 = 1``), float32, each with its gradient and the two Adam moments
      (16 bytes a parameter);
    * ``algorithm.batch_size``: the batch's states (float64) and one network's hidden activations on them
      (float32): ``batch_size (8 + 4 sum(hidden_sizes))`` bytes;
    * ``ddpg.buffer_size`` (DDPG only): the replay buffer's observation, next observation, action, cost
      and terminal flag, float32: 20 bytes a transition.
    """
    alg = config.algorithm
    widths = (1, *alg.hidden_sizes, 1)
    params = sum((a + 1) * b for a, b in zip(widths[:-1], widths[1:]))
    out = {"algorithm.hidden_sizes": 2 * 16 * params,
           "algorithm.batch_size": alg.batch_size * (8 + 4 * sum(alg.hidden_sizes))}
    if config.method == "ddpg":
        out["ddpg.buffer_size"] = 20 * config.ddpg.buffer_size
    return out


def _check_memory(config: TrainConfig) -> None:
    """Refuse a configuration whose memory lower bounds (:func:`memory_lower_bounds`) exceed the machine's
    memory, naming the first key whose own bound does, else the key with the largest bound."""
    total = machine_memory()
    if total is None:
        return
    need = memory_lower_bounds(config)
    if sum(need.values()) > total:
        key = next((k for k, v in need.items() if v > total), max(need, key=need.get))
        value = {k: getattr(getattr(config, k.split(".")[0]), k.split(".")[1]) for k in need}[key]
        raise ValueError(f"{key}: {value!r} needs at least {need[key] / 2**30:.3g} GiB (all of the run at least "
                         f"{sum(need.values()) / 2**30:.3g} GiB), more than this machine's {total / 2**30:.3g} GiB "
                         f"of memory")


#: The largest seed: torch and numpy generators take seeds of 64 bits.
MAX_SEED = 2**64 - 1


@dataclass(init=False)
class TrainConfig:
    """Configuration of one training run (Algorithm 2 or DDPG), in sections.

    A section left out (or given as a partial dict) takes the run's task's experiment configuration
    (:data:`PRESETS`, registered by the task; the double lane change's is
    :data:`mixedrl.envs.dlc_task.DLC_EXPERIMENT`) over the library defaults of the section's class.
    ``to_dict`` / ``from_dict`` round-trip exactly through JSON.
    """

    method: str
    """Which algorithm: ``"mixed"`` (Algorithm 2, IBE posterior), ``"model"`` (Algorithm 2 on the prior
    model of eq. 55, IBE off), ``"oracle"`` (Algorithm 2 with the true noise) or ``"ddpg"``."""

    seed: int
    """Seed of every generator of the run (network initialisation, initial states, noise, exploration,
    replay sampling). Same seed, same weights."""

    task: TaskConfig
    """The experiment: :class:`DoubleLaneChangeTaskConfig` (``name = "dlc"``, the default) or
    :class:`LinearTaskConfig` (``name = "linear"``); a task name or a nested dict is accepted
    (:func:`task_config`)."""

    algorithm: AlgorithmConfig
    """Algorithm 2 and the networks, optimiser and budget every method shares (:class:`AlgorithmConfig`)."""

    sampler: SamplerConfig
    """Where Algorithm 2's PEV/PIM states come from, chosen by ``sampler.name`` (:data:`SAMPLERS`):
    :class:`TrueCopiesSampler`, :class:`ModelRolloutsSampler` (the library default) or the double lane
    change's :class:`mixedrl.envs.dlc_task.CourseSampler`."""

    ddpg: DDPGConfig
    """What only DDPG has (:class:`DDPGConfig`)."""

    run: RunConfig
    """Evaluation, checkpoints, threads (:class:`RunConfig`)."""

    def __init__(self, method: str = "mixed", seed: int = 0, task: Any = "dlc", algorithm: Any = None,
                 sampler: Any = None, ddpg: Any = None, run: Any = None, **unknown: Any) -> None:
        _refuse_flat_form(unknown)
        check_unknown_keys(unknown, {f.name for f in dataclasses.fields(TrainConfig)}, "config")
        self.method = _choice(method, "method", METHODS)
        self.seed = check_nonnegative_int(seed, "seed")
        if self.seed > MAX_SEED:
            raise ValueError(f"seed: expected an integer in [0, 2**64 - 1] (torch's generator seed), got {seed!r}")
        self.task = task_config(task)
        preset = PRESETS.get(self.task.name, {})
        for name, value in (("algorithm", algorithm), ("ddpg", ddpg), ("run", run)):
            setattr(self, name, _section(_SECTION_CLASSES[name], value, preset.get(name, {}), name))
        self.sampler = _sampler(sampler, preset.get("sampler", {}), self.task.name)
        if self.method == "ddpg" and self.algorithm.feedforward != "learned":
            raise ValueError(f"algorithm.feedforward: {self.algorithm.feedforward!r} takes the feed-forward from "
                             f"the method's noise model; method 'ddpg' has none (use 'learned')")
        if self.method == "ddpg" and self.algorithm.critic_target != 0.0:
            raise ValueError(f"algorithm.critic_target: {self.algorithm.critic_target!r} is PEV's target critic "
                             f"(Algorithm 2); method 'ddpg' has its own target networks (ddpg.tau; use 0)")
        _check_memory(self)

    @classmethod
    def for_task(cls, task: Any = "dlc", **fields: Any) -> "TrainConfig":
        """The experiment configuration of ``task`` (its registered preset), with ``fields`` on top."""
        return cls(task=task, **fields)

    def validate(self) -> None:
        """Check every field (rebuilding the config from its dict).

        Raises
        ------
        ValueError
            The message starts with the offending field's dotted name.
        """
        TrainConfig.from_dict(self.to_dict())

    # ------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict[str, Any]:
        """Return the fields as a JSON-compatible nested dictionary (tuples become lists; ``inf`` a
        string; the double lane change's ``task.obs_scale`` left out when it is ``None``, its default)."""
        out = _jsonable(self)
        for section, name in (("algorithm", "grad_clip"), ("sampler", "box")):
            if name in out[section] and math.isinf(out[section][name]):
                out[section][name] = "inf"
        if out["task"].get("name") == "dlc" and out["task"].get("obs_scale", 0) is None:
            del out["task"]["obs_scale"]  # the default: config.json and config hashes as before the field
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "TrainConfig":
        """Build a config from a dictionary (the content of ``config.json``), nested sections included.

        ``"task": "dlc"`` (a name) stands for that task's defaults.

        Raises
        ------
        ValueError
            ``data`` has a key that is not a field, at any level (``config: unknown key(s)
            ['task.prior_mena']``), is in the flat form of :data:`FLAT_FORM_RELEASE` (the message names
            that release), or a field is invalid (the message starts with its dotted name).
        """
        if not isinstance(data, dict):
            raise ValueError(f"config: expected a dict, got {type(data).__name__}")
        data = copy.deepcopy(data)
        _refuse_flat_form(data)
        check_unknown_keys(data, {f.name for f in dataclasses.fields(cls)}, "config")
        for section, name in (("algorithm", "grad_clip"), ("sampler", "box")):
            if isinstance(data.get(section), dict) and data[section].get(name) == "inf":
                data[section] = {**data[section], name: math.inf}
        return cls(**data)

    def replace(self, **changes: Any) -> "TrainConfig":
        """Return a copy with ``changes`` applied; keys may be dotted (``**{"algorithm.iterations": 30}``,
        see :func:`apply_overrides`); unknown keys are an error."""
        changes = {k: _jsonable(v) for k, v in changes.items()}
        data = self.to_dict()
        if any(k in ("task", "task.name") for k in changes):  # a new task: its own presets for what is not given
            data = {"method": data["method"], "seed": data["seed"], "task": data["task"]}
        return TrainConfig.from_dict(apply_overrides(data, changes))

    def save(self, path: str | Path) -> None:
        """Write the config as JSON to ``path``."""
        Path(path).write_text(json.dumps(self.to_dict(), indent=2, sort_keys=True) + "\n")

    @classmethod
    def preset(cls, name: str, **fields: Any) -> "TrainConfig":
        """The config of the named preset of :data:`CONFIG_PRESETS` (``"paper"``: the paper's literal
        Algorithm 2; ``"library"``: ``TrainConfig(**fields)``, the library defaults), with ``fields``
        (``method``, ``seed``, ``task``, sections) given as to the constructor; the preset's settings win.

        Raises
        ------
        ValueError
            An unknown preset name (naming ``preset``), or as the constructor.
        """
        return cls(**{"method": "mixed", "seed": 0, **fields}).with_preset(name)

    def with_preset(self, name: str) -> "TrainConfig":
        """A copy with the settings of the preset ``name`` (:data:`CONFIG_PRESETS`) applied (its sampler
        section replaces the config's)."""
        if name not in CONFIG_PRESETS:
            raise ValueError(f"preset: expected one of {tuple(CONFIG_PRESETS)}, got {name!r}")
        data = self.to_dict()
        for section, values in CONFIG_PRESETS[name].items():
            data[section] = dict(values) if section == "sampler" else {**data[section], **values}
        return TrainConfig.from_dict(data)

    @classmethod
    def load(cls, path: str | Path) -> "TrainConfig":
        """Read a config written by :meth:`save`.

        Raises
        ------
        ValueError
            The file is not valid JSON, holds an unknown key or is in the flat form of
            :data:`FLAT_FORM_RELEASE`.
        """
        try:
            data = json.loads(Path(path).read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"path: {path} is not valid JSON ({exc})") from None
        return cls.from_dict(data)


def _section(cls: type, value: Any, preset: dict[str, Any], where: str) -> Any:
    """A section from an instance (as is), ``None`` (the preset) or a partial dict (over the preset)."""
    if isinstance(value, cls):
        return value
    if value is None:
        value = {}
    if not isinstance(value, dict):
        raise ValueError(f"{where}: expected a dict (a JSON object) or a {cls.__name__}, got {value!r}")
    return _build(cls, {**preset, **value}, where)


def _sampler(value: Any, preset: dict[str, Any], task: str) -> Any:
    if isinstance(value, str):
        value = {"name": value}
    if value is None:
        value = {}
    if isinstance(value, dict):
        if value.get("name", preset.get("name")) == preset.get("name"):
            value = {**preset, **value}
        if isinstance(value.get("box"), str) and value["box"] == "inf":
            value = {**value, "box": math.inf}
    return sampler_config(value, task)


# ----------------------------------------------------------------------------------------------------
# presets of Algorithm 2 (issue 40): the paper's literal form and the library defaults, one argument apart
# ----------------------------------------------------------------------------------------------------
#: The paper's value of every setting where the library departs from it (one module each in
#: :mod:`mixedrl.departures`, which reads its paper value from here): ``TrainConfig.preset("paper")``
#: (``mixedrl train --preset paper``) is the paper's Algorithm 2 -- the true copies as the batch, the plain
#: batch mean in PEV and PIM, fixed step sizes, the critic itself in PEV's target, one-step ``h``, the
#: MLP actor, the last actor deployed. The table of docs/algorithm2.rst gives each with the library's
#: default and why.
PAPER_SETTINGS: dict[str, dict[str, Any]] = {
    "sampler": {"name": "true_copies"},
    "algorithm": {"batch_weighting": "uniform", "lr_decay_to": 1.0, "critic_target": 0.0, "bellman_steps": 1,
                  "feedforward": "learned", "actor_average": 0.0},
}
#: Preset name -> section -> settings applied over ``TrainConfig(**fields)`` (:meth:`TrainConfig.preset`).
CONFIG_PRESETS: dict[str, dict[str, dict[str, Any]]] = {"library": {}, "paper": PAPER_SETTINGS}
