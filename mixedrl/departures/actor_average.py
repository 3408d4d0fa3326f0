"""Departure hook *averaging*: the policy evaluated and deployed is an average of the actor's weights.

The paper deploys the last actor ``pi(x; theta^K)``. With ``algorithm.actor_average = beta > 0`` the run
keeps the exponential moving average ``theta_bar <- beta theta_bar + (1 - beta) theta^{k+1}`` (updated at
the end of every iteration, :func:`end`) and evaluates and deploys ``pi(x; theta_bar)``
(:attr:`mixedrl.algorithms.agpi.AGPI.learned_policy`); training itself is unchanged. Measured effect
(docs/tuning.rst): smooths the last iterates' seed-to-seed scatter; not a default.
"""

from __future__ import annotations

from typing import Any

import torch
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

from mixedrl.config import PAPER_SETTINGS

NAME = "actor_average"
KEY = "algorithm.actor_average"
PAPER = PAPER_SETTINGS["algorithm"]["actor_average"]


def active(config: Any) -> bool:
    """Whether the deployed policy is the weight average."""
    return config.algorithm.actor_average > 0


def make(actor: torch.nn.Module, config: Any) -> AveragedModel | None:
    """The run's average actor, or ``None`` (the paper's: the last actor)."""
    if not active(config):
        return None
    return AveragedModel(actor, multi_avg_fn=get_ema_multi_avg_fn(config.algorithm.actor_average), use_buffers=True)


def end(run: Any) -> None:
    """The hook at the end of the iteration: ``theta_bar <- beta theta_bar + (1 - beta) theta^{k+1}``."""
    if run.actor_avg is not None:
        run.actor_avg.update_parameters(run.actor)
