"""Tests of validation.peers: the transition counter, the evaluation's observation and action mapping, argument
checks, the missing-extra error, and (marked ``peers``, extra 'peers') short seeded SB3 runs."""

from __future__ import annotations

import inspect
import json
import sys

import numpy as np
import pytest
import torch

from mixedrl.config import TrainConfig
from mixedrl.envs import DoubleLaneChangeEnv, evaluate_tracking
from mixedrl.runs import eval_seeds, make_trainer
from validation.peers import (
    INSTALL_HINT,
    PhysicalPolicy,
    TransitionCounter,
    import_sb3,
    make_peer_env,
    observation_mismatch,
    peer_task,
    train_peer,
)

#: Float64 round-off between the env's Python-float observation and the task's torch ``observe`` of the same
#: state (same formulas, different evaluation order); components are O(1).
OBS_ATOL = 1e-12


def test_peer_task_is_the_runs_task_and_seeds() -> None:
    cfg = TrainConfig(seed=3, run=dict(eval_seeds=4))
    task, seeds = peer_task(3, 4)
    assert seeds == eval_seeds(cfg)
    assert task.model.config == make_trainer(cfg).task.model.config
    env = make_peer_env(task)
    assert isinstance(env.unwrapped, DoubleLaneChangeEnv)
    assert env.unwrapped.config == task.model.config


def test_counter_counts_every_step_and_nothing_else(rng: np.random.Generator) -> None:
    env = TransitionCounter(DoubleLaneChangeEnv())
    env.reset(seed=0)
    assert env.count == 0
    steps = 0
    for a in rng.uniform(-0.2, 0.2, size=(37, 2)):
        _, _, terminated, truncated, _ = env.step(a)
        steps += 1
        if terminated or truncated:
            env.reset()
    env.reset(seed=1)
    assert env.count == steps == 37
    with pytest.raises(ValueError, match="action"):
        env.step(np.array([np.nan, 0.0]))
    assert env.count == 37  # a refused step is not a transition


def test_env_observation_is_the_tasks_observation_of_the_state(rng: np.random.Generator) -> None:
    """What the peer sees in training is ``task.observe(state)`` (what our actors see), at every step."""
    task, _ = peer_task(0)
    env = make_peer_env(task)
    worst = observation_mismatch(env, task, rng.uniform(-0.5, 0.5, size=(400, 2)), seed=5)
    assert env.count > 50
    assert worst <= OBS_ATOL


def test_evaluation_observations_are_the_tasks_observation_of_the_state() -> None:
    """The course evaluation feeds the policy ``task.observe`` of the state evaluate_tracking drives."""
    task, seeds = peer_task(0)
    seen: list[np.ndarray] = []

    def act(obs: np.ndarray) -> np.ndarray:
        seen.append(np.array(obs))
        return -np.tanh(obs[:2])

    res = evaluate_tracking(act, task.model.config, seed=seeds[0], normalized_actions=True, max_steps=300)
    obs = task.observe(torch.as_tensor(res.states, dtype=torch.float64)).numpy()
    np.testing.assert_allclose(np.asarray(seen), obs[:-1], rtol=0, atol=OBS_ATOL)


def test_physical_policy_evaluates_exactly_as_the_env_maps_actions() -> None:
    """task.evaluate(PhysicalPolicy(act)) (our runs' evaluation) == driving the env with act's normalised
    actions (clipped and scaled by the env itself), bit for bit, clipping included."""
    task, seeds = peer_task(1)

    def act(obs: np.ndarray) -> np.ndarray:  # leaves [-1, 1] on large errors
        return np.array([-8.0 * obs[4] - 5.0 * obs[3], -400.0 * obs[2]])

    ours = task.evaluate(PhysicalPolicy(act, task.model.config), seeds)
    runs = [evaluate_tracking(act, task.model.config, seed=s, normalized_actions=True) for s in seeds]
    assert any(np.any(np.abs(act(o)) > 1.0) for r in runs for o in r.observations)  # clipping exercised
    assert ours["lateral_mae"] == np.mean([r.mean_abs_lateral_error for r in runs])
    assert ours["speed_mae"] == np.mean([r.mean_abs_speed_error for r in runs])
    assert ours["cost"] == np.mean([r.total_cost for r in runs])


def test_physical_policy_values() -> None:
    task, _ = peer_task(0)
    cfg = task.model.config
    policy = PhysicalPolicy(lambda obs: np.array([0.5, -2.0]), cfg)
    np.testing.assert_array_equal(policy(np.zeros(5)), [0.5 * cfg.delta_max, -cfg.ax_max])


@pytest.mark.parametrize("kwargs, match", [
    ({"algo": "ppo"}, "algo"),
    ({"algo": "sac", "transitions": 0}, "transitions"),
    ({"algo": "sac", "transitions": 1.5}, "transitions"),
    ({"algo": "td3", "eval_every": -1}, "eval_every"),
    ({"algo": "td3", "eval_seeds": 0}, "eval_seeds"),
    ({"algo": "td3", "seed": -1}, "seed"),
    ({"algo": "td3", "seed": True}, "seed"),
    ({"algo": "td3", "kwargs": {"seed": 3}}, "kwargs"),
    ({"algo": "td3", "kwargs": {"learning_rate": object()}}, "kwargs"),
])
def test_bad_arguments(kwargs: dict, match: str, tmp_path) -> None:
    out = tmp_path / "x.json"
    with pytest.raises(ValueError, match=match):
        train_peer(**kwargs, out=out)
    assert not out.exists()


def test_kwargs_not_a_dict() -> None:
    with pytest.raises(TypeError, match="kwargs"):
        train_peer("sac", kwargs=[("learning_starts", 5)])  # type: ignore[arg-type]


def test_missing_sb3_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "stable_baselines3", None)  # import fails as if not installed
    with pytest.raises(ImportError) as info:
        import_sb3()
    assert "'peers'" in str(info.value) and "pip install" in str(info.value) and str(info.value) == INSTALL_HINT
    with pytest.raises(ImportError, match="peers"):
        train_peer("sac", transitions=10)


# ---------------------------------------------------------------------------------------- SB3 (extra 'peers')
TINY = {"transitions": 600, "eval_every": 300, "eval_seeds": 1, "kwargs": {"learning_starts": 100}}


@pytest.mark.peers
@pytest.mark.parametrize("algo", ["td3", "sac"])
def test_seeded_run_is_reproducible_and_counted(algo: str, tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("stable_baselines3")
    import tempfile

    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))  # where SB3's default logger would make its folder
    out = tmp_path / "runs" / f"{algo}.json"
    a = train_peer(algo, seed=4, out=out, **TINY)
    assert not [p.name for p in scratch.iterdir() if p.name.startswith("SB3-")]  # no SB3-<date> folder left behind
    b = train_peer(algo, seed=4, **TINY)
    assert [r["true_transitions"] for r in a["rows"]] == [300, 600]
    assert a["true_transitions"] == 600
    strip = lambda rows: [{k: v for k, v in r.items() if k != "wall_seconds"} for r in rows]  # noqa: E731
    assert strip(a["rows"]) == strip(b["rows"])
    assert all(np.isfinite(r["cost"]) and r["cost"] > 0 for r in a["rows"])
    walls = [r["wall_seconds"] for r in a["rows"]]
    assert 0 < walls[0] < walls[1] <= a["train_seconds"]
    # the written file is the returned record; the config says what ran
    assert json.loads(out.read_text()) == json.loads(json.dumps(a))
    cfg = a["config"]
    sb3 = import_sb3()
    assert cfg["sb3_version"] == sb3.__version__
    assert cfg["kwargs"] == {"learning_starts": 100}
    assert cfg["hyperparameters"]["learning_starts"] == 100
    assert cfg["eval_seeds"] == eval_seeds(TrainConfig(seed=4, run=dict(eval_seeds=1)))
    sig = inspect.signature({"td3": sb3.TD3, "sac": sb3.SAC}[algo].__init__)
    for name in ("learning_rate", "batch_size", "buffer_size", "tau", "gamma", "gradient_steps", "action_noise"):
        assert cfg["hyperparameters"][name] == sig.parameters[name].default  # SB3's defaults, untouched
    # another seed gives another run
    c = train_peer(algo, seed=5, **TINY)
    assert strip(c["rows"]) != strip(a["rows"])


@pytest.mark.peers
def test_evaluations_happen_after_learning_from_the_counted_transitions() -> None:
    """An evaluation period that SB3's rollouts do not divide (train_freq 7) still evaluates at the first
    rollout boundary after each multiple, with the exact count, and once more at the end; SB3 finishes its
    last rollout past the budget (250 -> 252), and the count says so."""
    pytest.importorskip("stable_baselines3")
    res = train_peer("td3", seed=0, transitions=250, eval_every=100, eval_seeds=1,
                     kwargs={"learning_starts": 50, "train_freq": 7})
    counts = [r["true_transitions"] for r in res["rows"]]
    assert counts == [105, 203, 252]  # first multiples of 7 at or after 100, 200; then the end of the last rollout
    assert res["true_transitions"] == 252
    assert res["config"]["hyperparameters"]["train_freq"] == {"frequency": 7, "unit": "step"}
