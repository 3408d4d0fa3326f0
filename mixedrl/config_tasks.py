"""The task configurations of :class:`mixedrl.config.TrainConfig` and their registry, with the vocabulary and
builders every section shares (re-exported by :mod:`mixedrl.config`).

:class:`LinearTaskConfig` is defined here; the double lane change's configuration is registered by its task
module (:func:`register_builtin_task`), so that the configuration imports no task module.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, ClassVar, Union

import numpy as np

from mixedrl.checks import as_vector, check_covariance, check_fraction, check_number, check_unknown_keys
from mixedrl.envs.disturbance import DISTURBANCE_LAWS, Disturbance
from mixedrl.lq import LQProblem

__all__ = ["METHODS", "TASKS", "MODEL_COURSE_STARTS", "BATCH_WEIGHTINGS", "FEEDFORWARDS", "RETIRED_FEEDFORWARDS",
           "RETIRED_AT", "RETIRED_ACTOR_OUTPUTS", "DISTURBANCE_LAWS", "ForceDisturbanceConfig", "GaussianNoiseConfig",
           "LinearTaskConfig", "register_task", "register_builtin_task", "task_names", "task_config",
           "task_config_union", "build_section", "to_jsonable", "check_choice", "BUILTIN_NAMES"]

#: The four methods of the reproduction (mixed RL, model-driven RL, oracle, DDPG).
METHODS = ("mixed", "model", "oracle", "ddpg")
#: The built-in tasks; :func:`task_names` lists these and the registered ones.
TASKS = ("dlc", "linear")
#: Where the course copies of the double lane change's sampler restart (``sampler.course_starts``).
MODEL_COURSE_STARTS = ("start", "along", "loop")
#: The values of ``algorithm.compile`` (:mod:`mixedrl.compiled`).
COMPILE_MODES = ("off", "on", "functional")
#: How Algorithm 2 weights the states of its batch (``algorithm.batch_weighting``).
BATCH_WEIGHTINGS = ("uniform", "relative")

#: Where the policy takes its action at the equilibrium (``algorithm.feedforward``).
FEEDFORWARDS = ("auto", "learned", "lq_ss", "lq_handover")
#: The commit that still runs the options retired first (docs/results.rst).
RETIRED_AT = "ee954d7"
#: The retired values of ``algorithm.feedforward``, each with the commit that still runs it: actors anchored at the
#: LQ optimum during training, and ``"lq"``, the actor shifted to the optimum's action at the equilibrium.
RETIRED_FEEDFORWARDS = {"lq_train": RETIRED_AT, "lq_affine": RETIRED_AT, "lq_affine_ss": RETIRED_AT, "lq": "c44231f"}
#: The retired values of ``algorithm.actor_output`` with the commit that still runs each: ``"clip"``, the
#: straight-through gradient in both directions.
RETIRED_ACTOR_OUTPUTS = {"clip": "c44231f"}


def to_jsonable(value: Any) -> Any:
    """Dataclasses to dicts, tuples to lists, recursively (what ``json.dumps`` writes)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, (tuple, list)):
        return [to_jsonable(v) for v in value]
    return value


def build_section(cls: type, data: Any, where: str) -> Any:
    """Instantiate the configuration dataclass ``cls`` from a JSON-like dict (or return an instance as is).

    ``where`` is the dotted path of ``data`` (``"task"``, ...), for unknown keys' names. Nested fields are
    passed on as given: each class's ``__post_init__`` builds its own nested configurations.
    """
    if isinstance(data, cls):
        return data
    if not isinstance(data, dict):
        raise ValueError(f"{where}: expected a dict (a JSON object) or a {cls.__name__}, got {data!r}")
    allowed = {f.name for f in dataclasses.fields(cls) if f.init}
    check_unknown_keys({f"{where}.{k}": v for k, v in data.items()}, {f"{where}.{k}" for k in allowed}, "config")
    return cls(**data)


#: The double lane change's true force ``F_dis`` (``task.disturbance``): :class:`mixedrl.envs.disturbance.Disturbance`.
ForceDisturbanceConfig = Disturbance


def _tuples(array: Any) -> tuple:
    """A vector or a matrix as a tuple (of tuples) of floats, its JSON face."""
    return tuple(tuple(row) if isinstance(row, list) else row for row in np.asarray(array, dtype=float).tolist())


# ---- the linear test bed ----
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
        self.law = str(check_choice(self.law, f"{self.WHERE}.law", DISTURBANCE_LAWS))
        self.mean = _tuples(as_vector(self.mean, f"{self.WHERE}.mean"))
        self.cov = _tuples(check_covariance(self.cov, f"{self.WHERE}.cov", len(self.mean)))


@dataclass
class LinearTaskConfig:
    """The linear test bed :class:`mixedrl.linear_task.LinearTask`: ``s' = A s + B u + xi``, utility
    ``s'^T Q s' + u^T R u`` (by default a sampled double integrator, ``dt = 0.1``, noise on the velocity).
    Dotted keys: ``task.<field>``; ``n`` = ``A``'s size, ``m`` = ``B``'s columns.

    Validated by, and :meth:`problem` returns, :class:`mixedrl.lq.LQProblem` (``(A, B)`` stabilisable,
    ``R`` positive definite).
    """

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
        self.gamma = check_fraction(self.gamma, "task.gamma", low_open=True, high_open=True)
        dist = self.disturbance
        if not isinstance(dist, (dict, GaussianNoiseConfig)):
            raise ValueError(f"task.disturbance: expected a dict (a JSON object), got {dist!r}")
        given = dist if isinstance(dist, dict) else vars(dist)
        # validated by LQProblem before the noise section, so the system's size decides which is wrong
        problem = _lq_problem(self, *(given.get(k, getattr(GaussianNoiseConfig, k)) for k in ("mean", "cov")))
        self.disturbance = build_section(GaussianNoiseConfig, dist, "task.disturbance")
        for name in _PROBLEM_FIELDS:  # the validated values, as JSON (tuples)
            value = getattr(problem, name)
            setattr(self, name, _tuples(value) if isinstance(value, np.ndarray) else value)
        self.init_box = check_number(self.init_box, "task.init_box", positive=True)
        self.action_bound = check_number(self.action_bound, "task.action_bound", positive=True)

    def problem(self) -> LQProblem:
        """The LQ problem this configuration describes (:class:`mixedrl.lq.LQProblem`)."""
        return _lq_problem(self, self.disturbance.mean, self.disturbance.cov)


#: Names of :class:`mixedrl.lq.LQProblem`'s fields that :class:`LinearTaskConfig` calls otherwise.
_PROBLEM_KEYS = {"noise_mean": "disturbance.mean", "noise_cov": "disturbance.cov"}
#: :class:`mixedrl.lq.LQProblem`'s fields that :class:`LinearTaskConfig` holds under the same name.
_PROBLEM_FIELDS = tuple(f.name for f in dataclasses.fields(LQProblem) if f.name not in _PROBLEM_KEYS)


def _lq_problem(cfg: LinearTaskConfig, mean: Any, cov: Any) -> LQProblem:
    """:class:`mixedrl.lq.LQProblem` of ``cfg`` with the true noise ``N(mean, cov)``; its errors name the
    dotted key (``task.A``, ``task.disturbance.mean``, ...)."""
    try:
        return LQProblem(**{name: getattr(cfg, name) for name in _PROBLEM_FIELDS}, noise_mean=mean, noise_cov=cov)
    except ValueError as exc:
        name, _, rest = str(exc).partition(":")
        raise ValueError(f"task.{_PROBLEM_KEYS.get(name, name)}:{rest}") from None


#: Task name -> its configuration class (:func:`register_builtin_task`, :func:`register_task`).
_TASK_CLASSES: dict[str, type] = {"linear": LinearTaskConfig}
#: Built-in task name -> the reader of its configuration from a dict (``reader(values, where="task")``).
_TASK_READERS: dict[str, Any] = {}
#: Names a built-in task module registers as ``mixedrl.config.<name>`` (:func:`register_builtin_task`).
BUILTIN_NAMES: dict[str, Any] = {}


def _task_name(config_cls: type) -> Any:
    """The default of the dataclass ``config_cls``'s ``name`` field (``None`` without one)."""
    fields = {f.name: f for f in dataclasses.fields(config_cls)} if dataclasses.is_dataclass(config_cls) else {}
    return fields["name"].default if "name" in fields else None


def register_builtin_task(config_cls: type, reader: Any = None, **names: Any) -> type:
    """Register the configuration class of a built-in task (a name of :data:`TASKS`) from the task's own
    module (:mod:`mixedrl.envs.dlc_task` registers the double lane change's).

    ``reader(values, where="task")`` builds the class from a JSON-like dict (default: the fields as keyword
    arguments); ``names`` (and the class) become readable as ``mixedrl.config.<name>``.

    Raises
    ------
    ValueError
        ``config_cls``'s ``name`` default is not a name of :data:`TASKS`.
    """
    name = _task_name(config_cls)
    if name not in TASKS:
        raise ValueError(f"config_cls: expected the configuration of a built-in task {TASKS}, got {config_cls!r}")
    _TASK_CLASSES[name] = config_cls
    if reader is not None:
        _TASK_READERS[name] = reader
    BUILTIN_NAMES.update({config_cls.__name__: config_cls, **names})
    return config_cls


def task_config_union() -> Any:
    """The type of a run's task configuration (``mixedrl.config.TaskConfig``): the union of the built-in
    tasks' configuration classes registered so far, in the order of :data:`TASKS`."""
    return Union[tuple(_TASK_CLASSES[n] for n in TASKS if n in _TASK_CLASSES)]


def register_task(config_cls: type) -> type:
    """Register the configuration dataclass of a named task (usable as a decorator).

    The name is the default of the class's ``name`` field; ``TrainConfig(task={"name": ..., ...})`` and
    ``--set task.name=...`` then build ``config_cls``. :func:`mixedrl.tasks.register_task` calls this
    function and registers the task class too.

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
    name = _task_name(config_cls)
    if not isinstance(name, str) or not name:
        raise ValueError(f"config_cls: expected a dataclass with a string default for 'name', got {config_cls!r}")
    if name in TASKS:
        raise ValueError(f"config_cls: the name {name!r} is a built-in task's")
    _TASK_CLASSES[name] = config_cls
    return config_cls


def task_names() -> tuple[str, ...]:
    """Names of the tasks a configuration can name: the built-in :data:`TASKS` and the registered ones."""
    return tuple(n for n in TASKS if n in _TASK_CLASSES) + tuple(n for n in _TASK_CLASSES if n not in TASKS)


def task_config(value: Any = "dlc") -> Any:
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
    name = check_choice(value.get("name", "dlc"), "task.name", task_names())
    if name in _TASK_READERS:
        return _TASK_READERS[name]({**value, "name": name}, where="task")
    return build_section(_TASK_CLASSES[name], {**value, "name": name}, "task")


def check_choice(value: Any, name: str, options: tuple, retired: dict[str, str] | None = None) -> Any:
    """``value`` if it is one of ``options``, else a ``ValueError`` naming ``name`` (and, for a value of
    ``retired``, a dict value -> commit, the commit that still runs it)."""
    if isinstance(value, str) and value in (retired or {}):
        raise ValueError(f"{name}: {value!r} was retired (its measured rows stay on the results page, "
                         f"docs/results.rst); expected one of {options}; git commit {retired[value]} can still run it")
    if value not in options:
        raise ValueError(f"{name}: expected one of {options}, got {value!r}")
    return value
