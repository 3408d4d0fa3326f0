"""Departure hook *region starts*: the rollout departure's start states drawn over the task's whole state region,
half of them carried over from earlier rollouts.

With the rollout departure (:mod:`.rollout`, ``algorithm.rollout_horizon = H > 0``) the ``H``-step rollouts of
PEV and PIM start from the sampler's batch (states of the model rollouts that restart from the training
distribution ``sample_initial``). With ``algorithm.rollout_region = rho > 0``, on a task that declares a state
region of its own (:meth:`mixedrl.task_base.Task.declares_region`: it overrides ``sample_region``), each run's
``B`` start states (``B = algorithm.batch_size``) are instead, every iteration (:func:`starts`),

* ``B - n_c`` states drawn afresh from the task's whole state region, ``task.sample_region(n, generator)``
  (:meth:`mixedrl.task_base.Task.sample_region`), and
* ``n_c = round((1 - rho) B)`` end states ``x_H`` of the previous iteration's rollouts, a random subset drawn
  with the run's generator (:func:`remember`); non-finite and terminal ones are dropped (their rows are drawn
  from the region). The first iteration starts from the region alone; the carried states are part of the
  run's checkpoint (``region_carry``), so a resumed run is the uninterrupted one.

A task that declares no region (its training distribution is where its policy must act: an equilibrium's
neighbourhood, a course) keeps the sampler's batch: the setting is a no-op there (:func:`applies`).

The carried states put the rollouts where the current policy takes the system (for a swing-up: near the top,
at ``2 H, 3 H, ..`` steps from a start), the region samples everywhere the critic will be asked about. The
sampler's batch still feeds the MVC check and the stopping test; the true transitions of mixed RL are the
sampler's as before. Applied identically to mixed RL, model-driven RL and the oracle (every draw from the
run's own generator, so the same seed gives the same run); ``R >= 1`` stacked runs (each run its rows and its
carried states). A state-dependent noise source (``ibe_case = 3``, a road grade) is refused: its planning mean
is taken at the sampler's states.

Measured effect (``experiments/results/learner_tuning/table.md``, mixed RL, seeds 100-102, variant ``swing_cri``
against ``swing_cri_noregion``, the same without it): on SwingUp (region ``theta in [-pi, pi]``, ``theta_dot in
[-8, 8]``) a return IQM of -135.5, -136.4, -136.8 against -137.6, -134.2, -142.7: a small effect, mostly on the
worst seed (the energy-pumping + LQR reference: -125.8). Near an equilibrium, where the region is the training
distribution itself, the evaluated cost over the discounted LQR with the true feed-forward is 0.959-0.961 against
0.961-0.962 on the cart with friction and 0.999 against 1.000-1.001 on the two tanks (steady offsets within issue
42's tolerance: cart 3 of 3 either way, tanks 0 of 3 either way).

Why only a task that declares a region: before, a task without one drew its region starts from ``sample_initial``.
With the candidate learner (``swing_cri_h16_rv03``: ``H = 16``, relative weights ``c = 0.3`` value_scale) those
starts against none (``swing_cri_h16_rv03_nr``), seeds 100-102: the cart's offset within tolerance on 2 of 3 against
3 of 3 (cost over the LQR 0.9595-0.961 against 0.960-0.962), the fast slalom's course cost 22.5-23.2 against
23.3-23.7, the two tanks 0.999 against 1.000; on the double lane change (held-out seeds 100-102, a feasibility check,
:file:`experiments/studies/learner_dlc_heldout_rv03_diag.toml`), whose ``sample_initial`` spreads wide tracking
errors along the whole course, the course cost rose to 37.4 +- 3.1 against 22.0 +- 1.2 without them (the library
defaults: 23.8 +- 3.4). The swing-up without its region: -164.6 to -171.0 against -138.4 to -139.8.
"""

from __future__ import annotations

from typing import Any, Sequence

import torch

from mixedrl.config import PAPER_SETTINGS

NAME = "region_starts"
KEY = "algorithm.rollout_region"
PAPER = PAPER_SETTINGS["algorithm"]["rollout_region"]

__all__ = ["NAME", "KEY", "PAPER", "active", "applies", "carried", "starts", "remember"]


def active(config: Any) -> bool:
    """Whether the setting is on: ``algorithm.rollout_region > 0`` with the rollouts (``rollout_horizon > 0``)."""
    return config.algorithm.rollout_region != PAPER and config.algorithm.rollout_horizon > 0 and config.method != "ddpg"


def applies(config: Any, task: Any) -> bool:
    """Whether the region starts change this run: the setting is on (:func:`active`) and ``task`` declares a
    state region (:meth:`mixedrl.task_base.Task.declares_region`)."""
    return active(config) and task.declares_region()


def carried(config: Any, batch: int) -> int:
    """How many of a run's ``batch`` start states are carried over: ``round((1 - rollout_region) batch)``.

    Parameters
    ----------
    config : TrainConfig
    batch : int

    Returns
    -------
    int
    """
    return int(round((1.0 - config.algorithm.rollout_region) * batch))


def starts(engine: Any, s: torch.Tensor, active_runs: Sequence[int]) -> torch.Tensor:
    """The rollouts' start states of every run: its carried states (:func:`remember`) topped up with region draws.

    Parameters
    ----------
    engine : BatchedAGPI
        The runs (``members``, ``task``, :meth:`rows`).
    s : torch.Tensor, shape (R B, state_dim)
        The sampler's batch: returned as it is when the departure does not apply (:func:`applies`), and the rows
        of an inactive run.
    active_runs : sequence of int
        The runs that iterate (only they draw from their generators).

    Returns
    -------
    torch.Tensor, shape (R B, state_dim)
        Of ``s``'s dtype; run ``r`` in :meth:`engine.rows(r)`.

    Raises
    ------
    ValueError
        A run's noise source is state-dependent (its planning mean is taken at the sampler's states).
    """
    if not applies(engine.members[0].config, engine.task):
        return s
    parts = []
    for r, m in enumerate(engine.members):
        rows = s[engine.rows(r)]
        if r not in active_runs:
            parts.append(rows)
            continue
        if m.noise.state_dependent:
            raise ValueError(f"{KEY}: the region starts need a state-independent noise source; run {r} "
                             f"({m.config.method}) has a state-dependent one")
        kept = getattr(m, "region_carry", None)
        kept = rows[:0] if kept is None else kept.to(rows.dtype)
        fresh = engine.task.sample_region(rows.shape[0] - kept.shape[0], m.generator).to(rows.dtype)
        parts.append(torch.cat([fresh, kept]))
    return torch.cat(parts)


def remember(engine: Any, ends: torch.Tensor, active_runs: Sequence[int]) -> None:
    """Keep ``carried`` of each active run's rollout end states for the next iteration's :func:`starts`.

    A random subset (``torch.randperm`` from the run's generator) of the finite, non-terminal end states,
    stored detached on the run (``run.region_carry``).

    Parameters
    ----------
    engine : BatchedAGPI
    ends : torch.Tensor, shape (R B, state_dim)
        The states ``x_H`` of the iteration's last rollout.
    active_runs : sequence of int
    """
    if not applies(engine.members[0].config, engine.task):
        return
    for r in active_runs:
        m = engine.members[r]
        x = ends[engine.rows(r)].detach()
        pick = torch.randperm(x.shape[0], generator=m.generator)[:carried(m.config, x.shape[0])]
        x = x[pick]
        m.region_carry = x[~engine.task.is_terminal(x)].clone()
