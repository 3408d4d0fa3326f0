"""Double-lane-change tracking: the shared model ``f`` (eqs. 53-54), cost, noise and a torch vector env.

How the reference enters (EQUATIONS.md, point 11)
-------------------------------------------------
Eq. (53) is kept literally as the body dynamics, in a road-fixed frame: ``phi`` is the yaw angle and
``y = Y`` the lateral position of the centre of gravity, so ``dY/dt = v_x sin(phi) + v_y cos(phi)`` is
eq. (53)'s last row. The longitudinal position ``X`` is added, ``dX/dt = v_x cos(phi) - v_y sin(phi)``,
and the deterministic *tracking state* is

.. math:: s = [v_y,\\ r,\\ v_x,\\ \\phi,\\ Y,\\ X] \\quad (6 \\text{ components; the first five obey eq. 53}).

The reference (:class:`~mixedrl.envs.reference.DoubleLaneChangeReference`) never enters the dynamics;
it enters only through the relative quantities that the paper calls ``y`` and ``phi``,

.. math:: e_y = Y - Y_{ref}(X), \\qquad e_\\phi = \\phi - \\psi_{ref}(X),

which appear in the policy's observation and in the cost (eq. 54). The environment that makes data
and the model that plans call the same :class:`~mixedrl.envs.vehicle.VehicleDynamics`; the only
difference is the additive noise ``xi = F_dis T / m`` on ``v_x`` (index :data:`NOISE_INDEX`).

One true step
-------------
The true environment, ``s' = f(s, u) + E xi`` (eq. 1 for this task), is written once:
:meth:`DoubleLaneChangeModel.true_step`. Training (:meth:`mixedrl.envs.dlc_task.DoubleLaneChangeTask.true_step`),
:class:`DoubleLaneChangeVectorEnv`, the Gymnasium env (:mod:`mixedrl.envs.dlc_env`) and the Table I
evaluation (:func:`~mixedrl.envs.evaluate_tracking`, which drives the Gymnasium env) all call it; each
keeps its own random stream (see the method's Notes).

The column functions :func:`tracking_errors`, :func:`observation_columns`,
:func:`observation_from_errors` and :func:`stage_cost` compute the errors, the observation and the
cost of eq. (54) on Python floats, numpy arrays or torch tensors; the model and the Gymnasium env share
them.

Where each part lives
---------------------
This module gathers the double lane change's public names; each idea has its own module:

* :mod:`mixedrl.envs.disturbance`: the true force :class:`Disturbance` and its laws;
* :mod:`mixedrl.envs.dlc_config`: the configuration, :class:`DoubleLaneChangeConfig` (the environment)
  and :class:`~mixedrl.envs.dlc_config.DoubleLaneChangeTaskConfig` (a run's ``task``), :func:`make_config`;
* :mod:`mixedrl.envs.columns`: the column functions;
* :mod:`mixedrl.envs.model`: :class:`DoubleLaneChangeModel` and the dimensions :data:`NOISE_INDEX`,
  :data:`STATE_DIM`, :data:`ACTION_DIM`;
* :mod:`mixedrl.envs.vector_env`: :class:`DoubleLaneChangeVectorEnv`.
"""

from mixedrl.envs.columns import observation_columns, observation_from_errors, stage_cost, tracking_errors
from mixedrl.envs.disturbance import Disturbance
from mixedrl.envs.dlc_config import CostWeights, DoubleLaneChangeConfig, DoubleLaneChangeTaskConfig, make_config
from mixedrl.envs.model import ACTION_DIM, NOISE_INDEX, STATE_DIM, DoubleLaneChangeModel
from mixedrl.envs.vector_env import DoubleLaneChangeVectorEnv

__all__ = ["CostWeights", "Disturbance", "DoubleLaneChangeConfig", "DoubleLaneChangeModel",
           "DoubleLaneChangeTaskConfig", "DoubleLaneChangeVectorEnv", "NOISE_INDEX", "STATE_DIM", "ACTION_DIM",
           "make_config", "observation_columns", "observation_from_errors", "stage_cost", "tracking_errors"]
