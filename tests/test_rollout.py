"""The rollout learner (:mod:`mixedrl.departures.rollout`): its losses against the paper's one-step ones, the
lambda-returns, the loop's use of it (reproducible, listed in ``departures``, R > 1 batches) and its keys."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from experiments.tuning_systems import CartFriction, SwingUp
from mixedrl.algorithms.agpi import AGPI
from mixedrl.algorithms.batched import BatchedAGPI
from mixedrl.config import TrainConfig
from mixedrl.departures import rollout, used
from mixedrl.networks import Actor, Critic
from mixedrl.pev import critic_loss as one_step_critic_loss
from mixedrl.pim import actor_objective
from mixedrl.runs import train

ALGORITHM = dict(batch_size=16, iterations=4, hidden_sizes=(8,), rollout_horizon=3, critic_target=0.8)
RUN = dict(eval_every=4, eval_seeds=1, checkpoint_every=4)


def _nets(task: CartFriction, seed: int = 0) -> tuple[torch.nn.Module, torch.nn.Module]:
    gen = torch.Generator().manual_seed(seed)
    actor = Actor(task.obs_dim, task.action_dim, (8,), "elu", gen, task.action_bound, obs_scale=task.obs_scale)
    critic = Critic(task.obs_dim, (8,), "elu", gen, obs_scale=task.obs_scale, output="square")
    return actor, critic


def _flat(module: torch.nn.Module) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1) for p in module.parameters()])


def _config(seed: int = 100, **algorithm: object) -> TrainConfig:
    return TrainConfig(method="mixed", task="linear", seed=seed, algorithm=dict(ALGORITHM, **algorithm), run=RUN)


def test_one_step_losses_are_the_papers() -> None:
    """H = 1, lambda = 0, the draw at the noise mean (K = 0): the actor loss is the one-step PIM objective of eq.
    (51) and the critic loss eq. (49)'s with the same network as target (a sign or a discount error fails)."""
    task = CartFriction()
    actor, critic = _nets(task)
    s = task.sample_initial(32, torch.Generator().manual_seed(1)).float()
    mean, cov = np.array([0.07]), np.zeros((1, 1))
    draws = rollout.noise_draws(mean, cov, task.noise_matrix, 1, 32, torch.Generator().manual_seed(2))
    offsets, weights = (task.noise_matrix.float() @ torch.tensor([0.07])).reshape(1, 2), torch.ones(1)
    gamma = torch.full((32,), task.gamma)
    states, costs = rollout.rollout(task, actor, s, draws)
    ours = rollout.actor_loss(task, critic, states, costs, gamma)
    paper = actor_objective(task, critic, actor, s, offsets, weights)
    assert torch.allclose(ours, paper, rtol=1e-5, atol=1e-7)
    with torch.no_grad():
        targets = rollout.lambda_returns(costs, critic(task.observe(states[1])).reshape(1, -1), gamma, 0.0)
    u = actor(task.observe(s)).detach()
    assert torch.allclose(rollout.critic_loss(task, critic, states[:1].detach(), targets),
                          one_step_critic_loss(task, critic, s, u, offsets, weights), rtol=1e-5, atol=1e-8)
    # the relative forms too
    assert torch.allclose(rollout.actor_loss(task, critic, states, costs, gamma, relative_offset=1.0),
                          actor_objective(task, critic, actor, s, offsets, weights, relative_offset=1.0), rtol=1e-5)


def test_actor_loss_is_the_discounted_rollout_cost_plus_the_tail() -> None:
    """H = 3 by hand: sum_t gamma^t l(x_{t+1}, u_t) + gamma^3 V(x_3), the states stepped by f + E xi_t."""
    task = CartFriction()
    actor, critic = _nets(task)
    s = task.sample_initial(8, torch.Generator().manual_seed(3)).float()
    draws = rollout.noise_draws(np.array([0.07]), np.array([[1e-4]]), task.noise_matrix, 3, 8,
                                torch.Generator().manual_seed(4))
    g = 0.9
    states, costs = rollout.rollout(task, actor, s, draws)
    x, total = s, torch.zeros(8)
    with torch.no_grad():
        for t in range(3):
            u = actor(x)
            x = task.f(x, u) + draws[t]
            total = total + g**t * task.cost(x, u)
        total = total + g**3 * critic(x).reshape(-1)
    loss = rollout.actor_loss(task, critic, states, costs, torch.full((8,), g))
    assert torch.allclose(loss, total.mean(), rtol=1e-5)


def test_lambda_returns() -> None:
    """lambda = 1: the H-step discounted return plus gamma^H V(x_H) at every t; lambda = 0: one-step targets;
    in between the recursion G_t = l_t + gamma ((1 - lambda) V_{t+1} + lambda G_{t+1})."""
    gen = torch.Generator().manual_seed(0)
    costs, values = torch.rand(4, 5, generator=gen), torch.rand(4, 5, generator=gen)
    gamma = torch.full((5,), 0.9)
    full = rollout.lambda_returns(costs, values, gamma, 1.0)
    for t in range(4):
        expected = sum(0.9**i * costs[t + i] for i in range(4 - t)) + 0.9 ** (4 - t) * values[-1]
        assert torch.allclose(full[t], expected)
    assert torch.allclose(rollout.lambda_returns(costs, values, gamma, 0.0), costs + 0.9 * values)
    mid = rollout.lambda_returns(costs, values, gamma, 0.5)
    assert torch.allclose(mid[1], costs[1] + 0.9 * (0.5 * values[1] + 0.5 * mid[2]))


def test_noise_draws_have_the_moments_and_follow_the_generator() -> None:
    e = torch.tensor([[0.0], [1.0]], dtype=torch.float64)
    d = rollout.noise_draws(np.array([0.5]), np.array([[0.04]]), e, 50, 400, torch.Generator().manual_seed(5))
    assert d.shape == (50, 400, 2) and torch.all(d[..., 0] == 0)
    assert abs(float(d[..., 1].mean()) - 0.5) < 0.005 and abs(float(d[..., 1].std()) - 0.2) < 0.005
    again = rollout.noise_draws(np.array([0.5]), np.array([[0.04]]), e, 50, 400, torch.Generator().manual_seed(5))
    assert torch.equal(d, again)


def test_training_descends_the_rollout_loss() -> None:
    """A few iterations lower the actor's rollout loss on fixed states and draws (a flipped sign raises it)."""
    task = CartFriction()
    cfg = _config(iterations=40, batch_size=64, actor_lr=3e-3)
    run = AGPI(task, cfg)
    s = task.sample_initial(256, torch.Generator().manual_seed(6)).float()
    draws = rollout.noise_draws(task.true_mean, task.true_cov, task.noise_matrix, 3, 256, torch.Generator().manual_seed(7))
    gamma = torch.full((256,), task.gamma)

    def loss() -> float:
        with torch.no_grad():
            return float(rollout.actor_loss(task, run.critic_target.module, *rollout.rollout(task, run.actor, s, draws),
                                            gamma))
    # the critic first, the actor's loss measured against one fixed critic
    for _ in range(40):
        run.iteration()
    critic = run.critic_target.module
    before = loss()
    frozen = {k: v.clone() for k, v in critic.state_dict().items()}
    for _ in range(20):
        run.iteration()
        run.critic_target.module.load_state_dict(frozen)
    assert loss() < before


def test_reproducible_and_listed(tmp_path) -> None:
    """Same seed, same weights; another seed, others; results.json lists the departure, the paper's path does not."""
    a, b, c = (AGPI(CartFriction(), _config(seed)) for seed in (100, 100, 101))
    for run in (a, b, c):
        for _ in range(3):
            run.iteration()
    assert torch.equal(_flat(a.actor), _flat(b.actor)) and torch.equal(_flat(a.critic), _flat(b.critic))
    assert not torch.equal(_flat(a.actor), _flat(c.actor))
    results = train(AGPI(CartFriction(), _config()), progress=False)
    assert "rollout" in results["departures"]
    assert "rollout" not in used(_config(rollout_horizon=0))


@pytest.mark.parametrize("task, extra", [(CartFriction, {}),
                                         (SwingUp, {"actor_output": "clip_inward", "rollout_region": 0.5})])
def test_batched_runs_do_not_depend_on_their_neighbours(task: type, extra: dict) -> None:
    """R = 2: a run's weights are the same bits whatever run shares its batch (its own generator draws its noise;
    with the clipped actor and the region starts too, :mod:`tests.test_swing_departures`)."""
    def pair(other: int) -> AGPI:
        runs = [AGPI(task(), _config(100, **extra)), AGPI(task(), _config(other, **extra))]
        engine = BatchedAGPI(runs)
        for _ in range(3):
            engine.iteration()
        return runs[0]
    assert torch.equal(_flat(pair(101).actor), _flat(pair(102).actor))


@pytest.mark.parametrize("key, bad", [("rollout_horizon", -1), ("rollout_horizon", 1.5), ("rollout_lambda", 1.5),
                                      ("rollout_discount_start", 1.0),
                                      ("rollout_discount_ramp", -0.1)])
def test_bad_values_are_refused_naming_the_key(key: str, bad: object) -> None:
    with pytest.raises(ValueError, match=f"algorithm.{key}"):
        _config(**{key: bad})


def test_discount_ramp() -> None:
    cfg = _config(iterations=100, rollout_discount_start=0.95, rollout_discount_ramp=0.4)
    assert rollout.discount(cfg, 0, 0.99) == pytest.approx(0.95)
    assert rollout.discount(cfg, 20, 0.99) == pytest.approx(0.97)
    assert rollout.discount(cfg, 60, 0.99) == pytest.approx(0.99)
    assert rollout.discount(_config(rollout_discount_start=0.0), 0, 0.97) == 0.97


def test_the_compiled_step_runs_the_rollout(monkeypatch: pytest.MonkeyPatch) -> None:
    """``algorithm.compile`` with the rollout departure steps the rollout's own losses (not the one-step ones): the
    functional step calls :func:`rollout.actor_loss_at` and :func:`rollout.critic_loss_at` (tests/test_compiled.py
    checks their numbers against the eager step)."""
    calls: list[str] = []
    real_actor, real_critic = rollout.actor_loss_at, rollout.critic_loss_at

    def actor(*a, **k):  # type: ignore[no-untyped-def]
        calls.append("actor")
        return real_actor(*a, **k)

    def critic(*a, **k):  # type: ignore[no-untyped-def]
        calls.append("critic")
        return real_critic(*a, **k)

    monkeypatch.setattr(rollout, "actor_loss_at", actor)
    monkeypatch.setattr(rollout, "critic_loss_at", critic)
    AGPI(CartFriction(), _config(compile="functional", j_max=1)).iteration()
    assert calls[:2] == ["actor", "critic"] and set(calls[2:]) <= {"actor"}  # then the MVC loop's PIM steps
