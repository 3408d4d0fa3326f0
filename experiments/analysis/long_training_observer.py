"""What happens when Algorithm 2 trains longer than the reproduction's budget (docs/reproduction.rst,
"Longer training"): the observer of ``experiments/studies/long_training.toml``.

Every ``every`` iterations :class:`LongTrainingObserver` records, on the run's current policy,

* the Table I errors and the total cost of the course (:meth:`DoubleLaneChangeTask.evaluate`, seeds 1, 2);
* ``J_train``: the discounted cost (gamma of the task, 400 steps, true noise) of the current policy from a
  fixed set of 1024 start states drawn from the *wide* training distribution (``sample_initial``);
* the policy at the origin of the observation (on the reference, at 12 m/s): its action ``pi(0)`` and its
  Jacobian ``d pi / d obs`` (the linear feedback gains).

The observer only evaluates (its own generators; nothing of the run is drawn or changed). The analysis
and the figure are ``experiments/analysis/long_training.py``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from mixedrl.config import TrainConfig
from mixedrl.runs import PeriodicObserver

__all__ = ["LongTrainingObserver", "long_training_observer", "discounted_cost", "policy_at_origin", "OBS_NAMES",
           "EVAL_SEEDS", "EVERY"]

#: The components of the policy's observation (the paper's relative state).
OBS_NAMES = ("v_y", "r", "v_x-12", "e_phi", "e_y")
#: The course seeds of the records.
EVAL_SEEDS = (1, 2)
#: Iterations between records in ``experiments/studies/long_training.toml``.
EVERY = 500


def discounted_cost(task: Any, actor: torch.nn.Module, starts: torch.Tensor, steps: int = 400,
                    seed: int = 999) -> float:
    """Mean over ``starts`` of ``sum_t gamma^t l(s_{t+1}, u_t)`` under the true noise (frozen after leaving)."""
    gen = torch.Generator().manual_seed(seed)
    s = starts.clone()
    total = torch.zeros(s.shape[0], dtype=torch.float64)
    alive = torch.ones(s.shape[0], dtype=torch.bool)
    with torch.no_grad():
        for t in range(steps):
            u = actor(task.observe(s.float())).double()
            s_next = task.true_step(s, u, gen)
            total += torch.where(alive, task.gamma**t * task.cost(s_next, u), torch.zeros_like(total))
            alive &= ~task.is_terminal(s_next)
            s = torch.where(alive[:, None], s_next, s)
    return float(total.mean())


def policy_at_origin(actor: torch.nn.Module, obs_dim: int) -> tuple[np.ndarray, np.ndarray]:
    """``pi(0)`` (action_dim,) and ``d pi / d obs`` at 0 (action_dim, obs_dim)."""
    jac = torch.autograd.functional.jacobian(lambda o: actor(o[None])[0], torch.zeros(obs_dim))
    with torch.no_grad():
        u0 = actor(torch.zeros(1, obs_dim))[0]
    return u0.numpy().astype(float), jac.numpy().astype(float)


class LongTrainingObserver(PeriodicObserver):
    """The records of the module docstring every ``every`` iterations, as ``long/...`` metrics of the row
    (a :class:`mixedrl.runs.PeriodicObserver`).

    Parameters
    ----------
    every : int
        Iterations between records (the row of iteration ``k`` with ``k % every == 0``).
    """

    def __init__(self, every: int = EVERY) -> None:
        super().__init__(every)
        self._starts: torch.Tensor | None = None

    def record(self, trainer: Any) -> dict[str, float]:
        """The records after iteration ``trainer.k``."""
        task = trainer.task
        if self._starts is None:
            self._starts = task.sample_initial(1024, torch.Generator().manual_seed(12345))
        ev = task.evaluate(trainer.policy, list(EVAL_SEEDS))
        u0, jac = policy_at_origin(trainer.policy, task.obs_dim)
        out = {"long/lateral_mae": float(ev["lateral_mae"]), "long/speed_mae": float(ev["speed_mae"]),
               "long/course_cost": float(ev["cost"]),
               "long/J_train": discounted_cost(task, trainer.policy, self._starts),
               "long/delta0": float(u0[0]), "long/ax0": float(u0[1])}
        out.update({f"long/ddelta_d{n}": float(jac[0, i]) for i, n in enumerate(OBS_NAMES)})
        out.update({f"long/dax_d{n}": float(jac[1, i]) for i, n in enumerate(OBS_NAMES)})
        return out


def long_training_observer(config: TrainConfig) -> LongTrainingObserver:
    """The ``observer`` of ``experiments/studies/long_training.toml``: a record every :data:`EVERY` iterations."""
    return LongTrainingObserver(EVERY)
