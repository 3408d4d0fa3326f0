"""Speed of the double-lane-change model and environments (measured here, never asserted).

Run: ``pytest benchmarks/test_bench_vehicle.py --benchmark-only``. Each model benchmark records
``extra_info["state_steps_per_s"] = batch / median time``. Targets (issue 4, 2-core machine): >= 10 M
state-steps/s at batch 4,096 and >= 30 M at 65,536 for the fused float32 model; <= 20 us per
Gymnasium step.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import gymnasium as gym
import mixedrl.envs as E
from mixedrl.envs import DoubleLaneChangeEnv, DoubleLaneChangeModel, DoubleLaneChangeVectorEnv

BATCHES = [1, 256, 4096, 65536]


@pytest.fixture(scope="module")
def models() -> dict[str, DoubleLaneChangeModel]:
    """Eager and fused models. Inductor bakes the thread count into its kernels when it compiles them,
    so the numbers are for the process's ``torch.get_num_threads()`` (set ``OMP_NUM_THREADS``; tox: 1)."""
    return {"eager": DoubleLaneChangeModel(), "compiled": DoubleLaneChangeModel(compile=True)}


def _batch(n: int, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(0)
    s = DoubleLaneChangeModel().reset_states(n, gen, dtype=dtype)
    u = 0.05 * torch.randn(n, 2, generator=gen, dtype=dtype)
    return s, u


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["f32", "f64"])
@pytest.mark.parametrize("mode", ["eager", "compiled"])
@pytest.mark.parametrize("batch", BATCHES)
def test_model_step(benchmark, models, batch: int, mode: str, dtype: torch.dtype) -> None:
    """``DoubleLaneChangeModel.step`` (the shared f on the 6-dim tracking state), no autograd."""
    model = models[mode]
    s, u = _batch(batch, dtype)
    with torch.no_grad():
        model.step(s, u)  # compile / warm up outside the timing
        benchmark.group = f"model-step-{mode}"
        benchmark(model.step, s, u)
    benchmark.extra_info["state_steps_per_s"] = batch / benchmark.stats.stats.median
    benchmark.extra_info["threads"] = torch.get_num_threads()


@pytest.mark.parametrize("batch", [4096, 65536])
def test_model_step_with_gradient(benchmark, models, batch: int) -> None:
    """Forward + backward through ``f`` (compiled, float32): what model-based policy updates pay."""
    model = models["compiled"]
    s, u = _batch(batch, torch.float32)
    u.requires_grad_(True)

    def fwd_bwd() -> None:
        model.step(s, u).sum().backward()

    fwd_bwd()
    benchmark.group = "model-step-grad"
    benchmark(fwd_bwd)
    benchmark.extra_info["state_steps_per_s"] = batch / benchmark.stats.stats.median


@pytest.mark.parametrize("batch", [4096])
def test_vector_env_step(benchmark, batch: int) -> None:
    """Full vector-env step (clip, noise, f, cost, termination, autoreset), float32, eager."""
    venv = DoubleLaneChangeVectorEnv(batch, seed=0)
    venv.reset()
    u = torch.zeros(batch, 2)
    benchmark.group = "vector-env"
    benchmark(venv.step, u)
    benchmark.extra_info["state_steps_per_s"] = batch / benchmark.stats.stats.median


def test_gym_step_raw(benchmark) -> None:
    """One ``DoubleLaneChangeEnv.step`` (float path), unwrapped."""
    env = DoubleLaneChangeEnv(course_length=1e9, max_lateral_error=1e9)
    env.reset(seed=0)
    a = np.array([0.0, -0.04])
    benchmark.group = "gym-step"
    benchmark(env.step, a)


def test_gym_step_registered(benchmark) -> None:
    """One step of ``gym.make("mixedrl/DoubleLaneChange-v0")`` (OrderEnforcing + PassiveEnvChecker)."""
    env = gym.make(E.ENV_ID, course_length=1e9, max_lateral_error=1e9)
    env.reset(seed=0)
    a = np.array([0.0, -0.04])
    env.step(a)
    benchmark.group = "gym-step"
    benchmark(env.step, a)
