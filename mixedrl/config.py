"""One typed, documented configuration object per training run, the experiment included.

:class:`TrainConfig` holds every knob of a run of Algorithm 2 (``method`` = ``mixed``, ``model``,
``oracle``) or of the DDPG baseline (``method = "ddpg"``); its field ``task`` holds the *experiment*:
which system, the designer's prior of the disturbance (eq. 8 / eq. 55), the true disturbance law, the
discount factor and the cost weights (eq. 54), the observation's preview. It is saved as
``config.json`` beside the run's results; loading a dictionary with a key that is not a field, at any
level, is an error naming the dotted key (a misspelt option must never be silently ignored).

The task configuration is one of two nested dataclasses, chosen by its ``name``:

* :class:`DoubleLaneChangeTaskConfig` (``name = "dlc"``, the paper's Section VI), with the nested
  :class:`ForceDisturbanceConfig` (``task.disturbance``) and :class:`CostWeights` (``task.cost``);
* :class:`LinearTaskConfig` (``name = "linear"``, a small LQ system with a known optimum), with the
  nested :class:`GaussianNoiseConfig` (``task.disturbance``).

Dotted keys address nested fields, the same way on the command line, in :func:`apply_overrides` and in
sweep specifications::

    mixedrl train --method mixed --out runs/p300 --set task.prior_force_mean=300 task.disturbance.variance=64
    mixedrl train --method model --out runs/lin --set task.name=\\"linear\\" task.prior_mean=[0,2]
    mixedrl train --method mixed --out runs/mine --config experiment.json   # nested JSON, like config.json

Old ``config.json`` files (``"task": "dlc"`` or ``"linear"`` as a string, ``train_half_widths`` at the
top level) still load: the string selects that task's defaults and the top-level ``train_half_widths``
moves to ``task.train_half_widths`` (it never had an effect on the linear task and is dropped there).

The defaults are the settings used for the reproduction of Table I (``mixedrl reproduce``). Every method
gets the *same* networks, optimiser, learning rates, batch of states and iteration budget; the
``ddpg_*`` fields only configure what DDPG has and the model-based methods do not (replay buffer,
target networks, exploration noise; textbook values, not tuned). The shared settings (learning rates,
their decay, ``horizon``, ``value_output``, ``batch_size``, the budget) were chosen by a small search
on mixed-RL runs of the double lane change (seeds 0-2) and then applied unchanged to every method.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Union

import numpy as np

from mixedrl.checks import as_matrix, as_vector, check_covariance, check_number, check_unknown_keys

__all__ = [
    "TrainConfig",
    "TaskConfig",
    "DoubleLaneChangeTaskConfig",
    "LinearTaskConfig",
    "ForceDisturbanceConfig",
    "GaussianNoiseConfig",
    "CostWeights",
    "task_config",
    "apply_overrides",
    "METHODS",
    "TASKS",
    "DISTURBANCE_LAWS",
    "BATCH_WEIGHTINGS",
    "MODEL_COURSE_STARTS",
]

#: The four methods of the reproduction (mixed RL, model-driven RL, oracle, DDPG).
METHODS = ("mixed", "model", "oracle", "ddpg")
#: Tasks a run can be trained on: the double lane change (paper) and a small linear system.
TASKS = ("dlc", "linear")
#: Laws of the true disturbance a task configuration may name (the IBE itself assumes a Gaussian):
#: ``"gaussian"`` (the paper's), ``"student_t"`` (heavy tails, ``dof`` degrees of freedom) and ``"bumps"`` (a
#: symmetric two-point law), all with the configured mean and variance (:class:`ForceDisturbanceConfig`).
#: The double lane change simulates all three; the linear task only ``"gaussian"``.
DISTURBANCE_LAWS = ("gaussian", "student_t", "bumps")
#: Where Algorithm 2's course rollouts on the model (re)start (``TrainConfig.model_course_starts``).
MODEL_COURSE_STARTS = ("start", "along", "loop")
#: How Algorithm 2 weights the states of its batch (``TrainConfig.batch_weighting``).
BATCH_WEIGHTINGS = ("uniform", "relative")


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
# the double lane change (Section VI of the paper)
# ----------------------------------------------------------------------------------------------------
@dataclass
class ForceDisturbanceConfig:
    """The true longitudinal disturbance force ``F_dis`` of the double lane change (eq. 53), in newtons.

    Its noise on ``v_x`` is ``xi = F_dis T / m`` (eq. 54). Dotted keys: ``task.disturbance.<field>``.
    ``grade_amplitude`` [rad], ``grade_wavelength`` [m] and ``grade_phase`` [rad] describe an optional road
    grade (:class:`mixedrl.envs.Disturbance`; amplitude 0, the default, is the paper's level road).

    Every law has mean ``mean`` (minus the grade's ``m g sin(theta(X))``) and variance ``variance``:
    ``F_dis = mean + sqrt(variance) z`` with the law's standardised draw ``z``:

    * ``law = "gaussian"`` (default, the paper's ``N(261, 32)``): ``z ~ N(0, 1)``;
    * ``law = "student_t"``: ``F_dis`` is Student-t with ``dof`` degrees of freedom, rescaled to the
      variance: scale ``sqrt(variance (dof - 2) / dof)`` (``dof > 2``; heavy tails);
    * ``law = "bumps"``: ``F_dis = mean - sqrt(variance)`` or ``mean + sqrt(variance)`` with probability 1/2
      each (a symmetric two-point law).

    Ten times the paper's variance is just ``variance = 320``. The planners model the noise as a
    Gaussian whatever the law (the oracle plans with ``N(mean, variance)``); see
    :class:`mixedrl.envs.Disturbance` for how each law is drawn.
    """

    WHERE: ClassVar[str] = "task.disturbance"

    law: str = "gaussian"
    """Distribution of ``F_dis``; one of :data:`DISTURBANCE_LAWS`: ``"gaussian"``, ``"student_t"``,
    ``"bumps"`` (same mean and variance for all three)."""

    mean: float = 261.0
    """Mean force on a level road [N] (paper: 261)."""

    variance: float = 32.0
    """Variance of ``F_dis`` [N^2] (paper: 32, ``N(261, 32)``; EQUATIONS.md, point 7)."""

    dof: float = 3.0
    """Degrees of freedom of the ``"student_t"`` law (> 2: a finite variance); ignored by the others."""

    # an optional road grade, a state-dependent mean (Case 3); amplitude 0 is the paper's level road. The
    # three fields are passed on to mixedrl.envs.Disturbance, which documents the grade's formula.
    grade_amplitude: float = 0.0
    grade_wavelength: float = 40.0
    grade_phase: float = 0.0

    def __post_init__(self) -> None:
        self.law = _law(self.law, f"{self.WHERE}.law")
        for f in dataclasses.fields(self):
            if f.name != "law":
                setattr(self, f.name, check_number(getattr(self, f.name), f"{self.WHERE}.{f.name}",
                                              nonneg=f.name == "variance", positive=f.name == "grade_wavelength"))
        if not self.dof > 2.0:
            raise ValueError(f"{self.WHERE}.dof: expected a number > 2 (the Student-t variance is finite only "
                             f"then), got {self.dof!r}")


@dataclass
class CostWeights:
    """Weights of the utility of eq. (54), ``T (q_speed (v_x - 12)^2 + q_lateral y^2 + u^T diag(r_steer,
    r_accel) u)``, charged on the next state. Dotted keys: ``task.cost.<field>``."""

    WHERE: ClassVar[str] = "task.cost"

    q_speed: float = 45.0
    """Weight of the squared speed error ``(v_x - 12)^2``. Paper: 45."""

    q_lateral: float = 60.0
    """Weight of the squared lateral error ``y^2``. Paper: 60."""

    r_steer: float = 800.0
    """Weight of the squared steering angle ``delta^2``. Paper: 800."""

    r_accel: float = 1.0
    """Weight of the squared acceleration ``a_x^2``. Paper: 1."""

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            setattr(self, f.name, check_number(getattr(self, f.name), f"{self.WHERE}.{f.name}", nonneg=True))


@dataclass
class DoubleLaneChangeTaskConfig:
    """The experiment of Section VI: the double lane change with a random longitudinal force.

    Dotted keys: ``task.<field>``; the prior of eq. (55) is given in force units and acts on ``v_x``
    (EQUATIONS.md, point 6): ``mu_M = prior_force_mean T / m``, ``K_M = (prior_force_std T / m)^2`` on
    ``v_x``, ``1e-20`` on the other four components of ``xi``.
    """

    WHERE: ClassVar[str] = "task"

    name: str = "dlc"
    """Always ``"dlc"`` for this class (selects it when loading)."""

    gamma: float = 0.99
    """Discount factor of eq. (2), in (0, 1)."""

    prior_force_mean: float = 150.0
    """The designer's prior mean of ``F_dis`` [N] (eq. 55; paper: 150)."""

    prior_force_std: float = 4.0
    """The designer's prior standard deviation ``sqrt(K_M)`` in force units [N] (paper: 4)."""

    disturbance: ForceDisturbanceConfig = field(default_factory=ForceDisturbanceConfig)
    """The true disturbance law (used by the true environment and the oracle only)."""

    cost: CostWeights = field(default_factory=CostWeights)
    """Weights of the utility, eq. (54)."""

    preview_distances: tuple[float, ...] = ()
    """Look-ahead distances [m] of the reference preview appended to the observation (default none: the
    paper's relative state ``[v_y, r, v_x - 12, e_phi, e_y]``); see
    :class:`mixedrl.envs.DoubleLaneChangeConfig`."""

    train_half_widths: tuple[float, ...] = (0.3, 0.2, 1.0, 0.1, 1.0)
    """Half-widths of the uniform perturbation of ``[v_y, r, v_x - 12, e_phi, e_y]`` of the training start
    states (anywhere on the course), see :meth:`mixedrl.envs.DoubleLaneChangeModel.reset_states`."""

    def __post_init__(self) -> None:
        if self.name != "dlc":
            raise ValueError(f"task.name: expected 'dlc' for DoubleLaneChangeTaskConfig, got {self.name!r}")
        self.gamma = _gamma(self.gamma)
        self.prior_force_mean = check_number(self.prior_force_mean, "task.prior_force_mean")
        self.prior_force_std = check_number(self.prior_force_std, "task.prior_force_std", positive=True)
        self.disturbance = _build(ForceDisturbanceConfig, self.disturbance, "task.disturbance")
        self.cost = _build(CostWeights, self.cost, "task.cost")
        if isinstance(self.preview_distances, (str, bytes)) or not isinstance(self.preview_distances, (list, tuple)):
            raise ValueError(f"task.preview_distances: expected a list of numbers, got {self.preview_distances!r}")
        self.preview_distances = tuple(check_number(d, "task.preview_distances", positive=True)
                                       for d in self.preview_distances)
        widths = self.train_half_widths
        if isinstance(widths, (str, bytes)) or not isinstance(widths, (list, tuple)) or len(widths) != 5:
            raise ValueError(f"task.train_half_widths: expected 5 finite numbers >= 0, got {widths!r}")
        self.train_half_widths = tuple(check_number(w, "task.train_half_widths", nonneg=True) for w in widths)


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
    """The linear test bed :class:`mixedrl.tasks.LinearTask`: ``s' = A s + B u + xi``, utility
    ``s'^T Q s' + u^T R u`` (a sampled double integrator, ``dt = 0.1``, the noise on the velocity, by
    default). Dotted keys: ``task.<field>``; ``n`` = ``A``'s size, ``m`` = ``B``'s columns.
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
        A = as_matrix(self.A, "task.A")
        n = A.shape[0]
        if A.shape != (n, n):
            raise ValueError(f"task.A: expected a square matrix, got shape {A.shape}")
        B = as_matrix(self.B, "task.B", (n, None))
        m = B.shape[1]
        self.A, self.B = _rows(A), _rows(B)
        self.Q = _rows(check_covariance(as_matrix(self.Q, "task.Q", (n, n)), "task.Q", n))
        self.R = _rows(check_covariance(as_matrix(self.R, "task.R", (m, m)), "task.R", m))
        self.prior_mean = tuple(as_vector(self.prior_mean, "task.prior_mean", n).tolist())
        self.prior_cov = _rows(check_covariance(as_matrix(self.prior_cov, "task.prior_cov", (n, n)),
                                                "task.prior_cov", n))
        dist = self.disturbance
        mean = dist.get("mean", GaussianNoiseConfig.mean) if isinstance(dist, dict) else getattr(dist, "mean", None)
        as_vector(mean, "task.disturbance.mean", n)  # the system's size decides which of mean / cov is wrong
        self.disturbance = _build(GaussianNoiseConfig, dist, "task.disturbance")
        self.init_box = check_number(self.init_box, "task.init_box", positive=True)
        self.action_bound = check_number(self.action_bound, "task.action_bound", positive=True)


#: The configuration of a run's task: one of the two classes, selected by ``name``.
TaskConfig = Union[DoubleLaneChangeTaskConfig, LinearTaskConfig]
_TASK_CLASSES: dict[str, type] = {"dlc": DoubleLaneChangeTaskConfig, "linear": LinearTaskConfig}


def task_config(value: Any = "dlc") -> TaskConfig:
    """Build a task configuration from its name, a JSON-like dict (``name`` selects the class, default
    ``"dlc"``; missing fields take that task's defaults) or a configuration object (returned as is).

    Raises
    ------
    ValueError
        Unknown task name (``task.name``), unknown key (``config: unknown key(s) ['task.<key>']``, e.g. a
        double-lane-change field given to the linear task) or an invalid value (message starts with the
        dotted field name).
    """
    if isinstance(value, (DoubleLaneChangeTaskConfig, LinearTaskConfig)):
        return value
    if isinstance(value, str):
        value = {"name": value}
    if not isinstance(value, dict):
        raise ValueError(f"task: expected a task name {TASKS} or a dict, got {value!r}")
    name = value.get("name", "dlc")
    if name not in _TASK_CLASSES:
        raise ValueError(f"task.name: expected one of {TASKS}, got {name!r}")
    return _build(_TASK_CLASSES[name], {**value, "name": name}, "task")


def apply_overrides(data: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    """Return a copy of the config dict ``data`` with dotted-key ``overrides`` applied.

    ``{"task.prior_force_mean": 300}`` sets ``data["task"]["prior_force_mean"]``; a plain key replaces a
    top-level value. Intermediate levels are created as dicts when missing; a string ``task`` (the old
    form, ``"dlc"``) is first expanded to ``{"name": "dlc"}``. Keys are not checked here: building the
    config (:meth:`TrainConfig.from_dict`) reports unknown ones with their dotted name.

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
            elif isinstance(child, str) and part == "task" and i == 0:
                child = node[part] = {"name": child}
            elif not isinstance(child, dict):
                raise ValueError(f"{key}: {'.'.join(parts[:i + 1])} is {child!r}, not a nested configuration")
            node = child
        node[parts[-1]] = copy.deepcopy(value)
    return out


@dataclass
class TrainConfig:
    """Configuration of one training run (Algorithm 2 or DDPG).

    Every field is documented below; ``to_dict`` / ``from_dict`` round-trip exactly through JSON.
    """

    method: str = "mixed"
    """Which algorithm: ``"mixed"`` (Algorithm 2, IBE posterior), ``"model"`` (Algorithm 2 on the prior
    model of eq. 55, IBE off), ``"oracle"`` (Algorithm 2 with the true noise) or ``"ddpg"``."""

    task: TaskConfig = field(default_factory=DoubleLaneChangeTaskConfig)
    """The experiment: :class:`DoubleLaneChangeTaskConfig` (``name = "dlc"``, the double lane change of
    Section VI) or :class:`LinearTaskConfig` (``name = "linear"``, a 2-state linear system with a
    quadratic cost and a known LQ optimum, used by the tests and the tutorial). The constructor also
    accepts a task name or a nested dict (see :func:`task_config`)."""

    seed: int = 0
    """Seed of every generator of the run (network initialisation, initial states, noise, exploration,
    replay sampling). Same seed, same weights."""

    iterations: int = 1500
    """Budget: number of outer iterations ``k`` (one PEV + PIM step of Algorithm 2, or one DDPG update)."""

    batch_size: int = 512
    """Number of states per iteration: the rollouts of the planning model (``state_source="model"``) or
    the parallel copies of the true environment (``"true"``) whose current states form the PEV/PIM batch
    (Algorithm 2), or the replay minibatch size (DDPG)."""

    horizon: int = 60
    """Steps after which a training copy of the environment is reset to a fresh initial state."""

    state_source: str = "model"
    """Where Algorithm 2's PEV/PIM states come from: ``"model"`` (the default and the reproduction's
    setting) = rollouts of the planning model ``f + xi_hat`` under the method's noise source
    (:class:`mixedrl.algorithms.model_data.ModelStateSampler`), the true environment only feeding the IBE
    (``true_envs``, ``true_steps``, ``true_every``); ``"true"`` = the ``batch_size`` copies of the true
    environment, one true step per copy per iteration (the setting of the earlier reproduction: 512
    true transitions per iteration)."""

    model_course_fraction: float = 0.75
    """``state_source="model"``: fraction of the batch's rollouts that drive the course from its start
    (the rest restart from the wide training distribution every ``horizon`` steps)."""

    model_course_start: int = 500
    """``state_source="model"``: iteration from which the course rollouts start from the course start;
    before it they restart from the wide distribution like the others (a schedule: the course is driven
    only by a policy that has first learnt to stay near the reference)."""

    model_course_starts: str = "along"
    """``state_source="model"``: where a course rollout restarts once ``model_course_start`` has passed
    (the copies keep driving from wherever they are at that iteration -- anywhere on the course, from the
    wide distribution -- with the longer horizon ``model_course_horizon``):

    * ``"start"`` (design M, the default before design S): at the course start (``X = 0``) when it leaves the box,
      ends or reaches its horizon; it is *not* restarted at the course's end, so a copy that started far
      along the course drives on past it, on the straight road beyond, until its horizon (by iteration
      1500 about 43% of the course copies are beyond the course's end, docs/model_based.rst);
    * ``"along"`` (the default, design S): on the reference at a point drawn
      uniformly along the course (``X ~ U(0, course_length)``, the start's small perturbation), also when
      it passes the course's end (the course copies then crowd towards the end: their density grows
      like ``X``);
    * ``"loop"``: at the course start, also when it passes the course's end, so that the copies loop
      over the course: uniformly spread over it at iteration ``model_course_start``, they stay so.

    The true-data copies of mixed RL always start at the course start."""

    model_course_horizon: int = 2000
    """``state_source="model"``: steps after which a course rollout (and a true-data copy) restarts at the
    course start (2000 = the whole double lane change)."""

    model_kick_prob: float = 0.01
    """``state_source="model"``: probability per step that a course rollout is kicked: a uniform random
    offset of ``model_kick_scale * obs_scale_i`` on each noise component is added to its state, and the
    policy has to recover (exploration in state space around the course)."""

    model_kick_scale: float = 1.0
    """``state_source="model"``: size of a kick, in units of the task's ``obs_scale``."""

    model_box: float = 3.0
    """``state_source="model"``: a rollout restarts when a component of its observation exceeds
    ``model_box`` times the task's ``obs_scale`` (``math.inf`` disables it)."""

    true_envs: int = 1
    """``state_source="model"``, mixed RL: true-environment copies driven at each collection."""

    true_steps: int = 20
    """``state_source="model"``, mixed RL: consecutive steps each true copy drives per collection."""

    true_every: int = 10
    """``state_source="model"``, mixed RL: iterations between collections (true transitions per iteration:
    ``true_envs * true_steps / true_every``; model-driven RL and the oracle collect none)."""

    batch_weighting: str = "relative"
    """How the states of Algorithm 2's batch are weighted in PEV and PIM (eqs. 50 and 52): ``"uniform"``
    = the plain batch mean (the paper's text); ``"relative"`` = each state by its relative error: PEV
    squares the relative TD error ``(V - V_target) / (|V_target| + c)`` and PIM weights state ``x`` by
    ``1 / (V(x) + c)`` (batch mean 1), ``c = batch_weight_offset``, so that states near the reference,
    of small value, are not outweighed by the far ones (:func:`mixedrl.pev.critic_loss`,
    :func:`mixedrl.pim.actor_objective`; docs/model_based.rst)."""

    batch_weight_offset: float = 1.0
    """``c`` of ``batch_weighting = "relative"``, in the units of the value (the cost)."""

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

    lr_decay_iterations: int = 1500
    """Length of the learning-rate decay in iterations; after it the rates stay at ``lr_decay_to`` times
    their start. 0 = the budget (``iterations``); a budget shorter than the length decays over the budget.
    A fixed length makes a longer budget the same run followed by iterations at the final rates, instead
    of a slower decay (see :func:`mixedrl.schedule.lr_factor`)."""

    actor_average: float = 0.0
    """Algorithm 2: decay ``beta`` of an exponential moving average of the actor's weights,
    ``theta_bar <- beta theta_bar + (1 - beta) theta`` after every iteration (Polyak averaging; a
    departure from the paper, applied identically to mixed, model-driven RL and the oracle). With
    ``beta > 0`` the *averaged* actor is the run's policy: it is evaluated, saved and deployed
    (:attr:`mixedrl.algorithms.agpi.AGPI.policy`), while the iterate ``theta`` keeps driving the training
    rollouts and the gradient steps. 0 (the default) = no averaging: the policy is the iterate. The
    window is about ``1 / (1 - beta)`` iterations (0.995: 200), the same whatever the budget."""

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
    batch both stay below ``stop_epsilon`` for ``stop_patience`` iterations; 0 disables it (the run
    uses its whole budget)."""

    stop_patience: int = 100
    """Consecutive iterations the stopping test must hold."""

    ibe_recursion: str = "exact"
    """Recursion of the Case-2 IBE (``"exact"`` = eq. 17 recursively, ``"paper"`` = eq. 18)."""

    ibe_case: int = 2
    """Which IBE mixed RL plans with (:func:`mixedrl.noise.make_noise_source`): ``2`` = Case 2, mean and
    covariance unknown (eqs. 17-18, the reproduction's); ``1`` = Case 1, covariance known (the true
    ``K``, eq. 16); ``3`` = Case 3, a state-dependent mean ``phi(x, u) = W^T g(x, u)`` on the task's
    features (for the vehicle a Fourier series along the course, for a road grade), covariance known
    (eq. 19, :class:`mixedrl.ibe.LinearFeatureIBE`). Only ``method = "mixed"`` reads it; ``ibe_recursion``
    must be ``"exact"`` unless it is 2."""

    eval_every: int = 100
    """Evaluate the policy on the full double lane change every ``eval_every`` iterations."""

    eval_seeds: int = 2
    """Number of noise realisations averaged by each evaluation."""

    checkpoint_every: int = 500
    """Write an atomic checkpoint every ``checkpoint_every`` iterations (and at the end)."""

    num_threads: int = 1
    """``torch.set_num_threads`` for the run (fixed, so results do not depend on the machine)."""

    ddpg_envs: int = 16
    """DDPG: parallel true-environment copies stepped once per iteration (transitions per iteration)."""

    ddpg_buffer_size: int = 200_000
    """DDPG: replay buffer capacity (transitions)."""

    ddpg_warmup: int = 2000
    """DDPG: transitions collected with exploration before the first update."""

    ddpg_tau: float = 0.005
    """DDPG: Polyak factor of the target networks."""

    ddpg_noise_std: float = 0.2
    """DDPG: standard deviation of the Gaussian exploration noise, as a fraction of each action bound."""

    def __post_init__(self) -> None:
        self.hidden_sizes = tuple(int(h) for h in self.hidden_sizes)
        self.task = task_config(self.task)
        self.validate()

    def validate(self) -> None:
        """Check every field.

        Raises
        ------
        ValueError
            The message starts with the offending field's name.
        """
        if self.method not in METHODS:
            raise ValueError(f"method: expected one of {METHODS}, got {self.method!r}")
        if not isinstance(self.task, (DoubleLaneChangeTaskConfig, LinearTaskConfig)):
            raise ValueError(f"task: expected a task configuration, got {self.task!r}")
        if self.expectation not in ("sigma", "samples"):
            raise ValueError(f"expectation: expected 'sigma' or 'samples', got {self.expectation!r}")
        if self.mvc_check not in ("mean", "all"):
            raise ValueError(f"mvc_check: expected 'mean' or 'all', got {self.mvc_check!r}")
        if self.activation not in ("elu", "tanh", "relu"):
            raise ValueError(f"activation: expected 'elu', 'tanh' or 'relu', got {self.activation!r}")
        if self.value_output not in ("softplus", "square", "linear"):
            raise ValueError(f"value_output: expected 'softplus', 'square' or 'linear', got {self.value_output!r}")
        if self.state_source not in ("true", "model"):
            raise ValueError(f"state_source: expected 'true' or 'model', got {self.state_source!r}")
        if not 0.0 <= float(self.model_course_fraction) <= 1.0:
            raise ValueError(f"model_course_fraction: expected a number in [0, 1], got {self.model_course_fraction!r}")
        if isinstance(self.model_course_start, bool) or not isinstance(self.model_course_start, int) \
                or self.model_course_start < 0:
            raise ValueError(f"model_course_start: expected a non-negative integer, got {self.model_course_start!r}")
        if self.model_course_starts not in MODEL_COURSE_STARTS:
            raise ValueError(f"model_course_starts: expected one of {MODEL_COURSE_STARTS}, got "
                             f"{self.model_course_starts!r}")
        if not 0.0 <= float(self.model_kick_prob) <= 1.0:
            raise ValueError(f"model_kick_prob: expected a number in [0, 1], got {self.model_kick_prob!r}")
        if not (float(self.model_kick_scale) >= 0 and math.isfinite(self.model_kick_scale)):
            raise ValueError(f"model_kick_scale: expected a finite number >= 0, got {self.model_kick_scale!r}")
        if not float(self.model_box) > 0:
            raise ValueError(f"model_box: expected a positive number, got {self.model_box!r}")
        if self.batch_weighting not in BATCH_WEIGHTINGS:
            raise ValueError(f"batch_weighting: expected one of {BATCH_WEIGHTINGS}, got {self.batch_weighting!r}")
        self.batch_weight_offset = check_number(self.batch_weight_offset, "batch_weight_offset", positive=True)
        if self.ibe_recursion not in ("exact", "paper"):
            raise ValueError(f"ibe_recursion: expected 'exact' or 'paper', got {self.ibe_recursion!r}")
        if isinstance(self.ibe_case, bool) or not isinstance(self.ibe_case, int) or self.ibe_case not in (1, 2, 3):
            raise ValueError(f"ibe_case: expected 1, 2 or 3 (the IBE's Case), got {self.ibe_case!r}")
        if self.ibe_case != 2 and self.ibe_recursion != "exact":
            raise ValueError(f"ibe_recursion: 'paper' is eq. (18), a Case 2 recursion; ibe_case is {self.ibe_case}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed: expected a non-negative integer, got {self.seed!r}")
        for name in ("iterations", "batch_size", "horizon", "noise_samples", "j_max", "stop_patience",
                     "eval_every", "eval_seeds", "checkpoint_every", "num_threads", "ddpg_envs",
                     "ddpg_buffer_size", "model_course_horizon", "true_envs", "true_steps", "true_every"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name}: expected a positive integer, got {value!r}")
        for name in ("ddpg_warmup", "lr_decay_iterations"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"{name}: expected a non-negative integer, got {value!r}")
        if not self.hidden_sizes or any(h < 1 for h in self.hidden_sizes):
            raise ValueError(f"hidden_sizes: expected positive widths, got {self.hidden_sizes!r}")
        for name in ("critic_lr", "actor_lr", "grad_clip", "ddpg_noise_std"):
            value = float(getattr(self, name))
            if not value > 0 or math.isnan(value):
                raise ValueError(f"{name}: expected a positive number, got {value!r}")
        if not (0.0 <= float(self.actor_average) < 1.0):
            raise ValueError(f"actor_average: expected a number in [0, 1) (the EMA decay; 0 = off), "
                             f"got {self.actor_average!r}")
        for name in ("lr_decay_to", "ddpg_tau"):
            value = float(getattr(self, name))
            if not 0 < value <= 1:
                raise ValueError(f"{name}: expected a number in (0, 1], got {value!r}")
        if not (self.stop_epsilon >= 0 and math.isfinite(self.stop_epsilon)):
            raise ValueError(f"stop_epsilon: expected a finite number >= 0, got {self.stop_epsilon!r}")

    # ------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict[str, Any]:
        """Return the fields as a JSON-compatible dictionary, the task configuration as a nested dict
        (tuples become lists; ``inf`` a string)."""
        out = _jsonable(self)
        for name in ("grad_clip", "model_box"):
            if math.isinf(out[name]):
                out[name] = "inf"
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "TrainConfig":
        """Build a config from a dictionary (the content of ``config.json``), nested ``task`` included.

        The old form is accepted: ``"task": "dlc"`` (a name: that task's defaults) and a top-level
        ``train_half_widths`` (moved to ``task.train_half_widths``; dropped for the linear task, on
        which it never had an effect).

        Raises
        ------
        ValueError
            ``data`` has a key that is not a field, at any level (``config: unknown key(s)
            ['task.prior_mena']``), or a field is invalid (the message starts with its dotted name).
        """
        if not isinstance(data, dict):
            raise ValueError(f"config: expected a dict, got {type(data).__name__}")
        data = dict(data)
        if "train_half_widths" in data:  # the old top-level field
            widths = data.pop("train_half_widths")
            task = data.get("task", "dlc")
            task = {"name": task} if isinstance(task, str) else dict(task) if isinstance(task, dict) else task
            if isinstance(task, dict) and task.get("name", "dlc") == "dlc":
                if "train_half_widths" in task and list(task["train_half_widths"]) != list(widths):
                    raise ValueError("train_half_widths: given both at the top level (old form) and as "
                                     "task.train_half_widths, with different values")
                task["train_half_widths"] = widths
            data["task"] = task
        check_unknown_keys(data, {f.name for f in dataclasses.fields(cls)}, "config")
        for name in ("grad_clip", "model_box"):
            if data.get(name) == "inf":
                data[name] = math.inf
        return cls(**data)

    def replace(self, **changes: Any) -> "TrainConfig":
        """Return a copy with ``changes`` applied; keys may be dotted (``**{"task.gamma": 0.95}``, see
        :func:`apply_overrides`); unknown keys are an error."""
        changes = {k: _jsonable(v) for k, v in changes.items()}
        return TrainConfig.from_dict(apply_overrides(self.to_dict(), changes))

    def save(self, path: str | Path) -> None:
        """Write the config as JSON to ``path``."""
        Path(path).write_text(json.dumps(self.to_dict(), indent=2, sort_keys=True) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> "TrainConfig":
        """Read a config written by :meth:`save`.

        Raises
        ------
        ValueError
            The file is not valid JSON or holds an unknown key.
        """
        try:
            data = json.loads(Path(path).read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"path: {path} is not valid JSON ({exc})") from None
        return cls.from_dict(data)

