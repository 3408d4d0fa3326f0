"""Departure hook *averaged actor*: the deployed policy takes the average of the actor's late weights.

The paper deploys the actor of the last iteration, ``pi(x; theta^K)``. With ``algorithm.actor_average_window = a > 0``
the run also keeps ``theta_bar``, the uniform average of the weights ``theta^{k+1}`` after every iteration
``k >= start = K - round(a K)`` of its budget ``K`` (stochastic weight averaging: Izmailov et al., *Averaging
weights leads to wider optima and better generalization*, UAI 2018; :class:`torch.optim.swa_utils.AveragedModel`),
updated at the end of each of those iterations (:func:`end`). From its first update on, the run's learned policy
(what is evaluated, deployed and shifted by the anchor: :attr:`mixedrl.algorithms.agpi.AGPI.learned_policy`) is
``pi(x; theta_bar)`` (:func:`policy`). Training is unchanged: PEV, PIM, the MVC and the sampler work on ``theta``.

A run that stops (its stopping test) before ``start`` deploys ``theta``. The average restarts when ``k`` reaches
``start``, so a run resumed with a longer budget averages the new budget's window if it had not reached it; a run
already past it keeps its average and continues it.

Config key ``algorithm.actor_average_window``: default 0.5, the paper's 0 (the last actor). Measured effect:
docs/tuning.rst, "One seed against another".
"""

from __future__ import annotations

from typing import Any

import torch
from torch.optim.swa_utils import AveragedModel

from mixedrl.config import PAPER_SETTINGS

NAME = "actor_average"
KEY = "algorithm.actor_average_window"
PAPER = PAPER_SETTINGS["algorithm"]["actor_average_window"]


def active(config: Any) -> bool:
    """Whether the run deploys an average of its actor's weights (Algorithm 2 only)."""
    return config.algorithm.actor_average_window > 0 and config.method != "ddpg"


def start(config: Any) -> int:
    """The first iteration ``k`` whose weights ``theta^{k+1}`` join the average: ``K - round(a K)``."""
    budget = config.algorithm.iterations
    return budget - int(round(config.algorithm.actor_average_window * budget))


def make(actor: torch.nn.Module, config: Any) -> AveragedModel | None:
    """The run's averaged actor (an :class:`~torch.optim.swa_utils.AveragedModel` of ``actor``, uniform
    weights, no gradient; empty until :func:`start`), or ``None`` (the paper's: the last actor)."""
    if not active(config):
        return None
    average = AveragedModel(actor)
    average.requires_grad_(False)
    return average


def end(run: Any) -> None:
    """The hook at the end of iteration ``k`` (before ``k`` is incremented): from :func:`start` on,
    ``theta_bar <- (n theta_bar + theta^{k+1}) / (n + 1)``; at ``k = start`` the average restarts from
    ``theta^{k+1}``."""
    average = getattr(run, "actor_average", None)
    if average is None:
        return
    first = start(run.config)
    if run.k < first:
        return
    if run.k == first:
        average.n_averaged.zero_()
    average.update_parameters(run.actor)


def policy(run: Any) -> torch.nn.Module:
    """The run's learned policy: the averaged actor once it holds a weight, else the actor."""
    average = getattr(run, "actor_average", None)
    if average is None or int(average.n_averaged) == 0:
        return run.actor
    return average.module
