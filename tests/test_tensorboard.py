"""TensorBoard scalars beside the metrics files (optional extra ``tensorboard``; tox env ``regression``)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from mixedrl.algorithms.agpi import AGPI
from mixedrl.config import TrainConfig
from mixedrl.runs import RunDirectory, train
from mixedrl.tasks import LinearTask

CFG = dict(method="mixed", task="linear", seed=0, algorithm=dict(iterations=6, batch_size=16, hidden_sizes=(8,)),
           run=dict(eval_every=3, checkpoint_every=3))


def _hide_tensorboard(monkeypatch: pytest.MonkeyPatch) -> None:
    """Make ``import tensorboard`` fail, as without the extra."""
    for name in [m for m in sys.modules if m.startswith(("tensorboard", "torch.utils.tensorboard"))]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "tensorboard", None)


@pytest.mark.regression
def test_metrics_rows_are_written_as_scalars(tmp_path: Path) -> None:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    run = RunDirectory(tmp_path / "run")
    train(AGPI(LinearTask(), TrainConfig(**CFG)), run, progress=False, tensorboard=True)
    rows = [json.loads(line) for line in run.metrics_path.read_text().splitlines()]
    acc = EventAccumulator(str(tmp_path / "run" / "tb"))
    acc.Reload()
    tags = set(acc.Tags()["scalars"])
    expected = {k for r in rows for k, v in r.items() if k != "iteration" and isinstance(v, (int, float))
                and not isinstance(v, bool)}
    assert "eval/cost" in tags and "train/critic_loss" in expected and tags == expected
    for tag in ("eval/cost", "train/critic_loss"):
        events = acc.Scalars(tag)
        want = [(r["iteration"], r[tag]) for r in rows if tag in r]
        assert [e.step for e in events] == [w[0] for w in want]
        assert [e.value for e in events] == pytest.approx([w[1] for w in want], rel=1e-6)  # float32 in the file


def test_missing_extra_is_a_clear_error_and_nothing_is_written(tmp_path: Path, monkeypatch: pytest.MonkeyPatch
                                                                 ) -> None:
    _hide_tensorboard(monkeypatch)
    run = RunDirectory(tmp_path / "run")
    with pytest.raises(ImportError, match=r"^tensorboard: .*pip install 'mixedrl\[tensorboard\]'"):
        train(AGPI(LinearTask(), TrainConfig(**CFG)), run, progress=False, tensorboard=True)
    assert not run.path.exists()  # nothing created (the run directory is created only after validation)


def test_tensorboard_needs_a_run_directory() -> None:
    with pytest.raises(ValueError, match="^tensorboard: needs a run directory"):
        train(AGPI(LinearTask(), TrainConfig(**CFG)), None, progress=False, tensorboard=True)


def test_cli_flag_without_the_extra_is_one_line_exit_2(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    from mixedrl.cli import main

    _hide_tensorboard(monkeypatch)
    out = tmp_path / "run"
    assert main(["train", "--method", "model", "--out", str(out), "--iterations", "2", "--no-progress",
                 "--tensorboard", "--set", "algorithm.batch_size=16"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("mixedrl train: error: tensorboard: ")
    assert not (out / "config.json").exists()
