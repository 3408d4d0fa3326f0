"""Faults that used to pass silently (issue 43): non-finite training, a task's attribute types, the IBE's
public state replaced, resource limits of the configuration, complex actions of the Gymnasium env."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
import torch

from mixedrl.algorithms.agpi import AGPI
from mixedrl.checkpoint import load_checkpoint
from mixedrl.checks import NonFiniteTrainingError, check_finite_metrics, check_task_types
from mixedrl.config import TrainConfig
from mixedrl.runs import RunDirectory, train
from mixedrl.tasks import check_task, task_from_config
from test_custom_task import Cruise as CruiseTask


class Cruise(CruiseTask):
    """The tutorial's cruise controller whose cost turns NaN on states ``v < nan_below`` once ``armed``."""

    armed = False
    nan_below = -0.5

    def cost(self, s_next: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        c = super().cost(s_next, u)
        return torch.where(s_next[:, 0] < self.nan_below, torch.nan, c) if self.armed else c


def _config(**algorithm: Any) -> TrainConfig:
    return TrainConfig(method="mixed", task="linear", seed=0,
                       algorithm=dict(iterations=6, batch_size=16, hidden_sizes=(8,), **algorithm),
                       run=dict(eval_every=3, checkpoint_every=2))


# ----------------------------------------------------------------------------------------------------
# item 5: non-finite training
# ----------------------------------------------------------------------------------------------------
def test_training_stops_at_the_first_non_finite_loss_and_keeps_the_last_good_checkpoint(tmp_path: Any) -> None:
    task = Cruise()
    run = RunDirectory(tmp_path / "run")

    def arm(row: dict[str, Any]) -> None:  # the cost turns NaN after iteration 2 (checkpointed)
        task.armed = task.armed or row["iteration"] == 2

    with pytest.raises(NonFiniteTrainingError, match=r"iteration 3: train/critic_loss is nan") as err:
        train(AGPI(task, _config()), run, progress=False, callback=arm)
    assert (err.value.iteration, err.value.key) == (3, "train/critic_loss") and math.isnan(err.value.value)
    assert str(run.path) in str(err.value)
    assert load_checkpoint(run.checkpoint_path)["trainer"]["k"] == 2
    assert [r["iteration"] for r in run.read_metrics()] == [1, 2]
    assert not (run.path / "results.json").exists()


def test_a_non_finite_evaluation_stops_training_in_memory_too() -> None:
    row = {"iteration": 3, "train/critic_loss": 0.5, "eval/cost": math.inf, "eval/mean_state_0": 0.0}
    with pytest.raises(NonFiniteTrainingError, match=r"^mixed seed 0: iteration 3: eval/cost is inf"):
        check_finite_metrics(row, "mixed seed 0")


def test_check_finite_metrics_reads_only_and_skips_what_is_nan_by_design() -> None:
    row = {"iteration": 1, "train/critic_loss": 1.0, "train/env_cost": math.nan, "data/true_transitions": math.nan,
           "ibe/count": 3.0, "mvc/lhs_mean": -2.0, "eval/cost": np.float64(4.0)}
    before = dict(row)
    check_finite_metrics(row)
    assert row.keys() == before.keys() and all(row[k] is before[k] for k in row)
    bad = {**row, "mvc/lhs_mean": math.nan, "train/actor_objective": -math.inf}
    with pytest.raises(NonFiniteTrainingError, match=r"mvc/lhs_mean is nan .*also non-finite: train/actor_objective"):
        check_finite_metrics(bad)


# ----------------------------------------------------------------------------------------------------
# item 5: the task's attribute types, value_scale, more than one batch of probe states
# ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["dlc", "linear", "pendulum"])
def test_the_built_in_tasks_pass_the_type_checks(name: str) -> None:
    check_task_types(task_from_config(name))


def test_a_numpy_noise_matrix_is_refused_up_front() -> None:
    task = Cruise()
    task.noise_matrix = np.eye(1)
    with pytest.raises(ValueError, match=r"^Cruise.noise_matrix: expected a torch.Tensor of shape \(1, 1\), got ndarray"):
        check_task_types(task)
    task.noise_matrix = torch.eye(1, dtype=torch.int64)
    with pytest.raises(ValueError, match=r"^Cruise.noise_matrix: expected a floating-point dtype"):
        check_task_types(task)
    task = Cruise()
    task.prior_mean = torch.zeros(1)
    with pytest.raises(ValueError, match=r"^Cruise.prior_mean: expected a numpy array, got a torch.Tensor"):
        check_task_types(task)


@pytest.mark.parametrize("scale", [0.0, -1.0, math.nan, math.inf, "1", True])
def test_value_scale_must_be_positive_and_finite(scale: Any) -> None:
    task = Cruise()
    task.value_scale = scale
    with pytest.raises(ValueError, match=r"^Cruise.value_scale: expected a positive finite number"):
        check_task_types(task)


def test_the_probe_reaches_states_beyond_the_first_batch() -> None:
    task = Cruise()
    task.armed, task.nan_below = True, -1.05  # start states lie in [-1, 1]: only a step with u < 0 gets there
    check_task(task)  # its probe (zero and upper-bound actions) does not reach them
    with pytest.raises(ValueError, match=r"^Cruise.cost: returned NaN or inf values on states of sample_initial"):
        check_task_types(task)
