"""Tests of the tasks (mixedrl.tasks): DoubleLaneChangeTask and LinearTask built from the run's task
configuration -- shapes, the true step ``f + E xi`` with the configured law (statistically), prior and
true moments, gamma and cost weights, the noise matrix, bad configuration values."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from mixedrl.config import TrainConfig, task_config
from mixedrl.tasks import DoubleLaneChangeTask, LinearTask, make_task, task_from_config

T, M = 1.0 / 200.0, 1500.0  # the paper's sampling time [s] and mass [kg]: xi = F_dis T / m


def _states(task: DoubleLaneChangeTask | LinearTask, n: int, seed: int = 0) -> torch.Tensor:
    return task.sample_initial(n, torch.Generator().manual_seed(seed))


def _actions(task: DoubleLaneChangeTask | LinearTask, n: int, seed: int = 1) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return (2 * torch.rand(n, task.action_dim, generator=gen, dtype=torch.float64) - 1) * 0.5 * task.action_bound.double()


# ------------------------------------------------------------------------------ the double lane change
def test_dlc_shapes_and_noise_matrix_selects_vx() -> None:
    task = task_from_config("dlc")
    s, u = _states(task, 7), _actions(task, 7)
    assert (task.state_dim, task.obs_dim, task.action_dim, task.noise_dim) == (6, 5, 2, 5)
    assert s.shape == (7, 6) and s.dtype == torch.float64
    assert task.f(s, u).shape == (7, 6) and task.observe(s).shape == (7, 5) and task.cost(s, u).shape == (7,)
    assert task.true_step(s, u, torch.Generator().manual_seed(0)).shape == (7, 6)
    E = task.noise_matrix
    assert E.shape == (6, 5) and torch.equal(E[:5], torch.eye(5)) and not E[5].any()
    assert task.noise_index == 2  # v_x in s = [v_y, r, v_x, phi, Y, X]
    e_vx = torch.zeros(5, dtype=torch.float64)
    e_vx[task.noise_index] = 1.0
    assert torch.equal(E.double() @ e_vx, torch.tensor([0, 0, 1.0, 0, 0, 0], dtype=torch.float64))


def test_dlc_prior_and_true_moments_follow_the_config() -> None:
    cfg = task_config({"prior_force_mean": 300.0, "prior_force_std": 10.0,
                       "disturbance": {"mean": 100.0, "variance": 50.0}})
    task = task_from_config(cfg)
    vx, k = task.noise_index, T / M
    assert task.force_scale == pytest.approx(k, rel=1e-15)
    assert task.prior_mean[vx] == pytest.approx(300.0 * k, rel=1e-12)
    assert task.prior_cov[vx, vx] == pytest.approx((10.0 * k) ** 2, rel=1e-12)
    assert task.true_mean[vx] == pytest.approx(100.0 * k, rel=1e-12)
    assert task.true_cov[vx, vx] == pytest.approx(50.0 * k * k, rel=1e-12)
    others = [i for i in range(5) if i != vx]
    assert np.all(task.prior_mean[others] == 0) and np.all(task.true_mean[others] == 0)
    assert np.all(np.diag(task.prior_cov)[others] == 1e-20) and np.all(np.diag(task.true_cov)[others] == 0)
    assert task.xi_to_force(task.force_to_xi(261.0)) == pytest.approx(261.0, rel=1e-14)
    # the defaults are the paper's (eq. 55 and N(261, 32)) and equal the constructor's
    default, direct = task_from_config(TrainConfig().task), DoubleLaneChangeTask()
    assert default.prior_mean[vx] == pytest.approx(150.0 * k) and default.true_mean[vx] == pytest.approx(261.0 * k)
    for name in ("prior_mean", "prior_cov", "true_mean", "true_cov"):
        assert np.array_equal(getattr(default, name), getattr(direct, name))
    assert default.gamma == direct.gamma == 0.99


def test_dlc_true_step_is_f_plus_E_xi_with_the_configured_law() -> None:
    """Residuals ``E^T (s' - f(s, u))`` of 20000 true steps recover the configured N(mean, variance) of
    ``F_dis T / m`` on v_x, and are exactly 0 on the other components."""
    mean_f, var_f, n = 400.0, 900.0, 20_000
    task = task_from_config({"disturbance": {"mean": mean_f, "variance": var_f}})
    s, u = _states(task, n), _actions(task, n)
    s_next = task.true_step(s, u, torch.Generator().manual_seed(3))
    xi = task.residuals(s, u, s_next).numpy()
    force = task.xi_to_force(xi[:, task.noise_index])
    se = math.sqrt(var_f / n)
    assert abs(force.mean() - mean_f) < 5 * se  # 5 standard errors (0.21 N)
    assert abs(force.var(ddof=1) / var_f - 1.0) < 5 * math.sqrt(2.0 / n)  # 5 standard errors (5%)
    others = [i for i in range(5) if i != task.noise_index]
    assert np.abs(xi[:, others]).max() < 1e-12
    assert torch.equal(s_next[:, 5] - task.f(s, u)[:, 5], torch.zeros(n, dtype=torch.float64))


def test_dlc_gamma_cost_weights_preview_and_widths_reach_the_task() -> None:
    task = task_from_config({"gamma": 0.95, "cost": {"q_speed": 2.0, "q_lateral": 0.0, "r_steer": 0.0,
                                                     "r_accel": 3.0},
                             "preview_distances": [5.0, 10.0], "train_half_widths": [0, 0, 0.5, 0, 0]})
    assert task.gamma == 0.95 and task.obs_dim == 7
    s, u = _states(task, 16), _actions(task, 16)
    assert task.observe(s).shape == (16, 7)
    # eq. 54 with these weights: T (2 (v_x - 12)^2 + 3 a_x^2), whatever the lateral error and steering
    expected = T * (2.0 * (s[:, 2] - 12.0) ** 2 + 3.0 * u[:, 1] ** 2)
    torch.testing.assert_close(task.cost(s, u), expected, rtol=1e-12, atol=0)
    dev = task.model.paper_state(s)
    assert dev[:, [0, 1, 3, 4]].abs().max() < 1e-9 and (s[:, 2] - 12.0).abs().max() <= 0.5
    assert (s[:, 2] - 12.0).abs().max() > 0.4  # the configured half-width, not the default 1.0
    lateral = task_from_config({"cost": {"q_speed": 0.0, "q_lateral": 1.0, "r_steer": 0.0, "r_accel": 0.0}})
    y_err = s[:, 4] - torch.as_tensor(lateral.model.reference.lateral(s[:, 5]))
    torch.testing.assert_close(lateral.cost(s, u), T * y_err**2, rtol=1e-12, atol=1e-18)


def test_dlc_bad_values_name_the_field() -> None:
    with pytest.raises(ValueError, match="^task.gamma"):
        task_from_config({"gamma": 1.5})
    with pytest.raises(ValueError, match="^gamma"):
        DoubleLaneChangeTask(gamma=0.0)
    with pytest.raises(ValueError, match="^prior_force_std"):
        DoubleLaneChangeTask(prior_force_std=-4.0)
    cfg = task_config("dlc")
    # the task configuration is the environment's (one frozen schema): it cannot go invalid after validation
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.disturbance.law = "cauchy"  # type: ignore[misc]
    with pytest.raises(ValueError, match=r"^disturbance\.law: expected one of .*'gaussian', 'student_t', 'bumps'"):
        DoubleLaneChangeTask(disturbance={"law": "cauchy"})
    assert task_from_config(cfg).model.config == cfg  # the environment runs on the task configuration itself
    with pytest.raises(ValueError, match="^config: expected a DoubleLaneChangeTaskConfig"):
        DoubleLaneChangeTask.from_config(cfg.disturbance)  # type: ignore[arg-type]


# ------------------------------------------------------------------------------ the linear task
def test_linear_from_config_shapes_moments_gamma_and_cost() -> None:
    cfg = {"name": "linear", "gamma": 0.8, "A": [[1, 0.2, 0], [0, 1, 0.2], [0, 0, 0.9]], "B": [[0], [0], [1]],
           "Q": np.diag([1.0, 2.0, 3.0]).tolist(), "R": [[0.5]], "prior_mean": [0, 0, 1],
           "prior_cov": np.diag([0.1, 0.2, 0.3]).tolist(),
           "disturbance": {"mean": [0.1, -0.2, 0.3], "cov": np.diag([0.01, 0.02, 0.03]).tolist()},
           "init_box": 2.0, "action_bound": 5.0}
    task = task_from_config(cfg)
    assert isinstance(task, LinearTask)
    assert (task.state_dim, task.obs_dim, task.action_dim, task.noise_dim, task.gamma) == (3, 3, 1, 3, 0.8)
    np.testing.assert_array_equal(task.prior_mean, [0, 0, 1])
    np.testing.assert_array_equal(task.true_mean, [0.1, -0.2, 0.3])
    np.testing.assert_array_equal(np.diag(task.true_cov), [0.01, 0.02, 0.03])
    np.testing.assert_array_equal(np.diag(task.prior_cov), [0.1, 0.2, 0.3])
    assert torch.equal(task.noise_matrix, torch.eye(3)) and float(task.action_bound[0]) == 5.0
    s, u = _states(task, 9), _actions(task, 9)
    assert s.abs().max() <= 2.0 and s.abs().max() > 1.0
    torch.testing.assert_close(task.f(s, u), s @ torch.tensor(cfg["A"], dtype=torch.float64).T + u * torch.tensor(
        [0.0, 0.0, 1.0], dtype=torch.float64))
    expected = (s**2 * torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)).sum(1) + 0.5 * u[:, 0] ** 2
    torch.testing.assert_close(task.cost(s, u), expected)
    # the default config is the constructor's default system
    default, direct = task_from_config("linear"), make_task("linear")
    for name in ("A", "B", "Q", "R", "prior_mean", "prior_cov", "true_mean", "true_cov"):
        assert np.array_equal(getattr(default, name), getattr(direct, name)), name
    assert default.gamma == direct.gamma == 0.9


def test_linear_true_step_recovers_the_configured_law() -> None:
    mean, cov, n = np.array([0.3, -0.5]), np.array([[0.04, 0.01], [0.01, 0.09]]), 20_000
    task = task_from_config({"name": "linear", "disturbance": {"mean": mean.tolist(), "cov": cov.tolist()}})
    s, u = _states(task, n), _actions(task, n)
    xi = task.residuals(s, u, task.true_step(s, u, torch.Generator().manual_seed(4))).numpy()
    se = np.sqrt(np.diag(cov) / n)
    assert np.all(np.abs(xi.mean(0) - mean) < 5 * se)
    np.testing.assert_allclose(np.cov(xi.T), cov, atol=5 * np.sqrt(2.0 / n) * 0.09)


def test_linear_bad_values_name_the_field() -> None:
    with pytest.raises(ValueError, match="^task.prior_cov"):
        task_from_config({"name": "linear", "prior_cov": [[1, 2], [2, 1]]})
    with pytest.raises(ValueError, match=r"^config: unknown key\(s\) \['task.prior_force_mean'\]"):
        task_from_config({"name": "linear", "prior_force_mean": 150})
    with pytest.raises(ValueError, match="^task.B"):
        task_from_config({"name": "linear", "B": [[1, 2, 3]]})
    with pytest.raises(ValueError, match="^task.A: .*not stabilisable"):  # the LQ problem's own check
        task_from_config({"name": "linear", "A": [[2.0, 0.0], [0.0, 1.0]], "B": [[0.0], [1.0]]})
    with pytest.raises(ValueError, match="^true_mean"):  # LinearTask's own argument names
        LinearTask(true_mean=[0.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="^problem: given together"):
        LinearTask(A=np.eye(2), problem=LinearTask().problem)


# ------------------------------------------------------------------------------ one schema per task
def test_a_field_of_the_environment_is_a_task_key_and_reaches_the_model() -> None:
    """The task configuration is the environment's: a field defined once (here the vehicle's mass, the
    desired speed, a reference offset) is set by a dotted key and acts on the model and the noise scale."""
    from mixedrl.config import apply_overrides
    from mixedrl.envs import DoubleLaneChangeEnv

    data = apply_overrides(TrainConfig().to_dict(), {"task.params.m": 1600.0, "task.v_des": 10.0,
                                                     "task.reference.dy1": 3.0})
    cfg = TrainConfig.from_dict(data)
    task = task_from_config(cfg.task)
    assert task.model.config is cfg.task and task.force_scale == pytest.approx(T / 1600.0, rel=1e-15)
    assert task.prior_mean[task.noise_index] == pytest.approx(150.0 * T / 1600.0, rel=1e-15)
    s = torch.zeros(1, 6, dtype=torch.float64)
    s[0, 2] = 10.0  # at the desired speed: no speed error in the observation
    assert float(task.observe(s)[0, 2]) == 0.0
    assert task.model.reference.dy1 == 3.0
    env = DoubleLaneChangeEnv(config=cfg.task)  # the Gymnasium env takes the task configuration as it is
    assert env.config is cfg.task
    with pytest.raises(ValueError, match=r"^config: unknown key\(s\) \['task.params.mass'\]"):
        TrainConfig(task={"params": {"mass": 1.0}})
    with pytest.raises(ValueError, match=r"^task\.params\.m: expected a positive number"):
        TrainConfig(task={"params": {"m": -1.0}})


def test_the_course_sampler_and_the_preset_are_registered_by_the_task() -> None:
    import mixedrl.config as config
    import mixedrl.tasks as tasks

    assert config.CourseSampler is tasks.CourseSampler is config.SAMPLERS["dlc_course"]
    assert config.DLC_EXPERIMENT == tasks.DLC_EXPERIMENT == config.PRESETS["dlc"]
    assert isinstance(TrainConfig(task="dlc").sampler, tasks.CourseSampler)
    with pytest.raises(AttributeError, match="no attribute 'CourseSamplr'"):
        config.CourseSamplr  # noqa: B018


def test_the_built_in_tasks_live_in_their_modules_and_stay_importable_from_tasks() -> None:
    """LinearTask (mixedrl.linear_task) and the double lane change's task, sampler and preset
    (mixedrl.envs.dlc_task) are the same objects through mixedrl.tasks, which builds them by name."""
    import mixedrl.tasks as tasks
    from mixedrl.envs import dlc_task
    from mixedrl import linear_task

    assert tasks.LinearTask is linear_task.LinearTask is LinearTask
    for name in ("DoubleLaneChangeTask", "CourseSampler", "DLC_EXPERIMENT"):
        assert getattr(tasks, name) is getattr(dlc_task, name), name
        assert name in dir(tasks) and name in tasks.__all__
    assert type(make_task("linear")) is linear_task.LinearTask
    assert type(make_task("dlc")) is dlc_task.DoubleLaneChangeTask
    with pytest.raises(AttributeError, match="no attribute 'LinearTsk'"):
        tasks.LinearTsk  # noqa: B018
    with pytest.raises(ValueError, match=r"^name: expected one of \('dlc', 'linear'"):
        make_task("lineer")


def test_the_lq_problem_has_one_representation() -> None:
    """LinearTask, LinearTaskConfig and validation.lq share mixedrl.lq.LQProblem; the optimum of the
    task's problem is the one the validation computes."""
    from mixedrl.config import LinearTaskConfig
    from mixedrl.lq import LQProblem, optimal_solution
    from validation import lq

    assert lq.LQProblem is LQProblem and lq.optimal_solution is optimal_solution
    cfg = LinearTaskConfig(prior_mean=(0.0, -1.0))
    task = task_from_config(cfg)
    prob = cfg.problem()
    assert isinstance(task.problem, LQProblem)
    for name in ("A", "B", "Q", "R", "noise_mean", "noise_cov", "prior_mean", "prior_cov"):
        assert np.array_equal(getattr(task.problem, name), getattr(prob, name)), name
    assert task.true_mean is task.problem.noise_mean and task.prior_mean[1] == -1.0
    default = LinearTask()
    for name in ("A", "B", "Q", "R", "true_mean", "true_cov", "prior_mean", "prior_cov"):
        assert np.array_equal(getattr(default, name), getattr(LinearTask.from_config(LinearTaskConfig()), name))
    # the optimum of the shared problem solves the Bellman equation of the task's own f and cost:
    # V*(x) = E[l(f(x, u*) + xi, u*) + gamma V*(f(x, u*) + xi)], xi ~ N(mu, K), exactly (quadratic forms)
    opt = optimal_solution(task.problem)
    x = np.random.default_rng(0).uniform(-1.0, 1.0, size=(8, 2))
    u = opt.policy(x)
    center = task.f(torch.as_tensor(x), torch.as_tensor(u)).numpy() + prob.noise_mean
    mu0 = torch.zeros(8, 2, dtype=torch.float64)
    stage = task.cost(torch.as_tensor(center), torch.as_tensor(u)).numpy() + np.sum(prob.Q * prob.noise_cov)
    rhs = stage + task.gamma * opt.value.expected(center, mu0[0].numpy(), prob.noise_cov)
    np.testing.assert_allclose(opt.value(x), rhs, rtol=1e-10, atol=1e-10)
