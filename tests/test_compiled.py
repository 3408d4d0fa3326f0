"""The compiled update of issue 44 (:mod:`mixedrl.compiled`, ``algorithm.compile``): the same numbers as the
eager step to float32 rounding, the same seed the same result, the optimisers' state in their checkpoints.

The ``functional`` mode is the compiled step's code run eagerly (fast); the tests that compile
(``algorithm.compile = "on"``) are marked ``compiled`` and run in the tox env ``bench``: cold, 28-32 s each
on the quiet 2-core machine (2026-12-07; the tiny task's loss, backward, Adam and MVC graphs, one per shape);
the cache they fill is pytest's cache folder (``pytest --cache-clear`` empties it), so later sessions load
the graphs from it.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from mixedrl.algorithms.batched import BatchedAGPI, StackedNetwork
from mixedrl.checkpoint import load_checkpoint, save_checkpoint
from mixedrl.compiled import Update, network_at
from mixedrl.config import ONE_STEP_LEARNER, TrainConfig
from mixedrl.runs import make_trainer
from mixedrl.schedule import Descent

METHODS = ("mixed", "model", "oracle")
RTOL = 1e-5


#: The rollout learner (mixedrl.departures.rollout) with the inward-clipped actor and region starts: its steps go
#: through the same compiled update.
ROLLOUT = {"rollout_horizon": 3, "critic_target": 0.8, "actor_output": "clip_inward", "rollout_region": 0.5,
           "batch_weighting": "relative", "batch_weight_offset": 0.3, "rollout_discount_start": 0.95}


def config(compile: str, seed: int = 0, method: str = "mixed", **algorithm: object) -> TrainConfig:
    """A tiny run of the one-step learner (:data:`~mixedrl.config.ONE_STEP_LEARNER`); ``algorithm`` on top
    (:data:`ROLLOUT`: the rollout learner at 3 steps; the default's 16 steps would compile 16 unrolled steps)."""
    return TrainConfig(method=method, seed=seed, task="linear",
                       algorithm={**ONE_STEP_LEARNER, "iterations": 6, "batch_size": 32, "hidden_sizes": [8, 8],
                                  "compile": compile, **algorithm},
                       run={"eval_every": 1000, "checkpoint_every": 1000, "eval_seeds": 1})


def engine(compile: str, runs: int = 1, first_seed: int = 0, **algorithm: object) -> tuple[list, object]:
    members = [make_trainer(config(compile, first_seed + r, METHODS[r % 3], **algorithm)) for r in range(runs)]
    return members, (members[0] if runs == 1 else BatchedAGPI(members))


def flat(members: list) -> torch.Tensor:
    return torch.cat([p.detach().flatten() for m in members for p in [*m.critic.parameters(), *m.actor.parameters()]])


def losses(rows: list, actor: str = "train/actor_objective") -> torch.Tensor:
    """The critic's and the actor's losses of every run and iteration (DDPG's actor key: ``train/actor_loss``)."""
    rows = [r for it in rows for r in (it if isinstance(it, list) else [it])]
    return torch.tensor([[r["train/critic_loss"], r[actor]] for r in rows], dtype=torch.float64)


def train(compile: str, runs: int = 1, iterations: int = 4, **algorithm: object) -> tuple[list, list]:
    members, e = engine(compile, runs, **algorithm)
    return members, [e.iteration() for _ in range(iterations)]


@pytest.fixture()
def compile_cache(request: pytest.FixtureRequest, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A compile cache that outlives the session (pytest's cache folder) when pytest keeps one."""
    cache = getattr(request.config, "cache", None)  # None with -p no:cacheprovider
    path = cache.mkdir("mixedrl-compile") if cache is not None else tmp_path / "mixedrl-compile"
    monkeypatch.setenv("MIXEDRL_CACHE_DIR", str(path))
    monkeypatch.delenv("TORCHINDUCTOR_CACHE_DIR", raising=False)  # restored after the test
    return path


# ----------------------------------------------------------------------------------------------------------- config
def test_a_bad_compile_value_names_the_key() -> None:
    with pytest.raises(ValueError, match=r"algorithm\.compile: expected one of \('off', 'on', 'functional'\)"):
        TrainConfig(algorithm={"compile": "yes"})
    with pytest.raises(ValueError, match=r"algorithm\.compile"):
        TrainConfig(algorithm={"compile": True})
    with pytest.raises(ValueError, match=r"^mode"):
        Descent([], [], [], [], mode="fast")


def test_the_default_leaves_config_json_as_before() -> None:
    assert "compile" not in TrainConfig().to_dict()["algorithm"]
    on = TrainConfig(algorithm={"compile": "on"})
    assert on.to_dict()["algorithm"]["compile"] == "on"
    assert TrainConfig.from_dict(on.to_dict()) == on
    assert TrainConfig.from_dict(TrainConfig().to_dict()).algorithm.compile == "off"


# ---------------------------------------------------------------------------------------------- functional = eager
@pytest.mark.parametrize("learner", [{}, ROLLOUT], ids=["one_step", "rollout"])
@pytest.mark.parametrize("runs", [1, 2])
def test_the_functional_step_gives_the_eager_numbers(runs: int, learner: dict) -> None:
    eager_members, eager_rows = train("off", runs, **learner)
    members, rows = train("functional", runs, **learner)
    torch.testing.assert_close(flat(members), flat(eager_members), rtol=RTOL, atol=1e-7)
    torch.testing.assert_close(losses(rows), losses(eager_rows), rtol=RTOL, atol=1e-9)
    for m, e in zip(members, eager_members):  # the random streams untouched: the same draws in the same order
        assert torch.equal(m.generator.get_state(), e.generator.get_state())


def test_the_same_seed_gives_the_same_result_functional() -> None:
    a, rows_a = train("functional", 2)
    b, rows_b = train("functional", 2)
    assert torch.equal(flat(a), flat(b))
    assert rows_a == rows_b


@pytest.mark.parametrize("first, then", [("functional", "off"), ("off", "functional")])
def test_the_adam_state_goes_through_a_checkpoint(tmp_path: Path, first: str, then: str) -> None:
    """Three iterations in one mode, a checkpoint, two more in the other: the run of one mode throughout, to
    rounding (the optimisers' ``step``, ``exp_avg``, ``exp_avg_sq`` are those of ``torch.optim.Adam``)."""
    members, e = engine(first, 2)
    for _ in range(3):
        e.iteration()
    for r, m in enumerate(members):
        save_checkpoint(tmp_path / f"run{r}.pt", {"trainer": m.state_dict()})
        steps = {float(s["step"]) for s in m.critic_opt.state_dict()["state"].values()}
        assert steps == {3.0} and len(m.critic_opt.state_dict()["state"]) == len(list(m.critic.parameters()))
    restored, e2 = engine(then, 2)
    for r, m in enumerate(restored):
        m.load_state_dict(load_checkpoint(tmp_path / f"run{r}.pt")["trainer"])
    e2 = BatchedAGPI(restored)  # the stacked tensors of the restored weights
    reference, e3 = engine(first, 2)
    for _ in range(5):
        e3.iteration()
    for _ in range(2):
        e.iteration()
        e2.iteration()
    torch.testing.assert_close(flat(restored), flat(members), rtol=RTOL, atol=1e-7)
    torch.testing.assert_close(flat(members), flat(reference), rtol=0, atol=0)


def test_a_loss_of_ones_own_through_descent_minimise() -> None:
    """The generic API: any pure loss of the stacked parameters; an inactive run keeps its weights and state."""
    torch.manual_seed(0)
    nets = [torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.Tanh(), torch.nn.Linear(4, 1)) for _ in range(2)]
    stacked = StackedNetwork(nets, batch=5)
    x, y = torch.randn(10, 3), torch.randn(10, 1)

    def loss(params: tuple[torch.Tensor, ...], x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return (network_at(stacked, params)(x) - y).pow(2).reshape(2, -1).mean(dim=1)

    def descent(mode: str) -> Descent:
        opts = [torch.optim.Adam(n.parameters(), lr=1e-2) for n in nets]
        return Descent(stacked.leaves, stacked.run_params(), opts, [0.5, 0.5], mode)

    start = [p.detach().clone() for p in stacked.leaves]
    eager = descent("off")
    for _ in range(3):
        eager.minimise(loss, (x, y))
    eager.minimise(loss, (x, y), active=[1])
    after_eager = [p.detach().clone() for p in stacked.leaves]
    with torch.no_grad():
        for p, s in zip(stacked.leaves, start):
            p.copy_(s)
    functional = descent("functional")
    for _ in range(3):
        value = functional.minimise(loss, (x, y))
    assert value.shape == (2,)
    before = [p.detach().clone() for p in stacked.leaves]
    functional.minimise(loss, (x, y), active=[1])
    for p, b, e in zip(stacked.leaves, before, after_eager):
        assert torch.equal(p[0], b[0])  # run 0 did not step
        torch.testing.assert_close(p, e, rtol=RTOL, atol=1e-7)
    assert {float(functional.optimizers[0].state[p]["step"]) for p in nets[0].parameters()} == {3.0}
    assert {float(functional.optimizers[1].state[p]["step"]) for p in nets[1].parameters()} == {4.0}
    with pytest.raises(ValueError, match="weight decay"):
        Update(loss, Descent(stacked.leaves, stacked.run_params(),
                             [torch.optim.Adam(n.parameters(), weight_decay=0.1) for n in nets], [1.0, 1.0]), "on")


# --------------------------------------------------------------------------------------------------------- compiled
def compiled_like_eager(runs: int, **algorithm: object) -> tuple[list, list]:
    eager_members, eager_rows = train("off", runs, **algorithm)
    members, rows = train("on", runs, **algorithm)
    torch.testing.assert_close(flat(members), flat(eager_members), rtol=RTOL, atol=1e-7)
    torch.testing.assert_close(losses(rows), losses(eager_rows), rtol=RTOL, atol=1e-9)
    return members, rows


@pytest.mark.compiled
def test_the_compiled_step_gives_the_eager_numbers_and_the_same_seed_the_same_result(compile_cache: Path) -> None:
    members, rows = compiled_like_eager(1)
    again, rows_again = train("on", 1)
    assert torch.equal(flat(again), flat(members)) and rows_again == rows
    assert any((compile_cache / "inductor").iterdir())  # the on-disk cache where the user can see and clear it


@pytest.mark.compiled
def test_the_compiled_step_of_stacked_runs(compile_cache: Path) -> None:
    compiled_like_eager(2)


@pytest.mark.compiled
def test_the_compiled_rollout_learner_gives_the_eager_numbers(compile_cache: Path) -> None:
    """The rollout learner's actor and critic steps (mixedrl.departures.rollout) compiled: the eager numbers."""
    compiled_like_eager(2, **ROLLOUT)


#: A loss with a scan and a custom autograd.Function, each holding the constant C (argv): run in a fresh process
#: on a shared cache directory, it prints whether the compiled gradient equals the eager one and the cache counters.
_CACHED_LOSS = """
import json, sys
import torch
from torch._higher_order_ops.scan import scan
from mixedrl.compiled import allow_in_cache
allow_in_cache()
C = float(sys.argv[1])

class Scale(torch.autograd.Function):
    @staticmethod
    def forward(x):
        return x.clone()

    @staticmethod
    def setup_context(ctx, inputs, output):
        pass

    @staticmethod
    def backward(ctx, g):
        return g * C

def loss(w, s, xs):
    def body(x, d):
        x_next = torch.tanh(Scale.apply(x * w)) * C + d
        return x_next.clone(), (x_next * x_next).sum(-1).clone()
    return scan(body, s, xs)[1].sum()

w = torch.linspace(0.5, 1.5, 4, requires_grad=True)
s, xs = torch.ones(3, 4), torch.full((5, 3, 4), 0.1)
compiled = torch.autograd.grad(torch.compile(loss, fullgraph=True, dynamic=False)(w, s, xs), w)[0]
eager = torch.autograd.grad(loss(w, s, xs), w)[0]
counters = torch._dynamo.utils.counters
print(json.dumps({"equal": torch.allclose(compiled, eager, rtol=1e-5), "aot": dict(counters["aot_autograd"]),
                  "inductor": dict(counters["inductor"])}))
"""


@pytest.mark.compiled
def test_the_cache_keeps_scan_and_custom_function_graphs_and_keys_them_by_their_bodies(tmp_path: Path) -> None:
    """allow_in_cache: a second process loads the graph (AOTAutograd and inductor hits, nothing bypassed); a
    body with another constant in the scan and in the function's backward misses, and gives its own numbers."""
    import json
    import os
    import subprocess
    import sys

    script = tmp_path / "cached_loss.py"
    script.write_text(_CACHED_LOSS)
    env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": str(tmp_path / "cache")}
    runs = [json.loads(subprocess.run([sys.executable, str(script), c], env=env, check=True, capture_output=True,
                                      text=True).stdout.splitlines()[-1]) for c in ("0.5", "0.5", "0.7")]
    assert all(r["equal"] for r in runs)
    first, again, other = runs
    assert first["aot"].get("autograd_cache_saved") == 1 and "autograd_cache_bypass" not in first["aot"]
    assert again["aot"].get("autograd_cache_hit") == 1 and again["inductor"].get("fxgraph_cache_miss", 0) == 0
    assert other["aot"].get("autograd_cache_miss") == 1


# ------------------------------------------------------------------------------------------------------------- DDPG
def ddpg_train(compile: str, runs: int, iterations: int = 5) -> tuple[list, list]:
    """A tiny DDPG run (or ``runs`` of them batched) with ``algorithm.compile``: its members and metrics rows."""
    from mixedrl.algorithms.batched_ddpg import BatchedDDPG

    members = [make_trainer(TrainConfig(method="ddpg", seed=r, task="linear",
                                        algorithm={"hidden_sizes": [8, 8], "compile": compile},
                                        ddpg={"warmup": 64, "batch_size": 32, "envs": 2},
                                        run={"eval_every": 1000, "checkpoint_every": 1000, "eval_seeds": 1}))
               for r in range(runs)]
    e = members[0] if runs == 1 else BatchedDDPG(members)
    return members, [e.iteration() for _ in range(iterations)]


def ddpg_like_eager(compile: str, runs: int) -> None:
    eager_members, eager_rows = ddpg_train("off", runs)
    members, rows = ddpg_train(compile, runs)
    torch.testing.assert_close(flat(members), flat(eager_members), rtol=RTOL, atol=1e-7)
    torch.testing.assert_close(losses(rows, actor="train/actor_loss"), losses(eager_rows, actor="train/actor_loss"),
                               rtol=RTOL, atol=1e-9)


@pytest.mark.parametrize("runs", [1, 2])
def test_the_functional_ddpg_update_gives_the_eager_numbers(runs: int) -> None:
    """DDPG's critic and actor steps through mixedrl.compiled (the target networks and the critic read, not
    trained): the eager step's weights and losses."""
    ddpg_like_eager("functional", runs)


@pytest.mark.compiled
def test_the_compiled_ddpg_update_gives_the_eager_numbers(compile_cache: Path) -> None:
    ddpg_like_eager("on", 2)


@pytest.mark.compiled
def test_the_progress_bar_says_when_the_steps_compile(compile_cache: Path, capsys: pytest.CaptureFixture) -> None:
    from mixedrl.runs import train as run_training

    run_training(make_trainer(config("on")), None, progress=True)
    assert "compiling the steps" in capsys.readouterr().err
    run_training(make_trainer(config("off")), None, progress=True)
    assert "compiling" not in capsys.readouterr().err
