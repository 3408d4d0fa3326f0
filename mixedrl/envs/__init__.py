"""Environments: the double-lane-change vehicle (eq. 53) and its Gymnasium face.

Importing this package registers the Gymnasium id ``mixedrl/DoubleLaneChange-v0``
(:class:`~mixedrl.envs.dlc_env.DoubleLaneChangeEnv`).

Planning API (torch, batched): :class:`~mixedrl.envs.tracking.DoubleLaneChangeModel` (``step`` = the
shared deterministic ``f``, ``observe``, ``cost``, ``reset_states``, ``NOISE_INDEX``); data collection:
:class:`~mixedrl.envs.tracking.DoubleLaneChangeVectorEnv` (same ``f`` plus the true noise) or the
Gymnasium env; Table I metrics: :func:`~mixedrl.envs.evaluation.evaluate_tracking`.
"""

import gymnasium as gym

from mixedrl.envs.dlc_env import DoubleLaneChangeEnv
from mixedrl.envs.evaluation import TrackingResult, evaluate_tracking
from mixedrl.envs.reference import DoubleLaneChangeReference
from mixedrl.envs.tracking import (
    ACTION_DIM,
    NOISE_INDEX,
    STATE_DIM,
    Disturbance,
    DoubleLaneChangeConfig,
    DoubleLaneChangeModel,
    DoubleLaneChangeVectorEnv,
    make_config,
)
from mixedrl.envs.vehicle import VehicleDynamics, VehicleParams, fiala_lateral_force

__all__ = [
    "ENV_ID",
    "ACTION_DIM",
    "NOISE_INDEX",
    "STATE_DIM",
    "Disturbance",
    "DoubleLaneChangeConfig",
    "DoubleLaneChangeEnv",
    "DoubleLaneChangeModel",
    "DoubleLaneChangeReference",
    "DoubleLaneChangeVectorEnv",
    "TrackingResult",
    "VehicleDynamics",
    "VehicleParams",
    "evaluate_tracking",
    "fiala_lateral_force",
    "make_config",
]

#: Gymnasium id of the double-lane-change environment.
ENV_ID = "mixedrl/DoubleLaneChange-v0"

if ENV_ID not in gym.registry:
    gym.register(id=ENV_ID, entry_point="mixedrl.envs.dlc_env:DoubleLaneChangeEnv")
