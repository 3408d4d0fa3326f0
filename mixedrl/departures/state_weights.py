"""Departure hook *state weights*: PEV and PIM weight the states of the batch by their relative error.

The paper's eqs. (50) and (52) average over the batch: every state counts alike (``"uniform"``). With
``"relative"`` PEV squares the relative TD error ``(V - V_target) / (|V_target| + c)`` and PIM weights state
``x`` by ``1 / (V(x) + c)`` (batch mean 1), ``c = algorithm.batch_weight_offset * task.value_scale``
(:func:`mixedrl.pev.critic_loss`, :func:`mixedrl.pim.actor_objective`). The offset is in the task's value
units, so the weights do not change when the cost is rescaled; states near the reference, whose values are
small, are fitted as precisely in relative terms as far ones.

Config key ``algorithm.batch_weighting``: default ``"relative"`` (``batch_weight_offset`` 0.3), the paper's
``"uniform"``. Measured effect: docs/tuning.rst ("The generic defaults, measured") and docs/algorithm2.rst.
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
