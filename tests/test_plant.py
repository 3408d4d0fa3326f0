"""The plant interface (issue 41): adapters, checks, saturation, least-squares residuals, failure and resume."""

from __future__ import annotations

import json
import math

import gymnasium as gym
import numpy as np
import pytest
import torch

from mixedrl.algorithms.agpi import AGPI
from mixedrl.algorithms.ddpg import DDPG
from mixedrl.config import TrainConfig
from mixedrl.envs.gym_models import (PendulumV1Task, mountain_car_noise_matrix, mountain_car_step,
                                     pendulum_noise_matrix, pendulum_v1_step)
from mixedrl.ibe import KnownCovarianceIBE
from mixedrl.ibe.common import check_noise_matrix, noise_coordinates, residuals
from mixedrl.plant import (CheckedPlant, DisturbedEnv, GymnasiumPlant, PlantError, SimulatedPlant, attach_plant,
                           evaluate_on_plant)
from mixedrl.runs import RunDirectory, load_checkpoint, train
from mixedrl.schedule import resolve_budget
from mixedrl.task_base import Task, check_task


# ------------------------------------------------------------------------------------------ physics
def _gym_steps(env_id: str, states: np.ndarray, actions: np.ndarray) -> np.ndarray:
    env = gym.make(env_id).unwrapped
    env.reset(seed=0)
    out = []
    for s, a in zip(states, actions):
        env.state = s.copy()
        env.step(a.astype(np.float32))
        out.append(np.asarray(env.state, dtype=np.float64))
    return np.stack(out)


def test_pendulum_v1_step_equals_gymnasium() -> None:
    rng = np.random.default_rng(0)
    s = np.column_stack([rng.uniform(-2 * np.pi, 2 * np.pi, 500), rng.uniform(-9, 9, 500)])
    u = rng.uniform(-3, 3, (500, 1))  # a third beyond the clip at 2
    ours = pendulum_v1_step(torch.as_tensor(s), torch.as_tensor(u)).numpy()
    np.testing.assert_allclose(ours, _gym_steps("Pendulum-v1", s, u), rtol=0, atol=1e-6)


def test_mountain_car_step_equals_gymnasium() -> None:
    rng = np.random.default_rng(1)
    s = np.column_stack([rng.uniform(-1.2, 0.6, 500), rng.uniform(-0.07, 0.07, 500)])
    s[:50, 0], s[:50, 1] = -1.2, -0.05  # at the left wall, moving left
    u = rng.uniform(-1.5, 1.5, (500, 1))
    ours = mountain_car_step(torch.as_tensor(s), torch.as_tensor(u)).numpy()
    np.testing.assert_allclose(ours, _gym_steps("MountainCarContinuous-v0", s, u), rtol=0, atol=1e-6)


@pytest.mark.parametrize("env_id,step,E", [
    ("Pendulum-v1", pendulum_v1_step, pendulum_noise_matrix()),
    ("MountainCarContinuous-v0", mountain_car_step, mountain_car_noise_matrix())])
def test_disturbed_env_is_the_additive_model(env_id: str, step: object, E: torch.Tensor) -> None:
    """x' = f(x, u) + E xi exactly, and the least-squares residual returns the force (E is no selection)."""
    env = DisturbedEnv(gym.make(env_id), mean=0.3)
    plant = GymnasiumPlant(env)
    x = plant.reset(seed=3)
    rng = np.random.default_rng(2)
    for _ in range(20):
        u = rng.uniform(-0.5, 0.5, 1)
        x_next = plant.step(u)
        xi = residuals(lambda a, b: step(torch.as_tensor(a), torch.as_tensor(b)).numpy(), x[None], u[None],
                       x_next[None], E.numpy())
        assert xi.shape == (1, 1)
        assert abs(xi[0, 0] - 0.3) < 1e-4, xi  # float32 states of the car
        x = x_next


def test_double_lane_change_behind_the_adapter() -> None:
    """The package's own env as a plant: its state is the task's, its actions normalised."""
    import mixedrl.envs  # noqa: F401  (registers the env)
    from mixedrl.tasks import task_from_config

    task = task_from_config("dlc")
    bound = task.action_bound.double().numpy()
    plant = GymnasiumPlant(gym.make("mixedrl/DoubleLaneChange-v0"), action_fn=lambda u: u / bound)
    x = torch.as_tensor(plant.reset(seed=0))[None]
    xs = []
    for _ in range(200):
        u = torch.tensor([[0.0, -0.2]], dtype=torch.float64)
        x_next = torch.as_tensor(plant.step(u[0].numpy()))[None]
        xs.append(task.residuals(x, u, x_next))
        x = x_next
    force = task.xi_to_force(float(torch.cat(xs)[:, task.noise_index].mean()))
    assert abs(force - 261.0) < 0.02 * 261.0, force


# ------------------------------------------------------------------------------------------ residuals
def test_residuals_least_squares_for_any_full_column_rank_E() -> None:
    rng = np.random.default_rng(0)
    E = np.array([[0.05, 0.0], [1.0, 0.2], [0.0, 1.0]])
    xi = rng.normal(size=(7, 2))
    x, u = rng.normal(size=(7, 3)), rng.normal(size=(7, 1))
    x_next = x + xi @ E.T
    np.testing.assert_allclose(residuals(lambda a, b: a, x, u, x_next, E), xi, atol=1e-12)
    got = residuals(lambda a, b: a, torch.as_tensor(x), torch.as_tensor(u), torch.as_tensor(x_next), torch.as_tensor(E))
    np.testing.assert_allclose(got.numpy(), xi, atol=1e-12)
    # E^T r would be off by E^T E != I (here by 0.25% on [dt, 1]^T)
    e1 = np.array([[0.05], [1.0]])
    r = np.array([[0.05, 1.0]])
    assert noise_coordinates(r, e1)[0, 0] == pytest.approx(1.0, abs=1e-14)
    assert abs((r @ e1)[0, 0] - 1.0) > 2e-3


def test_selection_E_is_bitwise_the_transpose() -> None:
    """The default tasks' 0/1 selections keep E^T r bit for bit (the shipped results stay identical)."""
    E = torch.zeros(7, 5)
    E[:5, :5] = torch.eye(5)
    r = torch.randn(9, 7, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    assert torch.equal(noise_coordinates(r, E.double()), r @ E.double())


def test_rank_deficient_E_is_named() -> None:
    with pytest.raises(ValueError, match=r"E: expected full column rank 2 .* got rank 1"):
        check_noise_matrix(np.array([[1.0, 2.0], [1.0, 2.0]]), "E")

    class Degenerate(PendulumV1Task):
        def __init__(self) -> None:
            super().__init__()
            self.noise_dim = 2
            self.noise_matrix = torch.tensor([[0.1, 0.2], [1.0, 2.0]], dtype=torch.float64)
            self.prior_mean, self.prior_cov = np.zeros(2), np.eye(2)
            self.true_mean, self.true_cov = np.zeros(2), np.eye(2)

    with pytest.raises(ValueError, match=r"Degenerate.noise_matrix: expected full column rank 2"):
        check_task(Degenerate())


# ------------------------------------------------------------------------------------------ saturation
class BiasedActuator(Task):
    """x' = A x + B clip(u + b) + B w: an actuator bias b entering *before* the clip at |u| = 1."""

    state_dim, obs_dim, action_dim, noise_dim, gamma = 2, 2, 1, 1, 0.9
    dt = 0.05

    def __init__(self) -> None:
        self.noise_matrix = torch.tensor([[self.dt**2], [self.dt]], dtype=torch.float64)  # not a selection
        self.prior_mean, self.prior_cov = np.zeros(1), np.eye(1)
        self.true_mean, self.true_cov = np.array([0.5]), np.array([[0.05**2]])
        self.action_bound = torch.tensor([1.5])
        self.action_limit = torch.tensor([1.0])
        self.saturation_margin = 0.55  # covers the prior's reach of the bias
        self.obs_scale = torch.ones(2)

    def f(self, s: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        v = s[:, 1] + self.dt * torch.clamp(u[:, 0], -1.0, 1.0)
        return torch.stack([s[:, 0] + self.dt * v, v], dim=-1)

    def plant(self, s: torch.Tensor, u: torch.Tensor, gen: torch.Generator) -> torch.Tensor:  # type: ignore[override]
        w = 0.05 * torch.randn(s.shape[0], 1, generator=gen, dtype=torch.float64)
        return self.f(s, torch.clamp(u + 0.5, -1.0, 1.0)) + w @ self.noise_matrix.T

    def observe(self, s: torch.Tensor) -> torch.Tensor:
        return s

    def cost(self, s_next: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return (s_next**2).sum(-1)

    def sample_initial(self, n: int, generator: torch.Generator) -> torch.Tensor:
        return torch.randn(n, 2, generator=generator, dtype=torch.float64)


def _saturation_estimate(seed: int, mask: bool) -> tuple[float, float]:
    task = BiasedActuator()
    if not mask:
        task.action_limit = None
    gen = torch.Generator().manual_seed(seed)
    s = task.sample_initial(2000, gen)
    u = 3.0 * torch.rand(2000, 1, generator=gen, dtype=torch.float64) - 1.5  # |u + 0.5| > 1 on a third
    s_next = task.plant(s, u, gen)
    clipped = float(((u + 0.5).abs() > 1.0).double().mean())
    xi = task.residuals(s, u, s_next)
    xi = xi[torch.isfinite(xi).all(dim=-1)]
    ibe = KnownCovarianceIBE(task.prior_mean, task.prior_cov, task.true_cov).update(xi.numpy())
    return float(ibe.mean[0]), clipped


def test_ibe_within_two_percent_when_a_third_saturates() -> None:
    for seed in range(10):
        est, clipped = _saturation_estimate(seed, mask=True)
        assert 0.30 < clipped < 0.37
        assert abs(est - 0.5) <= 0.02 * 0.5, (seed, est)
    # without the declared limit the clipped transitions pull the estimate far off (the test has power)
    est, _ = _saturation_estimate(0, mask=False)
    assert abs(est - 0.5) > 0.1 * 0.5


def test_pendulum_bias_before_the_clips_is_masked() -> None:
    """Pendulum-v1 with an actuator bias entering before its torque and speed clips: the declared limit
    and margin leave out exactly the transitions where the residual is not the bias."""
    rng = np.random.default_rng(0)
    for margin in (0.0, 0.65):
        task = PendulumV1Task()
        task.saturation_margin = margin
        plant = GymnasiumPlant(DisturbedEnv(gym.make("Pendulum-v1"), mean=0.5, before_clip=True))
        x, xi = torch.as_tensor(plant.reset(seed=0))[None], []
        for i in range(600):
            u = torch.as_tensor(rng.uniform(-2.0, 2.0, (1, 1)))
            x_next = torch.as_tensor(plant.step(u[0].numpy()))[None]
            xi.append(float(task.residuals(x, u, x_next)[0, 0]))
            x = torch.as_tensor(plant.reset(seed=i + 1))[None] if plant.last_truncated else x_next
        xi = np.array(xi)
        kept = xi[np.isfinite(xi)]
        if margin == 0:  # only |u| > 2 dropped: the torque clip of u + 0.5 and the speed clip bias the rest
            assert np.abs(kept - 0.5).max() > 0.1
        else:
            assert 0.2 < 1 - kept.size / xi.size < 0.6
            np.testing.assert_allclose(kept, 0.5, atol=1e-5)


# ------------------------------------------------------------------------------------------ plant checks
class Flaky:
    """A plant that misbehaves at step ``at`` (raises, NaN or a wrong shape)."""

    def __init__(self, inner: object, at: int, how: str) -> None:
        self.inner, self.at, self.how, self.n = inner, at, how, 0

    def __repr__(self) -> str:
        return "Flaky()"

    def reset(self, seed: int | None = None) -> np.ndarray:
        return self.inner.reset(seed)

    def step(self, u: np.ndarray) -> np.ndarray:
        x = self.inner.step(u)
        self.n += 1
        if self.n - 1 == self.at:
            if self.how == "raise":
                raise OSError("link down")
            return np.full_like(x, np.nan) if self.how == "nan" else x[:1]
        return x


@pytest.mark.parametrize("how,problem", [("raise", "raised OSError: link down"),
                                         ("nan", r"returned a non-finite state \[nan, nan\]"),
                                         ("shape", r"returned a state of shape \(1,\), expected \(2,\)")])
def test_plant_failures_name_plant_and_step(how: str, problem: str) -> None:
    plant = CheckedPlant(Flaky(SimulatedPlant(PendulumV1Task()), 3, how), 2)
    plant.reset(0)
    for _ in range(3):
        plant.step(np.zeros(1))
    with pytest.raises(PlantError, match=rf"plant Flaky \(Flaky\(\)\) at step 3 \(step\): {problem}"):
        plant.step(np.zeros(1))


def test_gymnasium_plant_needs_box_spaces() -> None:
    with pytest.raises(ValueError, match="env: action_space must be a gymnasium.spaces.Box, got Discrete"):
        GymnasiumPlant(gym.make("CartPole-v1"))


def _config(**sampler: object) -> TrainConfig:
    # the budget as given (region_budget 1): these tests count the plant's steps per iteration
    return TrainConfig(method="mixed", task="linear", seed=0,
                       algorithm=dict(iterations=12, batch_size=16, hidden_sizes=(8,), region_budget=1),
                       sampler=dict(name="model_rollouts", true_steps=2, true_every=1, **sampler),
                       run=dict(eval_every=6, eval_seeds=2, checkpoint_every=4))


def test_plant_failure_stops_the_run_and_resume_continues(tmp_path) -> None:
    run = RunDirectory(tmp_path / "run")
    env = DisturbedEnv(gym.make("Pendulum-v1"), mean=0.5)
    task = attach_plant(PendulumV1Task(), Flaky(GymnasiumPlant(env), 418, "nan"))
    # plant steps: 2 per iteration, 400 of the evaluation at iteration 6: step 418 is iteration 10's
    with pytest.raises(PlantError, match=r"plant Flaky \(Flaky\(\)\) at step 418 \(step\): returned a non-finite"):
        train(AGPI(task, _config()), run, progress=False)
    assert load_checkpoint(run.checkpoint_path)["trainer"]["k"] == 8  # the last checkpoint is intact
    task = attach_plant(PendulumV1Task(), GymnasiumPlant(env))  # the plant repaired
    results = train(AGPI(task, _config()), run, resume=True, progress=False)
    assert results["iterations"] == 12
    saved = json.loads(run.results_path.read_text())
    # training: 8 iterations in the checkpoint, 4 after it; evaluation: one 200-step episode per seed at
    # iterations 6 (counted in the checkpoint) and 12
    assert saved["plant_transitions"]["training"] == 24
    assert saved["plant_transitions"]["evaluation"] == 2 * 2 * 200
    assert saved["plant_transitions"]["plant"] == "GymnasiumPlant(Pendulum-v1)"
    assert abs(saved["final_ibe_mean"][0] - 0.5) < 0.05


def test_a_run_without_evaluation() -> None:
    task = attach_plant(PendulumV1Task(), GymnasiumPlant(gym.make("Pendulum-v1")), evaluation="none")
    cfg = TrainConfig(method="mixed", task="linear", seed=0,
                      algorithm=dict(iterations=4, batch_size=8, hidden_sizes=(8,)),
                      sampler=dict(name="model_rollouts", true_steps=3, true_every=2), run=dict(eval_every=2))
    results = train(AGPI(task, cfg), progress=False)
    assert results["final"] == {} and not any(k.startswith("eval/") for k in results["metrics"][-1])
    assert results["plant_transitions"]["training"] == 6 and results["plant_transitions"]["evaluation"] == 0


def test_evaluation_on_the_plant_is_sequential_and_counted() -> None:
    env = DisturbedEnv(gym.make("Pendulum-v1"), mean=0.2)
    task = attach_plant(PendulumV1Task(), GymnasiumPlant(env))
    policy = torch.nn.Linear(3, 1)
    a = evaluate_on_plant(task, policy, [0, 1], horizon=30)
    assert task.evaluation_transitions == 60
    assert a == evaluate_on_plant(task, policy, [0, 1], horizon=30)  # fixed episode seeds
    assert a["episode_length"] == 30 and a["terminated_fraction"] == 0.0
    assert math.isfinite(a["plant_return"]) and a["plant_return"] < 0 < a["cost"]
    assert attach_plant(task, task.plant, evaluation="none").evaluate(policy, [0]) == {}
    assert task.evaluation_transitions == 120
    with pytest.raises(ValueError, match="sampler.name: a task with a plant needs a model-rollout sampler"):
        AGPI(task, TrainConfig(method="mixed", task="linear", seed=0, sampler=dict(name="true_copies")))
    with pytest.raises(ValueError, match="config: method 'ddpg' steps batches of simulated true copies"):
        DDPG(task, TrainConfig(method="ddpg", task="linear", seed=0))
    bare = PendulumV1Task()
    bare.plant = GymnasiumPlant(env)
    with pytest.raises(ValueError, match="task.plant: expected the list attach_plant makes, got GymnasiumPlant"):
        AGPI(bare, TrainConfig(method="mixed", task="linear", seed=0, sampler=dict(name="model_rollouts")))


class Recorder:
    """A plant recording the seeds of its resets."""

    def __init__(self, inner: object) -> None:
        self.inner, self.seeds = inner, []

    def reset(self, seed: int | None = None) -> np.ndarray:
        self.seeds.append(seed)
        return self.inner.reset(seed)

    def step(self, u: np.ndarray) -> np.ndarray:
        return self.inner.step(u)


def test_resumed_run_continues_the_plant_episode_seeds(tmp_path) -> None:
    """Interrupted after 6 iterations and resumed to 12, a run resets its plant with the episode seeds of
    the uninterrupted run (the counter is in the sampler's checkpoint)."""
    from mixedrl.plant import episode_seed
    from mixedrl.runs import eval_seeds

    def run(iterations: int, path, resume: bool = False) -> list[int]:
        plant = Recorder(GymnasiumPlant(DisturbedEnv(gym.make("Pendulum-v1"), mean=0.5)))
        cfg = TrainConfig(method="mixed", task="linear", seed=0,
                          algorithm=dict(iterations=iterations, batch_size=8, hidden_sizes=(8,)),
                          sampler=dict(name="model_rollouts", true_steps=2, true_every=1, true_horizon=3),
                          run=dict(eval_every=6, eval_seeds=1, checkpoint_every=3))
        train(AGPI(attach_plant(PendulumV1Task(), plant), cfg), RunDirectory(path), resume=resume, progress=False)
        evaluation = {episode_seed(s, 1, 0) for s in eval_seeds(cfg)}
        return [s for s in plant.seeds if s not in evaluation]

    whole = run(12, tmp_path / "whole")
    first = run(6, tmp_path / "parts")
    state = load_checkpoint(RunDirectory(tmp_path / "parts").checkpoint_path)["trainer"]["sampler"]
    assert state["plant_episodes"] == len(first)
    second = run(12, tmp_path / "parts", resume=True)
    assert len(whole) > len(first) > 2 and second
    assert first + second == whole
    # a checkpoint without the key (older, or of a run without a plant) still loads: the seeds restart at 0
    from mixedrl.samplers import ModelStateSampler

    cfg = TrainConfig(method="mixed", task="linear", seed=0, algorithm=dict(batch_size=8),
                      sampler=dict(name="model_rollouts"))
    task = attach_plant(PendulumV1Task(), SimulatedPlant(PendulumV1Task()))
    sampler = ModelStateSampler(task, cfg, torch.Generator().manual_seed(0))
    old = {k: v for k, v in state.items() if k != "plant_episodes"}
    old.update(states=sampler.states, steps=sampler.steps)
    sampler.load_state_dict(old)
    assert sampler.plant.episodes == 0 and "plant_episodes" not in sampler.state_dict()
    with pytest.raises(ValueError, match="state: sampler plant_episodes is -1, expected an integer >= 0"):
        sampler.load_state_dict({**old, "plant_episodes": -1})


def test_pendulum_v1_reports_the_wrapped_angle_error() -> None:
    """Upright after a full turn (theta = 2 pi): the default evaluation reports the task's error measure,
    the wrapped angle (about 0), not the unwrapped state (about 6.28)."""
    class FullTurn(PendulumV1Task):
        def sample_initial(self, n: int, generator: torch.Generator) -> torch.Tensor:
            return torch.tensor([[2 * math.pi + 1e-6, 0.0]], dtype=torch.float64).expand(n, 2).clone()

    task = FullTurn(torque_std=0.0)
    s = torch.tensor([[2 * math.pi + 0.1, 0.5], [-math.pi - 0.1, -1.0]], dtype=torch.float64)
    np.testing.assert_allclose(task.state_error(s).numpy(), [[0.1, 0.5], [math.pi - 0.1, -1.0]], atol=1e-12)
    zero = torch.nn.Linear(3, 1)
    torch.nn.init.zeros_(zero.weight)
    torch.nn.init.zeros_(zero.bias)
    ev = task.evaluate(zero, [0], horizon=20)
    assert abs(ev["mean_state_0"]) < 0.01 and ev["mean_abs_state_0"] < 0.01, ev
    # the default measure is the state itself
    s = torch.randn(4, 2, dtype=torch.float64)
    assert Task.state_error(task, s) is s


# ------------------------------------------------------------------------------------------ tasks with their own evaluate
def test_builtin_evaluations_count_their_transitions() -> None:
    """The linear task's rollouts and the double lane change's simulated courses are evaluation transitions
    of the simulated plant (results.json reported them as null)."""
    from mixedrl.tasks import task_from_config

    linear = task_from_config("linear")
    policy = torch.nn.Linear(2, 1)
    linear.evaluate(policy, [0, 1])
    assert linear.evaluation_transitions == 2 * 64 * 100
    dlc = task_from_config("dlc")
    actor = torch.nn.Linear(dlc.obs_dim, 2)
    runs = dlc.evaluate(actor, [0, 1], keep_trajectory=True)["trajectories"]
    steps = sum(r.n_steps for r in runs)
    assert steps > 0 and dlc.evaluation_transitions == steps
    dlc.evaluate_many([actor, actor], [[0, 1], [0, 1]])
    assert dlc.evaluation_transitions == 3 * steps
    cfg = TrainConfig(method="mixed", task="linear", seed=0,
                      algorithm=dict(iterations=2, batch_size=8, hidden_sizes=(8,)),
                      run=dict(eval_every=2, eval_seeds=2))
    results = train(AGPI(task_from_config("linear"), cfg), progress=False)
    assert results["plant_transitions"]["evaluation"] == 2 * 64 * 100
    # a batch evaluates with its first run's task: each run is credited with its own evaluations
    from mixedrl.runs import train_batch

    batch = train_batch([AGPI(task_from_config("dlc"), TrainConfig(
        method="mixed", task="dlc", seed=s, algorithm=dict(iterations=2, batch_size=8, hidden_sizes=(8,)),
        run=dict(eval_every=2, eval_seeds=2))) for s in (0, 1)], progress=False)
    counts = [r["plant_transitions"]["evaluation"] for r in batch]
    assert all(c > 0 for c in counts), counts


def test_tasks_with_their_own_evaluate_on_a_plant() -> None:
    """The double lane change and the linear task evaluate on an attached plant (and count it); a task whose
    own evaluate cannot is refused at attach_plant."""
    import mixedrl.envs  # noqa: F401  (registers the env)
    from mixedrl.linear_task import LinearTask
    from mixedrl.tasks import task_from_config

    dlc = task_from_config("dlc")
    bound = dlc.action_bound.double().numpy()
    attach_plant(dlc, GymnasiumPlant(gym.make("mixedrl/DoubleLaneChange-v0"), action_fn=lambda u: u / bound))
    actor = torch.nn.Linear(dlc.obs_dim, 2)
    torch.nn.init.zeros_(actor.weight)
    torch.nn.init.zeros_(actor.bias)
    ev = dlc.evaluate(actor, [0])
    assert set(ev) == {"cost", "plant_return", "plant_terminated_fraction", "terminated_fraction",
                       "episode_length"}
    assert dlc.evaluation_transitions == ev["episode_length"] > 0
    assert dlc.evaluate_many([actor], [[0]]) == [ev]
    linear = attach_plant(LinearTask(), SimulatedPlant(LinearTask()))
    ev = linear.evaluate(torch.nn.Linear(2, 1), [0, 1])  # 100 steps or until the state leaves the domain
    assert "plant_return" in ev and 0 < ev["episode_length"] <= 100
    assert linear.evaluation_transitions == 2 * ev["episode_length"]

    class OwnEvaluation(PendulumV1Task):
        def evaluate(self, policy: torch.nn.Module, seeds: list[int], horizon: int | None = None) -> dict:
            return {"cost": 0.0}

    with pytest.raises(ValueError, match=r"evaluation: OwnEvaluation.evaluate is the task's own and cannot "
                                         r"evaluate on a plant"):
        attach_plant(OwnEvaluation(), SimulatedPlant(PendulumV1Task()))
    task = attach_plant(OwnEvaluation(), SimulatedPlant(PendulumV1Task()), evaluation="simulated")
    assert not task.counts_evaluation_transitions and PendulumV1Task.counts_evaluation_transitions


def test_gymnasium_plant_documented_for_its_three_envs() -> None:
    """The GymnasiumPlant docstring's example (Pendulum-v1, MountainCarContinuous-v0, the double lane
    change) runs, and the tutorial's plant section shows all three."""
    import inspect
    import textwrap
    from pathlib import Path

    doc = inspect.getdoc(GymnasiumPlant)
    code = textwrap.dedent(doc.split(".. code-block:: python", 1)[1])
    namespace = {"gym": gym, "attach_plant": attach_plant, "GymnasiumPlant": GymnasiumPlant}
    exec(compile(code, "GymnasiumPlant.__doc__", "exec"), namespace)  # noqa: S102 - the docstring's example
    for name in ("pendulum", "car", "dlc"):
        assert repr(namespace[name].plant[0].plant).startswith("GymnasiumPlant(")
    x = namespace["dlc"].plant[0].reset(0)
    assert x.shape == (namespace["dlc"].state_dim,)
    tutorial = Path(__file__).resolve().parents[1] / "docs" / "tutorial.rst"
    section = tutorial.read_text().split("4. Your real system as a plant", 1)[1].split("\nAPI of", 1)[0]
    for env_id in ('gym.make("Pendulum-v1")', 'gym.make("MountainCarContinuous-v0")',
                   'gym.make("mixedrl/DoubleLaneChange-v0")'):
        assert env_id in section and env_id in doc, env_id


def test_pendulum_v1_declares_the_envs_state_region() -> None:
    """The region starts of the default learner (``algorithm.rollout_region``) cover Pendulum-v1's speed range
    (``max_speed`` 8, read from the env), not only its resets (``|theta_dot| <= 1``)."""
    task = PendulumV1Task()
    assert task.declares_region()
    gen = torch.Generator().manual_seed(0)
    s = task.sample_region(4096, gen)
    max_speed = gym.make("Pendulum-v1").unwrapped.max_speed
    assert s.shape == (4096, 2) and s.dtype == torch.float64
    assert s[:, 0].abs().max() <= math.pi and s[:, 1].abs().max() <= max_speed
    assert s[:, 1].abs().max() > 0.9 * max_speed and s[:, 0].abs().max() > 0.9 * math.pi
    assert task.sample_initial(4096, gen)[:, 1].abs().max() <= 1.0


def _budget_config(**algorithm: object) -> TrainConfig:
    return TrainConfig(method="mixed", task="linear", seed=3,
                       algorithm=dict(iterations=5, batch_size=16, hidden_sizes=(8,), rollout_horizon=4, **algorithm),
                       sampler=dict(name="model_rollouts", true_steps=2, true_every=2),
                       run=dict(eval_every=2, eval_seeds=1, checkpoint_every=1000))


def test_a_global_task_trains_region_budget_times_longer_at_the_same_true_transitions(tmp_path) -> None:
    """``algorithm.region_budget``: on a task that declares a region, 4 x 5 iterations with the true drive every
    4 x 2 iterations; the run is the one configured so by hand, parameter for parameter; its config.json holds
    the resolved budget, its results.json the factor, and a resume from it trains the same budget."""
    auto = AGPI(PendulumV1Task(), _budget_config())
    assert auto.region_budget == 4
    assert (auto.config.algorithm.iterations, auto.config.sampler.true_every, auto.config.run.eval_every) == (20, 8, 8)
    assert auto.config.algorithm.region_budget == 1 and auto.config.run.checkpoint_every == 1000
    by_hand = AGPI(PendulumV1Task(), _budget_config(region_budget=1).replace(
        **{"algorithm.iterations": 20, "sampler.true_every": 8, "run.eval_every": 8}))
    assert by_hand.region_budget == 1
    run = RunDirectory(tmp_path / "auto")
    out = train(auto, run, progress=False)
    out_hand = train(by_hand, progress=False)
    assert out["iterations"] == 20 and out["region_budget"] == 4 and "region_budget" not in out_hand
    # the evaluations at k = 8, 16 and the final one, 20: as at 5 iterations every 2 (k = 2, 4, 5)
    assert [r["iteration"] for r in run.read_metrics() if "eval/cost" in r] == [8, 16, 20]
    assert out["true_transitions"] == out_hand["true_transitions"]
    # the true drive ran at k = 0, 8, 16: 3 collections of 2 steps, as at 5 iterations every 2 (k = 0, 2, 4)
    assert auto.sampler.true_transitions == by_hand.sampler.true_transitions == 6
    for a, b in zip(auto.actor.parameters(), by_hand.actor.parameters()):
        assert torch.equal(a, b)
    saved = json.loads(run.config_path.read_text())
    assert saved["algorithm"]["iterations"] == 20 and saved["algorithm"]["region_budget"] == 1
    assert saved["sampler"]["true_every"] == 8
    assert resolve_budget(auto.config, PendulumV1Task()) == (auto.config, 1)  # resolved once
    # a resume with the config as given resolves to the saved one (no conflict) and has nothing left to train
    resumed = AGPI(PendulumV1Task(), _budget_config())
    assert train(resumed, run, resume=True, progress=False)["iterations"] == 20 and resumed.k == 20


def test_region_budget_leaves_tasks_without_a_region_ddpg_and_the_paper_preset_alone() -> None:
    from mixedrl.tasks import task_from_config

    linear = task_from_config(_budget_config().task)
    assert not linear.declares_region()
    plain = AGPI(linear, _budget_config())
    assert plain.region_budget == 1 and plain.config == _budget_config()
    paper = TrainConfig.preset("paper").replace(method="mixed", seed=0)
    assert paper.algorithm.region_budget == 1
    assert AGPI(PendulumV1Task(), paper).config.algorithm.iterations == paper.algorithm.iterations
    ddpg = _budget_config().replace(method="ddpg")
    assert DDPG(PendulumV1Task(), ddpg).config.algorithm.iterations == 5
    with pytest.raises(ValueError, match=r"algorithm.region_budget"):
        _budget_config(region_budget=0)


def test_a_resumed_global_run_is_the_uninterrupted_one(tmp_path) -> None:
    """On a task that declares a region, the region starts carry end states from one iteration to the next
    (:mod:`mixedrl.departures.region`): they are in the checkpoint, so a run killed at iteration 8 and resumed
    ends where the uninterrupted run ends, bit for bit."""
    config = _budget_config(region_budget=1).replace(**{"algorithm.iterations": 12, "run.checkpoint_every": 4})
    whole = AGPI(PendulumV1Task(), config)
    out = train(whole, progress=False)
    run = RunDirectory(tmp_path / "cut")
    cut = AGPI(PendulumV1Task(), config)
    train(cut, run, stop_after=8, progress=False)
    assert cut.region_carry is not None and "region_carry" in load_checkpoint(run.checkpoint_path)["trainer"]
    resumed = AGPI(PendulumV1Task(), config)
    assert train(resumed, run, resume=True, progress=False)["final"] == out["final"]
    for a, b in zip(whole.actor.parameters(), resumed.actor.parameters()):
        assert torch.equal(a, b)
