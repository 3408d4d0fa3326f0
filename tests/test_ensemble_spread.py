"""The seed-spread diagnostic of issue 42 (experiments/analysis/ensemble_spread.py): the ensemble's action is the
mean of its actors', the paired figures are model-driven minus mixed RL per unit, and an ensemble size that leaves
fewer than two pairs is refused before anything is trained."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "experiments" / "analysis")]

import ensemble_spread as ES  # noqa: E402


class Constant(torch.nn.Module):
    def __init__(self, value: float) -> None:
        super().__init__()
        self.value = value

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.full((obs.shape[0], 1), self.value)


def test_the_ensemble_acts_with_the_mean_action() -> None:
    policy = ES.MeanPolicy([Constant(1.0), Constant(-0.5), Constant(2.0)])
    out = policy(torch.zeros(4, 5))
    assert out.shape == (4, 1)
    assert torch.allclose(out, torch.full((4, 1), 2.5 / 3))


def test_paired_figures_are_model_minus_mixed_per_unit() -> None:
    mixed, model = [0.02, 0.03, 0.04], [0.025, 0.028, 0.05]
    rows = [{"method": m, "unit": u, "course": {"lateral_mae": v}}
            for m, values in (("mixed", mixed), ("model", model)) for u, v in enumerate(values)]
    got = ES.paired(rows, "lateral_mae")
    d = np.array(model) - np.array(mixed)
    assert got["units"] == 3 and got["mixed_better"] == 2
    assert got["difference_mean"] == pytest.approx(d.mean())
    assert got["difference_sd"] == pytest.approx(d.std(ddof=1))
    assert got["mixed_mean"] == pytest.approx(0.03) and got["mixed_sd"] == pytest.approx(0.01)


def test_an_ensemble_size_without_two_pairs_is_refused_before_training(tmp_path: Path) -> None:
    with pytest.raises(SystemExit, match="--sizes"):
        ES.main(["--runs", "6", "--sizes", "1", "4", "--cache", str(tmp_path / "cache")])
    assert not (tmp_path / "cache").exists()
