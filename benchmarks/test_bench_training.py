"""Speed of one training iteration on the double lane change (measured here, never asserted).

Run: ``pytest benchmarks/test_bench_training.py --benchmark-only``. One Algorithm 2 iteration
(:meth:`mixedrl.algorithms.agpi.AGPI.iteration`: data from the 512 true-environment copies, PEV, PIM, IBE
update, MVC check and any inner PIM steps) for each noise source, and one DDPG iteration (16 environment
steps + one minibatch update of critic and actor), all with the reproduction's default
:class:`~mixedrl.config.TrainConfig` and one torch thread (what ``mixedrl reproduce`` uses per worker);
``test_iteration_compiled`` the same with ``algorithm.compile = "on"`` (side by side in one session: the
table script ``benchmarks/iteration_table.py --compile-ab`` alternates them).
``extra_info["iterations_per_s"] = 1 / median``; ``extra_info["seconds_per_1500"]`` is the time of the
default budget without evaluations.

The parts are timed too (``collect``, ``pev``, ``pim``, the IBE update on one batch of residuals, and
``mvc``: the three ``h`` evaluations and the check of eq. 38 that every iteration makes), so a slow
iteration can be traced to its step.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
import torch

from mixedrl.algorithms.agpi import h_value, mvc_check
from mixedrl.config import TrainConfig
from mixedrl.runs import make_trainer


@pytest.fixture(autouse=True)
def one_thread() -> Iterator[None]:
    """One torch thread, as each worker of ``mixedrl reproduce`` (restored afterwards, so the other
    benchmark files keep the process's setting)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _trainer(method: str, compile: str = "off") -> object:
    trainer = make_trainer(TrainConfig(method=method, seed=0, task="dlc", algorithm={"compile": compile}))
    for _ in range(3):  # past the first IBE update and any lazy initialisation
        trainer.iteration()
    return trainer


@pytest.mark.parametrize("method", ["mixed", "model", "oracle", "ddpg"])
def test_iteration(benchmark, method: str) -> None:
    """One outer iteration of Algorithm 2 (mixed / model / oracle) or of DDPG (default config)."""
    trainer = _trainer(method)
    benchmark.group = "training-iteration"
    benchmark.pedantic(trainer.iteration, rounds=60, iterations=1, warmup_rounds=2)
    median = benchmark.stats.stats.median
    benchmark.extra_info["iterations_per_s"] = 1.0 / median
    benchmark.extra_info["seconds_per_1500"] = 1500 * median
    benchmark.extra_info["batch_size"] = trainer.config.algorithm.batch_size


@pytest.mark.parametrize("method", ["mixed", "ddpg"])
def test_iteration_compiled(benchmark, method: str, request: pytest.FixtureRequest,
                            monkeypatch: pytest.MonkeyPatch) -> None:
    """The same iteration with ``algorithm.compile = "on"`` (:mod:`mixedrl.compiled`; compiled before the
    timing, in pytest's cache folder: cold the first time, about 40 s for mixed RL and 20 s for DDPG)."""
    cache = getattr(request.config, "cache", None)
    if cache is not None:
        monkeypatch.setenv("MIXEDRL_CACHE_DIR", str(cache.mkdir("mixedrl-compile")))
        monkeypatch.delenv("TORCHINDUCTOR_CACHE_DIR", raising=False)
    trainer = _trainer(method, "on")
    benchmark.group = "training-iteration"
    benchmark.pedantic(trainer.iteration, rounds=60, iterations=1, warmup_rounds=2)
    benchmark.extra_info["iterations_per_s"] = 1.0 / benchmark.stats.stats.median


@pytest.mark.parametrize("part", ["collect", "pev", "pim", "ibe", "mvc"])
def test_iteration_parts(benchmark, part: str) -> None:
    """The steps of one mixed-RL iteration, separately (same batch, same noise quadrature)."""
    trainer = _trainer("mixed")
    s, residuals = trainer.collect()
    offsets, weights = trainer.nodes(*trainer.noise_moments())
    obs = trainer.task.observe(s)

    def mvc() -> None:
        with torch.no_grad():
            u = trainer.actor(obs)
            h = [h_value(trainer.task, trainer.critic, s, u, offsets, weights) for _ in range(3)]
        mvc_check(h[0], h[1], h[2])

    calls = {
        "collect": trainer.collect,
        "pev": lambda: trainer.pev(s, offsets, weights),
        "pim": lambda: trainer.pim(s, offsets, weights),
        "ibe": lambda: trainer.noise.update(np.asarray(residuals)),
        "mvc": mvc,
    }
    benchmark.group = "training-iteration-parts"
    benchmark.pedantic(calls[part], rounds=60, iterations=1, warmup_rounds=2)
    benchmark.extra_info["batch_size"] = trainer.config.algorithm.batch_size


@pytest.mark.parametrize("calibration", [0, 1])
def test_deployed_policy(benchmark, calibration: int) -> None:
    """Building the deployed policy of the default (``"lq_handover"``) once, without and with the calibrated shift
    (:func:`mixedrl.departures.calibration.calibrate_shift`: one Newton step, 256 model closed loops over the task's
    evaluation horizon); a run builds it at each of its evaluations. Nothing is cached between rounds."""
    trainer = _trainer("mixed")
    trainer.config.algorithm.feedforward_calibration = calibration

    def build() -> None:
        trainer._calibration = None
        _ = trainer.policy

    benchmark.group = "deployed-policy"
    benchmark.pedantic(build, rounds=8, iterations=1, warmup_rounds=1)
    benchmark.extra_info["feedforward"] = trainer.feedforward
