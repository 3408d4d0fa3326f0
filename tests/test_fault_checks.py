"""Faults that used to pass silently (issue 43): non-finite training, a task's attribute types, the IBE's
public state replaced, resource limits of the configuration, complex actions of the Gymnasium env."""

from __future__ import annotations

import copy
import math
import re
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
from test_ibe import Linear


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
        check_task(task)
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
    # zero and upper-bound actions on one batch never get there; check_task's rolled random probe does
    with pytest.raises(ValueError, match=r"^Cruise.cost: returned NaN or inf values on states of sample_initial"):
        check_task(task)


# ----------------------------------------------------------------------------------------------------
# item 7: the IBE's public state is read-only
# ----------------------------------------------------------------------------------------------------
def _estimators() -> list[Any]:
    from mixedrl.ibe import KnownCovarianceIBE, LinearFeatureIBE, StateDependentIBE, UnknownCovarianceIBE

    def features(x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return torch.cat([torch.ones_like(x[:, :1]), x], dim=1)

    xi = np.array([[0.1, -0.2], [0.3, 0.0], [-0.1, 0.4]])
    x, u = np.arange(6.0).reshape(3, 2) / 6, np.zeros((3, 1))
    return [KnownCovarianceIBE(np.zeros(2), np.eye(2), 0.1 * np.eye(2)).update(xi),
            UnknownCovarianceIBE(np.zeros(2), np.eye(2)).update(xi),
            UnknownCovarianceIBE(np.zeros(2), np.eye(2), recursion="paper").update(xi),
            StateDependentIBE(Linear(2, 1, 2), 0.1 * np.eye(2), 2, 1, max_iter=5).update(x, u, xi),
            LinearFeatureIBE(features, np.zeros((3, 2)), 0.1 * np.eye(2), 2, 1).update(x, u, xi)]


_PUBLIC = ("mean", "prior_mean", "prior_cov", "noise_cov", "count", "cov", "mean_cov", "total", "data_mean",
           "scatter", "psi", "recursion", "max_iter", "iterations", "converged", "weights", "gram", "cross",
           "prior_weights", "prior_std", "state_dim", "action_dim", "phi", "features")


@pytest.mark.parametrize("index", range(5))
def test_the_ibe_public_state_cannot_be_replaced(index: int) -> None:
    est = _estimators()[index]
    before = {k: v.copy() if isinstance(v, np.ndarray) else v for k, v in est.state_dict().items()}
    probes = {"mean": [np.nan, 0.0], "prior_cov": -np.eye(2), "count": -3, "cov": np.full((2, 2), np.nan)}
    fields = [name for name in _PUBLIC if hasattr(est, name)]
    assert {"count", "cov"} <= set(fields)
    for name in fields:  # a computed property (Case 1's cov, Case 2's mean_cov) has Python's own message
        computed = isinstance(getattr(type(est), name), property)
        message = f"property '{name}'" if computed else rf"^{name}: read-only; {type(est).__name__}'s state changes only"
        with pytest.raises(AttributeError, match=message):
            setattr(est, name, probes.get(name, getattr(est, name)))
        with pytest.raises(AttributeError, match=message):
            delattr(est, name)
    after = est.state_dict()
    assert before.keys() == after.keys()
    for key, value in before.items():
        if isinstance(value, np.ndarray):
            np.testing.assert_array_equal(after[key], value)
        elif not isinstance(value, list):
            assert after[key] == value
    with pytest.raises(ValueError, match="read-only"):
        est.cov[0, 0] = 5.0  # writing into the arrays stays refused


def test_read_only_fields_keep_the_numbers_and_checkpoint_loading() -> None:
    for est in _estimators():
        twin = type(est).__new__(type(est))
        twin.__dict__.update(copy.deepcopy(est.__dict__))
        twin.load_state_dict(est.state_dict())
        for name in ("mean", "cov", "weights", "count"):
            if hasattr(est, name):
                np.testing.assert_array_equal(getattr(twin, name), getattr(est, name))


# ----------------------------------------------------------------------------------------------------
# item 8: resource limits, validated with the configuration
# ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("key, value, message", [
    ("algorithm.batch_size", 10**12, r"^mixedrl train: error: algorithm\.batch_size: 1000000000000 needs at least "),
    ("algorithm.hidden_sizes", [10**9], r"^mixedrl train: error: algorithm\.hidden_sizes: \(1000000000,\) needs at least "),
    ("run.num_threads", 100000, r"^mixedrl train: error: run\.num_threads: 100000 threads, more than this machine's "),
])
def test_limits_are_one_line_errors_before_anything_is_created(tmp_path: Any, capsys: pytest.CaptureFixture[str],
                                                               key: str, value: Any, message: str) -> None:
    from mixedrl.cli import main

    out = tmp_path / "run"
    assert main(["train", "--method", "mixed", "--out", str(out), "--no-progress", "--set", f"{key}={value}"]) == 2
    err = capsys.readouterr().err.strip()
    assert re.match(message, err) and "\n" not in err
    assert not out.exists()


def test_the_memory_bound_follows_the_machine(monkeypatch: pytest.MonkeyPatch) -> None:
    import mixedrl.config as config

    cfg = TrainConfig(method="ddpg", task="linear", algorithm=dict(batch_size=7, hidden_sizes=(100, 100)),
                      ddpg=dict(buffer_size=10**6, batch_size=1000))
    need = config.memory_lower_bounds(cfg)
    # actor and critic: (1 + 1) 100 + 101 * 100 + 101 parameters each, 16 bytes a parameter; DDPG's own minibatch
    assert need == {"algorithm.hidden_sizes": 2 * 16 * 10401, "ddpg.batch_size": 1000 * (8 + 800),
                    "ddpg.buffer_size": 20 * 10**6}
    assert config.memory_lower_bounds(cfg.replace(method="mixed")) == {"algorithm.hidden_sizes": 2 * 16 * 10401,
                                                                     "algorithm.batch_size": 7 * (8 + 800)}
    monkeypatch.setattr(config, "machine_memory", lambda: sum(need.values()))
    cfg.validate()  # exactly enough
    monkeypatch.setattr(config, "machine_memory", lambda: sum(need.values()) - 1)
    with pytest.raises(ValueError, match=r"^ddpg\.buffer_size: 1000000 needs at least 0\.0186 GiB"):
        cfg.validate()
    monkeypatch.setattr(config, "machine_memory", lambda: None)  # a system that does not report it
    cfg.replace(**{"ddpg.batch_size": 10**12}).validate()


def test_as_many_threads_as_cores_is_accepted() -> None:
    import os

    assert TrainConfig(run=dict(num_threads=os.cpu_count())).run.num_threads == os.cpu_count()
