"""The slalom tracking tuning system (experiments/tuning_tracking.py): a valid task, a differentiable model, a
reference that moves, and a reference controller that tracks it (and the current that matters)."""

from __future__ import annotations

import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from experiments.tuning_tracking import Slalom, SlalomReference  # noqa: E402
from mixedrl.task_base import check_task  # noqa: E402


class _Zero(torch.nn.Module):
    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.zeros(obs.shape[0], 1)


def test_slalom_is_a_task_with_a_differentiable_model() -> None:
    task = Slalom()
    check_task(task)
    s = task.sample_initial(5, torch.Generator().manual_seed(0)).requires_grad_(True)
    u = torch.full((5, 1), 0.5, dtype=torch.float64, requires_grad=True)
    task.cost(task.f(s, u), u).sum().backward()
    assert u.grad is not None and (u.grad.abs() > 0).all()  # the action reaches the cost within one step
    assert task.dt <= 0.01 and task.eval_horizon >= 1000
    # training states cover the whole course; the reference moves along it
    x = task.sample_initial(2000, torch.Generator().manual_seed(1))[:, 0]
    assert x.min() < 0.05 * task.length and x.max() > 0.95 * task.length
    y_ref, _, _ = task.reference(torch.linspace(0, task.length, 9, dtype=torch.float64))
    assert y_ref.max() - y_ref.min() > 2.0


def test_reference_controller_tracks_and_the_current_matters() -> None:
    task = Slalom()
    seeds = [1000]
    ref = task.evaluate(SlalomReference(task), seeds)
    blind = task.evaluate(SlalomReference(task, current=0.0), seeds)
    none = task.evaluate(_Zero(), seeds)
    assert ref["terminated_fraction"] == 0.0 and ref["lateral_mae"] < 0.08
    assert none["cost"] > 20 * ref["cost"] and none["terminated_fraction"] > 0.5
    # blind to the current: a steady offset downstream and a much larger course cost
    assert blind["lateral_mean"] > 0.2 and blind["cost"] > 4 * ref["cost"]
