"""The observer of ``experiments/studies/course_positions.toml`` (:mod:`experiments.analysis.course_positions`): its records, that
it changes nothing of the run, and that the spec's designs are those of ``experiments/studies/model_based.toml``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import torch

from mixedrl.config import TrainConfig
from mixedrl.runs import make_trainer, train
from mixedrl.sweep import expand, load_spec
from experiments.analysis.course_positions import PARTS, CoursePositionsObserver, course_positions_observer, share_key

ROOT = Path(__file__).resolve().parents[1]
SPEC = ROOT / "experiments" / "studies" / "course_positions.toml"
MODEL_BASED = ROOT / "experiments" / "studies" / "model_based.toml"
ITERATIONS = 200
EVERY = 100


def _config(variant: str) -> TrainConfig:
    """Variant ``variant`` of the spec, shortened to :data:`ITERATIONS` iterations."""
    (run,) = [r for r in expand(load_spec(SPEC)) if r.point["variant"] == variant]
    data = run.config.to_dict()
    data["algorithm"]["iterations"] = ITERATIONS
    data["run"].update(eval_every=ITERATIONS, checkpoint_every=ITERATIONS)
    return TrainConfig.from_dict(data)


def _train(observer: Any) -> tuple[list[dict[str, Any]], dict[str, torch.Tensor]]:
    trainer = make_trainer(_config("M"))
    out = train(trainer, progress=False, observer=observer)
    return out["metrics"], {k: v.detach().clone() for k, v in trainer.actor.state_dict().items()}


@pytest.fixture(scope="module")
def runs() -> dict[str, tuple[list[dict[str, Any]], dict[str, torch.Tensor]]]:
    torch.set_num_threads(1)
    return {"observed": _train(CoursePositionsObserver(EVERY)), "plain": _train(None)}


def test_records_every_every_iterations(runs: dict) -> None:
    rows, _ = runs["observed"]
    recorded = [r for r in rows if any(k.startswith("positions/") for k in r)]
    assert [r["iteration"] for r in recorded] == list(range(EVERY, ITERATIONS + 1, EVERY))
    for r in recorded:
        assert r["positions/X_q10"] <= r["positions/X_median"] <= r["positions/X_q90"]
        shares = [r[share_key(a, b)] for a, b in PARTS]
        assert all(0.0 <= s <= 1.0 for s in shares) and sum(shares) <= 1.0 + 1e-12


def _training_row(row: dict[str, Any]) -> dict[str, str]:
    """The row without the observer's metrics and the wall times, floats exactly (``repr``, NaN equal)."""
    return {k: repr(v) for k, v in row.items() if not k.startswith(("positions/", "time/"))}


def test_the_observer_changes_nothing_of_the_run(runs: dict) -> None:
    (rows_o, actor_o), (rows_p, actor_p) = runs["observed"], runs["plain"]
    assert len(rows_o) == len(rows_p) == ITERATIONS
    assert [_training_row(r) for r in rows_o] == [_training_row(r) for r in rows_p]
    assert actor_o.keys() == actor_p.keys()
    for k in actor_o:
        assert torch.equal(actor_o[k], actor_p[k]), k


def test_factory_and_every() -> None:
    assert course_positions_observer(_config("M")).every == 100
    with pytest.raises(ValueError, match="every"):
        CoursePositionsObserver(0)


@pytest.mark.parametrize("variant", ["M", "S"])
def test_spec_variants_are_those_of_the_model_based_study(variant: str) -> None:
    spec = load_spec(SPEC)
    assert list(spec.methods) == ["mixed"] and list(spec.seeds) == [0]
    assert spec.observer == "experiments.analysis.course_positions:course_positions_observer"
    (mine,) = [r for r in expand(spec) if r.point["variant"] == variant]
    (theirs,) = [r for r in expand(load_spec(MODEL_BASED))
                 if r.point["variant"] == variant and r.config.method == "mixed" and r.config.seed == 0]
    assert mine.config == theirs.config
    assert mine.config.to_dict() == theirs.config.to_dict()
