"""Environments: the double-lane-change vehicle (eq. 53) and its Gymnasium face.

Importing this package registers the Gymnasium id ``mixedrl/DoubleLaneChange-v0``
(:class:`~mixedrl.envs.dlc_env.DoubleLaneChangeEnv`).

Configuration: :class:`~mixedrl.envs.dlc_config.DoubleLaneChangeConfig` (the environment) and
:class:`~mixedrl.envs.dlc_config.DoubleLaneChangeTaskConfig` (the same with the discount and the prior:
a run's ``task``), with the true force :class:`~mixedrl.envs.disturbance.Disturbance` and the
:class:`~mixedrl.envs.dlc_config.CostWeights` of eq. (54). Planning API (torch, batched):
:class:`~mixedrl.envs.model.DoubleLaneChangeModel` (``step`` = the shared deterministic ``f``,
``observe``, ``cost``, ``reset_states``, ``NOISE_INDEX``); data collection:
:class:`~mixedrl.envs.vector_env.DoubleLaneChangeVectorEnv` (same ``f`` plus the true noise) or the
Gymnasium env; Table I metrics: :func:`~mixedrl.envs.evaluation.evaluate_tracking` (many courses in lock step:
:func:`~mixedrl.envs.evaluation.evaluate_courses`).
:mod:`mixedrl.envs.tracking` gathers these names (and says how the reference enters).

The task the algorithms train on, :class:`~mixedrl.envs.dlc_task.DoubleLaneChangeTask` (with its course
sampler and preset), is in :mod:`mixedrl.envs.dlc_task`, which this package does not import (it builds
on :mod:`mixedrl.task_base`; importing :mod:`mixedrl` imports it, through :mod:`mixedrl.tasks`).
"""

import gymnasium as gym

from mixedrl.envs.disturbance import Disturbance
from mixedrl.envs.dlc_config import CostWeights, DoubleLaneChangeConfig, DoubleLaneChangeTaskConfig, make_config
from mixedrl.envs.dlc_env import DoubleLaneChangeEnv
from mixedrl.envs.evaluation import TrackingResult, evaluate_courses, evaluate_tracking
from mixedrl.envs.model import ACTION_DIM, NOISE_INDEX, STATE_DIM, DoubleLaneChangeModel
from mixedrl.envs.reference import DoubleLaneChangeReference
from mixedrl.envs.vector_env import DoubleLaneChangeVectorEnv
from mixedrl.envs.vehicle import VehicleDynamics, VehicleParams, fiala_lateral_force

__all__ = ["ENV_ID", "ACTION_DIM", "NOISE_INDEX", "STATE_DIM", "CostWeights", "Disturbance", "DoubleLaneChangeConfig",
           "DoubleLaneChangeEnv", "DoubleLaneChangeModel", "DoubleLaneChangeReference", "DoubleLaneChangeTaskConfig",
           "DoubleLaneChangeVectorEnv", "TrackingResult", "VehicleDynamics", "VehicleParams", "evaluate_tracking",
           "evaluate_courses", "fiala_lateral_force", "make_config"]

#: Gymnasium id of the double-lane-change environment.
ENV_ID = "mixedrl/DoubleLaneChange-v0"

if ENV_ID not in gym.registry:
    gym.register(id=ENV_ID, entry_point="mixedrl.envs.dlc_env:DoubleLaneChangeEnv")
