"""The public face of the tasks: the task interface, the built-in tasks and the task registry.

Algorithm 2 (:mod:`mixedrl.algorithms.agpi`) and DDPG (:mod:`mixedrl.algorithms.ddpg`) see a system
only through the small interface :class:`Task`, so they run unchanged on the double lane change
(:class:`~mixedrl.envs.dlc_task.DoubleLaneChangeTask`, Section VI of the paper) and on any user system
(:class:`~mixedrl.linear_task.LinearTask`, and the tutorial). :func:`task_from_config` builds either from
the run's task configuration (:class:`mixedrl.config.DoubleLaneChangeTaskConfig`,
:class:`mixedrl.config.LinearTaskConfig`), and any task registered by name with :func:`register_task`
(the pendulum of :mod:`mixedrl.envs.pendulum`, registered when :mod:`mixedrl` is imported).

The names live where they are defined and this module gathers them (one import path for all):

* :mod:`mixedrl.task_base`: :class:`Task`, :func:`check_task`, with :class:`Equilibrium`, :class:`Linearisation`,
  :data:`EQUILIBRIUM_ATOL`, :func:`cost_hessian` of :mod:`mixedrl.equilibrium` (it imports no task, nor this module);
* :mod:`mixedrl.linear_task`: :class:`~mixedrl.linear_task.LinearTask`;
* :mod:`mixedrl.envs.dlc_task`: :class:`~mixedrl.envs.dlc_task.DoubleLaneChangeTask` with the double lane
  change's experiment (its course sampler :class:`~mixedrl.envs.dlc_task.CourseSampler`,
  ``sampler.name = "dlc_course"``, and its preset :data:`~mixedrl.envs.dlc_task.DLC_EXPERIMENT`, which it
  registers with :mod:`mixedrl.config`);
* here: the registry, :func:`register_task`, :func:`make_task` and :func:`task_from_config`.

The two task modules import :mod:`mixedrl.task_base`, never this module, and this module imports them
at its top: the import graph has no cycle (``tests/test_imports.py``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from mixedrl.config import LinearTaskConfig, task_config
from mixedrl.config import register_task as register_task_config
from mixedrl.envs.dlc_config import DoubleLaneChangeTaskConfig
from mixedrl.envs.dlc_task import DLC_EXPERIMENT, CourseSampler, DoubleLaneChangeTask

if TYPE_CHECKING:  # the union of the built-in tasks' configurations, complete once the task modules registered
    from mixedrl.config import TaskConfig
from mixedrl.linear_task import LinearTask
from mixedrl.task_base import EQUILIBRIUM_ATOL, Equilibrium, Linearisation, Task, check_task, cost_hessian

__all__ = ["Task", "LinearTask", "DoubleLaneChangeTask", "CourseSampler", "DLC_EXPERIMENT", "Equilibrium",
           "Linearisation", "EQUILIBRIUM_ATOL", "check_task", "cost_hessian", "make_task", "register_task",
           "task_from_config"]


#: Registered task name -> its :class:`Task` class (built by ``from_config``); :func:`register_task`.
_TASK_FACTORIES: dict[str, type] = {}

#: Built-in task name -> its :class:`Task` class; :func:`make_task`.
_BUILTIN_TASKS: dict[str, type] = {"dlc": DoubleLaneChangeTask, "linear": LinearTask}


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
    """Build a task by name: ``"dlc"`` (:class:`~mixedrl.envs.dlc_task.DoubleLaneChangeTask`), ``"linear"``
    (:class:`~mixedrl.linear_task.LinearTask`) or a registered one (:func:`register_task`), with constructor
    arguments ``kwargs``.

    Raises
    ------
    ValueError
        ``name`` unknown (the message lists the known names).
    """
    if name in _BUILTIN_TASKS:
        return _BUILTIN_TASKS[name](**kwargs)
    if name in _TASK_FACTORIES:
        return _TASK_FACTORIES[name](**kwargs)
    raise ValueError(f"name: expected one of {(*_BUILTIN_TASKS, *_TASK_FACTORIES)}, got {name!r}")


def task_from_config(config: TaskConfig | dict[str, Any] | str) -> Task:
    """Build the task of a run's task configuration (``TrainConfig.task``).

    Parameters
    ----------
    config : DoubleLaneChangeTaskConfig, LinearTaskConfig, a registered configuration, dict or str
        The configuration, or anything :func:`mixedrl.config.task_config` accepts (a name, a nested dict).

    Returns
    -------
    Task
        :class:`~mixedrl.envs.dlc_task.DoubleLaneChangeTask`, :class:`~mixedrl.linear_task.LinearTask` or
        the registered task class of ``config.name`` (:func:`register_task`).

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
