"""One true-environment step: training (DoubleLaneChangeTask.true_step), the torch vector env, the
Gymnasium env and the Table I evaluation all go through DoubleLaneChangeModel.true_step, so for the same
state, action and noise draw they give the same next state.

The expected next states are built here from the model's deterministic ``f`` (``step``) plus a force
computed by hand from the disturbance law (mean at the state before the step, a standard normal drawn
from a freshly seeded generator), not from ``true_step`` itself.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from gymnasium.utils import seeding

from mixedrl.envs import (
    DoubleLaneChangeEnv,
    DoubleLaneChangeModel,
    DoubleLaneChangeVectorEnv,
    evaluate_tracking,
)
from mixedrl.tasks import DoubleLaneChangeTask

# A road grade makes the mean force depend on X, so a draw at the wrong state would show.
GRADE = {"disturbance": {"grade_amplitude": 0.05, "grade_wavelength": 30.0, "grade_phase": 0.3}}
CROSS_BACKEND_ATOL = 1e-12  # math vs torch vs numpy libm: one step, values of order 10


def _batch(model: DoubleLaneChangeModel, n: int = 16, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    s = model.reset_states(n, gen, dtype=torch.float64)
    u = torch.stack([0.3 * torch.rand(n, generator=gen, dtype=torch.float64) - 0.15,
                     2.0 * torch.rand(n, generator=gen, dtype=torch.float64) - 1.0], dim=-1)
    return s, u  # inside the action box, so no path clips


def _hand_force(model: DoubleLaneChangeModel, X: np.ndarray, z: np.ndarray) -> np.ndarray:
    """F_dis = mean - m g sin(theta(X)) + std z  (eq. 53 with the configured grade), written out here."""
    cfg = model.config
    d, p = cfg.disturbance, cfg.params
    theta = d.grade_amplitude * np.sin(2.0 * math.pi / d.grade_wavelength * X + d.grade_phase)
    return d.mean - p.m * p.g * np.sin(theta) + math.sqrt(d.variance) * z


def _expected_next(model: DoubleLaneChangeModel, s: torch.Tensor, u: torch.Tensor, force: np.ndarray) -> np.ndarray:
    """f(s, u) + E xi with xi = F_dis T / m on v_x only (eq. 54)."""
    cfg = model.config
    out = model.step(s, u).numpy().copy()
    out[..., 2] += force * (cfg.dt / cfg.params.m)
    return out


def test_task_true_step_is_f_plus_the_configured_disturbance() -> None:
    task = DoubleLaneChangeTask(**GRADE)
    model = task.model
    s, u = _batch(model)
    got = task.true_step(s, u, torch.Generator().manual_seed(7))
    z = torch.randn(s.shape[0], generator=torch.Generator().manual_seed(7), dtype=torch.float64).numpy()
    expected = _expected_next(model, s, u, _hand_force(model, s[:, 5].numpy(), z))
    np.testing.assert_allclose(got.numpy(), expected, rtol=0, atol=1e-13)
    # the model's function with the same generator stream is the very same computation
    same = model.true_step(s, u, torch.Generator().manual_seed(7))
    assert torch.equal(got, same)


def test_zero_variance_step_uses_the_mean_at_the_state_before_the_step() -> None:
    task = DoubleLaneChangeTask(disturbance={**GRADE["disturbance"], "variance": 0.0})
    model = task.model
    s, u = _batch(model, seed=3)
    resid = (task.true_step(s, u, torch.Generator().manual_seed(0)) - model.step(s, u)).numpy()
    cfg = model.config
    xi = _hand_force(model, s[:, 5].numpy(), np.zeros(s.shape[0])) * cfg.dt / cfg.params.m
    # (f + xi) - f loses the bits of xi below ulp(v_x ~ 12) ~ 2e-15; a draw at the next state's X would be
    # off by ~3e-5 (X moves ~0.06 m per step)
    np.testing.assert_allclose(resid[:, 2], xi, rtol=0, atol=1e-14)
    assert np.ptp(xi) > 1e-5  # the grade really makes the mean state dependent
    assert not resid[:, [0, 1, 3, 4, 5]].any()  # E xi is zero off v_x


def test_vector_env_step_equals_task_true_step() -> None:
    task = DoubleLaneChangeTask(**GRADE)
    s, u = _batch(task.model, seed=1)
    venv = DoubleLaneChangeVectorEnv(s.shape[0], task.model.config, dtype=torch.float64, seed=11)
    venv.state = s.clone()
    _, _, _, _, info = venv.step(u)
    expected = task.true_step(s, u, torch.Generator().manual_seed(11))
    assert torch.equal(info["next_state"], expected)
    resid = (expected - task.model.step(s, u))[:, 2].numpy()
    np.testing.assert_allclose(info["xi"].numpy(), resid, rtol=0, atol=1e-14)  # ulp(v_x ~ 12) ~ 2e-15


def test_gym_env_step_equals_the_torch_true_step_for_the_same_draw() -> None:
    model = DoubleLaneChangeModel(GRADE)
    s, u = _batch(model, n=6, seed=2)
    env = DoubleLaneChangeEnv(GRADE)
    for i in range(s.shape[0]):
        env.reset(seed=100 + i, options={"state": s[i].numpy()})
        _, _, _, _, info = env.step_physical(u[i].numpy())
        z = seeding.np_random(100 + i)[0].standard_normal()
        force = _hand_force(model, s[i, 5].numpy(), np.asarray(z))
        assert info["disturbance"] == pytest.approx(float(force), rel=1e-15)
        expected = _expected_next(model, s[i], u[i], force)
        np.testing.assert_allclose(info["state"], expected, rtol=0, atol=CROSS_BACKEND_ATOL)
        # the torch path of the same function, same draw
        torch_next = model.true_step(s[i], u[i], force=torch.tensor(info["disturbance"], dtype=torch.float64))
        np.testing.assert_allclose(info["state"], torch_next.numpy(), rtol=0, atol=CROSS_BACKEND_ATOL)


def test_evaluation_trajectory_is_a_chain_of_true_steps() -> None:
    model = DoubleLaneChangeModel(GRADE)

    def policy(obs: np.ndarray) -> np.ndarray:
        return np.array([-0.2 * obs[4] - 0.5 * obs[3], -0.5 * obs[2]])

    res = evaluate_tracking(policy, model.config, seed=5, max_steps=40)
    assert res.n_steps == 40 and not res.terminated
    z = seeding.np_random(5)[0].standard_normal(40)  # one normal per step, in order
    np.testing.assert_allclose(res.disturbance, _hand_force(model, res.states[:-1, 5], z), rtol=1e-15)
    states = torch.tensor(res.states)
    actions = torch.tensor(res.actions)
    expected = _expected_next(model, states[:-1], actions, res.disturbance)
    np.testing.assert_allclose(res.states[1:], expected, rtol=0, atol=CROSS_BACKEND_ATOL)
    for k in range(40):  # the float path of the one function reproduces each step exactly
        nxt = model.true_step(tuple(res.states[k].tolist()), tuple(res.actions[k].tolist()),
                              force=float(res.disturbance[k]))
        assert nxt == tuple(res.states[k + 1].tolist())


def test_numpy_batch_path_draws_one_normal_per_state() -> None:
    model = DoubleLaneChangeModel(GRADE)
    s, u = _batch(model, seed=4)
    got = model.true_step(s.numpy(), u.numpy(), np.random.default_rng(9))
    z = np.random.default_rng(9).standard_normal(s.shape[0])
    expected = _expected_next(model, s, u, _hand_force(model, s[:, 5].numpy(), z))
    assert isinstance(got, np.ndarray) and got.shape == (s.shape[0], 6)
    np.testing.assert_allclose(got, expected, rtol=0, atol=CROSS_BACKEND_ATOL)


def test_true_step_rejects_bad_arguments() -> None:
    model = DoubleLaneChangeModel()
    s, u = _batch(model, n=2)
    with pytest.raises(ValueError, match="^generator"):
        model.true_step(s, u, torch.Generator(), force=torch.zeros(2, dtype=torch.float64))
    with pytest.raises(ValueError, match="^generator"):
        model.true_step(s, u, np.random.default_rng(0))
    with pytest.raises(ValueError, match="^generator"):
        model.true_step(s.numpy(), u.numpy(), torch.Generator())
    with pytest.raises(ValueError, match="^generator"):
        model.true_step(tuple(s[0].tolist()), (0.0, 0.0), None)
    with pytest.raises(ValueError, match="^s"):
        model.true_step((0.0, 1.0, 12.0), (0.0, 0.0), np.random.default_rng(0))
    with pytest.raises(ValueError, match="^u"):
        model.true_step(s, u[:, :1], torch.Generator())
