"""Departure hook *schedule*: the learning rates decay linearly, and the steps are Adam's, clipped.

The paper's eqs. (50) and (52) take plain gradient steps of fixed size. The library takes Adam steps with the
gradient norm clipped at ``algorithm.grad_clip``, at rates decayed linearly from ``critic_lr`` / ``actor_lr``
to ``lr_decay_to`` times them over ``lr_decay_iterations`` (:func:`mixedrl.schedule.lr_factor`). Measured
effect (docs/tuning.rst): without the decay the last iterates keep moving by the step size and the course
errors of the final policies scatter more from seed to seed; the decay makes them settle.

Active when ``algorithm.lr_decay_to != 1`` (the rates change over the run). Adam and the clip are the
optimiser of every run (the paper's plain step is not offered).
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
