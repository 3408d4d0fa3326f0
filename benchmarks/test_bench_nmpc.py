"""NMPC solve time and learned-policy inference time, side by side (measured here, never asserted).

Run: ``pytest benchmarks/test_bench_nmpc.py --benchmark-only``. Group ``online-control``: one warm-started
NMPC solve (2 s horizon, 400 stages, gamma = 0.99, true mean; the online work of one control step of
:class:`validation.nmpc.VehicleNMPC`) and one forward pass of :class:`mixedrl.networks.Actor` (the
default (64, 64) ELU network) on one observation. ``extra_info["ratio_to_actor"]`` on the NMPC row is
its median over the actor's. Skipped without CasADi (extra ``nmpc``).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

casadi = pytest.importorskip("casadi", reason="the NMPC benchmark needs CasADi: pip install -e '.[nmpc]'")

from mixedrl.config import TrainConfig  # noqa: E402
from mixedrl.envs import DoubleLaneChangeModel  # noqa: E402
from mixedrl.networks import Actor  # noqa: E402
from mixedrl.tasks import DoubleLaneChangeTask  # noqa: E402
from validation.nmpc import VehicleNMPC  # noqa: E402

_MEDIANS: dict[str, float] = {}


def _start() -> np.ndarray:
    cfg = DoubleLaneChangeModel().config
    ref = cfg.reference
    return np.array([0.0, 0.0, cfg.v_des, ref.heading(0.0), ref.lateral(0.0), 0.0])


def test_actor_inference(benchmark) -> None:
    """``Actor`` forward on one observation (float32, no autograd): the learned policy's online cost."""
    task = DoubleLaneChangeTask()
    cfg = TrainConfig()
    actor = Actor(task.obs_dim, task.action_dim, cfg.hidden_sizes, cfg.activation, torch.Generator().manual_seed(0),
                  task.action_bound, task.obs_scale)
    obs = task.observe(torch.tensor(_start()[None]))[0].float()
    benchmark.group = "online-control"
    with torch.no_grad():
        benchmark(actor, obs)
    _MEDIANS["actor"] = benchmark.stats.stats.median
    benchmark.extra_info["threads"] = torch.get_num_threads()


def test_nmpc_solve(benchmark) -> None:
    """One warm-started NMPC solve (shift by one step) from the course's start, 2 s horizon."""
    ctrl = VehicleNMPC(horizon=2.0, gamma=0.99, force="true")
    s = _start()
    model = DoubleLaneChangeModel()
    u = ctrl(s)  # cold solve outside the timing
    step = {"k": 0}

    def solve() -> None:
        nonlocal s, u
        s = np.asarray(model.step(s, u))
        step["k"] += 1
        u = ctrl.core.solve(s, step=step["k"]).u[0]

    benchmark.group = "online-control"
    benchmark.pedantic(solve, rounds=30, iterations=1, warmup_rounds=2)
    if "actor" in _MEDIANS:
        benchmark.extra_info["ratio_to_actor"] = benchmark.stats.stats.median / _MEDIANS["actor"]
