"""A run directory is never silently replaced, corrupted files are refused, one writer per directory,
every CLI failure is one line with nothing changed on disk (issues 22 and 20)."""

from __future__ import annotations

import io
import json
import os
import shutil
import signal
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from mixedrl.cli import main
from mixedrl.runs import RunDirectory, load_checkpoint, verify_digest, write_with_digest

#: A fast run (the only place that names config fields).
FAST = ["--iterations", "20", "--set", "run.checkpoint_every=10", "run.eval_seeds=1"]
RUN = ["--method", "mixed", "--seed", "3"]


def snapshot(root: Path) -> dict[str, bytes | tuple[str, str] | None]:
    """Every path under ``root`` (``root`` itself included) with its bytes (a symbolic link: its target, not
    followed; a directory: None)."""
    if not root.exists():
        return {}
    out: dict[str, bytes | tuple[str, str] | None] = {".": None if root.is_dir() else root.read_bytes()}
    if root.is_dir():
        for p in sorted(root.rglob("*")):
            rel = str(p.relative_to(root))
            out[rel] = ("->", os.readlink(p)) if p.is_symlink() else None if p.is_dir() else p.read_bytes()
    return out


def cli(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    rc = main(args)
    return rc, capsys.readouterr().err


def refused(args: list[str], capsys: pytest.CaptureFixture[str], root: Path, match: str) -> str:
    """Run ``mixedrl args``: exit 2, one line on stderr matching ``match``, ``root`` unchanged."""
    capsys.readouterr()  # what earlier commands printed
    before = snapshot(root)
    rc, err = cli(args, capsys)
    assert rc == 2, err
    assert len(err.strip().splitlines()) == 1 and match in err, err
    assert snapshot(root) == before
    return err


@pytest.fixture(scope="module")
def finished(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("finished") / "run"
    assert main(["train", *RUN, "--out", str(out), *FAST, "--no-progress"]) == 0
    return out


# ---------------------------------------------------------------------------------------------------
# 1. a run directory is never silently replaced
# ---------------------------------------------------------------------------------------------------
def test_train_refuses_a_finished_run(run_copy: Path, capsys: pytest.CaptureFixture[str]) -> None:
    refused(["train", "--method", "mixed", "--seed", "0", "--out", str(run_copy), *FAST, "--no-progress"],
            capsys, run_copy, "already holds a run")


@pytest.mark.parametrize("keep", ["config.json", "checkpoint.pt", "metrics.jsonl", "results.json"])
def test_train_refuses_any_part_of_a_run(run_copy: Path, keep: str, capsys: pytest.CaptureFixture[str]) -> None:
    for p in run_copy.iterdir():
        if p.name != keep:
            p.unlink()
    refused(["train", *RUN, "--out", str(run_copy), *FAST, "--no-progress"], capsys, run_copy, keep)


def test_train_refuses_a_directory_that_is_not_a_run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "notes.txt").write_text("mine\n")
    refused(["train", *RUN, "--out", str(tmp_path), *FAST, "--no-progress"], capsys, tmp_path, "holds no run")


def test_resume_refuses_a_run_without_checkpoint(run_copy: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (run_copy / "checkpoint.pt").unlink()
    refused(["train", *RUN, "--out", str(run_copy), *FAST, "--resume", "--no-progress"], capsys, run_copy,
            "no checkpoint.pt")


def test_resume_refuses_an_empty_directory(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    refused(["train", *RUN, "--out", str(tmp_path / "new"), *FAST, "--resume", "--no-progress"], capsys, tmp_path,
            "holds no run to resume")


def test_resume_with_only_a_config_starts_from_scratch(finished: Path, tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "killed"
    out.mkdir()
    shutil.copy(finished / "config.json", out / "config.json")  # killed before its first checkpoint
    rc, err = cli(["train", *RUN, "--out", str(out), *FAST, "--resume", "--no-progress"], capsys)
    assert rc == 0, err
    assert RunDirectory(out).read_results()["final"] == RunDirectory(finished).read_results()["final"]
    assert len(RunDirectory(out).read_metrics()) == 20


@pytest.mark.parametrize("flags, name", [(["--method", "model"], "method"), (["--seed", "9"], "seed"),
                                         (["--iterations", "10"], "iterations"),
                                         (["--set", "task.gamma=0.9"], "task.gamma")])
def test_resume_refuses_contradicting_flags(run_copy: Path, flags: list[str], name: str,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    args = ["train", "--method", "mixed", "--out", str(run_copy), *flags, "--resume", "--no-progress"]
    if "--method" in flags:
        args = ["train", "--out", str(run_copy), *flags, "--resume", "--no-progress"]
    refused(args, capsys, run_copy, name)


def test_resume_extends_the_budget(run_copy: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc, err = cli(["train", "--method", "mixed", "--out", str(run_copy), "--iterations", "30", "--resume",
                   "--no-progress"], capsys)
    assert rc == 0, err
    run = RunDirectory(run_copy)
    assert run.read_config().algorithm.iterations == 30 and run.read_results()["iterations"] == 30
    assert [r["iteration"] for r in run.read_metrics()] == list(range(1, 31))


@pytest.mark.parametrize("damage", ["delete", "truncate"])
def test_resume_never_drops_metrics(run_copy: Path, damage: str, capsys: pytest.CaptureFixture[str]) -> None:
    metrics = run_copy / "metrics.jsonl"
    if damage == "delete":
        metrics.unlink()
    else:
        metrics.write_text("".join(metrics.read_text().splitlines(keepends=True)[:5]))
    refused(["train", "--method", "mixed", "--out", str(run_copy), "--resume", "--no-progress"], capsys, run_copy,
            "metrics.jsonl")


# ---------------------------------------------------------------------------------------------------
# 2. every CLI failure: one line, exit 2, nothing created or changed
# ---------------------------------------------------------------------------------------------------
_TRAIN = ["train", *RUN, *FAST, "--no-progress"]


@pytest.mark.parametrize("args, match", [
    ([*_TRAIN, "--out", "{tmp}/o1", "--config", "{tmp}/missing.json"], "does not exist"),
    ([*_TRAIN, "--out", "{tmp}/o2", "--config", "{tmp}/adir"], "not a file"),
    ([*_TRAIN, "--out", "{tmp}/afile"], "is a file"),
    ([*_TRAIN, "--out", "{tmp}/o3", "--set", "method=ddpg"], "--method"),
    ([*_TRAIN, "--out", "{tmp}/o4", "--set", "task.prior_mena=1"], "prior_mena"),
    (["evaluate", "{tmp}/afile"], "not a directory"),
    (["evaluate", "{tmp}/no/such/dir"], "does not exist"),
    (["evaluate", "{tmp}/adir"], "config.json"),
], ids=["config-missing", "config-dir", "out-file", "set-method", "unknown-key", "evaluate-file",
        "evaluate-missing", "evaluate-not-a-run"])
def test_cli_failures_are_one_line_and_change_nothing(tmp_path: Path, args: list[str], match: str,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "afile").write_text("x\n")
    (tmp_path / "adir").mkdir()
    refused([a.format(tmp=tmp_path) for a in args], capsys, tmp_path, match)


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only directories")
def test_read_only_out_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "ro"
    out.mkdir()
    out.chmod(0o555)
    try:
        refused(["train", *RUN, "--out", str(out), *FAST, "--no-progress"], capsys, tmp_path, "cannot write")
    finally:
        out.chmod(0o755)


# ---------------------------------------------------------------------------------------------------
# 3. integrity of checkpoint.pt and results.json
# ---------------------------------------------------------------------------------------------------
def _actor_weight_member(path: Path) -> tuple[str, bytes]:
    """The zip member holding the first actor weight and its bytes."""
    weight = load_checkpoint(path)["trainer"]["actor"]["net.body.0.weight"].numpy().tobytes()
    with zipfile.ZipFile(path) as archive:
        for name in archive.namelist():
            data = archive.read(name)
            if data == weight:
                return name, data
    raise AssertionError("actor weight not found in the archive")


def _flip_exponents(data: bytes) -> bytes:
    values = np.frombuffer(data, dtype=np.uint32).copy()
    return (values ^ np.uint32(1 << 30)).tobytes()  # one exponent bit of every float32


def test_corrupted_checkpoint_is_refused_by_evaluate_and_resume(run_copy: Path,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    path = run_copy / "checkpoint.pt"
    name, data = _actor_weight_member(path)
    buffer = io.BytesIO()
    with zipfile.ZipFile(path) as src, zipfile.ZipFile(buffer, "w", zipfile.ZIP_STORED) as dst:
        for info in src.infolist():  # a valid zip (CRCs recomputed): only the digest can tell
            dst.writestr(info, _flip_exponents(data) if info.filename == name else src.read(info))
    path.write_bytes(buffer.getvalue())
    refused(["evaluate", str(run_copy)], capsys, run_copy, "checkpoint.pt is corrupted")
    refused(["train", "--method", "mixed", "--out", str(run_copy), "--resume", "--no-progress"], capsys, run_copy,
            "checkpoint.pt is corrupted")


def test_flipped_bytes_without_digest_are_caught_by_the_zip_crc(run_copy: Path,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    path = run_copy / "checkpoint.pt"
    (run_copy / "checkpoint.pt.sha256").unlink()  # as an old checkpoint, written before digests
    rc, err = cli(["evaluate", str(run_copy)], capsys)
    assert rc == 0, err  # an old checkpoint without digest still loads
    name, data = _actor_weight_member(path)
    raw = path.read_bytes()
    start = raw.index(data)
    path.write_bytes(raw[:start] + _flip_exponents(data) + raw[start + len(data):])
    refused(["evaluate", str(run_copy)], capsys, run_copy, "CRC")


def test_results_digest_is_verified(run_copy: Path) -> None:
    run = RunDirectory(run_copy)
    good = run.read_results()
    doc = json.loads(run.results_path.read_text())
    doc["cost"] = 1.0
    run.results_path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="^results: .*results.json is corrupted"):
        run.read_results()
    (run_copy / "results.json.sha256").unlink()  # an old results.json without digest still reads
    assert run.read_results()["cost"] == 1.0 != good["cost"]


def test_digest_write_is_crash_safe(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "results.json"
    write_with_digest(path, b"old")
    real = os.replace

    def crash_on_data(src: str, dst: str) -> None:
        if Path(dst) == path:
            raise OSError("killed")
        real(src, dst)

    monkeypatch.setattr(os, "replace", crash_on_data)
    with pytest.raises(OSError):
        write_with_digest(path, b"new")
    monkeypatch.undo()
    assert RunDirectory(tmp_path).results_path.read_bytes() == b"old"
    verify_digest(path, b"old", "results")  # the sidecar still accepts the file on disk
    write_with_digest(path, b"new")
    with pytest.raises(ValueError):
        verify_digest(path, b"old", "results")


# ---------------------------------------------------------------------------------------------------
# 4. one writer per run directory
# ---------------------------------------------------------------------------------------------------
HOLD = """
import sys, time
from mixedrl.runs import RunDirectory
with RunDirectory(sys.argv[1]).lock():
    print("locked", flush=True)
    time.sleep(120)
"""


def _holder(out: Path) -> subprocess.Popen[str]:
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(out)], stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])})
    assert proc.stdout is not None and proc.stdout.readline().strip() == "locked"
    return proc


def test_second_writer_refused_and_killed_holder_recovered(tmp_path: Path,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "run"
    holder = _holder(out)  # another process holds the lock
    try:
        err = refused(["train", *RUN, "--out", str(out), *FAST, "--no-progress"], capsys, out, "another process")
        assert str(out) in err and f"pid {holder.pid}" in err, err
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    rc, err = cli(["train", *RUN, "--out", str(out), *FAST, "--no-progress"], capsys)  # the stale lock is recovered
    assert rc == 0, err
    assert len(RunDirectory(out).read_metrics()) == 20
    with RunDirectory(out).lock():  # released at the end of the run
        pass


@pytest.mark.slow
def test_two_trainers_on_one_out(tmp_path: Path) -> None:
    out = tmp_path / "run"
    args = [sys.executable, "-c", "import sys; from mixedrl.cli import main; sys.exit(main(sys.argv[1:]))",
            "train", *RUN, "--out", str(out), "--iterations", "100", "--set", "run.checkpoint_every=25",
            "run.eval_seeds=1", "algorithm.rollout_horizon=4", "--no-progress"]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    procs = [subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
             for _ in range(2)]
    results = [p.communicate(timeout=600) for p in procs]
    codes = sorted(p.returncode for p in procs)
    assert codes == [0, 2], results
    assert [r["iteration"] for r in RunDirectory(out).read_metrics()] == list(range(1, 101))


# ---------------------------------------------------------------------------------------------------
# 5. sweeps refuse a directory that is not their own sweep's
# ---------------------------------------------------------------------------------------------------
SPEC = """
methods = ["mixed"]
seeds = [0]
[base]
"algorithm.iterations" = 20
"""


@pytest.mark.parametrize("resume", [False, True])
def test_sweep_refuses_a_foreign_sweep_json(tmp_path: Path, resume: bool, capsys: pytest.CaptureFixture[str]) -> None:
    other = {"methods": ["model"], "seeds": [4], "base": {}, "grid": {}, "runs": [], "summary": []}
    (tmp_path / "sweep.json").write_text(json.dumps(other))
    spec = tmp_path.parent / f"{tmp_path.name}.toml"
    spec.write_text(SPEC)
    args = ["sweep", str(spec), "--out", str(tmp_path), "--no-progress", *(["--resume"] if resume else [])]
    refused(args, capsys, tmp_path, "sweep")


@pytest.mark.parametrize("foreign", ["notes.txt", "runs/someone_else"])
def test_sweep_refuses_files_that_are_not_its_own(tmp_path: Path, foreign: str,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / foreign).parent.mkdir(parents=True, exist_ok=True)
    (tmp_path / foreign).write_text("x\n")
    spec = tmp_path.parent / f"{tmp_path.name}.toml"
    spec.write_text(SPEC)
    refused(["sweep", str(spec), "--out", str(tmp_path), "--no-progress", "--resume"], capsys, tmp_path,
            "not this sweep's")
