"""Tests of the batched engine (mixedrl.algorithms.batched): R runs of Algorithm 2 as one computation.

What is checked: a run alone is the engine with R = 1 (same bits as the run's own iteration); for R >= 2 a
run's weights, IBE and generator do not depend on what else shares the batch (two compositions); a batch
starts from the same floats as the runs alone; the MVC loop and the budget are per run (masks); the
runs of a batch keep their own optimiser state, checkpoints and resume; bad batches are refused.
"""

from __future__ import annotations

import copy

import pytest
import torch

from mixedrl.algorithms.agpi import AGPI
from mixedrl.algorithms.batched import BatchedAGPI, StackedNetwork, batch_key
from mixedrl.config import TrainConfig
from mixedrl.runs import RunDirectory, make_trainer, train_batch



def config(method: str, seed: int, task: str = "dlc", **algorithm: object) -> TrainConfig:
    algo = {"iterations": 6, "batch_size": 32, **algorithm}
    return TrainConfig(method=method, seed=seed, task=task, algorithm=algo,
                       run={"eval_every": 1000, "checkpoint_every": 1000, "eval_seeds": 1})


def weights(trainer: AGPI) -> list[torch.Tensor]:
    return [p.detach().clone() for p in [*trainer.critic.parameters(), *trainer.actor.parameters()]]


def assert_same(a: AGPI, b: AGPI) -> None:
    for x, y in zip(weights(a), weights(b)):
        assert torch.equal(x, y)
    assert torch.equal(a.generator.get_state(), b.generator.get_state())
    for x, y in zip(a.noise_moments(), b.noise_moments()):
        assert (x == y).all()


def test_a_run_alone_is_the_engine_with_one_run() -> None:
    a, b = make_trainer(config("mixed", 0)), make_trainer(config("mixed", 0))
    rows_a = [a.iteration() for _ in range(4)]
    engine = BatchedAGPI([b])
    rows_b = [engine.iteration()[0] for _ in range(4)]
    assert rows_a == rows_b
    assert_same(a, b)


@pytest.mark.parametrize("task", ["dlc", "linear"])
def test_a_run_has_the_same_bits_in_any_batch_of_two_or_more(task: str) -> None:
    target = [make_trainer(config("mixed", 0, task)) for _ in range(2)]
    first = BatchedAGPI([target[0], make_trainer(config("model", 1, task))])
    second = BatchedAGPI([make_trainer(config("oracle", 2, task)), make_trainer(config("model", 3, task)), target[1]])
    rows_1 = [first.iteration()[0] for _ in range(5)]
    rows_2 = [second.iteration()[2] for _ in range(5)]
    assert rows_1 == rows_2
    assert_same(target[0], target[1])


def test_a_batch_starts_where_the_runs_alone_do() -> None:
    # the batched and the unbatched kernels agree to float32 rounding (not bit for bit, see the module docs)
    alone = [make_trainer(config(m, s)) for m, s in (("mixed", 0), ("model", 1))]
    batch = BatchedAGPI([make_trainer(config(m, s)) for m, s in (("mixed", 0), ("model", 1))])
    rows = batch.iteration()
    for r, trainer in enumerate(alone):
        row = trainer.iteration()
        assert row["train/critic_loss"] == pytest.approx(rows[r]["train/critic_loss"], rel=1e-5)
        assert row["train/actor_objective"] == pytest.approx(rows[r]["train/actor_objective"], rel=1e-5)
        for x, y in zip(weights(trainer), weights(batch.members[r])):
            torch.testing.assert_close(x, y, rtol=1e-4, atol=1e-6)


def test_the_members_stay_usable_modules_bound_to_the_stacked_weights() -> None:
    runs = [make_trainer(config("mixed", s)) for s in (0, 1)]
    before = [copy.deepcopy(r.actor.state_dict()) for r in runs]
    batch = BatchedAGPI(runs)
    batch.iteration()
    obs = torch.zeros(3, runs[0].task.obs_dim)
    stacked = batch.actor(torch.zeros(2 * 32, runs[0].task.obs_dim))
    for r, run in enumerate(runs):
        assert not torch.equal(run.actor.state_dict()["net.body.0.weight"], before[r]["net.body.0.weight"])
        torch.testing.assert_close(run.actor(obs)[0], stacked[r * 32], rtol=1e-5, atol=1e-6)
        assert run.critic_opt.state_dict()["state"][0]["step"] == 1.0  # its own Adam stepped once


def test_inactive_runs_draw_nothing_and_do_not_move() -> None:
    runs = [make_trainer(config("mixed", s)) for s in (0, 1)]
    batch = BatchedAGPI(runs)
    batch.iteration()
    frozen = weights(runs[1]), runs[1].generator.get_state(), runs[1].k, runs[1].noise_moments()
    rows = batch.iteration([True, False])
    assert rows[1] is None and rows[0] is not None
    for x, y in zip(frozen[0], weights(runs[1])):
        assert torch.equal(x, y)
    assert torch.equal(frozen[1], runs[1].generator.get_state()) and runs[1].k == frozen[2] == 1
    assert runs[0].k == 2


def test_the_mvc_loop_is_masked_per_run() -> None:
    # j_max = 1 allows one inner step, j_max = 5 five: each run follows its own, and the run with
    # j_max = 5 gets the bits it gets beside any other run
    a = [make_trainer(config("mixed", 0, j_max=5, mvc_check="all")) for _ in range(2)]
    b = BatchedAGPI([a[0], make_trainer(config("mixed", 1, j_max=1, mvc_check="all"))])
    c = BatchedAGPI([a[1], make_trainer(config("model", 4, j_max=3))])
    steps_b, steps_c = [], []
    for _ in range(4):
        rb, rc = b.iteration(), c.iteration()
        assert rb[1]["mvc/inner_steps"] <= 1.0
        steps_b.append(rb[0]["mvc/inner_steps"])
        steps_c.append(rc[0]["mvc/inner_steps"])
    assert steps_b == steps_c and max(steps_b) > 1  # the "all" form fails often at the start
    assert_same(a[0], a[1])
    for r in (0,):
        assert b.members[r].actor_opt.state_dict()["state"][0]["step"] == 4 + sum(steps_b)


def test_train_batch_writes_each_run_and_resumes(tmp_path) -> None:
    cfgs = [config("mixed", 0), config("model", 1), config("oracle", 2, iterations=4)]
    whole = train_batch([make_trainer(c) for c in cfgs], [RunDirectory(tmp_path / f"w{i}") for i in range(3)],
                        progress=False)
    dirs = [RunDirectory(tmp_path / f"r{i}") for i in range(3)]
    cut = train_batch([make_trainer(c) for c in cfgs], dirs, progress=False, stop_after=3)
    assert all(c == {"interrupted_at": 3} for c in cut)
    resumed = train_batch([make_trainer(c) for c in cfgs], dirs, resume=True, progress=False)
    for w, r, c in zip(whole, resumed, cfgs):
        assert r["iterations"] == c.algorithm.iterations
        assert r["final"] == w["final"] and r["batch_size_runs"] == 3
    for i in range(3):
        assert len(dirs[i].read_metrics()) == cfgs[i].algorithm.iterations
        assert dirs[i].read_config() == cfgs[i]


def test_bad_batches_are_refused() -> None:
    with pytest.raises(ValueError, match="algorithm.batch_size"):
        BatchedAGPI([make_trainer(config("mixed", 0)), make_trainer(config("mixed", 1, batch_size=16))])
    with pytest.raises(ValueError, match="task"):
        BatchedAGPI([make_trainer(config("mixed", 0)), make_trainer(config("mixed", 1, task="linear"))])
    with pytest.raises(ValueError, match="not an AGPI"):
        BatchedAGPI([make_trainer(config("mixed", 0)), make_trainer(TrainConfig(method="ddpg"))])
    run = make_trainer(config("mixed", 0))
    with pytest.raises(ValueError, match="twice"):
        BatchedAGPI([run, run])
    with pytest.raises(ValueError, match="at least one"):
        BatchedAGPI([])
    engine = BatchedAGPI([make_trainer(config("mixed", 0)), make_trainer(config("mixed", 1))])
    with pytest.raises(ValueError, match="active"):
        engine.iteration([True])
    with pytest.raises(ValueError, match="multiple"):
        StackedNetwork([run.actor, make_trainer(config("mixed", 1)).actor], 32)(torch.zeros(33, run.task.obs_dim))


def test_batch_key_groups_by_shape_not_by_seed_or_method() -> None:
    assert batch_key(config("mixed", 0)) == batch_key(config("oracle", 7, critic_lr=1e-3, iterations=9))
    assert batch_key(config("mixed", 0)) != batch_key(config("mixed", 0, batch_size=64))
    ddpg = batch_key(TrainConfig(method="ddpg"))  # DDPG batches of its own (mixedrl.algorithms.batched_ddpg)
    assert ddpg[0] == "ddpg" and ddpg != batch_key(TrainConfig(method="mixed"))
