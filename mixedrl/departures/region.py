"""Departure hook *region starts*: the rollouts' start states drawn over the task's whole state region, the
rest carried over from earlier rollouts.

With the rollout departure (:mod:`.rollout`, ``algorithm.rollout_horizon = H > 0``) the ``H``-step rollouts of
PEV and PIM start from the sampler's batch. With ``algorithm.rollout_region = rho > 0``, on a task that
declares a state region of its own (:meth:`mixedrl.task_base.Task.declares_region`: it overrides
``sample_region``), each run's ``B = algorithm.batch_size`` start states are instead, every iteration
(:func:`starts`),

* ``B - n_c`` states drawn afresh from the task's whole state region, ``task.sample_region(n, generator)``
  (:meth:`mixedrl.task_base.Task.sample_region`), and
* ``n_c = round((1 - rho) B)`` end states ``x_H`` of the previous iteration's rollouts, a random subset drawn
  with the run's generator (:func:`remember`); non-finite and terminal ones are dropped (their rows are drawn
  from the region). The first iteration starts from the region alone; the carried states are part of the
  run's checkpoint (``region_carry``).

A task that declares no region (an equilibrium's neighbourhood, a course) keeps the sampler's batch: the
setting is a no-op there (:func:`applies`). The sampler's batch still feeds the MVC check, the stopping test
and the IBE. Every draw comes from the run's own generator; ``R >= 1`` stacked runs each have their rows and
carried states. A state-dependent noise source (``ibe_case = 3``) is refused: its planning mean is taken at
the sampler's states.

Config key ``algorithm.rollout_region``: default 0.5, the paper's 0. Measured effect: docs/tuning.rst ("A
global task declares its state region") and docs/algorithm2.rst.
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
    """How many of a run's ``batch`` start states are carried over: ``round((1 - rollout_region) batch)``."""
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
