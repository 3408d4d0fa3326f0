"""Departure hook *actor output*: the actor's action bounded by a clip, not a ``tanh``.

The library's actor (eq. 48) is ``u = u_bar tanh(MLP(o; theta))``. With ``algorithm.actor_output = "clip"`` it
is ``u = u_bar clip(MLP(o; theta), -1, 1)`` (:class:`mixedrl.networks.ClippedActor`), and the clip's gradient
is passed straight through for the actor's **parameters only**: ``du/dtheta = u_bar dMLP/dtheta`` also where the
output is clipped (so a saturated actor still receives the gradient that pulls it back), while ``du/do`` is the
clip's true derivative, zero where clipped (the gradient through a rollout's states, :mod:`.rollout`, is
the model's). The value of the action is exactly the clip's. Applied identically to mixed RL, model-driven RL
and the oracle; ``R >= 1`` stacked runs train it (the stacked call is the module's own ``forward``,
:class:`mixedrl.algorithms.batched.StackedNetwork`); an anchored ``feedforward`` and DDPG refuse it.

Why: with ``H``-step rollouts on a global task the gradient of a ``tanh`` output vanishes where it saturates and
the policy sets into bang-bang control (the feasibility prototype of ``/work/shared/notes``: return -612 with
``2 tanh`` against about -167 clipped); passing the clip's gradient straight through for the state as well
diverged there (gradient norms to 1e11).

Measured effect (``experiments/results/learner_tuning/table.md``, SwingUp, seeds 100-102, mixed RL): see the
rollout departure's docstring (:mod:`.rollout`), variants ``swing_clip*``.
"""

from __future__ import annotations

from typing import Any

from mixedrl.config import PAPER_SETTINGS

NAME = "actor_output"
KEY = "algorithm.actor_output"
PAPER = PAPER_SETTINGS["algorithm"]["actor_output"]

__all__ = ["NAME", "KEY", "PAPER", "active"]


def active(config: Any) -> bool:
    """Whether the actor's output is clipped (``algorithm.actor_output = "clip"``) instead of ``tanh``-squashed."""
    return config.algorithm.actor_output != PAPER
