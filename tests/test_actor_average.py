"""``AlgorithmConfig.actor_average_window`` (:mod:`mixedrl.departures.actor_average`): the deployed actor's weights
are the uniform average of the actor's after every iteration of the budget's last fraction ``a``; training is
unchanged."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from mixedrl import departures
from mixedrl.algorithms.agpi import AGPI
from mixedrl.algorithms.batched import BatchedAGPI
from mixedrl.config import TrainConfig
from mixedrl.departures import actor_average
from mixedrl.runs import RunDirectory, make_trainer, train

FAST = dict(task="linear", run=dict(eval_every=10, eval_seeds=1, checkpoint_every=10))
ALGORITHM = dict(batch_size=32, iterations=20, hidden_sizes=(8,), rollout_horizon=4)


def _flat(module: torch.nn.Module) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1) for p in module.parameters()])


def _snapshots(trainer: AGPI, iterations: int) -> list[torch.Tensor]:
    """The actor's weights after each of ``iterations`` iterations."""
    out = []
    for _ in range(iterations):
        trainer.iteration()
        out.append(_flat(trainer.actor).clone())
    return out


def test_the_deployed_actor_is_the_mean_of_the_late_weights() -> None:
    """a = 0.3 of 20 iterations: theta_bar is the mean of theta^{k+1} for k = 14 .. 19, not of k = 13 .. 19 or
    15 .. 19 (an off-by-one start fails this), and training itself is the run without the departure."""
    cfg = TrainConfig(method="mixed", algorithm=dict(ALGORITHM, actor_average_window=0.3), **FAST)
    assert actor_average.start(cfg) == 14
    trainer: AGPI = make_trainer(cfg)
    plain: AGPI = make_trainer(cfg.replace(**{"algorithm.actor_average_window": 0.0}))
    snaps = _snapshots(trainer, 13)
    assert trainer.learned_policy is trainer.actor  # nothing averaged before the window
    snaps += _snapshots(trainer, 7)
    _snapshots(plain, 20)
    assert torch.equal(_flat(trainer.actor), _flat(plain.actor))  # theta is untouched
    assert int(trainer.actor_average.n_averaged) == 6
    expected = torch.stack(snaps[14:]).mean(dim=0)
    assert torch.allclose(_flat(trainer.learned_policy), expected, rtol=1e-6, atol=1e-7)
    for wrong in (torch.stack(snaps[13:]).mean(dim=0), torch.stack(snaps[15:]).mean(dim=0), snaps[-1]):
        assert not torch.allclose(wrong, expected, rtol=1e-4, atol=1e-5)
    # the deployed policy (policy, feed-forward "learned" on the linear test bed at feedforward "learned") acts with
    # the average
    obs = trainer.task.observe(trainer.task.sample_initial(5, torch.Generator().manual_seed(0)).float())
    assert torch.equal(trainer.learned_policy(obs), trainer.actor_average.module(obs))
    assert not torch.allclose(trainer.learned_policy(obs), trainer.actor(obs))


def test_resume_equals_uninterrupted(tmp_path: Path) -> None:
    """Interrupted inside the averaging window and resumed: the average is the uninterrupted run's, bit for bit
    (dropping the average from the checkpoint fails this)."""
    cfg = TrainConfig(method="mixed", algorithm=dict(ALGORITHM, actor_average_window=0.5), **FAST)
    full = make_trainer(cfg)
    train(full, RunDirectory(tmp_path / "full"))
    first = make_trainer(cfg)
    assert train(first, RunDirectory(tmp_path / "cut"), stop_after=15) == {"interrupted_at": 15}
    resumed = make_trainer(cfg)
    train(resumed, RunDirectory(tmp_path / "cut"), resume=True)
    assert int(full.actor_average.n_averaged) == int(resumed.actor_average.n_averaged) == 10
    assert torch.equal(_flat(full.actor_average.module), _flat(resumed.actor_average.module))


def test_a_batch_averages_each_run_on_its_own() -> None:
    """Runs trained as one computation: each run's average is its own actor's (float32 rounding apart)."""
    cfgs = [TrainConfig(method=m, seed=s, algorithm=dict(ALGORITHM, actor_average_window=0.5), **FAST)
            for m, s in (("mixed", 0), ("model", 1))]
    alone = [make_trainer(c) for c in cfgs]
    together = [make_trainer(c) for c in cfgs]
    engine = BatchedAGPI(together)
    for _ in range(20):
        for t in alone:
            t.iteration()
        engine.iteration()
    for a, b in zip(alone, together):
        assert int(b.actor_average.n_averaged) == 10
        assert torch.allclose(_flat(a.actor_average.module), _flat(b.actor_average.module), rtol=1e-4, atol=1e-6)
    assert not torch.allclose(_flat(together[0].actor_average.module), _flat(together[1].actor_average.module))


def test_off_in_the_paper_preset_and_for_ddpg() -> None:
    paper = TrainConfig.preset("paper", method="mixed", **FAST)
    assert paper.algorithm.actor_average_window == 0.0 and "actor_average" not in departures.used(paper)
    trainer = make_trainer(paper.replace(**{"algorithm.iterations": 2}))
    trainer.iteration()
    assert trainer.actor_average is None and "actor_average" not in trainer.state_dict()
    assert trainer.learned_policy is trainer.actor
    cfg = TrainConfig(method="ddpg", algorithm=dict(actor_average_window=0.5))
    assert "actor_average" not in departures.used(cfg)
    assert "actor_average" in departures.used(cfg.replace(method="oracle"))


@pytest.mark.parametrize("bad", [-0.1, 1.5, float("nan"), "0.5"])
def test_actor_average_is_validated(bad: object) -> None:
    with pytest.raises(ValueError, match="^algorithm.actor_average_window"):
        TrainConfig(algorithm=dict(actor_average_window=bad))


def test_the_check_scripts_last_policy_is_the_run_without_the_departure(tmp_path: Path,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """experiments/analysis/actor_average_check.py evaluates one run twice; its ``last`` figures are those of a run
    trained without the departure (evaluating the average twice, or the last actor twice, fails this)."""
    root = Path(__file__).resolve().parents[1]
    monkeypatch.syspath_prepend(str(root / "experiments" / "analysis"))
    monkeypatch.syspath_prepend(str(root))
    import actor_average_check as check
    import learner_tuning

    monkeypatch.setattr(check, "OUT", tmp_path)
    short = dict(learner_tuning.VARIANTS, default=dict(learner_tuning.VARIANTS["default"], iterations=20))
    monkeypatch.setattr(check, "VARIANTS", short)
    row = check.run_one(("cart_friction", "mixed", 100, 0.5))
    assert row["averaged_iterations"] == 10 and (tmp_path / "runs" / "cart_friction_mixed_100.json").exists()
    task = check.SYSTEMS["cart_friction"]()
    plain = AGPI(task, TrainConfig(method="mixed", task="linear", seed=100,
                                   algorithm={**learner_tuning.ONESTEP, **short["default"]}))
    train(plain, progress=False)
    assert check.measure("cart_friction", task, plain, check.eval_seeds(plain.config)) == row["last"]
    assert row["average"] != row["last"]
    assert check.run_one(("cart_friction", "mixed", 100, 0.5)) == row  # read back, not trained again
