"""Tests of run directories, checkpoints, the config object and the shared training loop (mixedrl.runs,
mixedrl.config): atomic files, corrupted checkpoints, unknown keys, resume == uninterrupted."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import pytest
import torch

from mixedrl.config import TrainConfig
from mixedrl.runs import (
    RunDirectory,
    iterations_to_converge,
    load_checkpoint,
    make_trainer,
    save_checkpoint,
    train,
)

#: A short run of the default learner (its model rollouts cut to 4 steps: the plumbing, not the learning, is
#: under test).
FAST = dict(task="linear", algorithm=dict(iterations=40, batch_size=32, rollout_horizon=4),
            ddpg=dict(warmup=64, envs=8, batch_size=32), run=dict(eval_every=20, checkpoint_every=10, eval_seeds=1))


# ------------------------------------------------------------------------------ config
def test_config_round_trip_and_unknown_keys(tmp_path: Path) -> None:
    cfg = TrainConfig(method="model", seed=3, algorithm=dict(hidden_sizes=(16, 8), grad_clip=math.inf))
    path = tmp_path / "config.json"
    cfg.save(path)
    assert TrainConfig.load(path) == cfg
    with pytest.raises(ValueError, match="^config: unknown key.*'batchsize'"):
        TrainConfig.from_dict({**cfg.to_dict(), "batchsize": 3})
    with pytest.raises(ValueError, match="^config"):
        cfg.replace(lerning_rate=1.0)
    path.write_text("{not json")
    with pytest.raises(ValueError, match="^path"):
        TrainConfig.load(path)


@pytest.mark.parametrize("field,value", [("method", "ppo"), ("algorithm.iterations", 0), ("algorithm.batch_size", -1),
                                          ("algorithm.critic_lr", float("nan")), ("algorithm.mvc_check", "some"),
                                          ("seed", -2), ("ddpg.tau", 1.5), ("algorithm.expectation", "exact"),
                                          ("algorithm.hidden_sizes", ()), ("task", "cartpole")])
def test_config_rejects_bad_values(field: str, value: object) -> None:
    with pytest.raises(ValueError, match=f"^{field}"):  # the dotted key
        TrainConfig().replace(**{field: value})


# ------------------------------------------------------------------------------ checkpoints
def test_checkpoint_round_trip_is_atomic(tmp_path: Path) -> None:
    path = tmp_path / "checkpoint.pt"
    state = {"w": torch.arange(5.0), "k": 7, "gen": torch.Generator().manual_seed(1).get_state()}
    save_checkpoint(path, state)
    loaded = load_checkpoint(path)
    assert loaded["k"] == 7 and torch.equal(loaded["w"], state["w"]) and torch.equal(loaded["gen"], state["gen"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.pt", "checkpoint.pt.sha256"]  # no temporary file left


def test_failed_write_keeps_previous_checkpoint(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "checkpoint.pt"
    save_checkpoint(path, {"k": 1})

    def broken_replace(src: str, dst: str) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", broken_replace)
    with pytest.raises(OSError):
        save_checkpoint(path, {"k": 2})
    monkeypatch.undo()
    assert load_checkpoint(path)["k"] == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.pt", "checkpoint.pt.sha256"]


def test_corrupted_checkpoint_raises_value_error(tmp_path: Path) -> None:
    path = tmp_path / "checkpoint.pt"
    save_checkpoint(path, {"w": torch.zeros(1000)})
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])  # truncated
    with pytest.raises(ValueError, match="^checkpoint"):
        load_checkpoint(path)
    path.write_bytes(b"garbage" * 100)
    with pytest.raises(ValueError, match="^checkpoint"):
        load_checkpoint(path)
    torch.save({"something": 1}, path)  # a valid torch file, but not ours
    with pytest.raises(ValueError, match="^checkpoint"):
        load_checkpoint(path)
    with pytest.raises(ValueError, match="^checkpoint"):
        load_checkpoint(tmp_path / "missing.pt")


def test_resume_with_corrupted_checkpoint_is_a_clear_error(tmp_path: Path) -> None:
    cfg = TrainConfig(method="model", **FAST)
    train(make_trainer(cfg), RunDirectory(tmp_path), stop_after=10)
    (tmp_path / "checkpoint.pt").write_bytes(b"\x00" * 10)
    with pytest.raises(ValueError, match="^checkpoint"):
        train(make_trainer(cfg), RunDirectory(tmp_path), resume=True)


# ------------------------------------------------------------------------------ convergence criterion
def test_iterations_to_converge() -> None:
    its = [100, 200, 300, 400, 500, 600]
    # settles at 300: every later cost within 10% of the final level (median of the last three = 1.0)
    assert iterations_to_converge(its, [9.0, 3.0, 1.05, 0.98, 1.0, 1.02]) == 300
    # a late excursion above the band moves the convergence point after it
    assert iterations_to_converge(its, [9.0, 1.0, 1.0, 1.5, 1.0, 1.0]) == 500
    assert iterations_to_converge(its, [1.0] * 6) == 100
    assert iterations_to_converge(its, [1.0, 1.0, 1.0, 1.0, 1.0, float("nan")]) == 600
    with pytest.raises(ValueError, match="^iterations"):
        iterations_to_converge([], [])


# ------------------------------------------------------------------------------ run directory and resume
@pytest.mark.parametrize("method", ["mixed", "ddpg"])
def test_run_directory_files(tmp_path: Path, method: str) -> None:
    cfg = TrainConfig(method=method, **FAST)
    res = train(make_trainer(cfg), RunDirectory(tmp_path))
    names = {p.name for p in tmp_path.iterdir()}
    assert {"config.json", "checkpoint.pt", "metrics.jsonl", "metrics.csv", "results.json"} <= names
    assert TrainConfig.load(tmp_path / "config.json") == cfg
    rows = RunDirectory(tmp_path).read_metrics()
    assert [r["iteration"] for r in rows] == list(range(1, 41))
    assert "eval/cost" in rows[19] and "eval/cost" not in rows[18]
    assert "train/critic_loss" in rows[0]
    if method == "mixed":
        assert {"ibe/mean_error", "mvc/held", "mvc/inner_steps"} <= set(rows[0])
    assert json.loads((tmp_path / "results.json").read_text())["iterations"] == res["iterations"] == 40


GRADE = {"disturbance": {"grade_amplitude": 0.02}}


@pytest.mark.parametrize("method,task,extra", [("mixed", "linear", {}), ("model", "linear", {}), ("ddpg", "linear", {}),
                                               ("mixed", "dlc", {}), ("ddpg", "dlc", {}),
                                               ("mixed", "linear", {"ibe_case": 3}),
                                               ("mixed", GRADE, {"ibe_case": 3, "batch_size": 16}),
                                               ("oracle", GRADE, {"batch_size": 16})])  # algorithm fields
def test_resume_equals_uninterrupted(tmp_path: Path, method: str, task: Any, extra: dict) -> None:
    cfg = TrainConfig(method=method, **{**FAST, "task": task, "algorithm": {**FAST["algorithm"], **extra}})
    full = make_trainer(cfg)
    train(full, RunDirectory(tmp_path / "full"))
    first = make_trainer(cfg)
    out = train(first, RunDirectory(tmp_path / "cut"), stop_after=17)  # interrupted between checkpoints
    assert out == {"interrupted_at": 17}
    resumed = make_trainer(cfg)
    train(resumed, RunDirectory(tmp_path / "cut"), resume=True)
    for a, b in zip(full.state_dict()["actor"].values(), resumed.state_dict()["actor"].values()):
        assert torch.equal(a, b)
    for a, b in zip(full.state_dict()["critic"].values(), resumed.state_dict()["critic"].values()):
        assert torch.equal(a, b)
    rows_full = RunDirectory(tmp_path / "full").read_metrics()
    rows_cut = RunDirectory(tmp_path / "cut").read_metrics()
    strip = [{k: v for k, v in r.items() if not k.startswith("time/")} for r in rows_full]
    assert strip == [{k: v for k, v in r.items() if not k.startswith("time/")} for r in rows_cut]


def test_resume_rejects_a_changed_config(tmp_path: Path) -> None:
    cfg = TrainConfig(method="model", **FAST)
    train(make_trainer(cfg), RunDirectory(tmp_path), stop_after=10)
    with pytest.raises(ValueError, match="^config"):
        train(make_trainer(cfg.replace(**{"algorithm.actor_lr": 0.5})), RunDirectory(tmp_path), resume=True)
