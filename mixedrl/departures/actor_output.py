"""Departure hook *actor output*: the actor's action bounded by a clip, not a ``tanh``.

The library's actor (eq. 48) is ``u = u_bar tanh(MLP(o; theta))``. With ``algorithm.actor_output = "clip"`` or
``"clip_inward"`` it is ``u = u_bar clip(MLP(o; theta), -1, 1)`` (:class:`mixedrl.networks.ClippedActor`), and the
clip's gradient is passed straight through for the actor's **parameters only**: ``du/dtheta = u_bar dMLP/dtheta``
also where the output is clipped (so a saturated actor still receives the gradient that pulls it back), while
``du/do`` is the clip's true derivative, zero where clipped (the gradient through a rollout's states,
:mod:`.rollout`, is the model's). ``"clip"`` passes it straight through in both directions; ``"clip_inward"``
only where the descent step moves the clipped output back inside (``dJ/dz * z > 0``), so a saturated output
cannot wind up. The value of the action is exactly the clip's. Applied identically to mixed RL, model-driven RL
and the oracle; ``R >= 1`` stacked runs train it (the stacked call is the module's own ``forward``,
:class:`mixedrl.algorithms.batched.StackedNetwork`); DDPG refuses it.

Why: with ``H``-step rollouts on a global task the gradient of a ``tanh`` output vanishes where it saturates and
the policy sets into bang-bang control; passing the clip's gradient straight through for the state as well
diverges (the feasibility note of issue 42: gradient norms to 1e11), hence the parameters only.

Measured effect (``experiments/results/learner_tuning/table.md``, SwingUp, mixed RL, variant ``swing_cri``: ``H =
32``, 800 iterations, batch 256, tanh hidden layers, uniform state weights, ``j_max = 1``, region starts 0.5):
``"clip_inward"`` reaches a return IQM of -135.5, -136.4, -136.8 on seeds 100-102 (the energy-pumping + LQR
reference that knows the torque: -125.8); the same with ``"tanh"``: -605.4 (seed 100); with the two-sided
``"clip"``: -1174.4 (seed 100), the MLP's output winding up to ``|z|`` about 16 within 200 iterations (bang-bang
everywhere) and never coming back. Near an equilibrium the same setting gives a cost over the discounted LQR of
0.959-0.961 on the cart with friction and 0.999 on the two tanks (seeds 100-102).
"""

from __future__ import annotations

from typing import Any

from mixedrl.config import PAPER_SETTINGS

NAME = "actor_output"
KEY = "algorithm.actor_output"
PAPER = PAPER_SETTINGS["algorithm"]["actor_output"]

__all__ = ["NAME", "KEY", "PAPER", "active"]


def active(config: Any) -> bool:
    """Whether the actor's output is clipped (``algorithm.actor_output`` ``"clip"`` or ``"clip_inward"``) instead
    of ``tanh``-squashed: Algorithm 2's actor only (DDPG trains its ``tanh`` actor)."""
    return config.algorithm.actor_output != PAPER and config.method != "ddpg"
