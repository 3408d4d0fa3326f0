"""Departure hook *state weights*: PEV and PIM weight the states of the batch by their relative error.

The paper's eqs. (50) and (52) average over the batch: every state counts alike (``algorithm.batch_weighting
= "uniform"``). With ``"relative"`` (the library default) PEV squares the relative TD error
``(V - V_target) / (|V_target| + c)`` and PIM weights state ``x`` by ``1 / (V(x) + c)`` (batch mean 1),
``c = algorithm.batch_weight_offset * task.value_scale`` (:func:`mixedrl.pev.critic_loss`,
:func:`mixedrl.pim.actor_objective`): the offset is given in the task's value units, so the weights do not change
when the cost is rescaled.
Measured effect (docs/tuning.rst): states near the reference, whose values are small, are fitted as
precisely in relative terms as far ones; on the double lane change the course errors fall. With the rollout
learner (``experiments/results/learner_tuning/table.md``, variant ``swing_cri_h16_rv03``, seeds 100-102): at
``c = 0.3 value_scale`` the swing-up's return IQM is -138.4 to -139.8 and the fast slalom's course cost 22.5-23.2
(its reference 22.4); with uniform weights the slalom costs 51.3, and no offset in absolute units did both
(``c = 3``: the swing-up fails on 2 of 3 seeds; ``c = 30``: the slalom costs 28-29).
"""

from __future__ import annotations

from typing import Any
from mixedrl.config import PAPER_SETTINGS

NAME = "state_weights"
KEY = "algorithm.batch_weighting"
PAPER = PAPER_SETTINGS["algorithm"]["batch_weighting"]


def active(config: Any) -> bool:
    """Whether the batch is weighted (``algorithm.batch_weighting != "uniform"``)."""
    return config.algorithm.batch_weighting != PAPER


def offset(config: Any, value_scale: float = 1.0) -> float | None:
    """The hook of PEV and PIM: ``c`` of the relative weights, or ``None`` (the paper's batch mean).

    Parameters
    ----------
    config : TrainConfig
    value_scale : float
        The task's ``value_scale``: ``c = algorithm.batch_weight_offset * value_scale``.

    Returns
    -------
    float or None
    """
    return config.algorithm.batch_weight_offset * float(value_scale) if active(config) else None
