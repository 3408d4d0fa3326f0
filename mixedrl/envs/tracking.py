"""Double-lane-change tracking: the shared model ``f`` (eqs. 53-54), cost, noise and a torch vector env.

This module gathers the public names of :mod:`mixedrl.envs.disturbance`, :mod:`mixedrl.envs.dlc_config`,
:mod:`mixedrl.envs.columns`, :mod:`mixedrl.envs.model` and :mod:`mixedrl.envs.vector_env`.

The tracking state is ``s = [v_y, r, v_x, phi, Y, X]``: eq. (53) in the road-fixed frame plus the
longitudinal position. The reference never enters the dynamics, only the errors that the paper calls
``y`` and ``phi`` (docs/vehicle.rst, "The tracking state"):

.. math:: e_y = Y - Y_{ref}(X), \\qquad e_\\phi = \\phi - \\psi_{ref}(X).

The true step ``s' = f(s, u) + E xi`` (eq. 1) is written once, :meth:`DoubleLaneChangeModel.true_step`.
"""

from mixedrl.envs.columns import observation_columns, observation_from_errors, stage_cost, tracking_errors
from mixedrl.envs.disturbance import Disturbance
from mixedrl.envs.dlc_config import CostWeights, DoubleLaneChangeConfig, DoubleLaneChangeTaskConfig, make_config
from mixedrl.envs.model import ACTION_DIM, NOISE_INDEX, STATE_DIM, DoubleLaneChangeModel
from mixedrl.envs.vector_env import DoubleLaneChangeVectorEnv

__all__ = ["CostWeights", "Disturbance", "DoubleLaneChangeConfig", "DoubleLaneChangeModel",
           "DoubleLaneChangeTaskConfig", "DoubleLaneChangeVectorEnv", "NOISE_INDEX", "STATE_DIM", "ACTION_DIM",
           "make_config", "observation_columns", "observation_from_errors", "stage_cost", "tracking_errors"]
