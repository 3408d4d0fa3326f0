"""mixedrl: mixed reinforcement learning with additive stochastic uncertainty.

Implements Mu et al., *Mixed Reinforcement Learning with Additive Stochastic Uncertainty*. Equation
numbers ``eq. (N)`` everywhere in this package follow ``shared/paper/EQUATIONS.md``.

Importing the package imports :mod:`mixedrl.tasks` (the task interface of :mod:`mixedrl.task_base`, the
built-in tasks and the registry), hence :mod:`mixedrl.envs.dlc_task`, which registers the double lane change's experiment with the configuration
(its course sampler ``"dlc_course"`` in :data:`mixedrl.config.SAMPLERS` and its preset in
:data:`mixedrl.config.PRESETS`), so that every :class:`~mixedrl.config.TrainConfig` that names that task
sees them, and :mod:`mixedrl.envs.pendulum`, which registers the pendulum task by name
(``task.name = "pendulum"``).
"""

import logging

from mixedrl import tasks as _tasks  # noqa: F401  (the task interface, the built-in tasks, the registry)
from mixedrl.envs import dlc_task as _dlc_task  # noqa: F401  (registers the double lane change's sampler and preset)
from mixedrl.envs import pendulum as _pendulum  # noqa: F401  (registers the pendulum task by name)

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())
