"""Speed of the batched engine (mixedrl.algorithms.batched), measured here, never asserted.

Run: ``pytest benchmarks/test_bench_batched.py --benchmark-only``. One iteration of ``R`` Algorithm 2
runs in one batch (seeds x mixed / model / oracle, the double lane change's defaults, one torch thread)
for ``R = 1`` and ``R = 5``; ``extra_info["run_iterations_per_s"] = R / median``. The side-by-side table
with ``R = 15, 50`` and peak memory is ``python benchmarks/batched_table.py``.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import torch

from mixedrl.algorithms.batched import BatchedAGPI
from mixedrl.config import TrainConfig
from mixedrl.runs import make_trainer

METHODS = ("mixed", "model", "oracle")


@pytest.fixture(autouse=True)
def one_thread() -> Iterator[None]:
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.mark.parametrize("runs", [1, 5])
def test_batch_iteration(benchmark, runs: int) -> None:
    engine = BatchedAGPI([make_trainer(TrainConfig(method=METHODS[i % 3], seed=i // 3, task="dlc")) for i in range(runs)])
    for _ in range(2):
        engine.iteration()
    rows = benchmark.pedantic(engine.iteration, rounds=5, iterations=1)
    assert len(rows) == runs and all(r is not None for r in rows)
    benchmark.extra_info["run_iterations_per_s"] = runs / benchmark.stats.stats.median
