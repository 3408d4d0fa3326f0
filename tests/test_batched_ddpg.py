"""Tests of the batched DDPG engine (mixedrl.algorithms.batched_ddpg): R DDPG runs as one computation.

What is checked: a run alone is the engine with R = 1, bit for bit the textbook iteration of the shipped
DDPG (written out below); for R >= 2 a run's weights, targets, optimiser states, buffer, generator and rows
do not depend on what else shares the batch (two compositions, runs with other seeds, rates, environment
counts and tau beside it); a batch starts from the runs' own data and agrees with the runs alone to
float32 rounding; inactive runs draw nothing and do not move; true transitions are counted per run;
train_batch writes, resumes and restores a finished member as for Algorithm 2, and a batched run's
checkpoint is an ordinary DDPG run's; plan_batches groups DDPG runs; bad batches are refused by name.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from mixedrl.algorithms.batched import batch_key
from mixedrl.algorithms.batched_ddpg import BatchedDDPG
from mixedrl.algorithms.ddpg import DDPG
from mixedrl.config import OPTIMISER_FIELDS, TrainConfig
from mixedrl.runs import RunDirectory, evaluate_run, load_checkpoint, make_trainer, train_batch
from mixedrl.schedule import set_learning_rates
from mixedrl.sweep import expand, parse_spec, plan_batches, run_points

NETS = ("critic", "actor", "critic_target", "actor_target")


def config(seed: int, task: str = "linear", ddpg: dict | None = None, **fields: object) -> TrainConfig:
    """A small DDPG run; ``fields``: ``algorithm.*`` settings, DDPG's own (minibatch size, activation,
    learning rates, gradient clip: ``OPTIMISER_FIELDS``) going to ``ddpg.*``."""
    algo = {"iterations": 8, **{k: v for k, v in fields.items() if k not in OPTIMISER_FIELDS}}
    own = {"batch_size": 32, **{k: v for k, v in fields.items() if k in OPTIMISER_FIELDS}}
    return TrainConfig(method="ddpg", seed=seed, task=task, algorithm=algo,
                       ddpg={"envs": 4, "warmup": 40, **own, **(ddpg or {})},
                       run={"eval_every": 1000, "checkpoint_every": 1000, "eval_seeds": 1})


def state(agent: DDPG) -> dict[str, torch.Tensor]:
    """Everything of a run that training moves, as tensors (networks, Adam moments, generator, data)."""
    out = {f"{net}.{k}": v.detach().clone() for net in NETS for k, v in getattr(agent, net).state_dict().items()}
    for name in ("critic_opt", "actor_opt"):
        for i, s in getattr(agent, name).state_dict()["state"].items():
            out.update({f"{name}.{i}.{k}": torch.as_tensor(v).clone() for k, v in s.items()})
    out.update(generator=agent.generator.get_state(), states=agent.states.clone(), steps=agent.steps.clone())
    buf = agent.buffer.state_dict()
    out.update({f"buffer.{k}": torch.as_tensor(v) for k, v in buf.items()})
    out.update(k=torch.tensor(agent.k), true=torch.tensor(agent.true_transitions))
    return out


def assert_same(a: DDPG, b: DDPG) -> None:
    sa, sb = state(a), state(b)
    assert sa.keys() == sb.keys()
    for key in sa:
        assert torch.equal(sa[key], sb[key]), key


def textbook_iteration(agent: DDPG) -> dict[str, float]:
    """The DDPG iteration as shipped before the batched engine (backward/zero_grad form), for the bits."""
    cfg, task = agent.config, agent.task
    set_learning_rates(cfg, agent.k, agent.critic_opt, agent.actor_opt)
    mean_cost = agent.collect()
    while agent.buffer.size < cfg.ddpg.warmup:
        agent.collect()
    obs, act, cost, next_obs, terminal = agent.buffer.sample(cfg.ddpg.batch_size, agent.generator)
    scale = float(task.value_scale)
    with torch.no_grad():
        target = cost + task.gamma * (1.0 - terminal) * agent.critic_target(next_obs, agent.actor_target(next_obs))

    def step(loss: torch.Tensor, net: torch.nn.Module, opt: torch.optim.Optimizer) -> None:
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), cfg.ddpg.grad_clip)
        opt.step()

    q = agent.critic(obs, act)
    critic_loss = 0.5 * ((q - target) / scale).pow(2).mean()
    step(critic_loss, agent.critic, agent.critic_opt)
    agent.critic.requires_grad_(False)
    actor_loss = agent.critic(obs, agent.actor(obs)).mean() / scale
    step(actor_loss, agent.actor, agent.actor_opt)
    agent.critic.requires_grad_(True)
    for target_net, source in ((agent.critic_target, agent.critic), (agent.actor_target, agent.actor)):
        with torch.no_grad():
            for pt, ps in zip(target_net.parameters(), source.parameters()):
                pt.mul_(1.0 - cfg.ddpg.tau).add_(ps, alpha=cfg.ddpg.tau)
    agent.k += 1
    return {"train/critic_loss": float(critic_loss.detach()), "train/actor_loss": float(actor_loss.detach()),
            "train/value_mean": float(q.detach().mean()), "train/env_cost": mean_cost,
            "train/buffer_size": float(agent.buffer.size), "data/true_transitions": float(agent.true_transitions)}


@pytest.mark.parametrize("task", ["linear", "dlc"])
def test_a_run_alone_is_the_engine_with_one_run_and_the_shipped_bits(task: str) -> None:
    a, b, c = (make_trainer(config(0, task)) for _ in range(3))
    rows_a = [textbook_iteration(a) for _ in range(12)]
    rows_b = [b.iteration() for _ in range(12)]
    engine = BatchedDDPG([c])
    rows_c = [engine.iteration()[0] for _ in range(12)]
    assert rows_a == rows_b == rows_c
    assert_same(a, b)
    assert_same(a, c)


@pytest.mark.parametrize("task", ["linear", "dlc"])
def test_a_run_has_the_same_bits_in_any_batch_of_two_or_more(task: str) -> None:
    target = [make_trainer(config(0, task)) for _ in range(2)]
    first = BatchedDDPG([target[0], make_trainer(config(1, task))])
    second = BatchedDDPG([make_trainer(config(2, task, critic_lr=1e-3, ddpg={"envs": 7, "tau": 0.05})),
                          make_trainer(config(3, task, ddpg={"warmup": 100})), target[1]])
    rows_1 = [first.iteration()[0] for _ in range(10)]
    rows_2 = [second.iteration()[2] for _ in range(10)]
    assert rows_1 == rows_2
    assert_same(target[0], target[1])


def test_a_batch_starts_from_each_runs_own_data_and_agrees_with_it_alone_to_rounding() -> None:
    # the data (environment steps, exploration, warm-up, minibatch draws) are the run's own, bit for bit;
    # the batched and the unbatched kernels agree to float32 rounding (not bit for bit, see the module docs)
    alone = [make_trainer(config(s, "dlc", ddpg={"envs": 3 + s})) for s in (0, 1)]
    batch = BatchedDDPG([make_trainer(config(s, "dlc", ddpg={"envs": 3 + s})) for s in (0, 1)])
    rows = batch.iteration()
    for r, agent in enumerate(alone):
        row = agent.iteration()
        member = batch.members[r]
        for key in ("train/env_cost", "train/buffer_size", "data/true_transitions"):
            assert row[key] == rows[r][key]
        for key in ("train/critic_loss", "train/actor_loss", "train/value_mean"):
            assert row[key] == pytest.approx(rows[r][key], rel=1e-5)
        assert torch.equal(agent.generator.get_state(), member.generator.get_state())
        for key, value in agent.buffer.state_dict().items():
            assert torch.equal(torch.as_tensor(value), torch.as_tensor(member.buffer.state_dict()[key]))
        for net in NETS:
            for x, y in zip(getattr(agent, net).parameters(), getattr(member, net).parameters()):
                torch.testing.assert_close(x, y, rtol=1e-4, atol=1e-6)


def test_the_members_stay_usable_modules_with_their_own_adam_and_targets() -> None:
    runs = [make_trainer(config(s, ddpg={"tau": tau})) for s, tau in ((0, 0.005), (1, 0.5))]
    before = [[p.clone() for p in r.critic_target.parameters()] for r in runs]
    batch = BatchedDDPG(runs)
    batch.iteration()
    obs = torch.zeros(32 * 2, runs[0].task.obs_dim)
    stacked = batch.actor(obs)
    for r, run in enumerate(runs):
        torch.testing.assert_close(run.actor(obs[:3]), stacked[r * 32:r * 32 + 3], rtol=1e-5, atol=1e-6)
        assert run.critic_opt.state_dict()["state"][0]["step"] == 1.0
        assert run.actor_opt.state_dict()["state"][0]["step"] == 1.0
        tau = run.config.ddpg.tau  # each run's own Polyak factor: w' <- tau w + (1 - tau) w'
        for old, new, src in zip(before[r], run.critic_target.parameters(), run.critic.parameters()):
            torch.testing.assert_close(new, (1 - tau) * old + tau * src.detach(), rtol=1e-6, atol=1e-7)


def test_inactive_runs_draw_nothing_and_do_not_move() -> None:
    runs = [make_trainer(config(s)) for s in (0, 1)]
    batch = BatchedDDPG(runs)
    batch.iteration()
    frozen = state(runs[1])
    rows = batch.iteration([True, False])
    assert rows[1] is None and rows[0] is not None
    after = state(runs[1])
    for key in frozen:
        assert torch.equal(frozen[key], after[key]), key
    assert runs[0].k == 2 and runs[1].k == 1
    assert batch.iteration([False, False]) == [None, None]
    with pytest.raises(ValueError, match="active"):
        batch.iteration([True])


def test_true_transitions_are_counted_per_run_as_alone() -> None:
    # warm-up then ddpg.envs transitions per iteration (the first iteration's step counts towards the warm-up)
    shapes = ({"envs": 4, "warmup": 40}, {"envs": 7, "warmup": 100}, {"envs": 16, "warmup": 0})
    runs = [make_trainer(config(s, ddpg=d)) for s, d in enumerate(shapes)]
    batch = BatchedDDPG(runs)
    n = 6
    for _ in range(n):
        rows = batch.iteration()
    for run, d, row in zip(runs, shapes, rows):
        steps = max(1, math.ceil(d["warmup"] / d["envs"])) + n - 1
        assert run.true_transitions == steps * d["envs"] == row["data/true_transitions"]
        assert run.buffer.size == steps * d["envs"] == row["train/buffer_size"]
        alone = make_trainer(run.config)
        for _ in range(n):
            alone.iteration()
        assert alone.true_transitions == run.true_transitions


def test_train_batch_writes_each_run_resumes_and_loads_as_a_ddpg_run(tmp_path: Path) -> None:
    cfgs = [config(0), config(1, ddpg={"envs": 6}), config(2, iterations=5, critic_lr=1e-3)]
    whole_dirs = [RunDirectory(tmp_path / f"w{i}") for i in range(3)]
    whole = train_batch([make_trainer(c) for c in cfgs], whole_dirs, progress=False)
    dirs = [RunDirectory(tmp_path / f"r{i}") for i in range(3)]
    cut = train_batch([make_trainer(c) for c in cfgs], dirs, progress=False, stop_after=3)
    assert all(c == {"interrupted_at": 3} for c in cut)
    resumed = train_batch([make_trainer(c) for c in cfgs], dirs, resume=True, progress=False)
    for i, (w, r, c) in enumerate(zip(whole, resumed, cfgs)):
        assert r["iterations"] == c.algorithm.iterations and r["batch_size_runs"] == 3
        assert r["final"] == w["final"] and r["true_transitions"] == w["true_transitions"]
        assert len(dirs[i].read_metrics()) == c.algorithm.iterations
        strip = [{k: v for k, v in row.items() if k != "time/elapsed_s"} for row in dirs[i].read_metrics()]
        assert strip == [{k: v for k, v in row.items() if k != "time/elapsed_s"}
                         for row in whole_dirs[i].read_metrics()]
        a = load_checkpoint(dirs[i].checkpoint_path)["trainer"]
        b = load_checkpoint(whole_dirs[i].checkpoint_path)["trainer"]
        for net in NETS:
            assert all(torch.equal(a[net][k], b[net][k]) for k in a[net])
    # a batched run's checkpoint is an ordinary DDPG run's: it loads alone and evaluates
    agent = make_trainer(cfgs[0])
    agent.load_state_dict(load_checkpoint(dirs[0].checkpoint_path)["trainer"])
    assert agent.k == cfgs[0].algorithm.iterations and agent.buffer.size > 0
    assert agent.actor.state_dict()["net.body.0.weight"].shape == (64, agent.task.obs_dim)
    out = evaluate_run(dirs[0].path)
    assert out["iteration"] == cfgs[0].algorithm.iterations
    assert out["metrics"]["cost"] == pytest.approx(resumed[0]["final"]["cost"], rel=1e-12)


def test_a_sweep_resumes_a_batch_beside_its_finished_member(tmp_path: Path) -> None:
    # as for Algorithm 2 (sweep._train_points): when one run of a batch is left, a finished run of the batch
    # is restored beside it (inactive) so that it keeps the batched bits of the uninterrupted sweep
    cfgs = [config(0, iterations=4), config(1, iterations=8)]
    full = [str(tmp_path / "full" / f"run{i}") for i in range(2)]
    run_points([c.to_dict() for c in cfgs], full)
    cut = [RunDirectory(tmp_path / "cut" / f"run{i}") for i in range(2)]
    outcome = train_batch([make_trainer(c) for c in cfgs], cut, progress=False, stop_after=6)
    assert outcome[0]["iterations"] == 4 and outcome[1] == {"interrupted_at": 6}
    stamp = cut[0].results_path.stat().st_mtime_ns
    resumed = run_points([c.to_dict() for c in cfgs], [str(d.path) for d in cut], resume=True)
    assert cut[0].results_path.stat().st_mtime_ns == stamp  # finished: returned, not retrained
    a = load_checkpoint(cut[1].checkpoint_path)["trainer"]
    b = load_checkpoint(Path(full[1]) / "checkpoint.pt")["trainer"]
    for net in NETS:
        assert all(torch.equal(a[net][k], b[net][k]) for k in a[net])
    assert resumed[1]["final"] == RunDirectory(full[1]).read_results()["final"]
    assert resumed[1]["batch_size_runs"] == 2


def test_plan_batches_groups_ddpg_runs_in_batches_of_their_own() -> None:
    text = ('methods = ["mixed", "ddpg"]\nseeds = [0, 1, 2]\n[base]\ntask = "linear"\n"algorithm.iterations" = 20\n'
            '"algorithm.batch_size" = 32\n"ddpg.batch_size" = 32\n[variants.short]\n[variants.long]\n'
            'methods = ["ddpg"]\n"algorithm.iterations" = 40\n[variants.wide]\nmethods = ["ddpg"]\nseeds = [0]\n'
            '"ddpg.batch_size" = 16\n')
    runs = expand(parse_spec(text))
    ddpg = [i for i, r in enumerate(runs) if r.config.method == "ddpg" and r.config.ddpg.batch_size == 32]
    wide = [i for i, r in enumerate(runs) if r.config.ddpg.batch_size == 16]
    assert len(ddpg) == 6 and len(wide) == 1
    assert batch_key(runs[ddpg[0]].config) == batch_key(runs[ddpg[-1]].config)  # budgets may differ
    for workers, batch, sizes in ((1, 16, [6]), (2, 16, [3, 3]), (1, 4, [3, 3]), (4, 16, [2, 2, 2])):
        assert all([i] in plan_batches(runs, batch, workers) for i in ddpg)  # by default each DDPG run alone
        batches = plan_batches(runs, batch, workers, ddpg=True)
        assert sorted(i for b in batches for i in b) == list(range(len(runs)))
        for b in batches:  # Algorithm-2 and DDPG runs never share a batch
            assert len({runs[i].config.method == "ddpg" for i in b}) == 1
        assert sorted(len(b) for b in batches if b[0] in ddpg) == sizes, (workers, batch)
        assert wide in batches  # another minibatch size: its own group, of one
    assert plan_batches(runs, 1, 2, ddpg=True) == [[i] for i in range(len(runs))]


def test_bad_batches_are_refused_by_name(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="ddpg.batch_size"):
        BatchedDDPG([make_trainer(config(0)), make_trainer(config(1, batch_size=16))])
    with pytest.raises(ValueError, match="ddpg.activation"):
        BatchedDDPG([make_trainer(config(0)), make_trainer(config(1, activation="tanh"))])
    with pytest.raises(ValueError, match="algorithm.hidden_sizes"):
        BatchedDDPG([make_trainer(config(0)), make_trainer(config(1, hidden_sizes=(32, 32)))])
    with pytest.raises(ValueError, match="another task"):
        BatchedDDPG([make_trainer(config(0)), make_trainer(config(1, task="dlc"))])
    mixed = make_trainer(TrainConfig(method="mixed", task="linear", algorithm={"batch_size": 32}))
    with pytest.raises(ValueError, match="not a DDPG run"):
        BatchedDDPG([make_trainer(config(0)), mixed])
    run = make_trainer(config(0))
    with pytest.raises(ValueError, match="twice"):
        BatchedDDPG([run, run])
    with pytest.raises(ValueError, match="at least one"):
        BatchedDDPG([])
    # train_batch refuses a mixed or mismatched batch before it creates anything
    dirs = [RunDirectory(tmp_path / f"d{i}") for i in range(2)]
    with pytest.raises(ValueError, match="^trainers: entry 1 is AGPI .*batches of their own kind"):
        train_batch([make_trainer(config(0)), mixed], dirs, progress=False)
    with pytest.raises(ValueError, match="ddpg.batch_size"):
        train_batch([make_trainer(config(0)), make_trainer(config(1, batch_size=16))], dirs, progress=False)
    assert not any(d.path.exists() for d in dirs)


def test_mixedrl_sweep_batches_ddpg_only_when_asked(tmp_path: Path) -> None:
    """``mixedrl sweep`` trains DDPG runs alone by default (the shipped Table I's bits) and in one batch with
    ``--batch-ddpg``."""
    from mixedrl.cli import main

    spec = tmp_path / "spec.toml"
    spec.write_text('methods = ["ddpg"]\nseeds = [0, 1]\n[base]\n"task.name" = "linear"\n"algorithm.iterations" = 3\n'
                    '"ddpg.batch_size" = 16\n"ddpg.warmup" = 16\n"run.eval_every" = 3\n"run.eval_seeds" = 1\n')
    for flag, size in (([], 1), (["--batch-ddpg"], 2)):
        out = tmp_path / f"out{size}"
        assert main(["sweep", str(spec), "--out", str(out), "--workers", "1", "--no-progress", *flag]) == 0
        doc = json.loads((out / "sweep.json").read_text())
        assert [r["metrics"].get("batch_size_runs", 1) for r in doc["runs"]] == [size, size]
