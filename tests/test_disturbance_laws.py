"""The laws of the true disturbance force (``task.disturbance.law``): Gaussian, Student-t, two-point.

Every law must have the configured mean and variance (checked statistically, with tolerances derived
from the sample size), the laws must differ where they should (kurtosis, tails, support), every draw
comes from the generator passed in (same seed, same draws), and the Gaussian law must draw exactly what
the code drew before the other laws existed: the reference draws are computed here independently
(``torch.randn`` / ``Generator.standard_normal`` on a freshly seeded generator, the formula
``mean + sqrt(variance) z``), not by the code under test.
"""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
import torch
from scipy import stats

from mixedrl.config import DISTURBANCE_LAWS, TrainConfig
from mixedrl.envs import ENV_ID, Disturbance, DoubleLaneChangeModel
from mixedrl.tasks import LinearTask, task_from_config

N = 200_000  # draws per statistical check
Z = 5.0  # tolerance in standard errors
MEAN, VARIANCE = 261.0, 32.0


def _states(n: int) -> torch.Tensor:
    s = torch.zeros(n, 6, dtype=torch.float64)
    s[:, 2] = 12.0
    s[:, 5] = torch.linspace(0.0, 120.0, n, dtype=torch.float64)  # the mean must not depend on X (no grade)
    return s


def _model(law: str, **extra: float) -> DoubleLaneChangeModel:
    return DoubleLaneChangeModel({"disturbance": {"law": law, "mean": MEAN, "variance": VARIANCE, **extra}})


def _draws(law: str, backend: str, seed: int = 0, n: int = N, **extra: float) -> np.ndarray:
    model = _model(law, **extra)
    if backend == "torch":
        return model.sample_force(_states(n), torch.Generator().manual_seed(seed)).numpy()
    if backend == "numpy":
        return model.sample_force(_states(n).numpy(), np.random.default_rng(seed))
    rng = np.random.default_rng(seed)  # the Gymnasium env's path: one unbatched state at a time
    state = (0.0, 0.0, 12.0, 0.0, 0.0, 0.0)
    return np.array([model.sample_force(state, rng) for _ in range(n)])


BACKENDS = ["torch", "numpy", "scalar"]


def _n(backend: str) -> int:
    return N if backend != "scalar" else 40_000  # one Python call per draw on the scalar path


# ----------------------------------------------------------------------------------------------------
# mean and variance equal the configuration
# ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("law", DISTURBANCE_LAWS)
def test_sample_mean_is_the_configured_mean(law: str, backend: str) -> None:
    """|mean - 261| <= 5 standard errors, SE = sqrt(variance / n) (finite variance for every law)."""
    n = _n(backend)
    x = _draws(law, backend, n=n)
    assert x.shape == (n,) and np.isfinite(x).all()
    se = math.sqrt(VARIANCE / n)
    assert abs(x.mean() - MEAN) <= Z * se, (law, backend, x.mean())


@pytest.mark.parametrize("backend", BACKENDS)
def test_gaussian_variance_and_shape(backend: str) -> None:
    """Variance about the known mean: ``Var((x - mu)^2) = 2 sigma^4`` for a Gaussian, so the SE of the
    estimate is ``sqrt(2 / n) sigma^2``; the KS test against N(261, 32) checks the whole law."""
    n = _n(backend)
    x = _draws("gaussian", backend, n=n)
    var = np.mean((x - MEAN) ** 2)
    assert abs(var - VARIANCE) <= Z * math.sqrt(2.0 / n) * VARIANCE
    assert stats.kstest(x, stats.norm(loc=MEAN, scale=math.sqrt(VARIANCE)).cdf).pvalue > 1e-6


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dof", [3.0, 2.5, 7.0])
def test_student_t_is_the_rescaled_student_t(backend: str, dof: float) -> None:
    """For dof <= 4 the sample variance has infinite variance, so the variance is checked through the
    whole law instead: a Kolmogorov-Smirnov test against scipy's Student-t with scale
    ``sqrt(variance (dof - 2) / dof)`` (so its variance is 32), and the interquartile range against that
    law's within the delta-method standard error of a sample quantile."""
    n = _n(backend)
    x = _draws("student_t", backend, n=n, dof=dof)
    law = stats.t(df=dof, loc=MEAN, scale=math.sqrt(VARIANCE * (dof - 2.0) / dof))
    assert law.var() == pytest.approx(VARIANCE, rel=1e-12)  # the reference law has the configured variance
    assert stats.kstest(x, law.cdf).pvalue > 1e-6
    # sample p-quantile: SE = sqrt(p (1 - p) / n) / density(q_p); the IQR's SE is at most the sum of both
    q25, q75 = law.ppf([0.25, 0.75])
    se = 2.0 * math.sqrt(0.25 * 0.75 / n) / law.pdf(q75)
    iqr = np.subtract(*np.quantile(x, [0.75, 0.25]))
    assert abs(iqr - (q75 - q25)) <= Z * se


@pytest.mark.parametrize("backend", BACKENDS)
def test_bumps_is_the_two_point_law(backend: str) -> None:
    """Two values, mean -+ sqrt(variance), each with probability 1/2 (binomial SE sqrt(1/4n)): then the
    mean is 261 and ``(x - mu)^2 = variance`` for every draw."""
    n = _n(backend)
    x = _draws("bumps", backend, n=n)
    lo, hi = MEAN - math.sqrt(VARIANCE), MEAN + math.sqrt(VARIANCE)
    assert np.all((np.abs(x - lo) < 1e-9) | (np.abs(x - hi) < 1e-9))
    assert abs(np.mean(x > MEAN) - 0.5) <= Z * math.sqrt(0.25 / n)
    np.testing.assert_allclose((x - MEAN) ** 2, VARIANCE, rtol=1e-12)


def test_kurtosis_distinguishes_the_laws() -> None:
    """Excess kurtosis: Gaussian 0 (SE sqrt(24 / n)), two-point -2, Student-t(3) infinite (large in a
    sample); the fraction beyond 3 standard deviations orders them the same way."""
    kurt = {law: stats.kurtosis(_draws(law, "torch")) for law in DISTURBANCE_LAWS}
    assert abs(kurt["gaussian"]) <= Z * math.sqrt(24.0 / N)
    assert kurt["bumps"] == pytest.approx(-2.0, abs=1e-3)
    assert kurt["student_t"] > 2.0
    tail = {law: np.mean(np.abs(_draws(law, "numpy") - MEAN) > 3.0 * math.sqrt(VARIANCE)) for law in DISTURBANCE_LAWS}
    # exact tail probabilities: 0, 2 (1 - Phi(3)) = 0.0027, 2 P(T_3 > 3 sqrt(3)) = 0.0138
    p_gauss, p_t = 2.0 * stats.norm.sf(3.0), 2.0 * stats.t(df=3).sf(3.0 * math.sqrt(3.0))
    assert tail["bumps"] == 0.0
    assert abs(tail["gaussian"] - p_gauss) <= Z * math.sqrt(p_gauss / N)
    assert abs(tail["student_t"] - p_t) <= Z * math.sqrt(p_t / N)


# ----------------------------------------------------------------------------------------------------
# explicit generators; the Gaussian path is unchanged
# ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("law", DISTURBANCE_LAWS)
def test_same_seed_same_draws_other_seed_other_draws(law: str, backend: str) -> None:
    a, b, c = (_draws(law, backend, seed=s, n=500) for s in (3, 3, 4))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_gaussian_draws_are_those_of_the_formula_used_before() -> None:
    """``F = mean(X) + sqrt(variance) z`` with ``z`` one ``torch.randn`` / ``standard_normal`` per state from
    the same freshly seeded generator: bit for bit (so every existing result is unchanged)."""
    model = DoubleLaneChangeModel({"disturbance": {"mean": 250.0, "variance": 40.0, "grade_amplitude": 0.01}})
    s = _states(1000)
    for dtype in (torch.float64, torch.float32):
        got = model.sample_force(s.to(dtype), torch.Generator().manual_seed(5))
        z = torch.randn(1000, generator=torch.Generator().manual_seed(5), dtype=dtype)
        theta = 0.01 * torch.sin(2.0 * math.pi / 40.0 * s[:, 5].to(dtype))
        expected = (250.0 - 1500.0 * 9.81 * torch.sin(theta)) + math.sqrt(40.0) * z
        assert torch.equal(got, expected)
    got = model.sample_force(s.numpy(), np.random.default_rng(6))
    theta = 0.01 * np.sin(2.0 * math.pi / 40.0 * s[:, 5].numpy())
    expected = (250.0 - 1500.0 * 9.81 * np.sin(theta)) + math.sqrt(40.0) * np.random.default_rng(6).standard_normal(1000)
    np.testing.assert_array_equal(got, expected)
    rng, ref = np.random.default_rng(7), np.random.default_rng(7)
    for X in (0.0, 13.0, 77.5):
        got = model.sample_force((0.0, 0.0, 12.0, 0.0, 0.0, X), rng)
        mean = 250.0 - 1500.0 * 9.81 * math.sin(0.01 * math.sin(2.0 * math.pi / 40.0 * X))
        assert got == mean + math.sqrt(40.0) * float(ref.standard_normal())


def test_gym_env_draws_from_its_np_random_with_the_configured_law() -> None:
    """The Gymnasium env (the Table I evaluation's path) draws the configured law from ``np_random``:
    two-point forces, and the same forces as the model's scalar draws from a generator seeded alike."""
    env = gym.make(ENV_ID, disturbance={"law": "bumps"}).unwrapped
    env.reset(seed=11)
    forces = [env.step_physical(np.zeros(2))[4]["disturbance"] for _ in range(200)]
    std = math.sqrt(VARIANCE)
    assert set(np.round(forces, 9)) == {round(MEAN - std, 9), round(MEAN + std, 9)}
    env.reset(seed=11)
    rng = np.random.default_rng()  # reproduce np_random after reset(seed=11), then its draws
    rng.bit_generator.state = env.np_random.bit_generator.state
    model = _model("bumps")
    expected = [model.sample_force(tuple(env.state.tolist()), rng)]
    assert env.step_physical(np.zeros(2))[4]["disturbance"] == expected[0]


def test_torch_student_t_does_not_touch_the_global_generator() -> None:
    torch.manual_seed(0)
    before = torch.get_rng_state()
    _model("student_t").sample_force(_states(100), torch.Generator().manual_seed(1))
    assert torch.equal(torch.get_rng_state(), before)


# ----------------------------------------------------------------------------------------------------
# configuration
# ----------------------------------------------------------------------------------------------------
def test_unknown_law_names_the_field_and_lists_the_laws() -> None:
    with pytest.raises(ValueError, match=r"^task\.disturbance\.law: expected one of \('gaussian', 'student_t', "
                                         r"'bumps'\), got 'cauchy'"):
        TrainConfig(task={"disturbance": {"law": "cauchy"}})
    with pytest.raises(ValueError, match=r"^task\.disturbance\.dof: expected a number > 2"):
        TrainConfig(task={"disturbance": {"law": "student_t", "dof": 2}})
    with pytest.raises(ValueError, match=r"^dof"):
        Disturbance(law="student_t", dof=1.5)
    with pytest.raises(ValueError, match=r"^law"):
        Disturbance(law="Gaussian")


@pytest.mark.parametrize("law", DISTURBANCE_LAWS)
def test_the_task_simulates_the_law_and_its_moments_are_the_configured_ones(law: str) -> None:
    """The training task draws the configured law (its true step's residual on v_x is the force), and
    its ``true_mean`` / ``true_cov`` (what the oracle plans with) are the law's moments in xi units."""
    cfg = TrainConfig(task={"disturbance": {"law": law, "variance": 320.0, "dof": 5.0}})
    task = task_from_config(cfg.task)
    assert task.model.config.disturbance.law == law and task.model.config.disturbance.dof == 5.0
    scale = task.force_scale
    assert task.true_mean[task.noise_index] == pytest.approx(MEAN * scale, rel=1e-15)
    assert task.true_cov[task.noise_index, task.noise_index] == pytest.approx(320.0 * scale**2, rel=1e-15)
    s = _states(4000)
    u = torch.zeros(4000, 2, dtype=torch.float64)
    forces = task.xi_to_force(task.residuals(s, u, task.true_step(s, u, torch.Generator().manual_seed(2))))
    expected = _model(law, dof=5.0, variance=320.0).sample_force(s, torch.Generator().manual_seed(2))
    torch.testing.assert_close(forces[:, task.noise_index], expected, rtol=0.0, atol=1e-6)


def test_the_linear_task_simulates_only_the_gaussian_law() -> None:
    for law in ("student_t", "bumps"):
        with pytest.raises(ValueError, match="^task.disturbance.law: the linear task simulates only 'gaussian'"):
            task_from_config({"name": "linear", "disturbance": {"law": law}})
    assert isinstance(task_from_config({"name": "linear"}), LinearTask)
