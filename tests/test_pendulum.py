"""The second worked example: the inverted pendulum with an unmodelled torque bias (mixedrl.envs.pendulum).

The Task contract (shapes, ``f`` shared by the true step and the model, the bias only in the true
noise), the linearisation against autograd, the LQR-with-feed-forward yardstick on the linearisation
(``control.dare`` through :func:`validation.lq.optimal_solution`) and on the true nonlinear system, and a
short seeded mixed-RL run whose IBE estimate moves from the prior to the true bias.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from mixedrl.algorithms.agpi import AGPI
from mixedrl.config import TrainConfig, apply_overrides
from mixedrl.envs.pendulum import PendulumTask
from mixedrl.runs import train
from mixedrl.tasks import check_task
from validation.lq import LQProblem, optimal_solution


def lqr_reference(task: PendulumTask, noise_mean: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Discounted LQ optimum on the linearisation for ``noise_mean`` (noise coordinates): gain ``L``,
    feed-forward ``l0`` (``u = -L s - l0``) and the steady state it holds under the *true* mean."""
    lin = task.linearisation()
    A, B, E = lin["A"], lin["B"], lin["E"]
    problem = LQProblem(A=A, B=B, Q=lin["Q"], R=lin["R"], gamma=task.gamma, noise_mean=E @ task.true_mean,
                        noise_cov=E @ task.true_cov @ E.T, prior_mean=E @ task.prior_mean,
                        prior_cov=E @ task.prior_cov @ E.T)
    sol = optimal_solution(problem, noise_mean=E @ np.asarray(noise_mean))
    # s* = (A - B L) s* + E mu_true - B l0
    steady = np.linalg.solve(np.eye(2) - (A - B @ sol.gain), E @ task.true_mean - B @ sol.offset)
    return sol.gain, sol.offset, steady


class AffinePolicy(torch.nn.Module):
    def __init__(self, gain: np.ndarray, offset: np.ndarray, bound: float) -> None:
        super().__init__()
        self.gain, self.offset, self.bound = torch.tensor(gain), torch.tensor(offset), bound

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return (-(obs.double() @ self.gain.T) - self.offset).clamp(-self.bound, self.bound).float()


def test_task_contract_shapes_and_names() -> None:
    task = PendulumTask()
    check_task(task)
    assert task.name == "pendulum" and (task.state_dim, task.obs_dim, task.action_dim, task.noise_dim) == (2, 2, 1, 1)
    assert task.noise_matrix.tolist() == [[0.0], [1.0]]
    assert task.action_bound.tolist() == [4.0] and task.obs_scale.tolist() == pytest.approx([0.3, 0.3])
    # the bias is in the true noise only: prior mean 0, true mean dt tau / (m l^2) = 0.05 * 0.5
    assert task.prior_mean.tolist() == [0.0] and task.true_mean == pytest.approx([0.025], rel=1e-15)
    assert task.true_cov == pytest.approx(task.prior_cov) and task.true_cov[0, 0] == pytest.approx(0.01**2)
    assert task.torque_from_xi(task.true_mean[0]) == pytest.approx(0.5, rel=1e-12)
    for bad in (dict(dt=0.0), dict(torque_bound=-1.0), dict(mass=math.nan), dict(gamma=1.0), dict(torque_bias="x")):
        with pytest.raises(ValueError, match=f"^{next(iter(bad))}"):
            PendulumTask(**bad)


def test_f_is_the_euler_step_and_the_true_step_adds_the_noise_on_the_rate() -> None:
    task = PendulumTask()
    gen = torch.Generator().manual_seed(0)
    s = task.sample_initial(20_000, gen)
    u = (2 * torch.rand(20_000, 1, generator=gen, dtype=torch.float64) - 1) * 4.0
    th, om, uu = s[:, 0].numpy(), s[:, 1].numpy(), u[:, 0].numpy()
    expected = np.stack([th + 0.05 * om, om + 0.05 * (9.81 * np.sin(th) - 0.1 * om + uu)], axis=1)
    np.testing.assert_allclose(task.f(s, u).numpy(), expected, rtol=0, atol=1e-14)
    xi = task.true_step(s, u, gen) - task.f(s, u)          # the true environment is f plus E xi
    assert torch.equal(xi[:, 0], torch.zeros(20_000, dtype=torch.float64))
    n, sd = xi.shape[0], 0.01
    assert abs(float(xi[:, 1].mean()) - 0.025) < 4 * sd / math.sqrt(n)
    assert abs(float(xi[:, 1].var()) - sd**2) < 4 * sd**2 * math.sqrt(2 / (n - 1))
    np.testing.assert_allclose(task.residuals(s, u, task.true_step(s, u, torch.Generator().manual_seed(1)))[:, 0],
                               0.025 + 0.01 * torch.randn(n, generator=torch.Generator().manual_seed(1),
                                                          dtype=torch.float64).numpy(), atol=0.06)


def test_linearisation_is_the_jacobian_of_f_at_the_origin() -> None:
    task = PendulumTask()
    lin = task.linearisation()
    A, B = torch.autograd.functional.jacobian(lambda s, u: task.f(s[None], u[None])[0],
                                              (torch.zeros(2, dtype=torch.float64), torch.zeros(1, dtype=torch.float64)))
    np.testing.assert_allclose(lin["A"], A.numpy(), rtol=0, atol=1e-15)
    np.testing.assert_allclose(lin["B"], B.numpy(), rtol=0, atol=1e-15)
    s = torch.tensor([[0.2, -0.1]], dtype=torch.float64, requires_grad=False)
    u = torch.tensor([[0.3]], dtype=torch.float64)
    l_quadratic = s @ torch.tensor(lin["Q"]) @ s.T + u @ torch.tensor(lin["R"]) @ u.T
    assert float(task.cost(s, u)) == pytest.approx(float(l_quadratic), rel=1e-14)


def test_lqr_feed_forward_yardstick() -> None:
    """The steady offset the discounted LQ optimum holds (the yardstick of issue 21) with the true mean's
    feed-forward, against the prior's: the prior's optimum leaves the bias uncompensated."""
    task = PendulumTask()
    L, l0, steady_true = lqr_reference(task, task.true_mean)
    L_prior, l0_prior, steady_prior = lqr_reference(task, task.prior_mean)
    np.testing.assert_allclose(L, L_prior)        # the mean changes only the feed-forward
    assert l0_prior.tolist() == [0.0] and steady_true[1] == pytest.approx(0.0, abs=1e-15)
    # the optimum leans slightly into gravity to save torque (r u^2): a small offset of the opposite sign
    assert steady_true[0] == pytest.approx(-0.0240, abs=1e-4) and steady_prior[0] == pytest.approx(0.0506, abs=1e-4)
    # on the true, nonlinear system (noise, sin) the affine policy holds the same offset: the second half
    # of 200-step rollouts from 64 starts per seed; tolerance 2e-3 rad = about 4 standard errors of the
    # time-averaged angle (correlated samples; the noise moves theta by ~3e-3 rad rms)
    for (gain, ff), steady in (((L, l0), steady_true), ((L_prior, l0_prior), steady_prior)):
        ev = task.evaluate(AffinePolicy(gain, ff, 4.0), [0, 1])
        assert ev["terminated_fraction"] <= 1 / 64  # the bound is active: a corner start may fall (1 of 128)
        assert ev["mean_state_0"] == pytest.approx(steady[0], abs=2e-3)


def _short_config(method: str = "mixed", iterations: int = 20) -> TrainConfig:
    return TrainConfig(method=method, task="linear", seed=3,
                       algorithm=dict(iterations=iterations, batch_size=32, hidden_sizes=(8, 8), horizon=100,
                                      lr_decay_iterations=20),
                       sampler=dict(name="model_rollouts", true_horizon=100),
                       run=dict(eval_every=20, checkpoint_every=20, eval_seeds=1))


def test_short_mixed_run_is_reproducible_and_learns_the_bias() -> None:
    task = PendulumTask()
    runs = [AGPI(task, _short_config()) for _ in range(2)]
    results = [train(agent, progress=False) for agent in runs]
    for p, q in zip(runs[0].actor.parameters(), runs[1].actor.parameters()):
        assert torch.equal(p, q)
    assert results[0]["final"] == results[1]["final"] and results[0]["task"] == "pendulum"
    n = results[0]["true_transitions"]
    estimate = task.torque_from_xi(results[0]["final_ibe_mean"][0])
    # Case 2 with K_M = K: the prior weighs like one transition, so the estimate is n/(n+1) times the
    # sample mean of n draws of N(0.5, 0.2^2) N m: within 0.5/(n+1) + 4 * 0.2 / sqrt(n) of the true bias
    assert n == 40  # 2 collections (k = 0, 10) of true_steps = 20
    assert abs(estimate - 0.5) < 0.5 / (n + 1) + 4 * 0.2 / math.sqrt(n)
    # model-driven RL keeps the prior
    model = train(AGPI(task, _short_config(method="model", iterations=2)), progress=False)
    assert model["final_ibe_mean"] == [0.0] and model["true_transitions"] == 0


def test_the_pendulum_is_a_named_task_of_the_configuration() -> None:
    """``task.name = "pendulum"`` builds a PendulumTask from the task.<field> values (dict and --set)."""
    from mixedrl.config import task_names
    from mixedrl.tasks import make_task, task_from_config

    assert "pendulum" in task_names()
    config = TrainConfig(task={"name": "pendulum", "torque_bias": 0.3, "gamma": 0.95})
    task = task_from_config(config.task)
    assert isinstance(task, PendulumTask) and task.gamma == 0.95
    assert task.torque_from_xi(task.true_mean[0]) == pytest.approx(0.3, rel=1e-12)
    assert isinstance(make_task("pendulum", torque_bias=0.3), PendulumTask)
    # the default config is PendulumTask()'s
    default = task_from_config("pendulum")
    assert np.array_equal(default.true_mean, PendulumTask().true_mean) and default.gamma == PendulumTask().gamma
    data = apply_overrides({}, {"task.name": "pendulum", "task.init_angle": 0.2})  # as --set and a sweep spec
    assert task_from_config(TrainConfig.from_dict(data).task).obs_scale.tolist() == pytest.approx([0.2, 0.3])
    with pytest.raises(ValueError, match=r"task\.name: expected one of \('dlc', 'linear', 'pendulum'"):
        TrainConfig(task={"name": "pendulm"})
    with pytest.raises(ValueError, match=r"task\.dt: expected a positive number"):
        TrainConfig(task={"name": "pendulum", "dt": -0.1})
    with pytest.raises(ValueError, match=r"task\.gamma: expected a number in \(0, 1\)"):
        TrainConfig(task={"name": "pendulum", "gamma": 1.0})
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['task\.prior_force_mean'\]"):
        TrainConfig(task={"name": "pendulum", "prior_force_mean": 1.0})


def test_a_pendulum_run_records_its_name_and_resumes(tmp_path) -> None:
    from mixedrl.runs import RunDirectory, make_trainer

    config = TrainConfig(method="mixed", seed=1, task={"name": "pendulum", "torque_bias": 0.4},
                         algorithm=dict(iterations=2, batch_size=16, hidden_sizes=(8, 8)),
                         run=dict(eval_seeds=1, eval_every=2, checkpoint_every=1))
    run = RunDirectory(tmp_path / "p")
    first = train(make_trainer(config), run, progress=False)
    record = json.loads(run.config_path.read_text())
    assert record["task"]["name"] == "pendulum" and record["task"]["torque_bias"] == 0.4
    assert first["task"] == "pendulum"
    loaded = run.read_config()
    assert loaded.task == config.task and isinstance(make_trainer(loaded).task, PendulumTask)
    longer = TrainConfig.from_dict(apply_overrides(loaded.to_dict(), {"algorithm.iterations": 3}))
    resumed = train(make_trainer(longer), run, resume=True, progress=False)
    assert resumed["task"] == "pendulum" and resumed["iterations"] == 3
