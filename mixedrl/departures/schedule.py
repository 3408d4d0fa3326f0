"""Departure hook *schedule*: the learning rates decay linearly.

The paper's eqs. (50) and (52) take gradient steps of fixed size. Here the rates decay linearly from
``critic_lr`` / ``actor_lr`` to ``lr_decay_to`` times them over ``lr_decay_iterations``
(:func:`mixedrl.schedule.lr_factor`), so that the last iterates settle.

Config key ``algorithm.lr_decay_to``: default 0.01, the paper's 1.0 (fixed rates). Every run takes Adam steps
with the gradient norm clipped at ``algorithm.grad_clip`` (the paper's plain step is not offered). Measured
effect: docs/algorithm2.rst (the table of the paper's settings) and docs/tuning.rst.
"""

from __future__ import annotations

from typing import Any

from mixedrl.config import PAPER_SETTINGS
from mixedrl.schedule import set_learning_rates

NAME = "schedule"
KEY = "algorithm.lr_decay_to"
PAPER = PAPER_SETTINGS["algorithm"]["lr_decay_to"]


def active(config: Any) -> bool:
    """Whether the rates decay (``algorithm.lr_decay_to != 1``)."""
    return config.algorithm.lr_decay_to != PAPER


def start(run: Any) -> None:
    """The hook at the start of iteration ``k``: the run's learning rates of iteration ``k``."""
    set_learning_rates(run.config, run.k, run.critic_opt, run.actor_opt)
