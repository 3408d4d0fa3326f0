"""Tests of the ``mixedrl`` command line (mixedrl.cli)."""

from __future__ import annotations

import argparse
import json
import logging
import subprocess
import sys
from importlib.metadata import EntryPoint
from pathlib import Path

import pytest

import mixedrl.cli
from mixedrl.cli import COMMAND_GROUP, build_parser, main, parse_overrides
from mixedrl.config import TrainConfig
from mixedrl.runs import RunDirectory

REPO = Path(__file__).resolve().parents[1]
SMALL = ["task=\"linear\"", "algorithm.batch_size=32", "run.eval_every=20", "run.checkpoint_every=10",
         "run.eval_seeds=1", "ddpg.warmup=64", "ddpg.envs=8", "ddpg.batch_size=32"]


def test_parse_overrides() -> None:
    assert parse_overrides(["a=1", "b=[1, 2]", "c=linear", "d=\"x\"", "e=1e-3"]) == {
        "a": 1, "b": [1, 2], "c": "linear", "d": "x", "e": 1e-3}
    with pytest.raises(ValueError, match="^--set"):
        parse_overrides(["novalue"])


def test_repeated_set_flags_add_up(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--set a=1 --set b=2`` applies both (argparse's default would keep only the last flag's values)."""
    out = tmp_path / "run"
    assert main(["train", "--method", "model", "--out", str(out), "--iterations", "2", "--no-progress",
                 "--set", *SMALL, "--set", "task.init_box=0.25"]) == 0
    cfg = TrainConfig.load(out / "config.json")
    assert cfg.task.name == "linear" and cfg.task.init_box == 0.25
    printed = json.loads(capsys.readouterr().out)
    assert printed["cost_over_lqr"] == pytest.approx(printed["cost"] / printed["lqr_true_mean_cost"])


def test_train_then_evaluate(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "run"
    assert main(["train", "--method", "mixed", "--seed", "2", "--out", str(out), "--iterations", "20",
                 "--no-progress", "--set", *SMALL]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["method"] == "mixed" and printed["seed"] == 2 and printed["iterations"] == 20
    cfg = TrainConfig.load(out / "config.json")
    assert (cfg.method, cfg.seed, cfg.algorithm.iterations, cfg.task.name) == ("mixed", 2, 20, "linear")
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


def test_dotted_set_reaches_the_task_and_config_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--set task.x=...`` sets nested fields; the run's config.json holds the whole task configuration and
    the trainer's task is built from it."""
    out = tmp_path / "run"
    assert main(["train", "--method", "model", "--out", str(out), "--iterations", "2", "--no-progress", "--set",
                 *SMALL, "task.prior_mean=[0, -2]", "task.gamma=0.8", "task.disturbance.mean=[0, 1]"]) == 0
    capsys.readouterr()
    saved = json.loads((out / "config.json").read_text())["task"]
    assert saved["prior_mean"] == [0.0, -2.0] and saved["gamma"] == 0.8 and saved["disturbance"]["mean"] == [0.0, 1.0]
    assert saved["A"] == [[1.0, 0.1], [0.0, 1.0]] and saved["prior_cov"] == [[0.01, 0.0], [0.0, 0.01]]
    from mixedrl.runs import make_trainer

    task = make_trainer(TrainConfig.load(out / "config.json")).task
    assert task.gamma == 0.8 and list(task.prior_mean) == [0.0, -2.0] and list(task.true_mean) == [0.0, 1.0]


def test_nested_config_file_with_dotted_set(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    spec = tmp_path / "experiment.json"
    spec.write_text(json.dumps({"task": {"name": "linear", "prior_cov": [[0.04, 0], [0, 0.04]],
                                         "disturbance": {"cov": [[0, 0], [0, 0.02]]}}, "algorithm": {"batch_size": 32}}))
    out = tmp_path / "run"
    assert main(["train", "--method", "mixed", "--out", str(out), "--iterations", "2", "--no-progress",
                 "--config", str(spec), "--set", "run.eval_every=1", "run.eval_seeds=1", "task.init_box=0.5"]) == 0
    capsys.readouterr()
    cfg = TrainConfig.load(out / "config.json")
    assert cfg.algorithm.batch_size == 32 and cfg.task.name == "linear" and cfg.task.init_box == 0.5
    assert cfg.task.prior_cov == ((0.04, 0.0), (0.0, 0.04)) and cfg.task.disturbance.cov == ((0.0, 0.0), (0.0, 0.02))


def test_unknown_nested_key_is_a_one_line_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["train", "--method", "mixed", "--out", str(tmp_path / "r"), "--no-progress",
                 "--set", "task.prior_mena=300"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unknown key" in err and "'task.prior_mena'" in err
    assert main(["train", "--method", "mixed", "--out", str(tmp_path / "r"), "--no-progress",
                 "--set", "task.disturbance.law=cauchy"]) == 2
    assert capsys.readouterr().err.startswith("mixedrl train: error: task.disturbance.law:")


def test_evaluate_of_an_old_run_directory_names_the_release_that_reads_it(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A run written before the task configuration existed (``"task": "linear"`` and a top-level
    ``train_half_widths`` in config.json): a one-line error naming the release that reads it."""
    out = tmp_path / "run"
    assert main(["train", "--method", "mixed", "--out", str(out), "--iterations", "2", "--no-progress",
                 "--set", *SMALL]) == 0
    capsys.readouterr()
    assert main(["evaluate", str(out)]) == 0
    assert json.loads(capsys.readouterr().out)["iteration"] == 2
    old = {**json.loads((out / "config.json").read_text()), "task": "linear",
           "train_half_widths": [0.3, 0.2, 1.0, 0.1, 1.0]}
    (out / "config.json").write_text(json.dumps(old))
    (out / "config.json.sha256").unlink()
    assert main(["evaluate", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "['train_half_widths'] at the top level is the flat form, read by mixedrl 0.1.0 at " \
        "git commit b510485" in err


# ------------------------------------------------------------------------------ command plug-ins
def _hello_register(subparsers: argparse._SubParsersAction) -> object:
    subparsers.add_parser("hello").add_argument("--name", default="world")

    def handler(args: argparse.Namespace) -> int:
        print(f"hello {args.name}")
        if args.name == "bad":
            raise ValueError("name: bad")
        return 0
    return handler


def _broken_register(subparsers: argparse._SubParsersAction) -> object:
    raise ImportError("missing optional dependency")


def test_command_plugins_register_and_broken_ones_are_skipped(monkeypatch: pytest.MonkeyPatch,
                                                              capsys: pytest.CaptureFixture[str],
                                                              caplog: pytest.LogCaptureFixture) -> None:
    eps = [EntryPoint("hello", f"{__name__}:_hello_register", COMMAND_GROUP),
           EntryPoint("broken", f"{__name__}:_broken_register", COMMAND_GROUP)]
    monkeypatch.setattr(mixedrl.cli, "command_plugins", lambda: eps)
    with caplog.at_level(logging.WARNING, logger="mixedrl.cli"):
        assert main(["hello", "--name", "you"]) == 0
    assert capsys.readouterr().out == "hello you\n"
    assert any("broken" in r.getMessage() and "missing optional dependency" in r.getMessage() for r in caplog.records)
    assert main(["hello", "--name", "bad"]) == 2
    assert "mixedrl hello: error: name: bad" in capsys.readouterr().err
    assert main(["evaluate", "/nonexistent/run"]) == 2  # the built-in commands still work


def test_reproduce_is_an_installed_plugin() -> None:
    """The reproduction reaches the CLI through the entry point, not through an import of the core."""
    assert "reproduce" in {ep.name for ep in mixedrl.cli.command_plugins()}
    parser = build_parser()
    args = parser.parse_args(["reproduce", "--seeds", "5", "--out", "D", "--quick", "--resume", "--workers", "1",
                              "--no-progress"])
    assert (args.seeds, str(args.out), args.quick, args.resume, args.workers, args.no_progress) == (
        5, "D", True, True, 1, True)
    assert args.handler.__module__ == "validation.reproduce"
