"""NMPC solve time and learned-policy inference time, side by side (measured here, never asserted).

Run: ``pytest benchmarks/test_bench_nmpc.py --benchmark-only``. Group ``online-control``: one warm-started
NMPC solve (2 s horizon, 400 stages, gamma = 0.99, true mean; the online work of one control step of
:class:`validation.nmpc.VehicleNMPC`) and one forward pass of :class:`mixedrl.networks.Actor` (the
default (64, 64) ELU network) on one observation. ``extra_info["ratio_to_actor"]`` on the NMPC row is
its median over the actor's. Skipped without CasADi (extra ``nmpc``).

The preview policy of docs/references.rst ("Mixed RL with path preview"; experiments/analysis/preview_study.py), in the
same group and the same run: ``test_preview_actor_inference`` (the torch actor on the 11-dimensional
preview observation, the shipped seed-0 weights) and ``test_preview_step_numpy`` (the whole online work
of one control step on a plain-NumPy deployment path: the observation with its six preview distances
computed from the state, then the same weights' forward pass, :class:`preview_study.NumpyActor`).
``extra_info["ratio_to_preview_torch"]`` and ``["ratio_to_preview_numpy"]`` on the NMPC row are the NMPC
solve's median over theirs (the NMPC runs last in the file).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

casadi = pytest.importorskip("casadi", reason="the NMPC benchmark needs CasADi: pip install -e '.[nmpc]'")

from mixedrl.config import ONE_STEP_LEARNER, TrainConfig  # noqa: E402
from mixedrl.envs import DoubleLaneChangeModel  # noqa: E402
from mixedrl.networks import Actor  # noqa: E402
from mixedrl.tasks import DoubleLaneChangeTask  # noqa: E402
from validation.nmpc import VehicleNMPC  # noqa: E402
from validation.preview import NumpyActor  # noqa: E402

#: The preview distances of the chosen candidate P12 (experiments/analysis/preview_study.py, ``CANDIDATES["P12"]``).
PREVIEW_P12 = (2.0, 4.0, 6.0, 8.0, 10.0, 12.0)

from mixedrl.envs.tracking import observation_columns  # noqa: E402

_ROOT = Path(__file__).resolve().parents[1]

_MEDIANS: dict[str, float] = {}


def _start() -> np.ndarray:
    cfg = DoubleLaneChangeModel().config
    ref = cfg.reference
    return np.array([0.0, 0.0, cfg.v_des, ref.heading(0.0), ref.lateral(0.0), 0.0])


def test_actor_inference(benchmark) -> None:
    """``Actor`` forward on one observation (float32, no autograd): the learned policy's online cost."""
    task = DoubleLaneChangeTask()
    cfg = TrainConfig()
    actor = Actor(task.obs_dim, task.action_dim, cfg.algorithm.hidden_sizes, cfg.algorithm.activation, torch.Generator().manual_seed(0),
                  task.action_bound, task.obs_scale)
    obs = task.observe(torch.tensor(_start()[None]))[0].float()
    benchmark.group = "online-control"
    with torch.no_grad():
        benchmark(actor, obs)
    _MEDIANS["actor"] = benchmark.stats.stats.median
    benchmark.extra_info["threads"] = torch.get_num_threads()


def _preview_policy() -> tuple[DoubleLaneChangeTask, Actor, str]:
    """The task with the chosen preview and its actor: the shipped seed-0 weights (else a fresh actor of
    the same shape, which costs the same)."""
    preview = PREVIEW_P12
    task = DoubleLaneChangeTask(preview_distances=preview)
    cfg = TrainConfig(algorithm=ONE_STEP_LEARNER)  # the learner the preview study trained (ELU hidden layers)
    actor = Actor(task.obs_dim, task.action_dim, cfg.algorithm.hidden_sizes, cfg.algorithm.activation, torch.Generator().manual_seed(0),
                  task.action_bound, task.obs_scale)
    path = _ROOT / "experiments" / "results" / "preview" / "per_run" / "S" / "P12" / "mixed_s0.json"
    source = "fresh weights"
    if path.exists():
        weights = json.loads(path.read_text())["actor"]
        actor.load_state_dict({k: torch.tensor(v, dtype=torch.float32) for k, v in weights.items()})
        source = str(path.relative_to(_ROOT))
    return task, actor, source


def test_preview_actor_inference(benchmark) -> None:
    """The preview policy's torch ``Actor`` forward on one 11-dimensional observation (float32, no autograd)."""
    task, actor, source = _preview_policy()
    obs = task.observe(torch.tensor(_start()[None]))[0].float()
    benchmark.group = "online-control"
    with torch.no_grad():
        benchmark(actor, obs)
    _MEDIANS["preview_torch"] = benchmark.stats.stats.median
    benchmark.extra_info["weights"] = source


def test_preview_step_numpy(benchmark) -> None:
    """One whole control step of the preview policy in plain NumPy: observation (with the preview) from
    the state, then the forward pass of the same weights."""
    task, actor, source = _preview_policy()
    fast = NumpyActor(actor.state_dict())
    cfg = task.model.config
    s = tuple(float(x) for x in _start())

    def step() -> np.ndarray:
        return fast(np.array(observation_columns(cfg, *s)))

    with torch.no_grad():
        torch_u = actor(task.observe(torch.tensor(_start()[None]))[0].float()).double().numpy()
    np.testing.assert_allclose(step(), torch_u, rtol=0, atol=1e-5)  # the same policy
    benchmark.group = "online-control"
    benchmark(step)
    _MEDIANS["preview_numpy"] = benchmark.stats.stats.median
    benchmark.extra_info["weights"] = source


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
    for key in ("actor", "preview_torch", "preview_numpy"):
        if key in _MEDIANS:
            benchmark.extra_info[f"ratio_to_{key}"] = benchmark.stats.stats.median / _MEDIANS[key]
