"""Tests of the Table I reproduction (validation/reproduce.py) and of seeded short runs on the double lane
change: the IBE moves to the truth, mixed RL beats model-driven RL on speed error."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from validation.reproduce import METHODS, PAPER, check_targets, format_table


def _fake_results() -> dict:
    def entry(lat: float, spd: float, its: float) -> dict:
        runs = [{"seed": s, "lateral_mae": lat + 0.01 * s, "speed_mae": spd, "iterations_to_converge": its,
                 "train_seconds": 60.0} for s in range(2)]
        return {"runs": runs, "lateral_mae_mean": lat + 0.005, "lateral_mae_std": 0.007, "speed_mae_mean": spd,
                "speed_mae_std": 0.0, "iterations_to_converge_mean": its, "iterations_to_converge_std": 0.0,
                "train_seconds_mean": 60.0, "train_seconds_std": 0.0}
    res = {"paper": PAPER, "quick": False, "wall_seconds": 100.0, "convergence_criterion": "c",
           "mixed": entry(0.10, 0.010, 3000), "model": entry(0.12, 0.030, 3000), "ddpg": entry(0.20, 0.04, 7000),
           "oracle": entry(0.10, 0.0095, 3000)}
    res["mixed"]["final_ibe_mean"] = [[0, 0, 261.0 * 0.005 / 1500 * 1.01, 0, 0]]
    return res


def test_paper_values_are_table_one() -> None:
    assert PAPER["mixed"]["lateral_mae"] == 0.151 and PAPER["mixed"]["speed_mae"] == 0.021
    assert PAPER["ddpg"]["lateral_mae"] == 0.228 and PAPER["ddpg"]["speed_mae"] == 0.093
    assert PAPER["model"]["lateral_mae"] == 0.179 and PAPER["model"]["speed_mae"] == 0.051


def test_targets_and_table_on_known_numbers() -> None:
    res = _fake_results()
    t = check_targets(res)
    assert t["mixed_lateral_le_0.151"] and t["mixed_speed_le_0.021"]
    assert t["order_speed_mixed_lt_model_lt_ddpg"] and t["order_lateral_mixed_lt_model_lt_ddpg"]
    assert t["speed_gap_vs_model"] == pytest.approx(1 - 0.010 / 0.030)
    assert t["speed_gap_vs_model_ge_0.58"] and not t["speed_gap_vs_ddpg_ge_0.77"]  # 1 - 0.010/0.04 = 0.75
    assert t["ddpg_needs_2x_mixed"] and t["ibe_mean_within_2pct"]
    assert t["mixed_within_10pct_of_oracle"]
    table = format_table({**res, "targets": t})
    for number in ("0.151", "0.179", "0.228", "0.021", "0.051", "0.093"):
        assert number in table
    assert all(label in table for label in ("Mixed RL", "Model-driven RL", "DDPG", "Oracle"))


@pytest.mark.regression
@pytest.mark.slow
def test_reproduce_quick_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``mixedrl reproduce --quick``: every method and seed trained, results.json with the documented
    schema, the five figures, the table with the paper's numbers, the theory summary; the IBE mean of
    every mixed run ends within 2% of the true disturbance mean."""
    from mixedrl.cli import main

    out = tmp_path / "repro"
    assert main(["reproduce", "--quick", "--seeds", "2", "--out", str(out), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "0.151" in printed and "Mixed RL" in printed
    res = json.loads((out / "results.json").read_text())
    assert res["paper"]["mixed"]["speed_mae"] == 0.021
    for method in METHODS:
        runs = res[method]["runs"]
        assert [r["seed"] for r in runs] == [0, 1]
        for r in runs:
            assert set(r) >= {"seed", "lateral_mae", "speed_mae", "iterations_to_converge", "train_seconds"}
            assert np.isfinite(r["lateral_mae"]) and np.isfinite(r["speed_mae"])
        assert res[method]["lateral_mae_mean"] == pytest.approx(np.mean([r["lateral_mae"] for r in runs]))
        assert res[method]["speed_mae_mean"] == pytest.approx(np.mean([r["speed_mae"] for r in runs]))
    for method in ("mixed", "model", "oracle"):
        th = res[method]["theory"]
        assert 0.0 <= th["value_decrease"] <= 1.0 and 0.0 <= th["mvc_pointwise"] <= 1.0
    true_mean = 261.0 * (1 / 200) / 1500
    for mean in res["mixed"]["final_ibe_mean"]:
        assert abs(mean[2] - true_mean) <= 0.02 * true_mean
    for name in ("fig2_convergence", "fig3_trajectory", "fig4_speed_error", "fig5_lateral_error",
                 "fig6_ibe_effect"):
        assert (out / "figures" / f"{name}.png").stat().st_size > 1000
