"""``AlgorithmConfig.actor_average``: the Polyak (EMA) average of the actor is the run's policy."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from mixedrl.algorithms.agpi import AGPI
from mixedrl.config import TrainConfig
from mixedrl.runs import RunDirectory, make_trainer, train

FAST = dict(task="linear", run=dict(eval_every=10, eval_seeds=1, checkpoint_every=10))
ALGORITHM = dict(batch_size=32, iterations=30, hidden_sizes=(8,))


def _flat(module: torch.nn.Module) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1) for p in module.parameters()])


def test_the_average_is_the_ema_of_the_iterates_and_is_what_is_evaluated() -> None:
    beta = 0.9
    trainer: AGPI = make_trainer(TrainConfig(method="mixed", algorithm=dict(ALGORITHM, actor_average=beta), **FAST))
    expected = None
    for _ in range(12):
        trainer.iteration()
        theta = _flat(trainer.actor)
        # theta_bar_1 = theta_1; theta_bar_k = beta theta_bar_{k-1} + (1 - beta) theta_k
        expected = theta.clone() if expected is None else beta * expected + (1 - beta) * theta
    assert torch.allclose(_flat(trainer.policy), expected, rtol=1e-5, atol=1e-7)
    assert not torch.allclose(_flat(trainer.policy), _flat(trainer.actor))  # the iterate moved on
    # evaluate() drives the averaged policy, not the iterate
    assert trainer.evaluate([0]) == trainer.task.evaluate(trainer.policy, [0])
    assert trainer.evaluate([0])["cost"] != trainer.task.evaluate(trainer.actor, [0])["cost"]


def test_no_average_by_default() -> None:
    trainer: AGPI = make_trainer(TrainConfig(method="mixed", algorithm=ALGORITHM, **FAST))
    trainer.iteration()
    assert trainer.actor_avg is None and trainer.policy is trainer.actor
    assert "actor_avg" not in trainer.state_dict()


def test_resume_with_an_average_equals_uninterrupted(tmp_path: Path) -> None:
    cfg = TrainConfig(method="mixed", algorithm=dict(ALGORITHM, actor_average=0.95), **FAST)
    full = make_trainer(cfg)
    res_full = train(full, RunDirectory(tmp_path / "full"))
    cut = make_trainer(cfg)
    assert train(cut, RunDirectory(tmp_path / "cut"), stop_after=17) == {"interrupted_at": 17}
    resumed = make_trainer(cfg)
    res = train(resumed, RunDirectory(tmp_path / "cut"), resume=True)
    assert torch.equal(_flat(full.policy), _flat(resumed.policy))
    assert res["cost"] == res_full["cost"]


def test_a_checkpoint_without_the_average_is_refused_and_changes_nothing() -> None:
    cfg = TrainConfig(method="mixed", algorithm=dict(ALGORITHM, actor_average=0.95), **FAST)
    trainer: AGPI = make_trainer(cfg)
    trainer.iteration()
    state = trainer.state_dict()
    del state["actor_avg"]
    fresh: AGPI = make_trainer(cfg)
    before = _flat(fresh.policy).clone()
    with pytest.raises(ValueError, match="actor_avg"):
        fresh.load_state_dict(state)
    assert torch.equal(_flat(fresh.policy), before)


@pytest.mark.parametrize("bad", [-0.1, 1.0, float("nan"), 2])
def test_actor_average_is_validated(bad: float) -> None:
    with pytest.raises(ValueError, match="^algorithm.actor_average"):
        TrainConfig(algorithm=dict(actor_average=bad))
