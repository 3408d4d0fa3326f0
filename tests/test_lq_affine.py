"""``algorithm.feedforward = "lq_affine"`` (a departure): the LQ optimum's affine policy plus a learned
remainder of second order, ``u = u_bar tanh(z* + G_z (o - o*) + MLP(o) - MLP(o*) - J_MLP(o*) (o - o*))``.

What is checked: the MLP's hand-written Jacobian is :func:`torch.func.jacfwd`'s; at the equilibrium the
policy's action is the LQ optimum's for the run's own noise and its gain ``du/dx`` is the optimum's ``-L``
at every iteration, alone and inside a batch of three methods (the stacked call too), while the weights
move; away from it the remainder is of second order; the gain in observation coordinates maps back to
``-L`` through the observation's Jacobian; an observation that does not determine the coordinates is an
error naming the option. (The anchor's action, resume and batch bits are the tests of
tests/test_feedforward_train.py, run for both anchored classes.)
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mixedrl.algorithms.batched import BatchedAGPI
from mixedrl.config import TrainConfig
from mixedrl.envs.pendulum import PendulumTask
from mixedrl.networks import MLP, AffineAnchoredActor
from mixedrl.precision import equilibrium_gain, equilibrium_observation, lq_reference, policy_gap
from mixedrl.runs import make_trainer
from mixedrl.tasks import LinearTask


def _cfg(method: str, seed: int = 0) -> TrainConfig:
    return TrainConfig(method=method, task="linear", seed=seed,
                       algorithm={"batch_size": 16, "hidden_sizes": (8, 8), "feedforward": "lq_affine"},
                       run={"eval_every": 1000, "checkpoint_every": 1000, "eval_seeds": 1})


def _gap(trainer) -> dict:
    return policy_gap(trainer.task, trainer.actor, *trainer.noise_moments())


@pytest.mark.parametrize("activation", ["elu", "tanh", "relu"])
def test_mlp_jacobian_is_autodiffs(activation: str) -> None:
    mlp = MLP(3, 2, (16, 8), activation, torch.Generator().manual_seed(1), torch.tensor([0.5, 2.0, 3.0]))
    for x in torch.randn(5, 3, generator=torch.Generator().manual_seed(2)):
        assert torch.allclose(mlp.jacobian(x), torch.func.jacfwd(mlp)(x), atol=1e-6)


@pytest.mark.parametrize("method", ["mixed", "model", "oracle"])
def test_action_and_gain_are_the_lq_optimums_at_every_iteration(method: str) -> None:
    trainer = make_trainer(_cfg(method))
    assert isinstance(trainer.actor, AffineAnchoredActor)
    lin = trainer.task.linearisation()
    L = lq_reference(lin, trainer.task.prior_mean).solution.gain
    start = [p.detach().clone() for p in trainer.actor.parameters()]
    for _ in range(5):
        trainer.iteration()
        gap = _gap(trainer)
        assert max(abs(e) for e in gap["action_error"]) < 1e-5
        assert np.allclose(gap["gain"], -L, atol=1e-4) and gap["gain_error_rel"] < 1e-4
    moved = max(float((p - q).abs().max()) for p, q in zip(trainer.actor.parameters(), start))
    assert moved > 1e-3  # the weights trained, the first-order part did not move


def test_a_batch_keeps_each_runs_gain() -> None:
    runs = [make_trainer(_cfg(m, s)) for m, s in (("mixed", 0), ("model", 1), ("oracle", 2))]
    engine = BatchedAGPI(runs)
    lin = runs[0].task.linearisation()
    L = lq_reference(lin, runs[0].task.prior_mean).solution.gain
    o = equilibrium_observation(runs[0].task, lin)
    eps = 1e-2
    J_o = torch.func.jacrev(lambda x: runs[0].task.observe(lin.to_state(x[None]))[0])(
        torch.zeros(lin.A.shape[0], dtype=torch.float64)).float()
    for _ in range(3):
        engine.iteration()
        for t in runs:
            assert _gap(t)["gain_error_rel"] < 1e-4
        # the stacked (vmapped) call: central differences along each coordinate at o*, every run's rows
        rows = [o + s * eps * J_o[:, i] for i in range(J_o.shape[1]) for s in (1.0, -1.0)]
        block = torch.stack(rows)
        x = block.repeat(engine.batch // block.shape[0] + 1, 1)[:engine.batch]  # rows 0.. of each run: block
        with torch.no_grad():
            out = engine.actor(x.repeat(3, 1))
        for r in range(3):
            u = out[r * engine.batch:(r + 1) * engine.batch]
            slope = np.array([[(float(u[2 * i, a]) - float(u[2 * i + 1, a])) / (2 * eps)
                               for i in range(J_o.shape[1])] for a in range(L.shape[0])])
            assert np.allclose(slope, -L, rtol=2e-2, atol=2e-3)


def test_the_remainder_is_of_second_order() -> None:
    trainer = make_trainer(_cfg("mixed"))
    for _ in range(3):
        trainer.iteration()
    actor = trainer.actor
    o, d = actor.anchor_obs, torch.tensor([0.7, -0.4])
    u0 = actor(o[None])[0].double()
    slope = (actor.action_bound * (1 - torch.tanh(actor.anchor_z) ** 2)).double()
    G = actor.anchor_gain.double()

    def remainder(eps: float) -> float:  # in pre-tanh units, where the first-order part is exact
        with torch.no_grad():
            u = actor((o + eps * d)[None])[0].double()
        z = torch.atanh(u / actor.action_bound.double()) - torch.atanh(u0 / actor.action_bound.double())
        return float((z - eps * (G @ d.double()) / slope).abs().max())

    r1, r2 = remainder(0.1), remainder(0.05)
    assert r1 > 1e-6  # the learned part is not zero
    assert 2.5 < r1 / r2 < 6.0  # O(eps^2): halving eps quarters it (a first-order error would halve it)


def test_gain_in_observation_coordinates_maps_back_to_minus_l() -> None:
    """The pendulum observes (theta, theta_dot) scaled; G J_o = -L."""
    task = PendulumTask()
    lin = task.linearisation()
    G = equilibrium_gain(task, lin).numpy()
    J_o = torch.func.jacrev(lambda x: task.observe(lin.to_state(x[None]))[0])(
        torch.zeros(lin.A.shape[0], dtype=torch.float64)).numpy()
    L = lq_reference(lin, np.zeros(lin.E.shape[1])).solution.gain
    assert np.allclose(G @ J_o, -L, rtol=1e-10, atol=1e-10)


class _Blind(LinearTask):
    """Observes only the first coordinate: the observation does not determine the state."""

    def observe(self, s: torch.Tensor) -> torch.Tensor:
        return s[..., :1]


def test_an_observation_that_misses_a_coordinate_is_an_error() -> None:
    task = _Blind()
    with pytest.raises(ValueError, match=r"algorithm.feedforward: 'lq_affine' and 'lq_affine_ss' need observations .* rank 1"):
        equilibrium_gain(task, task.linearisation())


def test_gain_errors_name_the_argument() -> None:
    args = (2, 1, (4,), "elu", torch.Generator().manual_seed(0), torch.tensor([1.0]))
    with pytest.raises(ValueError, match=r"gain: expected a finite \(1, 2\) matrix"):
        AffineAnchoredActor(*args, anchor_obs=torch.zeros(2), gain=torch.zeros(2, 1))
    with pytest.raises(ValueError, match="gain: expected a finite"):
        AffineAnchoredActor(*args, anchor_obs=torch.zeros(2), gain=torch.tensor([[float("nan"), 0.0]]))
    actor = AffineAnchoredActor(*args, anchor_obs=torch.zeros(2), gain=torch.ones(1, 2))
    before = {k: v.clone() for k, v in actor.state_dict().items()}
    for bad in (torch.zeros(3), torch.tensor([0.0, float("inf")])):
        with pytest.raises(ValueError, match="obs: expected 2 finite numbers"):
            actor.set_anchor(bad, torch.tensor([0.5]))
    assert all(torch.equal(v, actor.state_dict()[k]) for k, v in before.items())  # left as it was


@pytest.mark.parametrize("method", ["mixed", "oracle"])  # (the prior's mean is 0 here: x_ss = 0 for "model")
def test_lq_affine_ss_holds_the_optimums_steady_state_exactly(method: str) -> None:
    """``"lq_affine_ss"``: the anchor is the LQ optimum's steady state ``x_ss`` for the run's own noise, so on
    the (exactly linear) task the mean closed loop under the run's own noise mean has ``x_ss`` as its fixed
    point, whatever the remainder's weights: ``A x_ss + B (u(x_ss) - u*) + E mu = x_ss``; the gain there is
    ``-L``. With ``"lq_affine"`` (anchored at the equilibrium) the remainder moves the fixed point."""
    errors = {}
    for ff in ("lq_affine_ss", "lq_affine"):
        trainer = make_trainer(_cfg(method).replace(**{"algorithm.feedforward": ff}))
        for _ in range(5):
            trainer.iteration()
        lin = trainer.task.linearisation()
        mean, cov = trainer.noise_moments()
        ref = lq_reference(lin, mean, cov)
        x_ss = torch.as_tensor(ref.steady_state)[None]

        def act(x: torch.Tensor) -> torch.Tensor:
            return trainer.actor(trainer.task.observe(lin.to_state(x).float()))[0].double()

        with torch.no_grad():
            u = act(x_ss).numpy()
        nxt = lin.A @ ref.steady_state + lin.B @ (u - lin.action) + lin.E @ np.asarray(mean)
        errors[ff] = float(np.abs(nxt - ref.steady_state).max())
        if ff == "lq_affine_ss":
            assert np.abs(ref.steady_state).max() > 0.1  # the anchor is away from the equilibrium
            assert np.allclose(trainer.actor.anchor_obs.double().numpy(),
                               trainer.task.observe(lin.to_state(x_ss)).numpy()[0], atol=1e-6)
            gain = torch.func.jacrev(lambda x: act(x[None]))(x_ss[0]).detach().numpy()
            assert np.allclose(gain, -ref.solution.gain, atol=1e-4)
    assert errors["lq_affine_ss"] < 1e-5 < 100 * 1e-5 < errors["lq_affine"], errors
