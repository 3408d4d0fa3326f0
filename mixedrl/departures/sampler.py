"""Departure hook *sampler*: where the batch of PEV and PIM comes from.

The paper's Algorithm 2 steps ``batch_size`` copies of the true environment once per iteration under the
current policy; their states are the batch and their residuals feed the IBE (``"true_copies"``,
:meth:`mixedrl.algorithms.agpi.AGPI.collect`). A model-rollout sampler takes the batch from rollouts of the
planning model ``f + E xi_hat`` and drives a few true copies for the IBE (``"model_rollouts"``,
:class:`mixedrl.algorithms.model_data.ModelStateSampler`; a task may register its own, as the double lane
change's course sampler, :mod:`mixedrl.envs.dlc_task`).

Config key ``sampler.name``: default ``"model_rollouts"`` (the double lane change: ``"dlc_course"``), the
paper's ``"true_copies"``. Measured effect: docs/algorithm2.rst and docs/model_based.rst.
"""

from __future__ import annotations

from typing import Any

from mixedrl.config import PAPER_SETTINGS

NAME = "sampler"
KEY = "sampler.name"
PAPER = PAPER_SETTINGS["sampler"]["name"]


def active(config: Any) -> bool:
    """Whether the batch comes from another sampler than the paper's true copies."""
    return config.sampler.name != PAPER


def collect(run: Any) -> tuple[Any, Any]:
    """The data hook: the run's batch ``x`` (float32, (B, state_dim)) and the residuals ``xi^D`` (eq. 10)
    of its true transitions this iteration (float64, (M, noise_dim))."""
    return run.collect()
