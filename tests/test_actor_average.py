"""``AlgorithmConfig.actor_average``: the Polyak (EMA) average of the actor is the run's policy."""

from __future__ import annotations

import pytest

from mixedrl.algorithms.agpi import AGPI
from mixedrl.config import TrainConfig
from mixedrl.runs import make_trainer

FAST = dict(task="linear", run=dict(eval_every=10, eval_seeds=1, checkpoint_every=10))
ALGORITHM = dict(batch_size=32, iterations=30, hidden_sizes=(8,))


def test_the_average_is_what_is_evaluated() -> None:
    trainer: AGPI = make_trainer(TrainConfig(method="mixed", algorithm=dict(ALGORITHM, actor_average=0.9), **FAST))
    for _ in range(12):
        trainer.iteration()
    # evaluate() drives the averaged policy, not the iterate
    assert trainer.evaluate([0]) == trainer.task.evaluate(trainer.policy, [0])
    assert trainer.evaluate([0])["cost"] != trainer.task.evaluate(trainer.actor, [0])["cost"]


def test_no_average_by_default() -> None:
    trainer: AGPI = make_trainer(TrainConfig(method="mixed", algorithm=ALGORITHM, **FAST))
    trainer.iteration()
    assert trainer.actor_avg is None and trainer.policy is trainer.actor
    assert "actor_avg" not in trainer.state_dict()


@pytest.mark.parametrize("bad", [-0.1, 1.0, float("nan"), 2])
def test_actor_average_is_validated(bad: float) -> None:
    with pytest.raises(ValueError, match="^algorithm.actor_average"):
        TrainConfig(algorithm=dict(actor_average=bad))
