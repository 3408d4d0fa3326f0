"""A user's own system as a first-class task: the default ``Task.evaluate``, the task's own name in the
results, :func:`mixedrl.tasks.check_task`'s errors naming the function, progress on by default."""

from __future__ import annotations

import io
import json
import sys
from typing import Any

import numpy as np
import pytest
import torch

from mixedrl.algorithms.agpi import AGPI
from mixedrl.algorithms.ddpg import DDPG
from mixedrl.config import TrainConfig
from mixedrl.runs import RunDirectory, train
from mixedrl.tasks import LinearTask, Task, check_task, task_from_config


class Cruise(Task):
    """The tutorial's cruise controller: ``v' = v + 0.1 (u - 0.1 v) + xi``, a constant headwind bias."""

    state_dim = obs_dim = noise_dim = 1
    action_dim = 1
    gamma = 0.95

    def __init__(self, true_std: float = 0.0) -> None:
        self.noise_matrix = torch.eye(1)
        self.prior_mean, self.prior_cov = np.zeros(1), np.array([[1e-4]])
        self.true_mean, self.true_cov = np.array([-0.02]), np.array([[true_std**2]])
        self.action_bound = torch.tensor([2.0])
        self.obs_scale = torch.tensor([1.0])

    def f(self, s: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return s + 0.1 * (u - 0.1 * s)

    def observe(self, s: torch.Tensor) -> torch.Tensor:
        return s

    def cost(self, s_next: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return (s_next**2 + 0.01 * u**2).sum(-1)

    def sample_initial(self, n: int, generator: torch.Generator) -> torch.Tensor:
        return 2.0 * torch.rand(n, 1, generator=generator, dtype=torch.float64) - 1.0


class ZeroPolicy(torch.nn.Module):
    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.zeros(obs.shape[0], 1)


def test_default_evaluate_matches_the_closed_form_rollout() -> None:
    """Zero action, no noise spread: s_t = 0.99^t s_0 - 0.02 (1 - 0.99^t) / 0.01, computed here in numpy."""
    task = Cruise()
    seeds, horizon = [3, 4], 40
    ev = task.evaluate(ZeroPolicy(), seeds, horizon=horizon)
    costs, abs_half, signed_half = [], [], []
    for seed in seeds:
        s0 = (2.0 * torch.rand(task.eval_starts, 1, generator=torch.Generator().manual_seed(seed),
                               dtype=torch.float64) - 1.0).numpy()[:, 0]
        t = np.arange(1, horizon + 1)[:, None]
        traj = 0.99**t * s0 - 2.0 * (1.0 - 0.99**t)          # s_1 .. s_H, shape (H, n)
        costs.append(((0.95 ** (t - 1)) * traj**2).sum(axis=0).mean())
        abs_half.append(np.abs(traj[horizon // 2:]))
        signed_half.append(traj[horizon // 2:])
    assert ev["cost"] == pytest.approx(np.mean(costs), rel=1e-12)
    assert ev["mean_abs_state"] == pytest.approx(np.mean(abs_half), rel=1e-12)
    assert ev["mean_abs_state_0"] == ev["mean_abs_state"]
    assert ev["mean_state_0"] == pytest.approx(np.mean(signed_half), rel=1e-12)
    assert ev["terminated_fraction"] == 0.0
    assert task.evaluate(ZeroPolicy(), seeds)["cost"] > ev["cost"]  # the default horizon (200) is longer


def test_default_evaluate_is_seeded_and_checks_its_arguments() -> None:
    task = Cruise(true_std=0.01)
    a, b = task.evaluate(ZeroPolicy(), [0, 1]), task.evaluate(ZeroPolicy(), [0, 1])
    assert a == b and task.evaluate(ZeroPolicy(), [2, 1]) != a
    for bad in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="^horizon"):
            task.evaluate(ZeroPolicy(), [0], horizon=bad)
    with pytest.raises(ValueError, match="^seeds"):
        task.evaluate(ZeroPolicy(), [])


def test_default_evaluate_stops_terminated_copies() -> None:
    class Leaving(Cruise):
        def is_terminal(self, s: torch.Tensor) -> torch.Tensor:
            return s[:, 0] < -0.5

    ev = Leaving().evaluate(ZeroPolicy(), [0], horizon=200)
    assert ev["terminated_fraction"] == 1.0  # the bias drives every copy below -0.5
    assert np.isfinite(ev["cost"]) and ev["cost"] < Cruise().evaluate(ZeroPolicy(), [0], horizon=200)["cost"]


def test_task_name_defaults_to_the_class_and_reaches_the_results(tmp_path: Any) -> None:
    assert Cruise.name == "Cruise" and LinearTask.name == "linear" and task_from_config("dlc").name == "dlc"

    class Named(Cruise):
        name = "my-cruise"

    config = TrainConfig(method="mixed", task="linear", seed=0, algorithm=dict(iterations=4, batch_size=16,
                         hidden_sizes=(8,)), run=dict(eval_every=4, checkpoint_every=4))
    results = train(AGPI(Cruise(), config), progress=False)
    assert results["task"] == "Cruise"
    assert {"cost", "mean_abs_state", "mean_state_0"} <= set(results["final"])
    run = RunDirectory(tmp_path / "run")
    assert train(AGPI(Named(), config), run, progress=False)["task"] == "my-cruise"
    assert run.read_results()["task"] == "my-cruise"
    builtin = train(AGPI(LinearTask(), config), progress=False)
    assert builtin["task"] == "linear"


def test_config_json_names_the_users_task_and_a_custom_run_resumes(tmp_path: Any) -> None:
    config = TrainConfig(method="mixed", task="linear", seed=0, algorithm=dict(iterations=4, batch_size=16,
                         hidden_sizes=(8,)), run=dict(eval_every=2, checkpoint_every=2))
    run = RunDirectory(tmp_path / "run")
    assert train(AGPI(Cruise(), config), run, progress=False, stop_after=2) == {"interrupted_at": 2}
    saved = json.loads(run.config_path.read_text())
    assert saved["task"] == {"name": "Cruise"}  # not the placeholder "linear" and its unused fields
    assert saved["algorithm"]["iterations"] == 4 and saved["method"] == "mixed"
    with pytest.raises(ValueError, match="^config: .*the user's own task 'Cruise'"):
        run.read_config()
    resumed = train(AGPI(Cruise(), config), run, resume=True, progress=False)
    assert resumed["iterations"] == 4 and resumed["task"] == "Cruise"
    with pytest.raises(ValueError, match=r"^config: .*task\.A .*\(saved: None\).*contradict"):  # another task
        train(AGPI(LinearTask(), config.replace(**{"algorithm.iterations": 6})), run, resume=True, progress=False)
    builtin = RunDirectory(tmp_path / "builtin")
    train(AGPI(LinearTask(), config), builtin, progress=False)
    assert json.loads(builtin.config_path.read_text())["task"] == config.to_dict()["task"]
    assert builtin.read_config().to_dict() == config.to_dict()


def _broken(**methods: Any) -> Task:
    cls = type("Broken", (Cruise,), methods)
    return cls()


@pytest.mark.parametrize(("methods", "message"), [
    ({"cost": lambda self, s, u: (s**2).sum(-1, keepdim=True)},
     r"^Broken\.cost: expected shape \(3,\), returned shape \(3, 1\)$"),
    ({"f": lambda self, s, u: s[:, :0]}, r"^Broken\.f: expected shape \(3, 1\), returned shape \(3, 0\)$"),
    ({"f": lambda self, s, u: (s + u).double()}, r"^Broken\.f: expected dtype torch\.float32, returned torch\.float64"),
    ({"f": lambda self, s, u: s + u / 0.0}, r"^Broken\.f: returned NaN or inf"),
    ({"f": lambda self, s, u: torch.as_tensor((s + u).detach().numpy())}, r"^Broken\.f: the output does not depend"),
    ({"f": lambda self, s, u: (s + u).tolist()}, r"^Broken\.f: expected a torch\.Tensor of shape \(3, 1\), returned list"),
    ({"observe": lambda self, s: torch.cat([s, s], 1)}, r"^Broken\.observe: expected shape \(3, 1\), returned shape \(3, 2\)"),
    ({"sample_initial": lambda self, n, g: torch.zeros(n, 1)},
     r"^Broken\.sample_initial: expected dtype torch\.float64, returned torch\.float32"),
    ({"sample_initial": lambda self, n, g: torch.zeros(n)},
     r"^Broken\.sample_initial: expected shape \(3, 1\), returned shape \(3,\)"),
    ({"gamma": 1.5}, r"^Broken\.gamma: expected a discount factor"),
    ({"action_dim": 0}, r"^Broken\.action_dim: expected a positive integer"),
])
def test_check_task_names_the_function_and_the_shapes(methods: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        check_task(_broken(**methods))


def test_check_task_names_array_attributes() -> None:
    task = Cruise()
    task.obs_scale = torch.tensor([1.0, 2.0])
    with pytest.raises(ValueError, match=r"^Cruise\.obs_scale: expected shape \(1,\), got shape \(2,\)"):
        check_task(task)
    task = Cruise()
    task.action_bound = torch.tensor([0.0])
    with pytest.raises(ValueError, match=r"^Cruise\.action_bound: expected positive"):
        check_task(task)


@pytest.mark.parametrize("trainer", ["mixed", "ddpg"])
def test_trainers_check_the_task_at_construction(trainer: str) -> None:
    """The error a (B, 1) cost gave deep inside the expectation now comes at construction, naming cost."""
    bad = _broken(cost=lambda self, s, u: (s**2).sum(-1, keepdim=True))
    config = TrainConfig(method=trainer, task="linear", algorithm=dict(batch_size=16, hidden_sizes=(8,)))
    with pytest.raises(ValueError, match=r"^Broken\.cost: expected shape \(3,\), returned shape \(3, 1\)"):
        (DDPG if trainer == "ddpg" else AGPI)(bad, config)


def test_builtin_tasks_pass_the_check() -> None:
    for task in (LinearTask(), task_from_config("dlc"), Cruise()):
        check_task(task)


def test_progress_bar_on_by_default_on_a_terminal(monkeypatch: pytest.MonkeyPatch) -> None:
    class Tty(io.StringIO):
        def isatty(self) -> bool:
            return True

    config = TrainConfig(method="model", task="linear", seed=0, algorithm=dict(iterations=3, batch_size=16,
                         hidden_sizes=(8,)), run=dict(eval_every=3, checkpoint_every=3))
    for progress, shown in ((None, True), (False, False)):
        err = Tty()
        monkeypatch.setattr(sys, "stderr", err)
        train(AGPI(Cruise(), config)) if progress is None else train(AGPI(Cruise(), config), progress=progress)
        assert ("model seed 0" in err.getvalue()) is shown
    quiet = io.StringIO()  # not a terminal: no bar by default
    monkeypatch.setattr(sys, "stderr", quiet)
    train(AGPI(Cruise(), config))
    assert quiet.getvalue() == ""
