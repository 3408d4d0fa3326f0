"""Tests of Algorithm 2 planning on model rollouts (mixedrl.algorithms.model_data, state_source="model"):
the batch comes from the planning model under the method's noise, the true environment only feeds the IBE
at the configured rate, model-driven RL uses zero true transitions, resume == uninterrupted."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from mixedrl.algorithms.agpi import AGPI
from mixedrl.samplers import ModelStateSampler
from mixedrl.config import TrainConfig
from mixedrl.runs import RunDirectory, make_trainer, train
from mixedrl.tasks import LinearTask

FAST = dict(task="linear", algorithm=dict(iterations=40, batch_size=32, rollout_horizon=4),
            run=dict(eval_every=20, checkpoint_every=10, eval_seeds=1),
            sampler={"name": "model_rollouts", "true_horizon": 30, "true_envs": 2, "true_steps": 3, "true_every": 4})


def _forbid_true_steps(monkeypatch: pytest.MonkeyPatch, task: object) -> None:
    def boom(*args: object, **kwargs: object) -> None:
        raise AssertionError("the true environment was stepped")

    monkeypatch.setattr(task, "true_step", boom)


@pytest.mark.parametrize("task_name", ["linear", "dlc"])
def test_model_driven_uses_zero_true_transitions(monkeypatch: pytest.MonkeyPatch, task_name: str) -> None:
    cfg = TrainConfig(method="model", **{**FAST, "task": task_name, "algorithm": dict(iterations=12, batch_size=32)})
    trainer = make_trainer(cfg)
    _forbid_true_steps(monkeypatch, trainer.task)
    rows = [trainer.iteration() for _ in range(12)]
    assert trainer.true_transitions == 0
    assert all(r["data/true_transitions"] == 0 for r in rows)
    assert trainer.noise.mean is not None and not hasattr(trainer.noise, "update")


def test_oracle_uses_zero_true_transitions(monkeypatch: pytest.MonkeyPatch) -> None:
    trainer = make_trainer(TrainConfig(method="oracle", **FAST))
    _forbid_true_steps(monkeypatch, trainer.task)
    for _ in range(9):
        trainer.iteration()
    assert trainer.true_transitions == 0


def test_mixed_true_transitions_follow_the_configured_rate() -> None:
    trainer = make_trainer(TrainConfig(method="mixed", **FAST))
    counts = []
    for _ in range(10):
        counts.append(trainer.iteration()["data/true_transitions"])
    # collections at k = 0, 4, 8 (true_every = 4), each 2 copies x 3 steps
    assert counts == [6, 6, 6, 6, 12, 12, 12, 12, 18, 18]
    assert trainer.true_transitions == 18
    # every true residual went to the IBE, and nothing else did
    assert trainer.noise.count == 18


def test_true_source_counts_one_true_step_per_copy() -> None:
    assert TrainConfig(task="dlc").sampler.name == "dlc_course"  # the DLC experiment plans on the model
    cfg = TrainConfig(method="mixed", task="linear", algorithm=dict(batch_size=16, iterations=5),
                      sampler="true_copies")
    trainer = make_trainer(cfg)
    assert trainer.sampler is None
    for _ in range(5):
        trainer.iteration()
    assert trainer.true_transitions == 5 * 16 == trainer.noise.count


def test_rollouts_use_the_planning_noise_not_the_true_one() -> None:
    # linear task: prior mean 0, true mean 0.5 on the velocity; the rollout increments must carry the prior's
    task = LinearTask(prior_cov=1e-4 * np.eye(2))
    cfg = TrainConfig(method="model", algorithm=dict(batch_size=2048), sampler=dict(name="dlc_course",
                      box=float("inf"), course_start=0, kick_prob=0.0))
    gen = torch.Generator().manual_seed(0)
    sampler = ModelStateSampler(task, cfg, gen)
    actor = torch.nn.Linear(2, 1)
    torch.nn.init.zeros_(actor.weight)
    torch.nn.init.zeros_(actor.bias)
    before = sampler.states.clone()
    alive = sampler.steps + 1 < sampler.horizons  # copies that will not restart at this step
    sampler.model_step(actor, task.prior_mean, task.prior_cov)
    xi = (sampler.states - task.f(before, torch.zeros(2048, 1, dtype=torch.float64)))[alive]
    assert abs(float(xi[:, 1].mean()) - 0.0) < 0.01  # prior mean (true mean 0.5 would be far outside)
    assert abs(float(xi[:, 1].std()) - 0.01) < 0.002
    sampler.model_step(actor, task.true_mean, task.true_cov)


def test_rollouts_restart_outside_the_box_and_at_the_horizon() -> None:
    task = LinearTask()
    cfg = TrainConfig(method="model", algorithm=dict(batch_size=64, horizon=5), sampler=dict(name="dlc_course",
                      box=2.0, course_fraction=0.25, true_horizon=7, course_horizon=7, course_start=0))
    sampler = ModelStateSampler(task, cfg, torch.Generator().manual_seed(1))
    assert int(sampler.course.sum()) == 16
    assert sampler.horizons.tolist() == [7] * 16 + [5] * 48
    unstable = torch.nn.Linear(2, 1)  # pushes the state out of the box quickly
    with torch.no_grad():
        unstable.weight.copy_(torch.tensor([[50.0, 50.0]]))
        unstable.bias.zero_()
    for _ in range(20):
        sampler.model_step(unstable, task.prior_mean, task.prior_cov)
        assert bool((sampler.states.abs() <= 2.0).all())  # every state in the box (obs_scale = 1)
        assert bool((sampler.steps < sampler.horizons).all())
    assert sampler.restarts > 64


def test_sampler_options_are_validated() -> None:
    with pytest.raises(ValueError, match="^sampler.name"):
        TrainConfig(sampler="replay")
    with pytest.raises(ValueError, match="^sampler.course_fraction"):
        TrainConfig(sampler=dict(name="dlc_course", course_fraction=1.5))
    with pytest.raises(ValueError, match="^sampler.box"):
        TrainConfig(sampler=dict(name="dlc_course", box=float("nan")))
    with pytest.raises(ValueError, match="^sampler.true_every"):
        TrainConfig(sampler=dict(name="dlc_course", true_every=0))
    unbounded = TrainConfig(sampler=dict(name="dlc_course", box=float("inf")))
    assert TrainConfig.from_dict(unbounded.to_dict()).sampler.box == float("inf")


@pytest.mark.parametrize("method,task", [("mixed", "linear"), ("model", "linear"), ("mixed", "dlc")])
def test_resume_equals_uninterrupted_on_the_model_path(tmp_path: Path, method: str, task: str) -> None:
    cfg = TrainConfig(method=method, **{**FAST, "task": task})
    full = make_trainer(cfg)
    train(full, RunDirectory(tmp_path / "full"))
    first = make_trainer(cfg)
    assert train(first, RunDirectory(tmp_path / "cut"), stop_after=17) == {"interrupted_at": 17}
    resumed = make_trainer(cfg)
    train(resumed, RunDirectory(tmp_path / "cut"), resume=True)
    for name in ("actor", "critic"):
        for a, b in zip(full.state_dict()[name].values(), resumed.state_dict()[name].values()):
            assert torch.equal(a, b)
    assert torch.equal(full.sampler.states, resumed.sampler.states)
    assert full.true_transitions == resumed.true_transitions
    strip = [{k: v for k, v in r.items() if not k.startswith("time/")} for r in RunDirectory(tmp_path / "full").read_metrics()]
    assert strip == [{k: v for k, v in r.items() if not k.startswith("time/")}
                     for r in RunDirectory(tmp_path / "cut").read_metrics()]


def test_load_state_dict_rejects_a_checkpoint_without_sampler() -> None:
    cfg = TrainConfig(method="mixed", **FAST)
    trainer: AGPI = make_trainer(cfg)
    trainer.iteration()
    state = trainer.state_dict()
    del state["sampler"]
    fresh = make_trainer(cfg)
    before = fresh.sampler.states.clone()
    with pytest.raises(ValueError, match="^state"):
        fresh.load_state_dict(state)
    assert torch.equal(fresh.sampler.states, before)


def test_course_rollouts_start_at_the_course_start_from_model_course_start() -> None:
    from mixedrl.noise import GaussianNoise
    from mixedrl.tasks import make_task

    task = make_task("dlc")
    cfg = TrainConfig(algorithm=dict(batch_size=64, horizon=1), sampler=dict(name="dlc_course",
                      course_fraction=1.0, course_start=2, true_horizon=1, course_horizon=1,
                      course_starts="start"))
    sampler = ModelStateSampler(task, cfg, torch.Generator().manual_seed(0))
    actor = torch.nn.Linear(5, 2)
    torch.nn.init.zeros_(actor.weight)
    torch.nn.init.zeros_(actor.bias)
    noise = GaussianNoise(task.prior_mean, task.prior_cov)
    sampler.collect(actor, noise, 1)  # before model_course_start: every copy restarts anywhere on the course
    assert float(sampler.states[:, 5].max()) > 30.0
    sampler.collect(actor, noise, 2)  # from it on: at the course start, X = 0
    assert float(sampler.states[:, 5].abs().max()) == 0.0
    assert sampler.true_transitions == 0  # a fixed noise source collects no true data


def test_kicks_move_only_course_copies_by_at_most_the_kick_size() -> None:
    task = LinearTask()
    cfg = TrainConfig(method="model", algorithm=dict(batch_size=40, horizon=1000), sampler=dict(name="dlc_course",
                      box=float("inf"), course_fraction=0.5, course_start=0, kick_prob=1.0, kick_scale=0.3,
                      true_horizon=1000, course_horizon=1000))
    kicked = ModelStateSampler(task, cfg, torch.Generator().manual_seed(2))
    plain = ModelStateSampler(task, cfg.replace(**{"sampler.kick_prob": 0.0}), torch.Generator().manual_seed(2))
    actor = torch.nn.Linear(2, 1)
    zero = np.zeros((2, 2))
    kicked.model_step(actor, task.prior_mean, zero)
    plain.model_step(actor, task.prior_mean, zero)
    diff = (kicked.states - plain.states).abs()
    assert bool((diff[20:] == 0).all())  # wide copies are never kicked
    assert bool((diff[:20] > 0).all()) and float(diff.max()) <= 0.3  # every course copy, within the size


def _course_sampler(starts: str) -> tuple[ModelStateSampler, Any, Any]:
    from mixedrl.noise import GaussianNoise
    from mixedrl.tasks import make_task

    task = make_task("dlc")
    cfg = TrainConfig(algorithm=dict(batch_size=256, horizon=1), sampler=dict(name="dlc_course",
                      course_fraction=1.0, course_start=0, true_horizon=2000, course_horizon=2000, kick_prob=0.0,
                      course_starts=starts))
    sampler = ModelStateSampler(task, cfg, torch.Generator().manual_seed(0))
    actor = torch.nn.Linear(5, 2)
    torch.nn.init.zeros_(actor.weight)
    torch.nn.init.zeros_(actor.bias)
    return sampler, actor, GaussianNoise(task.prior_mean, task.prior_cov)


def _place_on_reference(sampler: ModelStateSampler, rows: slice, X: float) -> None:
    ref = sampler.task.model.config.reference
    x = torch.full((sampler.states[rows].shape[0],), X, dtype=torch.float64)
    sampler.states[rows] = torch.stack([0 * x, 0 * x, 12.0 + 0 * x, ref.heading(x), ref.lateral(x), x], dim=-1)
    sampler.steps[rows] = 0


def test_course_copies_drive_in_step_from_the_start_and_spread_along_the_course_with_along() -> None:
    # "start": every course copy restarts at X = 0 (here all at once: their horizon ends), so they advance
    # together
    sampler, actor, noise = _course_sampler("start")
    sampler.steps.fill_(1999)
    sampler.collect(actor, noise, 0)
    for k in range(1, 3):
        sampler.collect(actor, noise, k)
    X = sampler.states[:, 5]
    assert float(X.max() - X.min()) < 1.0
    # "along": the copies restart at X ~ U(0, 120 m): every part of the course is in the batch
    sampler, actor, noise = _course_sampler("along")
    sampler.steps.fill_(1999)
    sampler.collect(actor, noise, 0)
    X = sampler.states[:, 5]
    assert float(X.min()) < 15.0 and float(X.max()) > 105.0
    counts = torch.histc(X.float(), bins=4, min=0.0, max=120.0)
    assert bool((counts > 256 / 4 * 0.6).all())  # about uniform over the four quarters
    # on the reference there, within the start's perturbation (e_y: 0.1 m, v_x: 0.1 m/s)
    ref = sampler.task.model.config.reference
    assert float((sampler.states[:, 4] - ref.lateral(X)).abs().max()) <= 0.1 + 1e-9
    assert float((sampler.states[:, 2] - 12.0).abs().max()) <= 0.1 + 1e-9


def test_along_course_copies_restart_when_they_pass_the_course_end() -> None:
    sampler, actor, noise = _course_sampler("along")
    sampler.collect(actor, noise, 0)
    _place_on_reference(sampler, slice(None), 119.99)  # every copy at the end of the course
    restarts = sampler.restarts
    sampler.collect(actor, noise, 1)  # one step at 12 m/s: 6 cm, past 120 m
    assert sampler.restarts - restarts == 256
    assert float(sampler.states[:, 5].max()) < 120.0


def test_model_course_starts_is_validated() -> None:
    with pytest.raises(ValueError, match="^sampler.course_starts"):
        TrainConfig(sampler=dict(name="dlc_course", course_starts="random"))


def test_loop_course_copies_restart_at_the_course_start_when_they_pass_its_end() -> None:
    sampler, actor, noise = _course_sampler("loop")
    sampler.collect(actor, noise, 0)
    _place_on_reference(sampler, slice(None), 100.0)
    _place_on_reference(sampler, slice(0, 128), 119.99)  # half the copies at the end of the course
    restarts = sampler.restarts
    sampler.collect(actor, noise, 1)
    assert sampler.restarts - restarts == 128
    assert float(sampler.states[:128, 5].abs().max()) == 0.0  # at the course start
    assert float(sampler.states[128:, 5].min()) > 0.0  # the others drive on


def test_start_course_copies_drive_past_the_course_end() -> None:
    sampler, actor, noise = _course_sampler("start")
    sampler.collect(actor, noise, 0)
    _place_on_reference(sampler, slice(None), 119.99)
    restarts = sampler.restarts
    sampler.collect(actor, noise, 1)
    assert sampler.restarts == restarts and float(sampler.states[:, 5].min()) > 120.0


def test_the_course_copies_drive_the_course_from_course_start_on() -> None:
    from mixedrl.noise import GaussianNoise
    from mixedrl.tasks import make_task

    task = make_task("dlc")
    cfg = TrainConfig(algorithm=dict(batch_size=64, horizon=1), sampler=dict(name="dlc_course",
                      course_fraction=0.5, course_start=2, true_horizon=1, course_horizon=1,
                      course_starts="start", kick_prob=0.0))
    sampler = ModelStateSampler(task, cfg, torch.Generator().manual_seed(0))
    actor = torch.nn.Linear(5, 2)
    torch.nn.init.zeros_(actor.weight)
    torch.nn.init.zeros_(actor.bias)
    noise = GaussianNoise(task.prior_mean, task.prior_cov)
    for k in range(12):  # every copy restarts every step (horizon 1): course copies at X = 0 once switched
        sampler.collect(actor, noise, k)
        switched = 0 if k < 2 else 32  # the 32 course copies switch together at course_start
        at_start = sampler.states[:, 5] == 0.0
        assert bool(at_start[:switched].all()), k
        assert not bool(at_start[switched:].any()), k  # the others (and every wide copy) restart wide
