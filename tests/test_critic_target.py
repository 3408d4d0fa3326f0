"""``AlgorithmConfig.critic_target``: PEV's target takes an EMA of the critic's weights (a departure; 0.8 by
default, with the rollout learner). The one-step PEV's target (eq. 50) is tested here: ``rollout_horizon = 0``."""

from __future__ import annotations

import pytest
import torch

from mixedrl.algorithms.agpi import AGPI
from mixedrl.algorithms.batched import BatchedAGPI
from mixedrl.config import TrainConfig
from mixedrl.expectation import h_value
from mixedrl.runs import make_trainer

FAST = dict(task="linear", run=dict(eval_every=10, eval_seeds=1, checkpoint_every=10))
ALGORITHM = dict(batch_size=32, iterations=30, hidden_sizes=(8,), batch_weighting="uniform", rollout_horizon=0)


def _flat(module: torch.nn.Module) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1) for p in module.parameters()])


def test_pev_regresses_on_the_targets_value() -> None:
    """The iteration's critic loss is 1/2 mean (V(x; w) - l(x', u) - gamma V(x'; w_bar))^2, with w_bar the
    target's weights and not the critic's (reverting the target to the critic fails this)."""
    cfg = TrainConfig(method="model", algorithm=dict(ALGORITHM, critic_target=0.9), **FAST)
    trainer: AGPI = make_trainer(cfg)
    for _ in range(5):
        trainer.iteration()
    twin: AGPI = make_trainer(cfg)
    twin.load_state_dict(trainer.state_dict())
    assert not torch.allclose(_flat(trainer.critic_target.module), _flat(trainer.critic))
    row = trainer.iteration()
    s = trainer.last_batch
    nodes = twin.nodes(*twin.noise_moments())
    task = twin.task
    with torch.no_grad():
        u = twin.actor(task.observe(s))
        v = twin.critic(task.observe(s))
        scale = float(getattr(task, "value_scale", 1.0))
        with_target = 0.5 * float((((v - h_value(task, twin.critic_target.module, s, u, *nodes)) / scale) ** 2).mean())
        with_critic = 0.5 * float((((v - h_value(task, twin.critic, s, u, *nodes)) / scale) ** 2).mean())
    assert row["train/critic_loss"] == pytest.approx(with_target, rel=1e-5)
    assert abs(with_target - with_critic) > 1e-3 * with_target


def test_off_at_zero_and_a_batch_equals_its_runs_alone() -> None:
    assert TrainConfig().algorithm.critic_target == 0.8
    trainer: AGPI = make_trainer(TrainConfig(method="mixed", algorithm=dict(ALGORITHM, critic_target=0.0), **FAST))
    trainer.iteration()
    assert trainer.critic_target is None and "critic_target" not in trainer.state_dict()
    cfgs = [TrainConfig(method=m, seed=s, algorithm=dict(ALGORITHM, critic_target=0.95), **FAST)
            for m, s in (("mixed", 0), ("model", 1), ("oracle", 2))]
    alone = [make_trainer(c) for c in cfgs]
    together = [make_trainer(c) for c in cfgs]
    engine = BatchedAGPI(together)
    for _ in range(8):
        for t in alone:
            t.iteration()
        engine.iteration()
    for a, b in zip(alone, together):
        assert torch.allclose(_flat(a.critic_target.module), _flat(b.critic_target.module), rtol=1e-4, atol=1e-6)
        assert torch.allclose(_flat(a.critic), _flat(b.critic), rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("bad", [-0.1, 1.0, float("nan"), "0.9"])
def test_critic_target_is_validated(bad: object) -> None:
    with pytest.raises(ValueError, match="^algorithm.critic_target"):
        TrainConfig(algorithm=dict(critic_target=bad))


def test_ddpg_ignores_the_pev_target() -> None:
    """DDPG has its own target networks (``ddpg.tau``): Algorithm 2's target critic is no departure of a DDPG run."""
    from mixedrl import departures

    cfg = TrainConfig(method="ddpg", algorithm=dict(critic_target=0.99))
    assert "critic_target" not in departures.used(cfg)
    assert "critic_target" in departures.used(cfg.replace(method="mixed"))
