"""The holes of issue 43 in run directories, checkpoints, sweeps and the command line: every refusal is one
line naming the argument or file (exit 2) and changes nothing on disk, and a run killed at any write of
its protocol resumes to the result of an uninterrupted run."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import torch

import mixedrl.checkpoint
import mixedrl.sweep
import mixedrl.sweep_spec
from mixedrl.cli import main
from mixedrl.config import TrainConfig
from mixedrl.runs import RunDirectory, hold_lock, load_checkpoint, make_trainer, save_checkpoint, train
from test_run_safety import refused

#: A fast run on the linear task (4 iterations, a checkpoint every 2).
SET = ["--set", 'task="linear"', "algorithm.iterations=4", "algorithm.batch_size=32", "run.eval_every=2",
       "run.checkpoint_every=2", "run.eval_seeds=1"]
TRAIN = ["train", "--method", "mixed", "--no-progress"]
CONFIG = TrainConfig.from_dict({"method": "mixed", "seed": 1, "task": "linear",
                                "algorithm": {"iterations": 4, "batch_size": 32},
                                "run": {"eval_every": 2, "checkpoint_every": 2, "eval_seeds": 1}})


@pytest.fixture(scope="module")
def finished(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("finished") / "run"
    assert main([*TRAIN, "--out", str(out), *SET]) == 0
    return out


# ---------------------------------------------------------------------------------------------------
# item 1: the lock file never follows a link and a directory holding a foreign .lock is not a run
# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("resume", [False, True], ids=["train", "resume"])
@pytest.mark.parametrize("kind", ["symlink", "hardlink", "other-content"])
def test_planted_lock_destroys_nothing(tmp_path: Path, kind: str, resume: bool,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    victim = tmp_path / "victim"
    victim.write_text("precious\n")
    out = tmp_path / "x"
    out.mkdir()
    if kind == "symlink":
        (out / ".lock").symlink_to(victim)
    elif kind == "hardlink":
        os.link(victim, out / ".lock")
    else:
        (out / ".lock").write_text("precious\n")
    refused([*TRAIN, "--out", str(out), *SET, *(["--resume"] if resume else [])], capsys, tmp_path, ".lock")
    assert victim.read_text() == "precious\n"


def test_lock_left_by_a_killed_run_is_not_foreign(run_copy: Path, tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """The lock a finished (or killed) run leaves is the package's: a new run there starts."""
    out = tmp_path / "fresh"
    out.mkdir()
    shutil.copy(run_copy / ".lock", out / ".lock")
    assert main([*TRAIN, "--out", str(out), *SET]) == 0
    assert (out / "results.json").is_file()


# ---------------------------------------------------------------------------------------------------
# item 2: config.json has a digest, verified by evaluate and --resume
# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("command", ["evaluate", "resume"])
def test_edited_config_is_refused(run_copy: Path, command: str, capsys: pytest.CaptureFixture[str]) -> None:
    path = run_copy / "config.json"
    record = json.loads(path.read_text())
    record["task"]["q_lateral"] = 2.0 * record["task"].get("q_lateral", 1.0)
    path.write_text(json.dumps(record, indent=2, sort_keys=True) + "\n")
    args = ["evaluate", str(run_copy)] if command == "evaluate" else [*TRAIN, "--out", str(run_copy), "--resume"]
    refused(args, capsys, run_copy, f"config: {path} is corrupted")


# ---------------------------------------------------------------------------------------------------
# item 3: a kill at any write of the protocol leaves a run that resumes to the uninterrupted result
# ---------------------------------------------------------------------------------------------------
class Killed(BaseException):
    """A simulated kill -9 (not an Exception: nothing catches it)."""


def _outcome(path: Path) -> dict[str, Any]:
    """What an interrupted and resumed run must share with an uninterrupted one (times left out, and the
    plant's evaluation transitions: an evaluation the kill interrupted is run again, and counted again)."""
    run = RunDirectory(path)
    results = {k: v for k, v in run.read_results().items() if k != "train_seconds"}
    results["plant_transitions"] = {k: v for k, v in results["plant_transitions"].items() if k != "evaluation"}
    rows = [{k: v for k, v in r.items() if k != "time/elapsed_s"} for r in run.read_metrics()]
    trainer = load_checkpoint(run.checkpoint_path)["trainer"]
    names = sorted(n for n in os.listdir(path) if not n.endswith(".tmp"))
    weights = {f"{net}.{name}": t.numpy().tobytes() for net in ("actor", "critic") for name, t in trainer[net].items()}
    return {"results": results, "rows": rows, "weights": weights, "k": trainer["k"],
            "config": run.read_record(), "names": names}


def _kill_at(n: int, monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Make the ``n``-th write of a run (an atomic file write or an append of metrics rows) die half-way:
    an atomic write leaves its temporary file, an append half of its bytes. Returns the write counter."""
    count = [0]
    atomic, append = mixedrl.checkpoint.atomic_write_bytes, RunDirectory.append_metrics

    def atomic_write_bytes(path: str | Path, data: bytes) -> None:
        count[0] += 1
        if count[0] == n:
            path = Path(path)
            (path.parent / f".{path.name}.killed.tmp").write_bytes(data[: len(data) // 2])
            raise Killed
        atomic(path, data)

    def append_metrics(self: RunDirectory, rows: list[dict[str, Any]]) -> None:
        if rows:
            count[0] += 1
            if count[0] == n:
                text = "".join(json.dumps(r) + "\n" for r in rows)
                with open(self.metrics_path, "a") as fh:
                    fh.write(text[: len(text) // 2 + 1])
                raise Killed
        append(self, rows)

    monkeypatch.setattr(mixedrl.checkpoint, "atomic_write_bytes", atomic_write_bytes)
    monkeypatch.setattr(RunDirectory, "append_metrics", append_metrics)
    return count


def test_a_kill_at_every_write_resumes_to_the_uninterrupted_run(tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    with monkeypatch.context() as m:
        count = _kill_at(0, m)
        train(make_trainer(CONFIG), RunDirectory(tmp_path / "whole"), progress=False)
    writes = count[0]
    reference = _outcome(tmp_path / "whole")
    assert writes >= 12  # config, metrics and checkpoints at 2 and 4, csv, results (each with its digest)
    for n in range(1, writes + 1):
        out = tmp_path / f"killed{n}"
        with monkeypatch.context() as m:
            _kill_at(n, m)
            with pytest.raises(Killed):
                train(make_trainer(CONFIG), RunDirectory(out), progress=False)
        train(make_trainer(CONFIG), RunDirectory(out), resume=True, progress=False)
        assert _outcome(out) == reference, f"killed at write {n} of {writes}"
        evaluated, whole = (RunDirectory(p).read_results()["plant_transitions"]["evaluation"]
                            for p in (out, tmp_path / "whole"))
        assert evaluated >= whole and evaluated % 6400 == 0, (n, evaluated, whole)  # whole evaluations only


def test_resume_after_a_kill_before_anything_was_written(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A run killed right after taking its lock (or while writing its first config.json) resumes from scratch
    on the command line; an empty directory is still not a run to resume."""
    out = tmp_path / "run"
    with pytest.raises(Killed):
        with RunDirectory(out).lock():
            (out / ".config.json.sha256.abc_1.tmp").write_text("half")
            raise Killed
    assert main([*TRAIN, "--out", str(out), *SET, "--resume"]) == 0
    assert RunDirectory(out).read_results()["iterations"] == 4
    (tmp_path / "empty").mkdir()
    refused([*TRAIN, "--out", str(tmp_path / "empty"), *SET, "--resume"], capsys, tmp_path, "holds no run")


def test_metrics_without_their_checkpoint_are_refused(run_copy: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Rows beyond the first checkpoint without checkpoint.pt: the checkpoint was removed, not never written."""
    (run_copy / "checkpoint.pt").unlink()
    (run_copy / "checkpoint.pt.sha256").unlink()
    (run_copy / "results.json").unlink()
    (run_copy / "results.json.sha256").unlink()
    (run_copy / "metrics.csv").unlink()
    refused([*TRAIN, "--out", str(run_copy), "--resume"], capsys, run_copy, "has no checkpoint.pt")


def test_a_checkpoint_without_its_config_is_refused(run_copy: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (run_copy / "config.json").unlink()
    refused([*TRAIN, "--out", str(run_copy), *SET, "--resume"], capsys, run_copy, "no config.json")


def test_a_sweep_run_killed_in_its_first_checkpoint_resumes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    """Inside a sweep: a run killed between its first metrics rows and its checkpoint is resumed by --resume
    (not failed on every --resume), to the result of an uninterrupted sweep."""
    spec = _spec(tmp_path, SPEC)
    args = ["sweep", str(spec), "--workers", "1", "--no-progress"]
    assert main([*args, "--out", str(tmp_path / "whole")]) == 0
    with monkeypatch.context() as m:
        _kill_at(4, m)  # spec.toml, config.json's digest, config.json, then the metrics rows
        with pytest.raises(Killed):
            main([*args, "--out", str(tmp_path / "killed")])
    run = tmp_path / "killed" / "runs" / "model_seed0"
    assert (run / "metrics.jsonl").is_file() and not (run / "checkpoint.pt").exists()
    capsys.readouterr()
    assert main([*args, "--out", str(tmp_path / "killed"), "--resume"]) == 0
    docs = [json.loads((tmp_path / d / "sweep.json").read_text()) for d in ("whole", "killed")]
    assert docs[1]["failed"] == 0 and docs[1]["finished"] is True
    assert [{k: v for k, v in r["metrics"].items()} for r in docs[1]["runs"]] == \
        [{k: v for k, v in r["metrics"].items()} for r in docs[0]["runs"]]


# ---------------------------------------------------------------------------------------------------
# item 6: a checkpoint's record is checked field by field
# ---------------------------------------------------------------------------------------------------
def _edit_k(state: dict) -> None:
    state["trainer"]["k"] = -5


def _drop_trainer(state: dict) -> None:
    del state["trainer"]


def _empty_trainer(state: dict) -> None:
    state["trainer"] = {}


def _list_trainer(state: dict) -> None:
    state["trainer"] = [1, 2]


def _nan_elapsed(state: dict) -> None:
    state["elapsed"] = float("nan")


def _list_weights(state: dict) -> None:
    state["trainer"]["actor"] = [torch.zeros(2)]


def _int_weights(state: dict) -> None:
    name = next(iter(state["trainer"]["critic"]))
    state["trainer"]["critic"][name] = state["trainer"]["critic"][name].long()


def _k_beyond_budget(state: dict) -> None:
    state["trainer"]["k"] = 10**6


@pytest.mark.parametrize("edit, field", [
    (_edit_k, "field trainer.k is -5"), (_drop_trainer, "field trainer is missing"),
    (_empty_trainer, "field trainer.k is None"), (_list_trainer, "field trainer is list"),
    (_nan_elapsed, "field elapsed is nan"), (_list_weights, "field trainer.actor is a list"),
    (_int_weights, "field trainer.critic."), (_k_beyond_budget, "field trainer.k is 1000000"),
], ids=["negative-k", "no-trainer", "empty-trainer", "list-trainer", "nan-elapsed", "list-weights",
        "int-weights", "k-beyond-budget"])
@pytest.mark.parametrize("command", ["evaluate", "resume"])
def test_crafted_checkpoint_is_refused_naming_the_field(run_copy: Path, edit: Any, field: str, command: str,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    path = run_copy / "checkpoint.pt"
    state = load_checkpoint(path)
    edit(state)
    save_checkpoint(path, state)  # a valid sidecar: the digest does not catch it
    args = ["evaluate", str(run_copy)] if command == "evaluate" else [*TRAIN, "--out", str(run_copy), "--resume"]
    refused(args, capsys, run_copy, f"checkpoint: {path} {field}")


# ---------------------------------------------------------------------------------------------------
# item 9: one line naming the argument or file, nothing created
# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("line, match", [
    (b"[1, 2]\n", "line 5 is a JSON list"),
    (b'{"iteration": "5"}\n', "line 5 has iteration '5'"),
    (b'{"iteration": 5, "x": "\xff"}\n', "line 5 is not UTF-8"),
], ids=["list", "string-iteration", "invalid-utf8"])
def test_bad_metrics_rows_are_one_line(run_copy: Path, line: bytes, match: str,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    path = run_copy / "metrics.jsonl"
    with open(path, "ab") as fh:
        fh.write(line)
    refused([*TRAIN, "--out", str(run_copy), "--resume", "--iterations", "6"], capsys, run_copy,
            f"metrics: {path} {match}")


def test_checkpoint_link_to_dev_zero(run_copy: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = run_copy / "checkpoint.pt"
    path.unlink()
    path.symlink_to("/dev/zero")
    for args in (["evaluate", str(run_copy)], [*TRAIN, "--out", str(run_copy), "--resume"]):
        refused(args, capsys, run_copy, f"checkpoint: {path} is a symbolic link")


def test_out_symlink_loop(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "loop").symlink_to("loop")
    for extra in ([], ["--resume"]):
        refused([*TRAIN, "--out", str(tmp_path / "loop"), *SET, *extra], capsys, tmp_path, "symbolic link")


@pytest.mark.parametrize("seed", ["18446744073709551616", "-1"])
def test_seed_out_of_range(tmp_path: Path, seed: str, capsys: pytest.CaptureFixture[str]) -> None:
    refused([*TRAIN, "--out", str(tmp_path / "o"), "--seed", seed, *SET], capsys, tmp_path, "--seed")


# ---------------------------------------------------------------------------------------------------
# sweeps: item 8 (grid size, duplicates), item 9 (dates, seeds, a directory as spec), item 4 (one driver)
# ---------------------------------------------------------------------------------------------------
SPEC = """methods = ["model"]
seeds = [0]

[base]
task = "linear"
"algorithm.iterations" = 2
"algorithm.batch_size" = 32
"run.eval_every" = 2
"run.eval_seeds" = 1
"""


def _spec(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "spec.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("tail, match", [
    ('\n[grid]\n"task.prior_force_mean" = [1979-05-27]\n', "grid.task.prior_force_mean: 1979-05-27 is a TOML date"),
    ('\n[grid]\n"algorithm.critic_lr" = [1, 1.0]\n', "have the same config"),
    ('\n[grid]\n"algorithm.actor_lr" = [1, 2]\n"algorithm.critic_lr" = ' + str(list(range(1, 5002))) + "\n",
     "expands to 10002 runs, more than the 10000"),
], ids=["toml-date", "int-float-duplicate", "too-many-runs"])
def test_bad_sweep_grids_are_one_line(tmp_path: Path, tail: str, match: str,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    spec = _spec(tmp_path, SPEC + tail)
    refused(["sweep", str(spec), "--out", str(tmp_path / "out"), "--workers", "1", "--no-progress"], capsys,
            tmp_path, match)


def test_force_accepts_a_large_grid(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(mixedrl.sweep_spec, "MAX_RUNS", 2)  # parse_spec reads it there (re-exported by mixedrl.sweep)
    text = SPEC + '\n[grid]\n"algorithm.critic_lr" = [0.001, 0.002, 0.003]\n'
    with pytest.raises(ValueError, match="^grid: spec expands to 3 runs, more than the 2"):
        mixedrl.sweep.parse_spec(text)
    assert len(mixedrl.sweep.expand(mixedrl.sweep.parse_spec(text, force=True))) == 3


def test_sweep_argument_errors_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    refused(["sweep", str(tmp_path), "--out", str(tmp_path / "out")], capsys, tmp_path, "is a directory")
    spec = _spec(tmp_path, SPEC.replace("seeds = [0]", "seeds = [18446744073709551616]"))
    refused(["sweep", str(spec), "--out", str(tmp_path / "out")], capsys, tmp_path, "seeds: 18446744073709551616")
    (tmp_path / "loop").symlink_to("loop")
    refused(["sweep", str(_spec(tmp_path, SPEC)), "--out", str(tmp_path / "loop")], capsys, tmp_path,
            "symbolic link")


def test_a_live_sweep_driver_is_the_only_writer(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A --resume beside a live driver is refused (naming its pid) and writes nothing; a foreign .lock in the
    sweep directory makes it not a sweep."""
    spec, out = _spec(tmp_path, SPEC), tmp_path / "out"
    assert main(["sweep", str(spec), "--out", str(out), "--workers", "1", "--no-progress"]) == 0
    with hold_lock(out / ".lock"):  # what a running driver holds
        err = refused(["sweep", str(spec), "--out", str(out), "--workers", "1", "--resume", "--no-progress"],
                      capsys, tmp_path, "being written by another process")
        assert f"pid {os.getpid()}" in err
    assert main(["sweep", str(spec), "--out", str(out), "--workers", "1", "--resume", "--no-progress"]) == 0
    other = tmp_path / "other"
    other.mkdir()
    (other / ".lock").symlink_to(spec)
    refused(["sweep", str(spec), "--out", str(other), "--workers", "1", "--no-progress"], capsys, tmp_path, ".lock")


def _children(pid: int) -> list[int]:
    """The pids of the processes whose parent is ``pid`` (Linux /proc)."""
    out = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                fields = Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid:
                out.append(int(entry))
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.sweep
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux /proc")
def test_a_killed_sweep_driver_takes_its_workers_with_it(tmp_path: Path) -> None:
    """kill -9 on the driver alone: the pool's workers end within seconds, and the run and sweep locks are
    free again (an immediate --resume is not refused)."""
    spec = _spec(tmp_path, SPEC.replace('"algorithm.iterations" = 2', '"algorithm.iterations" = 100000')
                 .replace("seeds = [0]", "seeds = [0, 1]"))
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).resolve().parents[1]),
                                                         os.environ.get("PYTHONPATH", "")]), "OMP_NUM_THREADS": "1"}
    driver = subprocess.Popen([sys.executable, "-m", "mixedrl.cli", "sweep", str(spec), "--out", str(out),
                               "--workers", "2", "--batch", "1", "--no-progress"], env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    workers: list[int] = []
    try:
        deadline = time.monotonic() + 120
        runs = [out / "runs" / f"model_seed{s}" for s in (0, 1)]
        while not all((r / ".lock").is_file() and b"pid" in (r / ".lock").read_bytes() for r in runs):  # training
            assert driver.poll() is None and time.monotonic() < deadline, "the sweep did not start"
            time.sleep(0.2)
        workers += [p for p in _children(driver.pid) if _alive(p)]
        assert len(workers) >= 2
        driver.kill()
        driver.wait()
        deadline = time.monotonic() + 10
        while any(_alive(p) for p in workers):
            assert time.monotonic() < deadline, "a pool worker outlived its driver"
            time.sleep(0.1)
        with hold_lock(out / ".lock"):
            for r in runs:
                with RunDirectory(r).lock():
                    pass
    finally:
        driver.kill()
        driver.wait()
        for p in workers:  # this test's own workers, should they have survived
            if _alive(p):
                os.kill(p, signal.SIGKILL)


def test_a_setting_the_first_iteration_rejects_leaves_no_run(tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    """task.prior_force_mean=1e308 (whose square overflows float64 in the IBE) is refused with the
    configuration, naming the key, before anything is created; the plain rerun is accepted."""
    out = tmp_path / "run"
    args = [*TRAIN, "--out", str(out), "--set", "algorithm.iterations=2", "run.eval_every=2", "run.eval_seeds=1"]
    assert main([*args, "task.prior_force_mean=1e308"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "task.prior_force_mean" in err, err
    assert not out.exists()
    assert main(args) == 0
    assert RunDirectory(out).read_results()["iterations"] == 2
