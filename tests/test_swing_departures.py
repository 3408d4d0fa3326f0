"""The departures for a global task (issue 42): the clipped actor with a straight-through gradient for its
parameters only (:mod:`mixedrl.departures.actor_output`) and the rollouts' start states over the task's whole
region plus carried-over end states (:mod:`mixedrl.departures.region`)."""

from __future__ import annotations

import math

import pytest
import torch

from experiments.tuning_systems import CartFriction, SwingUp
from mixedrl.algorithms.agpi import AGPI
from mixedrl.algorithms.batched import BatchedAGPI
from mixedrl.config import TrainConfig
from mixedrl.departures import region, used
from mixedrl.networks import Actor, ClippedActor

ALGORITHM = dict(batch_size=16, iterations=4, hidden_sizes=(8,), rollout_horizon=3, critic_target=0.8,
                 actor_output="clip_inward", rollout_region=0.5)


def _config(seed: int = 100, **algorithm: object) -> TrainConfig:
    return TrainConfig(method="mixed", task="linear", seed=seed, algorithm=dict(ALGORITHM, **algorithm))


def _flat(module: torch.nn.Module) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1) for p in module.parameters()])


def _saturating_actor() -> ClippedActor:
    """A clipped actor whose output is clipped on part of the inputs (a large output layer)."""
    actor = ClippedActor(3, 1, (8,), "tanh", torch.Generator().manual_seed(3), torch.tensor([2.5]))
    with torch.no_grad():
        actor.net.body[-1].weight.mul_(30.0)
    return actor


def test_clipped_value_and_straight_through_gradients() -> None:
    """Value: u_bar clip(z). Parameters: the gradient of the unclipped u_bar z on the unclipped rows (the clipped
    ones: the next test). Observations: the unclipped gradient where |z| < 1, zero where clipped (a tanh or a
    straight-through state gradient fails one of the three)."""
    actor = _saturating_actor()
    obs = torch.randn(64, 3, generator=torch.Generator().manual_seed(4), requires_grad=True)
    z = actor.net(obs)
    clipped = (z.abs() > 1).reshape(-1)
    assert 5 < int(clipped.sum()) < 59  # both kinds of rows present
    u = actor(obs)
    assert torch.equal(u, actor.action_bound * z.clamp(-1, 1))
    params = list(actor.parameters())
    weights = torch.randn(64, 1, generator=torch.Generator().manual_seed(5))
    g_clip = torch.autograd.grad((weights * u).sum(), params + [obs], retain_graph=True)
    g_free = torch.autograd.grad((weights * actor.action_bound * actor.net(obs)).sum(), params + [obs])
    inside = weights * (~clipped).to(z.dtype)[:, None]  # the parameters' gradient of the unclipped rows
    g_in = torch.autograd.grad((inside * u).sum(), params)
    g_in_free = torch.autograd.grad((inside * actor.action_bound * actor.net(obs)).sum(), params)
    for a, b in zip(g_in, g_in_free):
        assert torch.allclose(a, b, rtol=1e-5, atol=1e-6)
    assert torch.equal(g_clip[-1][clipped], torch.zeros_like(g_clip[-1][clipped]))
    assert torch.allclose(g_clip[-1][~clipped], g_free[-1][~clipped], rtol=1e-5, atol=1e-6)


def test_inward_straight_through_only_moves_a_clipped_output_back() -> None:
    """``clip_inward``: a clipped row passes its parameter gradient only where descent moves z back inside
    (dJ/dz * z > 0); the unclipped rows as before (the two-sided gradient, or none, fails)."""
    actor = _saturating_actor()
    obs = torch.randn(64, 3, generator=torch.Generator().manual_seed(4))
    weights = torch.randn(64, 1, generator=torch.Generator().manual_seed(5))
    z = actor.net(obs)
    clipped = z.abs() > 1
    back = clipped & (weights * z > 0)
    assert 0 < int(back.sum()) < int(clipped.sum())  # both kinds of clipped rows present
    keep = (~clipped | back).to(z.dtype)
    params = list(actor.parameters())
    got = torch.autograd.grad((weights * actor(obs)).sum(), params)
    want = torch.autograd.grad((keep * weights * actor.action_bound * actor.net(obs)).sum(), params)
    for a, b in zip(got, want):
        assert torch.allclose(a, b, rtol=1e-5, atol=1e-6)


def test_clipped_actor_without_gradient_is_the_clip() -> None:
    actor = _saturating_actor()
    obs = torch.randn(32, 3, generator=torch.Generator().manual_seed(6))
    with torch.no_grad():
        assert torch.equal(actor(obs), actor.action_bound * actor.net(obs).clamp(-1, 1))


def test_region_sampler_covers_the_region_and_follows_the_generator() -> None:
    task = SwingUp()
    x = task.sample_region(20000, torch.Generator().manual_seed(7))
    for i, high in enumerate((math.pi, 8.0)):
        assert x[:, i].abs().max() <= high and x[:, i].min() < -0.99 * high and x[:, i].max() > 0.99 * high
        assert abs(float(x[:, i].mean())) < 0.02 * high  # uniform, centred
        assert abs(float((x[:, i].abs() < high / 2).double().mean()) - 0.5) < 0.02
    assert torch.equal(x, task.sample_region(20000, torch.Generator().manual_seed(7)))
    assert SwingUp.declares_region() and not CartFriction.declares_region()
    with pytest.raises(NotImplementedError, match="CartFriction declares no state region"):
        CartFriction().sample_region(50, torch.Generator().manual_seed(8))


def test_a_task_without_a_region_keeps_the_samplers_batch() -> None:
    """rollout_region > 0 on a task that declares no region: the starts are the sampler's batch, nothing carried."""
    engine = BatchedAGPI([AGPI(CartFriction(), _config())])
    s = torch.randn(16, engine.task.state_dim, generator=torch.Generator().manual_seed(9))
    assert region.active(engine.members[0].config) and not region.applies(engine.members[0].config, engine.task)
    assert region.starts(engine, s, [0]) is s
    region.remember(engine, s, [0])
    assert getattr(engine.members[0], "region_carry", None) is None
    assert region.starts(engine, s, [0]) is s


def test_starts_mix_region_draws_and_carried_end_states() -> None:
    """First iteration: B region draws. Afterwards: B/2 region draws then B/2 of the last rollout's end states."""
    run = AGPI(SwingUp(), _config())
    engine = BatchedAGPI([run])
    s = torch.zeros(16, 2)
    first = region.starts(engine, s, [0])
    assert first.shape == (16, 2) and (first[:, 1].abs() > 1).any()  # beyond sample_initial's |theta_dot| <= 1
    ends = torch.arange(32, dtype=torch.float32).reshape(16, 2)
    region.remember(engine, ends, [0])
    nxt = region.starts(engine, s, [0])
    kept = nxt[8:]
    assert region.carried(run.config, 16) == 8 and kept.shape == (8, 2)
    assert all(any(torch.equal(k, e) for e in ends) for k in kept) and len({float(k[0]) for k in kept}) == 8
    assert not any(torch.equal(f, e) for f in nxt[:8] for e in ends)
    # an inactive run's rows are the sampler's, and the departure off returns the batch itself
    assert torch.equal(region.starts(engine, s, []), s)
    off = BatchedAGPI([AGPI(SwingUp(), _config(rollout_region=0.0))])
    assert region.starts(off, s, [0]) is s


def test_reproducible_and_listed() -> None:
    """Same seed, same weights; both departures listed (R = 2 batches: tests/test_rollout.py)."""
    a, b = AGPI(SwingUp(), _config()), AGPI(SwingUp(), _config())
    for run in (a, b):
        for _ in range(3):
            run.iteration()
    assert type(a.actor) is ClippedActor and torch.equal(_flat(a.actor), _flat(b.actor))
    assert {"actor_output", "region_starts"} <= set(used(_config()))
    assert not {"actor_output", "region_starts"} & set(used(_config(actor_output="tanh", rollout_region=0.0)))
    assert type(AGPI(SwingUp(), _config(actor_output="tanh")).actor) is Actor
    with pytest.raises(ValueError, match=r"^algorithm\.actor_output: 'clip' was retired .* git commit c44231f"):
        _config(actor_output="clip")  # the two-sided straight-through gradient: retired


@pytest.mark.parametrize("key, bad, extra", [("actor_output", "sigmoid", {}), ("actor_output", "inward", {}),
                                             ("rollout_region", 1.5, {})])
def test_bad_values_are_refused_naming_the_key(key: str, bad: object, extra: dict) -> None:
    with pytest.raises(ValueError, match=f"algorithm.{key}"):
        _config(**{key: bad, **extra})


def test_the_clipped_output_is_algorithm_2s_only() -> None:
    """DDPG trains its tanh actor: the setting is no departure of its (the library default is ``"clip_inward"``)."""
    from mixedrl.departures import actor_output

    assert actor_output.active(_config(actor_output="clip_inward"))
    assert not actor_output.active(_config(actor_output="clip_inward").replace(method="ddpg"))
