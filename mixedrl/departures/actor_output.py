"""Departure hook *actor output*: the actor's action bounded by a clip, not a ``tanh``.

The library's actor (eq. 48) is ``u = u_bar tanh(MLP(o; theta))``. With ``"clip_inward"`` it is
``u = u_bar clip(MLP(o; theta), -1, 1)`` (:class:`mixedrl.networks.ClippedActor`), and the clip's gradient is
passed straight through for the actor's **parameters only**: ``du/dtheta = u_bar dMLP/dtheta`` also where the
output is clipped and the descent step moves it back inside (``dJ/dz * z > 0``: a saturated actor still receives
the gradient that pulls it back, and cannot wind up), while ``du/do`` is the clip's true derivative, zero where
clipped (a straight-through gradient for the states of a rollout, :mod:`.rollout`, diverges). The action's
value is exactly the clip's. With ``H``-step rollouts on a global task a saturated
``tanh`` output has a vanishing gradient and the policy sets into bang-bang control.

Config key ``algorithm.actor_output``: default ``"clip_inward"``, the paper's ``"tanh"``. Algorithm 2 only
(``R >= 1`` stacked runs train it; DDPG refuses it). Measured effect: docs/algorithm2.rst and
``experiments/results/learner_tuning/table.md``. Retired (refused naming the commit,
:data:`mixedrl.config.RETIRED_ACTOR_OUTPUTS`): ``"clip"``, straight through in both directions (it winds up;
commit c44231f still runs it).
"""

from __future__ import annotations

from typing import Any

from mixedrl.config import PAPER_SETTINGS

NAME = "actor_output"
KEY = "algorithm.actor_output"
PAPER = PAPER_SETTINGS["algorithm"]["actor_output"]

__all__ = ["NAME", "KEY", "PAPER", "active"]


def active(config: Any) -> bool:
    """Whether the actor's output is clipped (``algorithm.actor_output = "clip_inward"``) instead
    of ``tanh``-squashed: Algorithm 2's actor only (DDPG trains its ``tanh`` actor)."""
    return config.algorithm.actor_output != PAPER and config.method != "ddpg"
