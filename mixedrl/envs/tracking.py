"""Double-lane-change tracking: the public names of :mod:`mixedrl.envs.disturbance`,
:mod:`mixedrl.envs.dlc_config`, :mod:`mixedrl.envs.columns`, :mod:`mixedrl.envs.model` and
:mod:`mixedrl.envs.vector_env` in one place (the tracking state and its errors: docs/vehicle.rst).
"""

from mixedrl.envs.columns import observation_columns, observation_from_errors, stage_cost, tracking_errors
from mixedrl.envs.disturbance import Disturbance
from mixedrl.envs.dlc_config import CostWeights, DoubleLaneChangeConfig, DoubleLaneChangeTaskConfig, make_config
from mixedrl.envs.model import ACTION_DIM, NOISE_INDEX, STATE_DIM, DoubleLaneChangeModel
from mixedrl.envs.vector_env import DoubleLaneChangeVectorEnv

__all__ = ["CostWeights", "Disturbance", "DoubleLaneChangeConfig", "DoubleLaneChangeModel",
           "DoubleLaneChangeTaskConfig", "DoubleLaneChangeVectorEnv", "NOISE_INDEX", "STATE_DIM", "ACTION_DIM",
           "make_config", "observation_columns", "observation_from_errors", "stage_cost", "tracking_errors"]
