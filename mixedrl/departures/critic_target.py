"""Departure hook *target values*: PEV's target takes a slowly moving copy of the critic.

The paper's eq. (50) computes ``V_target = l(x', u) + gamma V^k(x'; w)`` with the critic itself. With
``algorithm.critic_target = beta > 0`` the network inside ``V_target`` is ``V(x'; w_bar)``, the exponential
moving average ``w_bar <- beta w_bar + (1 - beta) w^{k+1}`` of the critic's weights, updated at the end of
every iteration (:func:`end`).

Config key ``algorithm.critic_target``: default 0.8, the paper's 0 (the critic itself). Measured effect:
docs/algorithm2.rst and docs/precision.rst.
"""

from __future__ import annotations

from typing import Any

import torch
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

from mixedrl.config import PAPER_SETTINGS

NAME = "critic_target"
KEY = "algorithm.critic_target"
PAPER = PAPER_SETTINGS["algorithm"]["critic_target"]


def active(config: Any) -> bool:
    """Whether PEV's target uses the average critic (Algorithm 2 only: DDPG has its own target networks,
    ``ddpg.tau``)."""
    return config.algorithm.critic_target > 0 and config.method != "ddpg"


def make(critic: torch.nn.Module, config: Any) -> AveragedModel | None:
    """The run's target critic (an :class:`~torch.optim.swa_utils.AveragedModel` of ``critic``, no gradient),
    or ``None`` (the paper's: the critic itself)."""
    if not active(config):
        return None
    target = AveragedModel(critic, multi_avg_fn=get_ema_multi_avg_fn(config.algorithm.critic_target),
                           use_buffers=True)
    target.requires_grad_(False)
    return target


def end(run: Any) -> None:
    """The hook at the end of the iteration: ``w_bar <- beta w_bar + (1 - beta) w^{k+1}``."""
    if run.critic_target is not None:
        run.critic_target.update_parameters(run.critic)
