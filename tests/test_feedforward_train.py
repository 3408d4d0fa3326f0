"""``algorithm.feedforward = "lq_train"`` / ``"lq_affine"`` / ``"lq_affine_ss"`` (departures): anchored actors as the policy class of training.

``u(o) = u_bar tanh(MLP(o) - MLP(o*) + atanh(u_ff / u_bar))`` with ``u_ff`` the discounted LQ optimum's action
for the run's own noise moments, refreshed at the start of every iteration. What is checked: the anchor holds
at the start of every iteration for the moments of that iteration (mixed: the IBE moves; model: the prior),
and at its end for the moments the next one plans with; the actor is smooth and bounded and keeps the draws of
the plain actor; in a batch of three runs of different methods each run is anchored at its own noise and has
the same bits in two compositions; resume equals an uninterrupted run; the errors name the option.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from mixedrl.algorithms.agpi import AGPI
from mixedrl.algorithms.batched import BatchedAGPI, batch_key
from mixedrl.config import TrainConfig
from mixedrl.networks import Actor, AnchoredActor
from mixedrl.precision import equilibrium_observation, lq_reference
from mixedrl.runs import RunDirectory, evaluate_run, make_trainer, train, train_batch
from mixedrl.tasks import LinearTask

ATOL = 1e-5


#: The anchored policy classes (``"lq_affine"`` adds the LQ gain, ``"lq_affine_ss"`` anchors at the optimum's
#: steady state; tests/test_lq_affine.py checks the gain and the steady state).
ANCHORED = ["lq_train", "lq_affine", "lq_affine_ss"]


def _cfg(method: str, seed: int = 0, feedforward: str = "lq_train", **algorithm: object) -> TrainConfig:
    return TrainConfig(method=method, task="linear", seed=seed,
                       algorithm={"batch_size": 16, "hidden_sizes": (8,), "feedforward": feedforward, **algorithm},
                       run={"eval_every": 1000, "checkpoint_every": 1000, "eval_seeds": 1})


def _anchor_obs(trainer: AGPI) -> torch.Tensor:
    """Where the actor should take :func:`_wanted`: the equilibrium's observation, or (``"lq_affine_ss"``)
    that of the LQ optimum's steady state for the trainer's current own noise."""
    lin = trainer.task.linearisation()
    if trainer.config.algorithm.feedforward != "lq_affine_ss":
        return equilibrium_observation(trainer.task, lin)
    x_ss = lq_reference(lin, *trainer.noise_moments()).steady_state
    return trainer.task.observe(lin.to_state(torch.as_tensor(x_ss)[None]).float())[0]


def _at_anchor(trainer: AGPI) -> np.ndarray:
    with torch.no_grad():
        return trainer.actor(_anchor_obs(trainer)[None])[0].double().numpy()


def _wanted(trainer: AGPI) -> np.ndarray:
    ref = lq_reference(trainer.task.linearisation(), *trainer.noise_moments())
    return ref.steady_action if trainer.config.algorithm.feedforward == "lq_affine_ss" else ref.action


def _record_at_collect(trainer: AGPI, log: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> None:
    """Wrap ``collect`` (the first use of the actor in an iteration): log (action at o*, wanted, mean)."""
    collect = trainer.collect

    def wrapped() -> tuple[torch.Tensor, torch.Tensor]:
        log.append((_at_anchor(trainer), _wanted(trainer), trainer.noise_moments()[0]))
        return collect()

    trainer.collect = wrapped  # type: ignore[method-assign]


@pytest.mark.parametrize("feedforward", ANCHORED)
@pytest.mark.parametrize("method", ["mixed", "model", "oracle"])
def test_the_actor_takes_the_lq_action_of_each_iterations_moments(method: str, feedforward: str) -> None:
    trainer = make_trainer(_cfg(method, feedforward=feedforward))
    assert isinstance(trainer.actor, AnchoredActor) and trainer.policy is trainer.actor
    log: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    _record_at_collect(trainer, log)
    for _ in range(5):
        trainer.iteration()
        assert _at_anchor(trainer) == pytest.approx(_wanted(trainer), abs=ATOL)  # for the next iteration
    assert len(log) == 5
    for u, wanted, _ in log:
        assert u == pytest.approx(wanted, abs=ATOL)
    means = np.array([m for _, _, m in log])
    task = trainer.task
    if method == "mixed":  # the IBE moves, and the anchor with it
        assert abs(means[0][1] - task.prior_mean[1]) < 1e-12 and abs(means[-1][1] - task.prior_mean[1]) > 0.1
        assert abs(float(log[0][0][0] - log[-1][0][0])) > 0.1
    else:
        expected = task.prior_mean if method == "model" else task.true_mean
        assert np.allclose(means, expected[None], atol=1e-12)
    lin = task.linearisation()
    if method != "oracle":  # prior and truth give different anchors (so the check above has teeth)
        assert np.abs(lq_reference(lin, task.prior_mean, task.prior_cov).action
                      - lq_reference(lin, task.true_mean, task.true_cov).action).max() > 0.1


def test_the_anchored_actor_is_smooth_bounded_and_draws_like_the_actor() -> None:
    args = (2, 1, (8,), "elu")
    bound = torch.tensor([2.0])
    plain = Actor(*args, torch.Generator().manual_seed(3), bound)
    anchored = AnchoredActor(*args, torch.Generator().manual_seed(3), bound, anchor_obs=torch.tensor([0.5, -0.2]))
    for a, b in zip(plain.parameters(), anchored.parameters()):
        assert torch.equal(a, b)
    anchored.set_anchor_action(torch.tensor([5.0]))  # beyond the bound: clipped to 0.999 of it
    obs = torch.randn(64, 2, generator=torch.Generator().manual_seed(0)) * 10
    with torch.no_grad():
        assert float(anchored(torch.tensor([[0.5, -0.2]]))[0, 0]) == pytest.approx(2.0 * 0.999, abs=1e-5)
        assert bool((anchored(obs).abs() <= 2.0).all())
        anchored.set_anchor_action(torch.tensor([-0.7]))
        assert float(anchored(torch.tensor([0.5, -0.2]))[0]) == pytest.approx(-0.7, abs=1e-6)
        # away from o*: the pre-tanh output is the plain one shifted by a constant
        z = torch.atanh(anchored(obs) / 2.0) - torch.atanh(plain(obs).clamp(-1.999, 1.999) / 2.0)
    assert torch.allclose(z, z[:1].expand_as(z), atol=1e-3)
    assert set(anchored.state_dict()) == set(plain.state_dict()) | {"anchor_obs", "anchor_z"}


@pytest.mark.parametrize("feedforward", ANCHORED)
def test_a_batch_anchors_each_run_at_its_own_noise_and_keeps_the_bits(feedforward: str) -> None:
    """Three methods in one batch (R = 3): the stacked anchors follow each run's refresh; a run has the
    same bits in two compositions (as a plain run does, tests/test_batched.py)."""
    runs = [make_trainer(_cfg(m, seed, feedforward)) for m, seed in (("mixed", 0), ("model", 1), ("oracle", 2))]
    logs: list[list] = [[] for _ in runs]
    for t, log in zip(runs, logs):
        _record_at_collect(t, log)
    engine = BatchedAGPI(runs)
    other = BatchedAGPI([make_trainer(_cfg("oracle", 5, feedforward)), make_trainer(_cfg("mixed", 0, feedforward))])
    for _ in range(4):
        engine.iteration()
        other.iteration()
        # the stacked (vmapped) call, every run's rows at its own o*
        o = torch.cat([_anchor_obs(t)[None].expand(engine.batch, -1) for t in runs]).contiguous()
        with torch.no_grad():
            stacked = engine.actor(o)
        for r, t in enumerate(runs):
            assert _at_anchor(t) == pytest.approx(_wanted(t), abs=ATOL)
            assert stacked[r * engine.batch].double().numpy() == pytest.approx(_wanted(t), abs=ATOL)
    for log in logs:
        assert len(log) == 4 and all(u == pytest.approx(w, abs=ATOL) for u, w, _ in log)
    assert abs(float(_at_anchor(runs[0])[0] - _at_anchor(runs[1])[0])) > 0.1  # own noise: not the same anchor
    a, b = runs[0], other.members[1]
    for x, y in zip([*a.critic.state_dict().values(), *a.actor.state_dict().values()],
                    [*b.critic.state_dict().values(), *b.actor.state_dict().values()]):
        assert torch.equal(x, y)
    assert torch.equal(a.generator.get_state(), b.generator.get_state())


def test_lq_train_and_other_runs_train_in_separate_batches() -> None:
    plain = TrainConfig(method="mixed", task="linear", seed=0, algorithm={"batch_size": 16, "hidden_sizes": (8,)})
    lq = plain.replace(**{"algorithm.feedforward": "lq"})
    assert batch_key(plain) == batch_key(lq) != batch_key(_cfg("mixed"))
    assert batch_key(_cfg("mixed")) == batch_key(_cfg("model", 3))
    affine = _cfg("mixed", feedforward="lq_affine")
    assert batch_key(affine) == batch_key(_cfg("oracle", 2, "lq_affine"))
    assert batch_key(affine) not in (batch_key(plain), batch_key(_cfg("mixed")))
    steady = _cfg("mixed", feedforward="lq_affine_ss")
    assert batch_key(steady) == batch_key(_cfg("model", 1, "lq_affine_ss")) != batch_key(affine)
    with pytest.raises(ValueError, match="algorithm.feedforward = 'lq_train'"):
        BatchedAGPI([make_trainer(plain), make_trainer(_cfg("mixed", 1))])
    with pytest.raises(ValueError, match="train in batches of their own kind"):
        BatchedAGPI([make_trainer(_cfg("mixed", 1)), make_trainer(affine)])


@pytest.mark.parametrize("method,feedforward", [("mixed", "lq_train"), ("model", "lq_train"), ("mixed", "lq_affine"),
                                               ("mixed", "lq_affine_ss")])
def test_resume_equals_uninterrupted(tmp_path: Path, method: str, feedforward: str) -> None:
    cfg = _cfg(method, feedforward=feedforward, iterations=12).replace(**{"run.checkpoint_every": 4})
    full = make_trainer(cfg)
    train(full, RunDirectory(tmp_path / "full"), progress=False)
    out = train(make_trainer(cfg), RunDirectory(tmp_path / "cut"), stop_after=7, progress=False)
    assert out == {"interrupted_at": 7}
    resumed = make_trainer(cfg)
    train(resumed, RunDirectory(tmp_path / "cut"), resume=True, progress=False)
    for part in ("actor", "critic"):
        a, b = full.state_dict()[part], resumed.state_dict()[part]
        assert set(a) == set(b) and all(torch.equal(a[k], b[k]) for k in a)
    assert "anchor_z" in full.state_dict()["actor"]
    strip = [{k: v for k, v in r.items() if not k.startswith("time/")} for r in RunDirectory(tmp_path / "full").read_metrics()]
    assert strip == [{k: v for k, v in r.items() if not k.startswith("time/")}
                     for r in RunDirectory(tmp_path / "cut").read_metrics()]
    results = evaluate_run(tmp_path / "cut")
    if feedforward != "lq_affine_ss":  # (its anchor is the steady state, not the equilibrium policy_gap reads)
        assert max(abs(e) for e in results["policy_gap"]["action_error"]) < ATOL
    with pytest.raises(ValueError, match=f"'{feedforward}' is a training-time"):
        evaluate_run(tmp_path / "cut", feedforward="lq")


def test_batched_resume_equals_uninterrupted(tmp_path: Path) -> None:
    cfgs = [_cfg("mixed", 0, iterations=6), _cfg("model", 1, iterations=6), _cfg("oracle", 2, iterations=4)]
    whole = train_batch([make_trainer(c) for c in cfgs], [RunDirectory(tmp_path / f"w{i}") for i in range(3)],
                        progress=False)
    dirs = [RunDirectory(tmp_path / f"r{i}") for i in range(3)]
    train_batch([make_trainer(c) for c in cfgs], dirs, progress=False, stop_after=3)
    resumed = train_batch([make_trainer(c) for c in cfgs], dirs, resume=True, progress=False)
    for w, r in zip(whole, resumed):
        assert r["final"] == w["final"] and r["batch_size_runs"] == 3


class _NoEquilibrium(LinearTask):
    def equilibrium(self) -> None:
        return None


def test_errors_name_the_option(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"algorithm.feedforward: 'lq_train' .* method 'ddpg' has none"):
        TrainConfig(method="ddpg", task="linear", algorithm={"feedforward": "lq_train"})
    with pytest.raises(ValueError, match=r"algorithm.feedforward: 'lq_train' needs a task with an equilibrium"):
        AGPI(_NoEquilibrium(), _cfg("mixed"))
    with pytest.raises(ValueError, match=r"algorithm.feedforward: 'lq_train' anchors the MLP actor"):
        AGPI(LinearTask(), _cfg("mixed"), architecture="quadratic")
    plain = TrainConfig(method="mixed", task="linear", seed=0,
                        algorithm={"batch_size": 16, "hidden_sizes": (8,), "iterations": 2})
    train(make_trainer(plain), RunDirectory(tmp_path / "plain"), progress=False)
    with pytest.raises(ValueError, match="'lq_train' is a training-time"):
        evaluate_run(tmp_path / "plain", feedforward="lq_train")
