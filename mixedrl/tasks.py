"""The public face of the tasks: the task interface, the built-in tasks and the task registry.

Algorithm 2 and DDPG see a system only through :class:`Task`, so they run unchanged on the double lane
change (:class:`~mixedrl.envs.dlc_task.DoubleLaneChangeTask`, Section VI), the linear test bed
(:class:`~mixedrl.linear_task.LinearTask`) and any user system. :func:`task_from_config` builds the task of a
run's task configuration, including tasks registered by name with :func:`register_task` (the pendulum).

This module gathers the names of :mod:`mixedrl.task_base` (:class:`Task`, :func:`check_task`, with those of
:mod:`mixedrl.equilibrium`), :mod:`mixedrl.linear_task` and :mod:`mixedrl.envs.dlc_task`, and holds the
registry. The task modules import :mod:`mixedrl.task_base`, never this module, so there is no import cycle.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from mixedrl.config import register_task as register_task_config
from mixedrl.config import task_config
from mixedrl.envs.dlc_task import DLC_EXPERIMENT, CourseSampler, DoubleLaneChangeTask

if TYPE_CHECKING:  # complete only once the task modules registered their configurations
    from mixedrl.config import TaskConfig
from mixedrl.linear_task import LinearTask
from mixedrl.task_base import EQUILIBRIUM_ATOL, Equilibrium, Linearisation, Task, check_task, cost_hessian

__all__ = ["Task", "LinearTask", "DoubleLaneChangeTask", "CourseSampler", "DLC_EXPERIMENT", "Equilibrium",
           "Linearisation", "EQUILIBRIUM_ATOL", "check_task", "cost_hessian", "make_task", "register_task",
           "task_from_config"]


#: Task name (built-in or :func:`register_task`) -> its :class:`Task` class (with ``from_config``).
_TASK_FACTORIES: dict[str, type] = {"dlc": DoubleLaneChangeTask, "linear": LinearTask}


def register_task(task_cls: type, config_cls: type) -> type:
    """Register a named task: its :class:`Task` class and its configuration dataclass.

    ``config_cls`` is registered with :func:`mixedrl.config.register_task` (its ``name`` default must equal
    ``task_cls.name``); :func:`task_from_config` then builds ``task_cls.from_config(config)`` and
    :func:`make_task` ``task_cls(**kwargs)``, so runs, ``--set task.name=...`` and sweeps can name the task.

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
    """Build a task by name (``"dlc"``, ``"linear"`` or a registered one) with constructor arguments ``kwargs``.

    Raises
    ------
    ValueError
        ``name`` unknown (the message lists the known names).
    """
    if name not in _TASK_FACTORIES:
        raise ValueError(f"name: expected one of {tuple(_TASK_FACTORIES)}, got {name!r}")
    return _TASK_FACTORIES[name](**kwargs)


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
    return _TASK_FACTORIES[config.name].from_config(config)
