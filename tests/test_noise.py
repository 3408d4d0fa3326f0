"""The noise sources (mixedrl.noise): one factory for Algorithms 1 and 2, the protocol's ``learns`` flag,
Case 3 (StateDependentIBE, LinearFeatureIBE) planned with by Algorithm 2 through per-state nodes and
selected by ``AlgorithmConfig.ibe_case``, and the oracle of a state-dependent truth (a road grade)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mixedrl.algorithms.agpi import AGPI
from mixedrl.algorithms.policy_iteration import ibe_step
from mixedrl.config import TrainConfig
from mixedrl.ibe import KnownCovarianceIBE, LinearFeatureIBE, StateDependentIBE, UnknownCovarianceIBE
from mixedrl.noise import GaussianNoise, StateDependentGaussianNoise, make_noise_source
from mixedrl.runs import RunDirectory, make_trainer, train
from mixedrl.tasks import LinearTask, task_from_config
from validation.lq import example_problem


@pytest.mark.parametrize("source", [LinearTask(), example_problem()])
def test_one_factory_for_both_algorithms(source) -> None:
    mixed = make_noise_source("mixed", source)
    assert isinstance(mixed, UnknownCovarianceIBE) and mixed.learns and not mixed.state_dependent
    assert np.array_equal(mixed.mean, source.prior_mean)
    assert make_noise_source("mixed", source, "paper").recursion == "paper"
    known = make_noise_source("mixed", source, covariance="known")
    assert isinstance(known, KnownCovarianceIBE) and np.array_equal(known.noise_cov, source.true_cov)
    model, oracle = make_noise_source("model", source), make_noise_source("oracle", source)
    assert isinstance(model, GaussianNoise) and not model.learns
    assert np.array_equal(model.mean, source.prior_mean) and np.array_equal(oracle.mean, source.true_mean)
    for kwargs, name in (({"method": "ddpg"}, "method"), ({"method": "mixed", "recursion": "x"}, "recursion"),
                         ({"method": "mixed", "covariance": "x"}, "covariance"),
                         ({"method": "mixed", "recursion": "paper", "covariance": "known"}, "recursion")):
        with pytest.raises(ValueError, match=f"^{name}"):
            make_noise_source(task=source, **kwargs)


def test_fixed_sources_do_not_learn_and_cannot_be_updated() -> None:
    prior = GaussianNoise([0.0], [[1.0]])
    assert not hasattr(prior, "update")  # no silent no-op
    with pytest.raises(ValueError, match="^noise"):
        ibe_step(prior, np.zeros((3, 1)))
    ibe_step(prior, None)  # a fixed source with no data: the IBE step is the identity
    assert np.array_equal(prior.mean, [0.0])


class Phi(torch.nn.Module):
    """phi(x, u) = x W + b: a state-dependent mean of the noise (Case 3)."""

    def __init__(self) -> None:
        super().__init__()
        self.lin = torch.nn.Linear(2, 2, dtype=torch.float64)
        with torch.no_grad():
            self.lin.weight.copy_(torch.tensor([[0.0, 0.0], [0.8, -0.4]]))
            self.lin.bias.zero_()

    def forward(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return self.lin(x)


def test_agpi_plans_with_a_state_dependent_ibe() -> None:
    """Algorithm 2 runs with Case 3 and plans, at each state of the batch, with nodes centred at
    phi(x, pi^k(x)) of the current fit; the fit moves with the data."""
    task = LinearTask()
    noise = StateDependentIBE(Phi(), task.true_cov + 1e-4 * np.eye(2), 2, 1, prior_std=1.0, max_iter=20)
    assert noise.learns and noise.state_dependent
    ag = AGPI(task, TrainConfig(method="mixed", task="linear", algorithm=dict(batch_size=16, iterations=5),
                                sampler="true_copies"),
              noise_source=noise)
    seen: list[tuple[torch.Tensor, torch.Tensor]] = []
    original = ag.pev

    def spy(s, offsets, weights):  # noqa: ANN001
        with torch.no_grad():
            centre = noise.mean_at(s.double(), ag.actor(task.observe(s)).double())
        seen.append((torch.einsum("p,pbn->bn", weights.double(), offsets.double()), centre))
        return original(s, offsets, weights)

    ag.pev = spy
    w_before = noise.phi.lin.weight.detach().clone()
    rows = [ag.iteration() for _ in range(3)]
    assert all(np.isfinite(v) for r in rows for v in r.values())
    assert noise.count == 3 * 16 and rows[-1]["ibe/count"] == 48.0
    assert not torch.equal(w_before, noise.phi.lin.weight)  # the IBE learned
    for mean_used, centre in seen:
        assert mean_used.shape == (16, 2)
        torch.testing.assert_close(mean_used, centre @ task.noise_matrix.double().T, rtol=1e-6, atol=1e-6)
        assert float(centre[:, 1].std()) > 1e-3  # the nodes differ from state to state


# ----------------------------------------------------------------------------------------------------
# AlgorithmConfig.ibe_case; Case 3 on the vehicle's road grade; the oracle of a state-dependent truth
# ----------------------------------------------------------------------------------------------------
GRADE = {"disturbance": {"grade_amplitude": 0.02, "grade_wavelength": 40.0}}
T_OVER_M = (1.0 / 200.0) / 1500.0


def _true_force(X: np.ndarray) -> np.ndarray:
    """The grade's mean force, transcribed from the docs: 261 - m g sin(0.02 sin(2 pi X / 40))."""
    return 261.0 - 1500.0 * 9.81 * np.sin(0.02 * np.sin(2.0 * np.pi * X / 40.0))


def _course_states(task, X: np.ndarray) -> torch.Tensor:  # noqa: ANN001
    s = torch.zeros(len(X), task.state_dim, dtype=torch.float64)
    s[:, 2], s[:, 5] = 12.0, torch.as_tensor(X)
    return s


@pytest.mark.parametrize("case,cls", [(1, KnownCovarianceIBE), (2, UnknownCovarianceIBE), (3, LinearFeatureIBE)])
@pytest.mark.parametrize("task", ["linear", "dlc"])
def test_ibe_case_selects_the_estimator(case: int, cls: type, task: str) -> None:
    ag = AGPI(task_from_config(task), TrainConfig(method="mixed", task=task, algorithm=dict(ibe_case=case,
                                                  batch_size=8)))
    assert isinstance(ag.noise, cls)
    assert ag.noise.learns and ag.noise.state_dependent == (case == 3)
    for method in ("model", "oracle"):  # only mixed RL reads ibe_case
        fixed = AGPI(task_from_config(task), TrainConfig(method=method, task=task, algorithm=dict(ibe_case=case,
                                                         batch_size=8))).noise
        assert isinstance(fixed, GaussianNoise)
    assert TrainConfig().algorithm.ibe_case == 2  # the reproduction's Case 2 stays the default


@pytest.mark.parametrize("changes,field", [({"ibe_case": 0}, "ibe_case"), ({"ibe_case": 4}, "ibe_case"),
                                           ({"ibe_case": 2.0}, "ibe_case"), ({"ibe_case": True}, "ibe_case"),
                                           ({"ibe_case": "3"}, "ibe_case"),
                                           ({"ibe_case": 3, "ibe_recursion": "paper"}, "ibe_recursion"),
                                           ({"ibe_case": 1, "ibe_recursion": "paper"}, "ibe_recursion")])
def test_ibe_case_is_validated(changes: dict, field: str) -> None:
    with pytest.raises(ValueError, match=f"^algorithm.{field}:"):
        TrainConfig(algorithm=changes)
    with pytest.raises(ValueError, match="^state_dependent"):
        make_noise_source("mixed", LinearTask(), state_dependent=True)  # Case 3 needs covariance="known"


def test_case3_prior_and_features_on_the_vehicle() -> None:
    """Before any data the Case-3 mean is the prior's 150 N everywhere; the features are the Fourier series
    [1, sin(2 pi k X / 120), cos(2 pi k X / 120)], k = 1..8; sigma_w = the prior's 4 N in xi units."""
    task = task_from_config(GRADE)
    noise = make_noise_source("mixed", task, covariance="known", state_dependent=True)
    X = np.linspace(0.0, 120.0, 13)
    s = _course_states(task, X)
    u = torch.zeros(len(X), 2, dtype=torch.float64)
    np.testing.assert_allclose(noise.mean_at(s, u).numpy(), np.tile(task.prior_mean, (len(X), 1)), rtol=1e-15)
    assert noise.prior_std == pytest.approx(4.0 * T_OVER_M, rel=1e-12)
    np.testing.assert_array_equal(noise.noise_cov, task.true_cov)
    k = np.arange(1, 9)
    expected = np.hstack([np.ones((len(X), 1)), np.sin(2 * np.pi * np.outer(X, k) / 120.0),
                          np.cos(2 * np.pi * np.outer(X, k) / 120.0)])
    np.testing.assert_allclose(task.mean_features(s, u).numpy(), expected, rtol=1e-12, atol=1e-12)


def test_oracle_on_a_grade_plans_with_the_true_state_dependent_mean() -> None:
    task = task_from_config(GRADE)
    assert task.true_mean_varies and not task_from_config("dlc").true_mean_varies
    oracle = make_noise_source("oracle", task)
    assert isinstance(oracle, StateDependentGaussianNoise) and not oracle.learns and not hasattr(oracle, "update")
    X = np.linspace(0.0, 120.0, 241)
    s = _course_states(task, X)
    mean = oracle.mean_at(s, torch.zeros(len(X), 2, dtype=torch.float64)).numpy()
    np.testing.assert_allclose(mean[:, 2], _true_force(X) * T_OVER_M, rtol=1e-12)
    assert np.all(mean[:, [0, 1, 3, 4]] == 0.0)
    assert isinstance(make_noise_source("oracle", task_from_config("dlc")), GaussianNoise)  # level road: unchanged
    ag = AGPI(task, TrainConfig(method="oracle", task=GRADE, algorithm=dict(batch_size=16)))
    batch = ag.states.float()
    got, cov = ag.planning_moments(batch, ag.actor(task.observe(batch)))
    np.testing.assert_allclose(got[:, 2], _true_force(batch[:, 5].double().numpy()) * T_OVER_M, rtol=1e-5)
    np.testing.assert_array_equal(cov, task.true_cov)


def test_case3_learns_the_grade_along_the_course() -> None:
    """Mixed RL with ibe_case=3 on a road grade: after 20 iterations (1280 residuals) the fitted mean force
    along the course is the true one within 5 x its own standard error, sqrt(sigma_F^2 tr(G^-1 M)) (RMS
    over the course of a least-squares fit with Gram matrix G, M = the features' second moments on the
    course grid); a constant mean (Case 2) cannot follow the grade's +-294 N."""
    cfg = TrainConfig(method="mixed", task=GRADE, algorithm=dict(ibe_case=3, batch_size=64, iterations=20),
                      sampler="true_copies")
    ag = AGPI(task_from_config(cfg.task), cfg)
    for _ in range(20):
        ag.iteration()
    task, noise = ag.task, ag.noise
    assert noise.count == 20 * 64
    X = np.linspace(0.0, 120.0, 481)
    s = _course_states(task, X)
    u = torch.zeros(len(X), 2, dtype=torch.float64)
    fitted = noise.mean_at(s, u).numpy()[:, 2] / T_OVER_M
    rms = float(np.sqrt(np.mean((fitted - _true_force(X)) ** 2)))
    g = task.mean_features(s, u).numpy()
    se = float(np.sqrt(32.0 * np.trace(np.linalg.solve(noise.gram, g.T @ g / len(X)))))
    assert rms <= 5.0 * se, (rms, se)
    assert float(np.sqrt(np.mean((_true_force(X) - _true_force(X).mean()) ** 2))) > 100.0 * se


def test_case3_and_the_grade_oracle_on_model_rollouts() -> None:
    """The course sampler: the rollouts step with the per-state mean, and every true residual reaches
    the Case-3 IBE with its state and action."""
    base = dict(task=GRADE, sampler=dict(name="dlc_course", true_envs=2, true_steps=3, true_every=2, course_start=0,
                                         kick_prob=0.0), algorithm=dict(batch_size=16))
    ag = AGPI(task_from_config(GRADE), TrainConfig(method="mixed", **{**base, "algorithm": dict(ibe_case=3, batch_size=16)}))
    for _ in range(4):
        ag.iteration()
    assert ag.noise.count == ag.true_transitions == 2 * 2 * 3
    oracle = AGPI(task_from_config(GRADE), TrainConfig(method="oracle", **base))
    sampler, task = oracle.sampler, oracle.task
    s = sampler.states.clone()
    zero = np.zeros((task.noise_dim, task.noise_dim))
    sampler.model_step(oracle.actor, oracle.noise.mean_at, zero)
    with torch.no_grad():
        u = oracle.actor(task.observe(s.float())).double()
    expected = task.f(s, u) + task.true_mean_at(s, u) @ task.noise_matrix.double().T
    stepped = sampler.steps > 0  # the rows that were not restarted after the step
    assert bool(stepped.any())
    torch.testing.assert_close(sampler.states[stepped], expected[stepped], rtol=1e-12, atol=1e-12)


def test_case3_results_report_the_batch_average_of_the_planning_mean(tmp_path) -> None:  # noqa: ANN001
    cfg = TrainConfig(method="mixed", task="linear", algorithm=dict(ibe_case=3, iterations=3, batch_size=16),
                      run=dict(eval_every=3, eval_seeds=1))
    trainer = make_trainer(cfg)
    res = train(trainer, RunDirectory(tmp_path))
    mean, cov = trainer.noise_moments()
    assert res["final_ibe_mean"] == mean.tolist() and res["final_ibe_cov_diag"] == np.diag(cov).tolist()
    assert mean.shape == (2,) and not np.allclose(mean, trainer.task.prior_mean)
