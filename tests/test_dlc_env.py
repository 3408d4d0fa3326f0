"""The double-lane-change task: reference, tracking model, noise, Gymnasium env, vector env, metrics.

Expected values come from formulas written out here (EQUATIONS.md), or from statistical bands.
"""

from __future__ import annotations

import math
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import mixedrl.envs as E
from mixedrl.envs import (
    ENV_ID,
    NOISE_INDEX,
    DoubleLaneChangeConfig,
    DoubleLaneChangeEnv,
    DoubleLaneChangeModel,
    DoubleLaneChangeReference,
    DoubleLaneChangeVectorEnv,
    evaluate_tracking,
    make_config,
)

T = 1.0 / 200.0
M = 1500.0


def y_ref_textbook(X: np.ndarray) -> np.ndarray:
    """EQUATIONS.md: Y_ref = dy1/2 (1 + tanh z1) - dy2/2 (1 + tanh z2)."""
    z1 = 2.4 / 25 * (X - 27.19) - 1.2
    z2 = 2.4 / 21.95 * (X - 56.46) - 1.2
    return 4.05 / 2 * (1 + np.tanh(z1)) - 5.7 / 2 * (1 + np.tanh(z2))


def psi_ref_textbook(X: np.ndarray, h: float = 1e-5) -> np.ndarray:
    return np.arctan((y_ref_textbook(X + h) - y_ref_textbook(X - h)) / (2 * h))


# ------------------------------------------------------------------------------------------------------
# reference
# ------------------------------------------------------------------------------------------------------
def test_reference_matches_equations() -> None:
    ref = DoubleLaneChangeReference()
    X = np.linspace(-20.0, 160.0, 1801)
    np.testing.assert_allclose(ref.lateral(X), y_ref_textbook(X), rtol=0, atol=1e-13)
    np.testing.assert_allclose(ref.heading(X), psi_ref_textbook(X), rtol=0, atol=1e-9)
    lat, head = ref.lateral_and_heading(torch.tensor(X))
    np.testing.assert_allclose(lat.numpy(), y_ref_textbook(X), rtol=0, atol=1e-13)
    np.testing.assert_allclose(head.numpy(), psi_ref_textbook(X), rtol=0, atol=1e-9)
    assert ref.lateral(37.0) == pytest.approx(float(y_ref_textbook(np.array(37.0))), abs=1e-13)
    # the course starts on Y ~ 0 and ends at dy1 - dy2 = -1.65 m
    assert abs(ref.lateral(0.0)) < 0.05 and ref.lateral(120.0) == pytest.approx(-1.65, abs=0.01)


def test_reference_rejects_bad_fields() -> None:
    with pytest.raises(ValueError, match="^len1"):
        DoubleLaneChangeReference(len1=0.0)
    with pytest.raises(ValueError, match="^dy1"):
        DoubleLaneChangeReference(dy1=float("nan"))


# ------------------------------------------------------------------------------------------------------
# config
# ------------------------------------------------------------------------------------------------------
def test_config_unknown_keys_and_roundtrip() -> None:
    with pytest.raises(ValueError, match="^config"):
        make_config(dt_typo=0.1)
    with pytest.raises(ValueError, match="^disturbance"):
        make_config(disturbance={"maen": 1.0})
    with pytest.raises(ValueError, match="^preview_distances"):
        make_config(preview_distances=(-1.0,))
    cfg = make_config(disturbance={"mean": 100.0}, preview_distances=(5.0, 10.0))
    assert cfg.disturbance.mean == 100.0 and cfg.disturbance.variance == 32.0
    assert DoubleLaneChangeConfig.from_dict(cfg.to_dict()) == cfg
    assert DoubleLaneChangeConfig().max_steps == 2000  # 120 m at 12 m/s with T = 1/200 s


# ------------------------------------------------------------------------------------------------------
# tracking model: observation, cost, termination, noise
# ------------------------------------------------------------------------------------------------------
def some_states(n: int = 32, seed: int = 0) -> torch.Tensor:
    model = DoubleLaneChangeModel()
    return model.reset_states(n, torch.Generator().manual_seed(seed), dtype=torch.float64)


def test_observation_and_cost_are_the_paper_quantities() -> None:
    model = DoubleLaneChangeModel({"preview_distances": (6.0,)})
    s = some_states()
    u = torch.randn(32, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    vy, r, vx, phi, Y, X = (s[:, i].numpy() for i in range(6))
    e_y = Y - y_ref_textbook(X)
    e_phi = phi - psi_ref_textbook(X)
    want_obs = np.column_stack([vy, r, vx - 12.0, e_phi, e_y, y_ref_textbook(X + 6.0) - y_ref_textbook(X)])
    np.testing.assert_allclose(model.observe(s).numpy(), want_obs, rtol=0, atol=1e-9)
    np.testing.assert_allclose(model.observe(s.numpy()), want_obs, rtol=0, atol=1e-9)
    un = u.numpy()
    want_cost = T * (45 * (vx - 12) ** 2 + 60 * e_y**2 + 800 * un[:, 0] ** 2 + un[:, 1] ** 2)
    np.testing.assert_allclose(model.cost(s, u).numpy(), want_cost, rtol=1e-12, atol=0)
    paper = model.paper_state(s).numpy()
    np.testing.assert_allclose(paper, np.column_stack([vy, r, vx, e_phi, e_y]), rtol=0, atol=1e-9)


def test_reset_states_distribution() -> None:
    model = DoubleLaneChangeModel()
    s = model.reset_states(4000, torch.Generator().manual_seed(0), dtype=torch.float64)
    s2 = model.reset_states(4000, torch.Generator().manual_seed(0), dtype=torch.float64)
    assert torch.equal(s, s2)
    obs = model.observe(s).numpy()
    w = np.array(model.config.train_half_widths)
    assert np.all(np.abs(obs) <= w + 1e-9)
    # uniform on [-w, w]: each coordinate's mean is within 4 standard errors of 0
    assert np.all(np.abs(obs.mean(axis=0)) < 4 * w / math.sqrt(3 * 4000))
    X = s[:, 5].numpy()
    assert X.min() >= 0 and X.max() <= 120.0 and abs(X.mean() - 60.0) < 4 * 120 / math.sqrt(12 * 4000)
    assert not model.is_terminated(s).any()


def test_is_terminated() -> None:
    model = DoubleLaneChangeModel()
    s = torch.tensor([[0, 0, 12.0, 0, 0, 0]] * 4, dtype=torch.float64)
    s[1, 4] = 3.2  # e_y ~ 3.2 m > 3 m: off the road
    s[2, 2] = 0.5  # too slow for the bicycle model
    s[3, 0] = float("nan")
    assert model.is_terminated(s).tolist() == [False, True, True, True]
    assert model.is_terminated(s.numpy()).tolist() == [False, True, True, True]


def test_action_helpers() -> None:
    model = DoubleLaneChangeModel()
    u = torch.tensor([[1.0, -10.0], [0.1, 1.0]])
    np.testing.assert_allclose(model.clip_action(u).numpy(), [[0.4, -4.0], [0.1, 1.0]], rtol=1e-7)
    squashed = model.squash_action(torch.tensor([[100.0, -100.0], [0.0, 0.0]]))
    np.testing.assert_allclose(squashed.numpy(), [[0.4, -4.0], [0.0, 0.0]], rtol=1e-7)


def test_grade_disturbance_mean_depends_on_X() -> None:
    """F_dis mean = 261 - m g sin(theta(X)), theta = A sin(2 pi X / lambda): sample means at 3 positions."""
    amp, lam = 0.02, 40.0
    model = DoubleLaneChangeModel({"disturbance": {"grade_amplitude": amp, "grade_wavelength": lam}})
    gen = torch.Generator().manual_seed(5)
    n = 20000
    for X in (0.0, 10.0, 30.0):
        s = torch.tensor([[0, 0, 12.0, 0, 0, X]], dtype=torch.float64).expand(n, 6)
        F = model.sample_force(s, gen).numpy()
        want = 261.0 - M * 9.81 * math.sin(amp * math.sin(2 * math.pi * X / lam))
        assert abs(F.mean() - want) < 4 * math.sqrt(32.0 / n)
        np.testing.assert_allclose(model.xi_mean(s[:1]).numpy(), want * T / M, rtol=1e-12)


# ------------------------------------------------------------------------------------------------------
# Gymnasium env
# ------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kwargs", [{}, {"preview_distances": (5.0, 10.0)}])
def test_check_env_no_warnings(kwargs: dict) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        env = gym.make(ENV_ID, **kwargs)
        check_env(env.unwrapped)
        env.close()


def test_registered_and_spaces() -> None:
    env = gym.make(ENV_ID)
    assert isinstance(env.unwrapped, DoubleLaneChangeEnv)
    assert env.action_space.shape == (2,) and env.observation_space.shape == (5,)
    with pytest.raises(ValueError, match="^config"):
        gym.make(ENV_ID, not_a_field=1)


def rollout(env: DoubleLaneChangeEnv, actions: np.ndarray, seed: int) -> list[np.ndarray]:
    obs, _ = env.reset(seed=seed)
    out = [obs]
    for a in actions:
        obs, *_ = env.step(a)
        out.append(obs)
    return out


def test_reset_seed_reproducible() -> None:
    actions = np.random.default_rng(0).uniform(-0.2, 0.2, size=(50, 2))
    a = rollout(DoubleLaneChangeEnv(), actions, seed=3)
    b = rollout(DoubleLaneChangeEnv(), actions, seed=3)
    c = rollout(DoubleLaneChangeEnv(), actions, seed=4)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not np.array_equal(a[-1], c[-1])


def test_step_is_f_plus_xi_and_reward_is_eq54() -> None:
    env = DoubleLaneChangeEnv()
    model = DoubleLaneChangeModel()
    _, info = env.reset(seed=0)
    s = info["state"]
    for k in range(20):
        a = np.array([0.1 * math.sin(k), 0.05])
        obs, reward, term, trunc, info = env.step(a)
        u = a * np.array([0.4, 4.0])
        np.testing.assert_array_equal(info["action"], u)
        assert info["xi"] == pytest.approx(info["disturbance"] * T / M, rel=1e-15)
        resid = info["state"] - model.step(s, u)
        np.testing.assert_allclose(resid, np.eye(6)[NOISE_INDEX] * info["xi"], rtol=0, atol=1e-12)
        vx, Y, X = info["state"][2], info["state"][4], info["state"][5]
        e_y = Y - y_ref_textbook(np.array(X))
        assert info["lateral_error"] == pytest.approx(float(e_y), abs=1e-12)
        assert info["speed_error"] == pytest.approx(vx - 12.0, abs=1e-14)
        cost = T * (45 * (vx - 12) ** 2 + 60 * e_y**2 + 800 * u[0] ** 2 + u[1] ** 2)
        assert reward == pytest.approx(-float(cost), rel=1e-12)
        np.testing.assert_allclose(obs, model.observe(info["state"]), rtol=0, atol=1e-14)
        s = info["state"]


def test_disturbance_statistics_in_env() -> None:
    """F_dis ~ N(261, 32): sample mean within 4 standard errors, sample variance within 4 of its SEs."""
    env = DoubleLaneChangeEnv(max_lateral_error=1e9, course_length=1e9)
    env.reset(seed=11)
    n = 20000
    F = np.empty(n)
    for k in range(n):
        _, _, _, _, info = env.step_physical(np.array([0.0, -0.174]))
        F[k] = info["disturbance"]
    assert abs(F.mean() - 261.0) < 4 * math.sqrt(32.0 / n)
    assert abs(F.var(ddof=1) - 32.0) < 4 * 32.0 * math.sqrt(2.0 / (n - 1))


def test_nan_action_raises_and_leaves_state() -> None:
    env = DoubleLaneChangeEnv()
    env.reset(seed=0)
    before = env.state
    for bad in ([np.nan, 0.0], [0.0, np.inf]):
        with pytest.raises(ValueError, match="^action"):
            env.step(np.array(bad))
        with pytest.raises(ValueError, match="^u"):
            env.step_physical(np.array(bad))
    with pytest.raises(ValueError, match="^action"):
        env.step(np.zeros(3))
    np.testing.assert_array_equal(env.state, before)


def test_out_of_bounds_actions_are_clipped() -> None:
    e1, e2, e3 = DoubleLaneChangeEnv(), DoubleLaneChangeEnv(), DoubleLaneChangeEnv()
    for e in (e1, e2, e3):
        e.reset(seed=7)
    o1, r1, *_, i1 = e1.step(np.array([5.0, -3.0]))
    o2, r2, *_, i2 = e2.step(np.array([1.0, -1.0]))
    o3, r3, *_, i3 = e3.step_physical(np.array([2.0, -40.0]))
    np.testing.assert_array_equal(o1, o2)
    np.testing.assert_array_equal(o1, o3)
    assert r1 == r2 == r3
    assert i1["action_clipped"] and not i2["action_clipped"] and i3["action_clipped"]
    np.testing.assert_array_equal(i1["action"], [0.4, -4.0])


def test_termination_and_truncation() -> None:
    env = DoubleLaneChangeEnv()
    env.reset(options={"state": [0, 0, 12.0, 0, 3.5, 0]})  # e_y ~ 3.5 m: already off the road
    _, _, term, trunc, _ = env.step(np.zeros(2))
    assert term and not trunc
    env.reset(options={"state": [0, 0, 1.0, 0, 0, 0]})
    _, _, term, _, _ = env.step_physical(np.array([0.0, -4.0]))  # v_x drops below 1 m/s
    assert term
    short = DoubleLaneChangeEnv(course_length=1.2, max_lateral_error=100.0)  # 20 steps
    short.reset(seed=0)
    flags = [short.step(np.zeros(2))[2:4] for _ in range(20)]
    assert [tr for _, tr in flags] == [False] * 19 + [True] and not any(te for te, _ in flags)
    with pytest.raises(ValueError, match="^options"):
        env.reset(options={"sate": [0] * 6})


def test_numpy_env_and_torch_model_agree_over_1000_steps() -> None:
    """The env's float path and the torch model (float64) give the same trajectory to 1e-9."""
    env = DoubleLaneChangeEnv(max_lateral_error=1e6)  # open-loop steering: the car leaves the course
    model = DoubleLaneChangeModel()
    _, info = env.reset(seed=1)
    s_t = torch.tensor(info["state"], dtype=torch.float64)
    rng = np.random.default_rng(2)
    worst = 0.0
    for k in range(1000):
        a = np.array([0.3 * math.sin(0.01 * k), 0.1]) + rng.normal(0, 0.05, 2)
        _, _, term, _, info = env.step(a)
        assert not term
        u = torch.tensor(info["action"], dtype=torch.float64)
        s_t = model.step(s_t, u) + model.noise_vector(torch.tensor(info["xi"], dtype=torch.float64))
        worst = max(worst, float(np.max(np.abs(s_t.numpy() - info["state"]))))
    assert worst < 1e-9


# ------------------------------------------------------------------------------------------------------
# vector env
# ------------------------------------------------------------------------------------------------------
def test_vector_env_same_f_noise_and_autoreset() -> None:
    venv = DoubleLaneChangeVectorEnv(64, {"course_length": 0.6}, dtype=torch.float64, seed=0)  # 10 steps
    model = DoubleLaneChangeModel()
    obs = venv.reset()
    assert obs.shape == (64, 5)
    xis = []
    for k in range(10):
        u = 0.05 * torch.randn(64, 2, generator=torch.Generator().manual_seed(k), dtype=torch.float64)
        obs, reward, term, trunc, info = venv.step(u)
        resid = info["next_state"] - model.step(info["state"], info["action"])
        np.testing.assert_allclose(resid.numpy(), model.noise_vector(info["xi"]).numpy(), rtol=0, atol=1e-12)
        np.testing.assert_allclose(reward.numpy(), -model.cost(info["next_state"], info["action"]).numpy(),
                                   rtol=1e-14)
        xis.append(info["xi"])
    assert bool(trunc.all()) and not bool(term.any())
    np.testing.assert_allclose(venv.state[:, 5].numpy(), 0.0)  # reset to the start of the course
    F = torch.cat(xis).numpy() * M / T
    assert abs(F.mean() - 261.0) < 4 * math.sqrt(32.0 / F.size)


def test_vector_env_reproducible_and_rejects_nan() -> None:
    outs = []
    for _ in range(2):
        venv = DoubleLaneChangeVectorEnv(8, seed=3)
        venv.reset()
        outs.append(venv.step(torch.zeros(8, 2))[0])
    assert torch.equal(outs[0], outs[1])
    before = venv.state.clone()
    bad = torch.zeros(8, 2)
    bad[3, 0] = float("nan")
    with pytest.raises(ValueError, match="^u"):
        venv.step(bad)
    with pytest.raises(ValueError, match="^u"):
        venv.step(torch.zeros(8, 2, dtype=torch.float64))
    assert torch.equal(venv.state, before)


# ------------------------------------------------------------------------------------------------------
# evaluate_tracking
# ------------------------------------------------------------------------------------------------------
def test_evaluate_tracking_straight_run_matches_reference_formula() -> None:
    """No input, no disturbance: the car drives straight along Y = 0 at 12 m/s, so e_y(t) = -Y_ref(12 t)."""
    cfg = {"disturbance": {"mean": 0.0, "variance": 0.0}, "max_lateral_error": 100.0}
    res = evaluate_tracking(lambda obs: np.zeros(2), cfg, start_state=np.array([0, 0, 12.0, 0, 0, 0]))
    t = np.arange(1, 2001) * T
    want = np.abs(y_ref_textbook(12.0 * t))
    assert res.n_steps == 2000 and not res.terminated
    assert res.mean_abs_lateral_error == pytest.approx(want.mean(), rel=1e-10)
    assert res.max_abs_lateral_error == pytest.approx(want.max(), rel=1e-10)
    assert res.mean_abs_speed_error == 0.0 and res.max_abs_speed_error == 0.0
    assert res.states.shape == (2001, 6) and res.actions.shape == (2000, 2)
    assert res.table_row()["eval/lateral_error_m"] == res.mean_abs_lateral_error


def test_evaluate_tracking_policies_and_errors() -> None:
    lin = torch.nn.Linear(5, 2, dtype=torch.float64)
    torch.nn.init.zeros_(lin.weight)
    torch.nn.init.zeros_(lin.bias)
    r_mod = evaluate_tracking(lin, max_steps=50, seed=2)
    r_fun = evaluate_tracking(lambda o: np.zeros(2), max_steps=50, seed=2)
    np.testing.assert_array_equal(r_mod.states, r_fun.states)
    with pytest.raises(ValueError, match="^u"):
        evaluate_tracking(lambda o: np.array([np.nan, 0.0]), max_steps=5)
    with pytest.raises(ValueError, match="^max_steps"):
        evaluate_tracking(lambda o: np.zeros(2), max_steps=0)


def test_package_exports() -> None:
    assert callable(E.evaluate_tracking) and E.ENV_ID == "mixedrl/DoubleLaneChange-v0"
    assert E.NOISE_INDEX == 2 and DoubleLaneChangeModel.NOISE_INDEX == 2


def test_step_after_episode_end_raises_until_reset() -> None:
    """Gymnasium's contract: no step after termination or truncation without a reset."""
    env = DoubleLaneChangeEnv()
    env.reset(options={"state": [0, 0, 12.0, 0, 3.5, 0]})  # off the road: terminates at once
    assert env.step(np.zeros(2))[2]
    before = env.state
    for stepper in (env.step, env.step_physical):
        with pytest.raises(RuntimeError, match="episode has ended.*reset"):
            stepper(np.zeros(2))
    np.testing.assert_array_equal(env.state, before)
    short = DoubleLaneChangeEnv(course_length=0.06, max_lateral_error=100.0)  # 1 step, then truncated
    short.reset(seed=0)
    assert short.step(np.zeros(2))[3]
    with pytest.raises(RuntimeError, match="episode has ended"):
        short.step(np.zeros(2))
    short.reset(seed=1)
    short.step(np.zeros(2))  # a reset makes stepping legal again


@pytest.mark.parametrize("bad", ["left", b"ab", ["0.1", "0.2"], object(), {"a": 1}, None])
def test_non_numeric_action_names_its_type_and_the_space(bad: object) -> None:
    env = DoubleLaneChangeEnv()
    env.reset(seed=0)
    before = env.state
    with pytest.raises(TypeError, match=rf"^action: expected a numeric array in Box\(-1\.0, 1\.0, \(2,\), float64\), "
                                        rf"got {type(bad).__name__}"):
        env.step(bad)
    with pytest.raises(TypeError, match=rf"^u: .*got {type(bad).__name__}"):
        env.step_physical(bad)
    np.testing.assert_array_equal(env.state, before)


@pytest.mark.parametrize("bad", [np.array([0.1 + 0.5j, 0.0]), [0.1 + 0j, 0.2], np.array([0.1, 0.2], dtype=np.complex64)])
def test_complex_action_is_an_error_not_a_warning(bad: object) -> None:
    env = DoubleLaneChangeEnv()
    env.reset(seed=0)
    before = env.state
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the cast's ComplexWarning must not be the only sign
        with pytest.raises(TypeError, match=r"^action: expected real numbers \(got complex(128|64)\) in Box\(-1\.0, 1\.0"):
            env.step(bad)
        with pytest.raises(TypeError, match=r"^u: expected real numbers \(got complex"):
            env.step_physical(bad)
    np.testing.assert_array_equal(env.state, before)
