"""Tests of the ``mixedrl`` command line (mixedrl.cli)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from mixedrl.cli import build_parser, main, parse_overrides
from mixedrl.config import TrainConfig
from mixedrl.runs import RunDirectory

REPO = Path(__file__).resolve().parents[1]
SMALL = ["task=\"linear\"", "batch_size=32", "eval_every=20", "checkpoint_every=10", "eval_seeds=1",
         "ddpg_warmup=64", "ddpg_envs=8"]


def test_parse_overrides() -> None:
    assert parse_overrides(["a=1", "b=[1, 2]", "c=linear", "d=\"x\"", "e=1e-3"]) == {
        "a": 1, "b": [1, 2], "c": "linear", "d": "x", "e": 1e-3}
    with pytest.raises(ValueError, match="^--set"):
        parse_overrides(["novalue"])


def test_train_then_evaluate(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "run"
    assert main(["train", "--method", "mixed", "--seed", "2", "--out", str(out), "--iterations", "20",
                 "--no-progress", "--set", *SMALL]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["method"] == "mixed" and printed["seed"] == 2 and printed["iterations"] == 20
    cfg = TrainConfig.load(out / "config.json")
    assert (cfg.method, cfg.seed, cfg.iterations, cfg.task) == ("mixed", 2, 20, "linear")
    assert main(["evaluate", str(out)]) == 0
    ev = json.loads(capsys.readouterr().out)
    assert ev["iteration"] == 20 and ev["cost"] == pytest.approx(RunDirectory(out).read_results()["final"]["cost"])


def test_train_resume_finishes_an_interrupted_run(tmp_path: Path) -> None:
    from mixedrl.runs import make_trainer, train

    full, cut = tmp_path / "full", tmp_path / "cut"
    args = ["--method", "ddpg", "--seed", "1", "--iterations", "30", "--no-progress", "--set", *SMALL]
    assert main(["train", "--out", str(full), *args]) == 0
    cfg = TrainConfig.load(full / "config.json")
    train(make_trainer(cfg), RunDirectory(cut), stop_after=15)  # an interruption after iteration 15
    assert main(["train", "--out", str(cut), "--resume", *args]) == 0
    assert RunDirectory(cut).read_results()["final"] == RunDirectory(full).read_results()["final"]


def test_bad_input_is_a_one_line_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["train", "--method", "mixed", "--out", str(tmp_path / "r"), "--no-progress",
                 "--set", "batchsize=3"]) == 2
    err = capsys.readouterr().err
    assert "unknown key" in err and "batchsize" in err
    assert main(["evaluate", str(tmp_path / "nothing")]) == 2
    with pytest.raises(SystemExit):
        build_parser().parse_args(["train", "--method", "ppo", "--out", "x"])


def test_console_entry_point_help() -> None:
    proc = subprocess.run([sys.executable, "-m", "mixedrl.cli", "--help"], cwd=REPO, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0
    for cmd in ("train", "evaluate", "reproduce"):
        assert cmd in proc.stdout
