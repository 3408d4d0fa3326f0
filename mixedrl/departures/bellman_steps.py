"""Departure hook *Bellman steps*: PEV's target and PIM's objective look ``n`` model steps ahead.

The paper's ``h`` (eq. 37) is one model step and the critic at the next state. With
``algorithm.bellman_steps = n > 1`` both PEV and PIM use the ``n``-step ``h_n`` (:func:`mixedrl.pev.h_steps`:
``n`` steps of the planning model under the actor, then the critic), the gradient of PIM back-propagated
through the whole rollout. Measured effect (docs/tuning.rst): not a default; kept for the study that
measured it.
"""

from __future__ import annotations

from typing import Any

from mixedrl.config import PAPER_SETTINGS

NAME = "bellman_steps"
KEY = "algorithm.bellman_steps"
PAPER = PAPER_SETTINGS["algorithm"]["bellman_steps"]


def active(config: Any) -> bool:
    """Whether ``h`` looks more than one step ahead."""
    return config.algorithm.bellman_steps != PAPER


def steps(config: Any) -> int:
    """The hook of PEV and PIM: the model steps of ``h``."""
    return config.algorithm.bellman_steps
