"""The library's departures from the paper's Algorithm 2, each a plug-in at a named hook of the loop.

:func:`mixedrl.algorithms.algorithm2.iteration` is the paper's loop; where the library departs from it, the
loop calls a hook, and each hook lives in one module of this folder, which says what it does, its config key,
its default and where its measured effect is documented. Every hook is applied the same way to mixed RL,
model-driven RL and the oracle (the noise source is the only difference between them).

=====================  ===========================================  ==========================================
hook                   module                                       where the loop calls it
=====================  ===========================================  ==========================================
schedule               :mod:`~mixedrl.departures.schedule`          start of the iteration (learning rates)
anchor                 :mod:`~mixedrl.departures.anchor`            ``AGPI.policy``; after PIM (trained box)
anchor (calibration)   :mod:`~mixedrl.departures.calibration`       ``AGPI.policy`` (the shift corrected)
sampler                :mod:`~mixedrl.departures.sampler`           data (the batch and the true transitions)
state weights          :mod:`~mixedrl.departures.state_weights`     PEV and PIM (per-state weights)
target values          :mod:`~mixedrl.departures.critic_target`     PEV (the network inside ``V_target``)
rollouts               :mod:`~mixedrl.departures.rollout`           PEV and PIM (``H``-step model rollouts)
region starts          :mod:`~mixedrl.departures.region`            PEV and PIM (the rollouts' start states)
actor output           :mod:`~mixedrl.departures.actor_output`      the actor's class (clip, not ``tanh``)
=====================  ===========================================  ==========================================

:func:`used` lists the departures a configuration switches on (written to a run's ``results.json`` as
``departures``); :data:`DEPARTURES` holds, per departure, its dotted key, the paper's value and the module.
"""

from __future__ import annotations

from typing import Any

from mixedrl.departures import (actor_output, anchor, critic_target, region, rollout, sampler, schedule,
                                state_weights)

__all__ = ["DEPARTURES", "used", "actor_output", "anchor", "critic_target", "region", "rollout", "sampler", "schedule",
           "state_weights"]

#: Every departure module, in the order of the loop.
DEPARTURES = (schedule, anchor, actor_output, sampler, state_weights, critic_target, region, rollout)


def used(config: Any) -> list[str]:
    """The names of the departures ``config`` (a :class:`mixedrl.config.TrainConfig` of Algorithm 2) switches
    on, in the order of the loop (``[]``: the paper's Algorithm 2)."""
    return [d.NAME for d in DEPARTURES if d.active(config)]
