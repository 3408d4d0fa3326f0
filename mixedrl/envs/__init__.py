"""Environments: the double-lane-change vehicle (eq. 53) and its Gymnasium face (docs/vehicle.rst).

Importing this package registers the Gymnasium id ``mixedrl/DoubleLaneChange-v0``
(:class:`~mixedrl.envs.dlc_env.DoubleLaneChangeEnv`). The task the algorithms train on,
:class:`~mixedrl.envs.dlc_task.DoubleLaneChangeTask`, is not imported here (importing :mod:`mixedrl`
imports it).
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
