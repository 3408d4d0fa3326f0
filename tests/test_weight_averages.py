"""The EMA of weights of ``algorithm.critic_target`` (PEV's target critic): it follows the EMA recurrence, and
it is state of the run, saved in its checkpoints."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import pytest
import torch

from mixedrl.algorithms.agpi import AGPI
from mixedrl.config import TrainConfig
from mixedrl.runs import RunDirectory, make_trainer, train

FAST = dict(task="linear", run=dict(eval_every=10, eval_seeds=1, checkpoint_every=10))
ALGORITHM = dict(batch_size=32, iterations=30, hidden_sizes=(8,))

#: (config field, its key in AGPI.state_dict(), the averaged network, the network it averages)
AVERAGES: list[tuple[str, str, Callable[[AGPI], torch.nn.Module], Callable[[AGPI], torch.nn.Module]]] = [
    ("critic_target", "critic_target", lambda t: t.critic_target.module, lambda t: t.critic),
]


def _flat(module: torch.nn.Module) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1) for p in module.parameters()])


@pytest.mark.parametrize("field,key,averaged,iterate", AVERAGES)
def test_the_average_is_the_ema_of_the_iterates(field: str, key: str, averaged: Callable, iterate: Callable) -> None:
    beta = 0.9
    trainer: AGPI = make_trainer(TrainConfig(method="mixed", algorithm=dict(ALGORITHM, **{field: beta}), **FAST))
    expected = None
    for _ in range(12):
        trainer.iteration()
        w = _flat(iterate(trainer))
        # w_bar_1 = w_1; w_bar_k = beta w_bar_{k-1} + (1 - beta) w_k
        expected = w.clone() if expected is None else beta * expected + (1 - beta) * w
    assert torch.allclose(_flat(averaged(trainer)), expected, rtol=1e-5, atol=1e-7)
    assert not torch.allclose(_flat(averaged(trainer)), _flat(iterate(trainer)))  # the iterate moved on


@pytest.mark.parametrize("field,key,averaged,_", AVERAGES)
def test_resume_with_an_average_equals_uninterrupted(tmp_path: Path, field: str, key: str, averaged: Callable,
                                                     _: Callable) -> None:
    cfg = TrainConfig(method="mixed", algorithm=dict(ALGORITHM, **{field: 0.95}), **FAST)
    full = make_trainer(cfg)
    res_full = train(full, RunDirectory(tmp_path / "full"))
    cut = make_trainer(cfg)
    assert train(cut, RunDirectory(tmp_path / "cut"), stop_after=17) == {"interrupted_at": 17}
    resumed = make_trainer(cfg)
    res = train(resumed, RunDirectory(tmp_path / "cut"), resume=True)
    assert torch.equal(_flat(averaged(full)), _flat(averaged(resumed)))
    assert res["cost"] == res_full["cost"]


@pytest.mark.parametrize("field,key,averaged,iterate", AVERAGES)
def test_a_checkpoint_without_the_average_is_refused_and_changes_nothing(field: str, key: str, averaged: Callable,
                                                                        iterate: Callable) -> None:
    cfg = TrainConfig(method="mixed", algorithm=dict(ALGORITHM, **{field: 0.95}), **FAST)
    trainer: AGPI = make_trainer(cfg)
    trainer.iteration()
    state = trainer.state_dict()
    del state[key]
    fresh: AGPI = make_trainer(cfg)
    before = [_flat(averaged(fresh)).clone(), _flat(iterate(fresh)).clone()]
    with pytest.raises(ValueError, match=key):
        fresh.load_state_dict(state)
    assert torch.equal(_flat(averaged(fresh)), before[0]) and torch.equal(_flat(iterate(fresh)), before[1])
