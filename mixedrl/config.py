"""The configuration of a training run: :class:`TrainConfig`, in sections, and its dotted-key overrides.

:class:`TrainConfig` holds a run of Algorithm 2 (``method`` ``"mixed"``, ``"model"``, ``"oracle"``) or of
DDPG (``"ddpg"``): ``method``, ``seed``, ``task`` (the experiment, chosen by its ``name``: ``"dlc"``,
``"linear"`` or a task registered with :func:`register_task`), ``algorithm``, ``sampler``, ``ddpg`` and
``run``. It is saved as ``config.json`` beside the run's results; a key that is not a field, at any level, is
an error naming the dotted key.

``TrainConfig()`` (no task named) holds the library defaults (docs/algorithm2.rst), with the double lane
change's task defaults. When a task is named (``task="dlc"``; in a dictionary a missing ``task`` is
``"dlc"``), a section that is not given takes that task's experiment configuration (:data:`PRESETS`; the
double lane change's is :data:`mixedrl.envs.dlc_task.DLC_EXPERIMENT`).

Dotted keys address nested fields, the same way on the command line, in :func:`apply_overrides` and in
sweep specifications::

    mixedrl train --method mixed --out runs/p300 --set task.prior_force_mean=300 algorithm.iterations=300
    mixedrl train --method mixed --out runs/true --set sampler.name=\\"true_copies\\"
    mixedrl train --method mixed --out runs/mine --config experiment.json   # nested JSON, like config.json

The flat form of the first release (top-level ``iterations``, ``ddpg_tau`` ...) is refused with an error
naming :data:`FLAT_FORM_RELEASE`.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mixedrl import config_sections, config_tasks
from mixedrl.checks import check_nonnegative_int, check_unknown_keys
from mixedrl.config_sections import (OPTIMISER_FIELDS, PRESETS, SAMPLERS, AlgorithmConfig, DDPGConfig,
                                     ModelRolloutsSampler, RunConfig, SamplerConfig, TrueCopiesSampler, register_preset,
                                     register_sampler, sampler_config)
from mixedrl.config_tasks import (BATCH_WEIGHTINGS, BUILTIN_NAMES, DISTURBANCE_LAWS, FEEDFORWARDS, METHODS,
                                  MODEL_COURSE_STARTS, RETIRED_ACTOR_OUTPUTS, RETIRED_AT, RETIRED_FEEDFORWARDS, TASKS,
                                  ForceDisturbanceConfig, GaussianNoiseConfig, LinearTaskConfig, build_section,
                                  check_choice, register_builtin_task, register_task, task_config, task_config_union,
                                  task_names, to_jsonable)

# this module's names, those of config_tasks and config_sections, and those served by __getattr__
__all__ = ["TrainConfig", "PAPER_SETTINGS", "PAPER_HYPERPARAMETERS", "ONE_STEP_LEARNER", "CONFIG_PRESETS",
           "FLAT_FORM_RELEASE", "memory_lower_bounds", "optimiser_section", "optimiser_prefix", "machine_memory",
           "apply_overrides", "flatten_table", "TaskConfig", "DoubleLaneChangeTaskConfig", "CostWeights",
           "CourseSampler", "DLC_EXPERIMENT", *config_tasks.__all__, *config_sections.__all__]


def __getattr__(name: str) -> Any:
    """The names the double lane change registers (:func:`register_builtin_task`, ``CourseSampler``,
    ``DLC_EXPERIMENT``) and ``TaskConfig``, the union of the built-in tasks' configurations."""
    if name in BUILTIN_NAMES:
        return BUILTIN_NAMES[name]
    if name == "TaskConfig":
        return task_config_union()
    if name == "CourseSampler" and "dlc_course" in SAMPLERS:
        return SAMPLERS["dlc_course"]
    if name == "DLC_EXPERIMENT" and "dlc" in PRESETS:
        return PRESETS["dlc"]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


# ---- the flat configuration form of the first release ----
#: The release that reads the flat configuration form (top-level ``iterations``, ``ddpg_tau`` ...).
FLAT_FORM_RELEASE = "mixedrl 0.1.0 at git commit b510485"


#: Deleted settings (docs/results.rst, "Deleted settings") with the value that behaves as today's code: a saved
#: config holding that value loads (the key dropped), any other value is refused naming the key.
DELETED_SETTINGS: dict[tuple[str, str], Any] = {
    ("algorithm", "rollout_critic_steps"): 1,
    ("algorithm", "rollout_updates"): 1,
    ("algorithm", "actor_average"): 0.0,
    ("algorithm", "actor_average_window"): 0.0,
    ("algorithm", "bellman_steps"): 1,
    ("sampler", "course_ramp"): 0,
    ("algorithm", "feedforward_spread"): 0.0,
    ("algorithm", "feedforward_handover"): False,
}
#: The commit that can still run a deleted setting at another value (where the refusal names it).
DELETED_AT: dict[tuple[str, str], str] = {("sampler", "course_ramp"): RETIRED_AT,
                                          ("algorithm", "feedforward_handover"): "2488be5",
                                          ("algorithm", "actor_average_window"): "f18569e"}


def optimiser_prefix(config: Any) -> str:
    """The section that holds the network and optimiser settings (:data:`OPTIMISER_FIELDS`) of ``config``'s
    method: ``"ddpg"`` for DDPG, ``"algorithm"`` for Algorithm 2 (the prefix of their dotted keys)."""
    return "ddpg" if config.method == "ddpg" else "algorithm"


def optimiser_section(config: Any) -> Any:
    """The section of ``config`` whose :data:`OPTIMISER_FIELDS` the run trains with: ``config.ddpg`` for
    ``method = "ddpg"``, else ``config.algorithm``."""
    return getattr(config, optimiser_prefix(config))


def flatten_table(table: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Flatten nested TOML tables into dotted keys: ``{"a": {"b": 1}}`` -> ``{"a.b": 1}``.

    TOML's ``a.b = 1`` (a nested table) and ``"a.b" = 1`` (one key) both become ``"a.b"``; lists and
    scalars are leaves.
    """
    out: dict[str, Any] = {}
    for key, value in table.items():
        out.update(flatten_table(value, f"{prefix}{key}.") if isinstance(value, dict) else {f"{prefix}{key}": value})
    return out


def apply_overrides(data: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    """Return a copy of the config dict ``data`` with dotted-key ``overrides`` applied.

    ``{"task.prior_force_mean": 300}`` sets ``data["task"]["prior_force_mean"]``; a plain key replaces a
    top-level value. Missing levels are created as dicts; a string ``task`` or ``sampler`` (a name) is first
    expanded to ``{"name": ...}``. Keys are not checked here (:meth:`TrainConfig.from_dict` does).

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


def machine_memory() -> int | None:
    """The machine's physical memory in bytes (``None`` where the system does not report it)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, OSError, ValueError):
        return None


def memory_lower_bounds(config: TrainConfig) -> dict[str, int]:
    """Lower bounds, in bytes, of the memory a run of ``config`` allocates, by the key that sets it.

    Every bound takes the smallest task (one observation, one action):

    * ``algorithm.hidden_sizes``: the actor and the critic, each ``P = sum_i (h_{i-1} + 1) h_i + h_last + 1``
      float32 parameters (``h_0 = 1``) with gradient and two Adam moments, 16 bytes a parameter;
    * ``algorithm.batch_size`` (DDPG: ``ddpg.batch_size``): the batch's float64 states and one network's
      float32 activations, ``batch_size (8 + 4 sum(hidden_sizes))`` bytes;
    * ``ddpg.buffer_size`` (DDPG only): the float32 replay buffer, 20 bytes a transition.
    """
    alg = config.algorithm
    widths = (1, *alg.hidden_sizes, 1)
    params = sum((a + 1) * b for a, b in zip(widths[:-1], widths[1:]))
    batch = optimiser_section(config).batch_size
    out = {"algorithm.hidden_sizes": 2 * 16 * params,
           f"{optimiser_prefix(config)}.batch_size": batch * (8 + 4 * sum(alg.hidden_sizes))}
    if config.method == "ddpg":
        out["ddpg.buffer_size"] = 20 * config.ddpg.buffer_size
    return out


def _over(base: dict[str, Any], value: dict[str, Any]) -> dict[str, Any]:
    """``value`` over ``base``, or ``value`` alone if it names another ``name`` (a sampler) than ``base``."""
    return {**base, **value} if value.get("name", base.get("name")) == base.get("name") else value


#: The fields that may be ``math.inf``, written ``"inf"`` in ``config.json`` (section, field).
_INFINITE_FIELDS = (("algorithm", "grad_clip"), ("ddpg", "grad_clip"), ("sampler", "box"))

#: The largest seed: torch and numpy generators take seeds of 64 bits.
MAX_SEED = 2**64 - 1


@dataclass(init=False)
class TrainConfig:
    """Configuration of one training run (Algorithm 2 or DDPG), in sections; a section left out (or given as a
    partial dict) takes its class's defaults, under the named task's preset (:data:`PRESETS`)."""

    method: str
    """Which algorithm: ``"mixed"`` (Algorithm 2, IBE posterior), ``"model"`` (Algorithm 2 on the prior
    model of eq. 55, IBE off), ``"oracle"`` (Algorithm 2 with the true noise) or ``"ddpg"``."""

    seed: int
    """Seed of every generator of the run, in [0, 2**64 - 1]. Same seed, same weights."""

    task: TaskConfig
    """The experiment (``name``: ``"dlc"``, the default, ``"linear"`` or a registered task); a task name or
    a nested dict is accepted (:func:`task_config`)."""

    algorithm: AlgorithmConfig
    """Algorithm 2, and the settings every method shares (:class:`AlgorithmConfig`)."""

    sampler: SamplerConfig
    """Where Algorithm 2's PEV/PIM states come from, chosen by ``sampler.name`` (:data:`SAMPLERS`); a
    departure from the paper unless ``"true_copies"`` (docs/algorithm2.rst)."""

    ddpg: DDPGConfig
    """What only DDPG has, its own optimiser settings included (:class:`DDPGConfig`)."""

    run: RunConfig
    """Evaluation, checkpoints, threads (:class:`RunConfig`)."""

    def __init__(self, method: str = "mixed", seed: int = 0, task: Any = None, algorithm: Any = None,
                 sampler: Any = None, ddpg: Any = None, run: Any = None, **unknown: Any) -> None:
        old = {f.name for cls in (AlgorithmConfig, RunConfig) for f in dataclasses.fields(cls)}
        old |= {f"ddpg_{f.name}" for f in dataclasses.fields(DDPGConfig) if f.name not in OPTIMISER_FIELDS}
        flat = sorted(k for k in unknown if k in old | {"state_source", "train_half_widths"}
                      or str(k).startswith(("model_", "true_")))
        if flat:
            raise ValueError(f"config: {flat} at the top level is the flat form, read by {FLAT_FORM_RELEASE}; this "
                             f"release reads the sections (algorithm.iterations, sampler.course_starts, ...)")
        check_unknown_keys(unknown, {f.name for f in dataclasses.fields(TrainConfig)}, "config")
        self.method = check_choice(method, "method", METHODS)
        self.seed = check_nonnegative_int(seed, "seed")
        if self.seed > MAX_SEED:
            raise ValueError(f"seed: expected an integer in [0, 2**64 - 1] (torch's generator seed), got {seed!r}")
        # no task named: the library defaults, with the double lane change's task defaults
        self.task = task_config("dlc" if task is None else task)
        preset = PRESETS.get(self.task.name, {}) if task is not None else {}
        sampler = {"name": sampler} if isinstance(sampler, str) else sampler
        for name, cls, value in (("algorithm", AlgorithmConfig, algorithm), ("ddpg", DDPGConfig, ddpg),
                                 ("run", RunConfig, run), ("sampler", None, sampler)):
            if value is None or isinstance(value, dict):  # over the preset, "inf" read as math.inf
                value = {k: math.inf if (name, k) in _INFINITE_FIELDS and str(v) == "inf" else v
                         for k, v in _over(preset.get(name, {}), value or {}).items()}
            setattr(self, name, build_section(cls, value, name) if cls else sampler_config(value, self.task.name))
        if self.method == "ddpg" and self.algorithm.feedforward not in ("learned", "auto"):
            raise ValueError(f"algorithm.feedforward: {self.algorithm.feedforward!r} takes the feed-forward from "
                             f"the method's noise model; method 'ddpg' has none (use 'learned')")
        total, need = machine_memory(), memory_lower_bounds(self)
        if total is not None and sum(need.values()) > total:  # the first key whose own bound does, else the largest
            key = next((k for k, v in need.items() if v > total), max(need, key=need.get))
            value = getattr(getattr(self, key.split(".")[0]), key.split(".")[1])
            raise ValueError(f"{key}: {value!r} needs at least {need[key] / 2**30:.3g} GiB (all of the run at least "
                             f"{sum(need.values()) / 2**30:.3g} GiB), more than this machine's {total / 2**30:.3g} GiB "
                             f"of memory")

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
        """Return the fields as a JSON-compatible nested dictionary (tuples become lists, ``inf`` a string;
        the double lane change's ``task.obs_scale`` and ``algorithm.compile`` left out at their defaults)."""
        out = to_jsonable(self)
        for section, name in _INFINITE_FIELDS:
            if name in out[section] and math.isinf(out[section][name]):
                out[section][name] = "inf"
        if out["task"].get("name") == "dlc" and out["task"].get("obs_scale", 0) is None:
            del out["task"]["obs_scale"]  # defaults left out keep config.json and config hashes unchanged
        if out["algorithm"].get("compile") == "off":
            del out["algorithm"]["compile"]
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "TrainConfig":
        """Build a config from a dictionary (the content of ``config.json``), nested sections included.

        ``"task": "dlc"`` (a name) stands for that task's defaults; a dict without ``task`` names ``"dlc"``.
        A DDPG run's dict lacking one of :data:`OPTIMISER_FIELDS` in ``ddpg`` takes it from ``algorithm``.
        A deleted setting at today's behaviour is dropped (``DELETED_SETTINGS``).

        Raises
        ------
        ValueError
            ``data`` has a key that is not a field, at any level (``config: unknown key(s)
            ['task.prior_mena']``), is in the flat form (naming :data:`FLAT_FORM_RELEASE`), or a field is
            invalid (the message starts with its dotted name).
        """
        if not isinstance(data, dict):
            raise ValueError(f"config: expected a dict, got {type(data).__name__}")
        data = copy.deepcopy(data)
        for (section, name), value in DELETED_SETTINGS.items():
            part = data.get(section)
            if isinstance(part, dict) and name in part:
                if part[name] != value:
                    commit = DELETED_AT.get((section, name))
                    raise ValueError(f"{section}.{name}: this setting was deleted (docs: results, 'Deleted settings'); "
                                     f"only {value!r}, today's behaviour, can be read, got {part[name]!r}"
                                     + (f"; git commit {commit} can still run it" if commit else ""))
                del part[name]
        algo, ddpg = data.get("algorithm"), data.get("ddpg", {})
        if data.get("method") == "ddpg" and isinstance(algo, dict) and isinstance(ddpg, dict):
            data["ddpg"] = {**{name: algo[name] for name in OPTIMISER_FIELDS if name in algo}, **ddpg}
        return cls(**{"task": "dlc", **data})

    def replace(self, **changes: Any) -> "TrainConfig":
        """Return a copy with ``changes`` applied; keys may be dotted (``**{"algorithm.iterations": 30}``,
        see :func:`apply_overrides`); unknown keys are an error."""
        changes = {k: to_jsonable(v) for k, v in changes.items()}
        data = self.to_dict()
        if any(k in ("task", "task.name") for k in changes):  # a new task: its own presets for what is not given
            data = {"method": data["method"], "seed": data["seed"], "task": data["task"]}
        return TrainConfig.from_dict(apply_overrides(data, changes))

    def save(self, path: str | Path) -> None:
        """Write the config as JSON to ``path``."""
        Path(path).write_text(json.dumps(self.to_dict(), indent=2, sort_keys=True) + "\n")

    @classmethod
    def preset(cls, name: str, **fields: Any) -> "TrainConfig":
        """The config of the preset ``name`` of :data:`CONFIG_PRESETS` (``"paper"``, ``"library"``), with
        ``fields`` given as to the constructor applied over it: a section given as a dict changes only the
        settings it names (``algorithm=dict(iterations=60)``), a section object replaces it.

        Raises
        ------
        ValueError
            An unknown preset name (naming ``preset``), or as the constructor.
        """
        head = {k: fields.pop(k) for k in ("method", "seed", "task") if k in fields}
        data = cls(**head).with_preset(name).to_dict()
        for section, value in fields.items():
            if isinstance(value, str) and section == "sampler":
                value = {"name": value}
            if isinstance(value, dict) and isinstance(data.get(section), dict):
                data[section] = _over(data[section], to_jsonable(value))
            elif value is not None:  # None: the preset's
                data[section] = value
        return cls.from_dict(data)

    def with_preset(self, name: str) -> "TrainConfig":
        """A copy with the preset ``name`` (:data:`CONFIG_PRESETS`) applied; its sampler replaces the config's."""
        if name not in CONFIG_PRESETS:
            raise ValueError(f"preset: expected one of {tuple(CONFIG_PRESETS)}, got {name!r}")
        data = self.to_dict()
        for section, values in CONFIG_PRESETS[name].items():
            data[section] = _over(data[section], values)
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


# ---- presets of Algorithm 2: the paper's literal form and the library defaults ----
#: The paper's value of every setting where the library departs from it (:mod:`mixedrl.departures` reads
#: them here): ``TrainConfig.preset("paper")`` is the paper's Algorithm 2. The table of docs/algorithm2.rst
#: gives each with the library's default and why.
PAPER_SETTINGS: dict[str, dict[str, Any]] = {
    "sampler": {"name": "true_copies"},
    "algorithm": {"batch_weighting": "uniform", "lr_decay_to": 1.0, "critic_target": 0.0,
                  "feedforward": "learned", "rollout_horizon": 0,
                  "rollout_region": 0.0, "actor_output": "tanh"},
}
#: The budget, networks and step sizes of the ``paper`` preset, those of the one-step learner; not
#: departures: the paper gives none of them.
PAPER_HYPERPARAMETERS: dict[str, Any] = {
    "iterations": 1500, "batch_size": 512, "activation": "elu", "critic_lr": 3e-3, "actor_lr": 3e-4,
    "grad_clip": 10.0, "j_max": 5, "batch_weight_offset": 1.0, "rollout_discount_start": 0.0}
#: The ``algorithm`` settings of the one-step learner (docs/tuning.rst): :data:`PAPER_HYPERPARAMETERS` with the
#: rollout learner's departures off, the library's sampler, state weights and decay kept.
ONE_STEP_LEARNER: dict[str, Any] = {**PAPER_HYPERPARAMETERS, "critic_target": 0.0, "rollout_horizon": 0,
                                    "rollout_region": 0.0, "actor_output": "tanh", "feedforward": "learned"}
#: Preset name -> section -> settings applied over ``TrainConfig(**fields)`` (:meth:`TrainConfig.preset`).
CONFIG_PRESETS: dict[str, dict[str, dict[str, Any]]] = {
    "library": {},
    "paper": {**PAPER_SETTINGS, "algorithm": {**PAPER_SETTINGS["algorithm"], **PAPER_HYPERPARAMETERS,
                                              "region_budget": 1}}}
