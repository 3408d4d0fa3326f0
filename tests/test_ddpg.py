"""Tests of the DDPG baseline (mixedrl.algorithms.ddpg): data only, replay buffer, target networks,
exploration, reproducibility."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from mixedrl.algorithms.ddpg import DDPG, ReplayBuffer
from mixedrl.config import OPTIMISER_FIELDS, TrainConfig
from mixedrl.runs import train
from mixedrl.tasks import LinearTask

CFG = dict(method="ddpg", task="linear", algorithm=dict(iterations=30), ddpg=dict(envs=8, warmup=64, batch_size=32),
           run=dict(eval_every=30))


def test_replay_buffer_ring_and_state_dict() -> None:
    buf = ReplayBuffer(5, obs_dim=2, action_dim=1)
    for i in range(3):
        n = 2
        obs = torch.full((n, 2), float(i))
        buf.add(obs, torch.zeros(n, 1), torch.full((n,), float(i)), obs + 1, torch.zeros(n))
    assert buf.size == 5 and buf.pointer == 1
    # the oldest transition (i = 0, first row) was overwritten by the last batch's second row
    assert buf.cost.tolist() == [2.0, 0.0, 1.0, 1.0, 2.0]
    other = ReplayBuffer(5, 2, 1)
    other.load_state_dict(buf.state_dict())
    g1, g2 = torch.Generator().manual_seed(0), torch.Generator().manual_seed(0)
    for a, b in zip(buf.sample(7, g1), other.sample(7, g2)):
        assert torch.equal(a, b)
    with pytest.raises(ValueError, match="^n"):
        ReplayBuffer(3, 2, 1).sample(1, g1)


class CountingTask(LinearTask):
    """Counts calls of the model ``f`` outside and inside the true environment's step."""

    def __init__(self) -> None:
        super().__init__()
        self.f_calls = 0
        self.true_steps = 0

    def f(self, s: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        self.f_calls += 1
        return super().f(s, u)

    def true_step(self, s: torch.Tensor, u: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        self.true_steps += 1
        return super().true_step(s, u, generator)


def test_ddpg_uses_data_only() -> None:
    """The model f is evaluated only inside the simulated true environment, never to learn."""
    task = CountingTask()
    agent = DDPG(task, TrainConfig(**CFG))
    task.f_calls = task.true_steps = 0  # the construction's check_task probes f; count from here
    for _ in range(10):
        agent.iteration()
    assert task.true_steps > 0 and task.f_calls == task.true_steps
    assert agent.buffer.size == 64 + 9 * 8  # warm-up, then ddpg_envs transitions per iteration


def test_target_networks_follow_by_polyak_averaging() -> None:
    agent = DDPG(LinearTask(), TrainConfig(**CFG))
    before = [p.clone() for p in agent.critic_target.parameters()]
    agent.iteration()
    tau = agent.config.ddpg.tau
    for t_old, t_new, src in zip(before, agent.critic_target.parameters(), agent.critic.parameters()):
        torch.testing.assert_close(t_new, (1 - tau) * t_old + tau * src.detach(), rtol=1e-6, atol=1e-7)


def test_same_seed_identical_weights() -> None:
    def weights(seed: int) -> list[torch.Tensor]:
        agent = DDPG(LinearTask(), TrainConfig(seed=seed, **CFG))
        for _ in range(15):
            agent.iteration()
        return [p.detach().clone() for p in agent.actor.parameters()]

    a, b, c = weights(4), weights(4), weights(5)
    assert all(torch.equal(x, y) for x, y in zip(a, b))
    assert not all(torch.equal(x, y) for x, y in zip(a, c))


def test_ddpg_rejects_other_methods() -> None:
    with pytest.raises(ValueError, match="^config"):
        DDPG(LinearTask(), TrainConfig(method="mixed", task="linear"))
    agent = DDPG(LinearTask(), TrainConfig(**CFG))
    state = agent.state_dict()
    del state["buffer"]
    with pytest.raises(ValueError, match="^state"):
        agent.load_state_dict(state)


@pytest.mark.regression
def test_ddpg_improves_on_the_linear_task() -> None:
    """A quantitative learning check: after 1500 updates the discounted cost of the greedy policy is
    below half that of the initial (near-zero) policy on the same evaluation episodes."""
    cfg = TrainConfig(**{**CFG, "algorithm": dict(iterations=1500),
                         "ddpg": dict(envs=8, warmup=64, batch_size=128, critic_lr=3e-3, actor_lr=1e-3),
                         "run": dict(eval_every=1500)})
    agent = DDPG(LinearTask(), cfg)
    initial = agent.evaluate([11, 12])["cost"]
    res = train(agent)
    assert res["final"]["cost"] < 0.5 * initial


def test_true_transitions_are_counted_steps_of_the_true_environment() -> None:
    """``true_transitions`` counts every row the true environment stepped (warm-up included), per call."""

    class StepCounter(LinearTask):
        rows = 0

        def true_step(self, s: torch.Tensor, u: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
            StepCounter.rows += s.shape[0]
            return super().true_step(s, u, generator)

    task = StepCounter()
    agent = DDPG(task, TrainConfig(**CFG))
    for _ in range(5):  # training iterations only (the evaluation drives the true environment too)
        metrics = agent.iteration()
    assert StepCounter.rows == CFG["ddpg"]["warmup"] + 4 * CFG["ddpg"]["envs"]  # warm-up, then one step per copy
    assert agent.true_transitions == StepCounter.rows == metrics["data/true_transitions"]
    twin = DDPG(LinearTask(), TrainConfig(**CFG))
    twin.load_state_dict(agent.state_dict())
    assert twin.true_transitions == agent.true_transitions


# ----------------------------------------------------------------------------------------------------
# DDPG's own network and optimiser settings (ddpg.batch_size, activation, critic_lr, actor_lr, grad_clip)
# ----------------------------------------------------------------------------------------------------
def _weights_after(config: TrainConfig, iterations: int = 4) -> list[torch.Tensor]:
    agent = DDPG(LinearTask(), config)
    for _ in range(iterations):
        agent.iteration()
    return [p.detach().clone() for net in (agent.actor, agent.critic) for p in net.parameters()]


def _same(a: list[torch.Tensor], b: list[torch.Tensor]) -> bool:
    return len(a) == len(b) and all(x.shape == y.shape and torch.equal(x, y) for x, y in zip(a, b))


#: Values of the five settings away from the defaults (and from CFG's), each of which changes a run that reads it
#: (a clip of 1e-3 binds on every step).
_OTHER = {"batch_size": 16, "activation": "tanh", "critic_lr": 2e-3, "actor_lr": 2e-3, "grad_clip": 1e-3}


def test_ddpg_trains_with_its_own_settings_not_algorithm_2s() -> None:
    """Algorithm 2's ``algorithm.batch_size``, ``activation``, ``critic_lr``, ``actor_lr``, ``grad_clip`` do not
    change a DDPG run (same seed, same weights); each of DDPG's own ``ddpg.<field>`` does."""
    assert set(_OTHER) == set(OPTIMISER_FIELDS)
    base = TrainConfig(**CFG)
    reference = _weights_after(base)
    for name, value in _OTHER.items():
        assert _same(_weights_after(base.replace(**{f"algorithm.{name}": value})), reference), name
        assert not _same(_weights_after(base.replace(**{f"ddpg.{name}": value})), reference), name
    every = base.replace(**{f"algorithm.{name}": value for name, value in _OTHER.items()})
    assert _same(_weights_after(every), reference)


@pytest.mark.parametrize("name, value", [("batch_size", 0), ("batch_size", 2.5), ("activation", "sigmoid"),
                                         ("critic_lr", 0.0), ("actor_lr", float("nan")), ("actor_lr", -1e-3),
                                         ("grad_clip", 0.0), ("grad_clip", -1.0)])
def test_bad_ddpg_settings_are_refused_naming_the_key(name: str, value: object) -> None:
    with pytest.raises(ValueError, match=rf"^ddpg\.{name}: "):
        TrainConfig(method="ddpg", task="linear", ddpg={name: value})
    with pytest.raises(ValueError, match=rf"^ddpg\.{name}: "):
        TrainConfig.from_dict({"method": "mixed", "task": "linear", "ddpg": {name: value}})


def test_ddpg_settings_default_to_the_shipped_values_and_round_trip() -> None:
    cfg = TrainConfig(method="ddpg")
    assert {name: getattr(cfg.ddpg, name) for name in OPTIMISER_FIELDS} == {
        "batch_size": 512, "activation": "elu", "critic_lr": 3e-3, "actor_lr": 3e-4, "grad_clip": 10.0}
    unclipped = cfg.replace(**{"ddpg.grad_clip": math.inf})
    assert unclipped.to_dict()["ddpg"]["grad_clip"] == "inf"
    assert TrainConfig.from_dict(json.loads(json.dumps(unclipped.to_dict()))) == unclipped


def _old_record(values: dict[str, object], method: str = "ddpg") -> dict:
    """A config.json as written before DDPG had its own settings: ``values`` in ``algorithm``, none in ``ddpg``."""
    record = TrainConfig(method=method, task="linear", algorithm=values, ddpg=CFG["ddpg"]).to_dict()
    for name in OPTIMISER_FIELDS:
        del record["ddpg"][name]
    return json.loads(json.dumps(record))


def test_an_old_ddpg_config_reads_its_settings_from_algorithm(tmp_path: Path) -> None:
    """A DDPG run's config.json from before ``ddpg.batch_size`` etc. is the same run: DDPG takes the values it
    read then from ``algorithm``; a ``ddpg`` value, where given, wins; other methods keep DDPG's defaults."""
    old = {"iterations": 30, **_OTHER, "grad_clip": 5.0}
    path = tmp_path / "config.json"
    path.write_text(json.dumps(_old_record(old)))
    loaded = TrainConfig.load(path)
    assert {name: getattr(loaded.ddpg, name) for name in OPTIMISER_FIELDS} == {**_OTHER, "grad_clip": 5.0}
    assert {name: getattr(loaded.algorithm, name) for name in OPTIMISER_FIELDS} == {**_OTHER, "grad_clip": 5.0}
    own = TrainConfig(**{**CFG, "ddpg": {**CFG["ddpg"], **_OTHER, "grad_clip": 5.0}})
    assert loaded.ddpg == own.ddpg
    assert _same(_weights_after(loaded), _weights_after(own))
    unclipped = _old_record({**old, "grad_clip": math.inf})
    assert unclipped["algorithm"]["grad_clip"] == "inf"
    assert TrainConfig.from_dict(unclipped).ddpg.grad_clip == math.inf
    given = _old_record(old)
    given["ddpg"]["critic_lr"] = 1e-4
    assert TrainConfig.from_dict(given).ddpg.critic_lr == 1e-4
    assert TrainConfig.from_dict(given).ddpg.actor_lr == _OTHER["actor_lr"]
    mixed = TrainConfig.from_dict(_old_record(old, method="mixed"))
    assert all(getattr(mixed.ddpg, name) == getattr(TrainConfig().ddpg, name) for name in OPTIMISER_FIELDS)
    assert mixed.algorithm.critic_lr == _OTHER["critic_lr"]
