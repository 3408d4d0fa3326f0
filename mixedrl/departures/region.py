"""Departure hook *region starts*: the rollout departure's start states drawn over the task's whole state region,
half of them carried over from earlier rollouts.

With the rollout departure (:mod:`.rollout`, ``algorithm.rollout_horizon = H > 0``) the ``H``-step rollouts of
PEV and PIM start from the sampler's batch (states of the model rollouts that restart from the training
distribution ``sample_initial``). With ``algorithm.rollout_region = rho > 0`` each run's ``B`` start states
(``B = algorithm.batch_size``) are instead, every iteration (:func:`starts`),

* ``B - n_c`` states drawn afresh from the task's whole state region, ``task.sample_region(n, generator)``
  (:meth:`mixedrl.task_base.Task.sample_region`; by default the training distribution ``sample_initial``), and
* ``n_c = round((1 - rho) B)`` end states ``x_H`` of the previous iteration's rollouts, a random subset drawn
  with the run's generator (:func:`remember`); non-finite and terminal ones are dropped (their rows are drawn
  from the region). The first iteration, and a run resumed from a checkpoint (the carried states are not part
  of it), start from the region alone.

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
"""

from __future__ import annotations

from typing import Any, Sequence

import torch

from mixedrl.config import PAPER_SETTINGS

NAME = "region_starts"
KEY = "algorithm.rollout_region"
PAPER = PAPER_SETTINGS["algorithm"]["rollout_region"]

__all__ = ["NAME", "KEY", "PAPER", "active", "carried", "starts", "remember"]


def active(config: Any) -> bool:
    """Whether the rollouts start from region draws and carried states (``algorithm.rollout_region > 0``)."""
    return config.algorithm.rollout_region != PAPER


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
        The sampler's batch: returned as it is when the departure is off, and the rows of an inactive run.
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
    if not active(engine.members[0].config):
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
    if not active(engine.members[0].config):
        return
    for r in active_runs:
        m = engine.members[r]
        x = ends[engine.rows(r)].detach()
        pick = torch.randperm(x.shape[0], generator=m.generator)[:carried(m.config, x.shape[0])]
        x = x[pick]
        m.region_carry = x[~engine.task.is_terminal(x)].clone()
