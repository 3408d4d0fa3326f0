"""Checkpoints are safe to share (issue 9, item 8): they hold plain data, load with
``torch.load(weights_only=True)``, and a file carrying a pickled callable is refused without running it.
Old v1 files are refused with a message naming the release that reads them."""

from __future__ import annotations

import builtins
import os
import re
from collections import OrderedDict
from pathlib import Path

import numpy as np
import pytest
import torch

import mixedrl.checkpoint
from mixedrl.config import TrainConfig
from mixedrl.runs import RunDirectory, load_checkpoint, make_trainer, save_checkpoint, train

V1, V2 = "mixedrl-checkpoint-v1", "mixedrl-checkpoint-v2"
FAST = dict(task="linear", algorithm=dict(iterations=12, batch_size=32), ddpg=dict(warmup=20, batch_size=32),
            run=dict(eval_every=6, checkpoint_every=5, eval_seeds=1))


class _WritesMarker:
    """Unpickling this runs ``open(marker, "w")``: it creates an empty file (and nothing else)."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple:
        return (builtins.open, (str(self.marker), "w"))


def _rich_state() -> dict:
    linear = torch.nn.Linear(2, 3).state_dict()  # an OrderedDict with _metadata
    rng = np.random.default_rng(5)
    rng.standard_normal(3)  # advance, so the state is not the seed's
    gen = torch.Generator().manual_seed(3)
    torch.rand(4, generator=gen)
    return {
        "weights": linear,
        "f64": np.array([[1.0, np.nextafter(1.0, 2.0)], [np.inf, -0.0]]),
        "i64": np.arange(5, dtype=np.int64), "b": np.array([True, False]), "f32": np.float32([1.5, 2.25]),
        "zero_d": np.array(3.25), "np_float": np.float64(0.1), "np_int": np.int64(7), "big": 2**100,
        "nested": [(1, 2.5, "x", None, b"raw"), {"deep": np.ones((2, 2))}],
        "rng": rng, "gen": gen, "gen_state": gen.get_state(), "dtype": torch.float64,
    }


def test_round_trip_keeps_types_shapes_and_bits(tmp_path: Path) -> None:
    path = tmp_path / "checkpoint.pt"
    state = _rich_state()
    save_checkpoint(path, state)
    raw = torch.load(path, weights_only=True)  # plain data: torch's safe loader reads it unaided
    assert raw["format"] == V2
    got = load_checkpoint(path)
    assert isinstance(got["weights"], OrderedDict) and got["weights"]._metadata == state["weights"]._metadata
    for key in ("weight", "bias"):
        assert torch.equal(got["weights"][key], state["weights"][key])
    for key in ("f64", "i64", "b", "f32", "zero_d"):
        assert isinstance(got[key], np.ndarray) and got[key].dtype == state[key].dtype
        assert got[key].shape == state[key].shape and got[key].tobytes() == state[key].tobytes()
    assert type(got["np_float"]) is np.float64 and got["np_float"] == state["np_float"]
    assert type(got["np_int"]) is np.int64 and got["np_int"] == 7 and got["big"] == 2**100
    assert got["nested"][0] == (1, 2.5, "x", None, b"raw") and isinstance(got["nested"][0], tuple)
    assert np.array_equal(got["nested"][1]["deep"], np.ones((2, 2)))
    # generators continue exactly where they were
    assert np.array_equal(got["rng"].standard_normal(4), state["rng"].standard_normal(4))
    assert torch.equal(torch.rand(3, generator=got["gen"]), torch.rand(3, generator=state["gen"]))
    assert torch.equal(got["gen_state"], state["gen_state"]) and got["dtype"] is torch.float64


@pytest.mark.parametrize("method", ["mixed", "ddpg"])
def test_a_run_checkpoint_is_plain_data(tmp_path: Path, method: str) -> None:
    cfg = TrainConfig(method=method, **FAST)
    trainer = make_trainer(cfg)
    train(trainer, RunDirectory(tmp_path), stop_after=10)
    raw = torch.load(tmp_path / "checkpoint.pt", weights_only=True)
    assert raw["format"] == V2
    state = load_checkpoint(tmp_path / "checkpoint.pt")["trainer"]
    fresh = make_trainer(cfg)
    fresh.load_state_dict(state)
    for a, b in zip(fresh.state_dict()["actor"].values(), trainer.state_dict()["actor"].values()):
        assert torch.equal(a, b)
    if method == "mixed":  # the IBE state (numpy arrays) comes back as numpy arrays, bit for bit
        for key, value in trainer.noise.state_dict().items():
            assert np.array_equal(np.asarray(fresh.noise.state_dict()[key]), np.asarray(value))


def test_a_pickled_callable_is_refused_and_not_run(tmp_path: Path) -> None:
    marker = tmp_path / "marker_created_by_unpickling"
    evil = tmp_path / "evil.pt"
    torch.save({"format": V2, "state": {"trainer": _WritesMarker(marker)}}, evil)
    # the test has teeth: an ordinary (unsafe) load of this very file would run the payload
    probe_marker = tmp_path / "probe"
    probe = tmp_path / "probe.pt"
    torch.save({"format": V2, "state": {"trainer": _WritesMarker(probe_marker)}}, probe)
    torch.load(probe, weights_only=False)["state"]["trainer"].close()
    assert probe_marker.exists()

    with pytest.raises(ValueError, match=f"^checkpoint: {re.escape(str(evil))} .*open.*refused"):
        load_checkpoint(evil)
    assert not marker.exists()

    system = tmp_path / "system.pt"
    torch.save({"format": V2, "state": {"x": os.system}}, system)
    with pytest.raises(ValueError, match=f"^checkpoint: {re.escape(str(system))} .*system.*could execute code"):
        load_checkpoint(system)


def test_resume_refuses_a_checkpoint_with_code(tmp_path: Path) -> None:
    cfg = TrainConfig(method="model", **FAST)
    train(make_trainer(cfg), RunDirectory(tmp_path), stop_after=5)
    marker = tmp_path / "marker"
    torch.save({"format": V2, "state": {"trainer": _WritesMarker(marker)}}, tmp_path / "checkpoint.pt")
    (tmp_path / "checkpoint.pt.sha256").unlink()  # a hostile directory without a digest (else the digest refuses it)
    with pytest.raises(ValueError, match="^checkpoint: .*refused"):
        train(make_trainer(cfg), RunDirectory(tmp_path), resume=True)
    assert not marker.exists()


def test_save_rejects_what_a_checkpoint_cannot_hold(tmp_path: Path) -> None:
    path = tmp_path / "checkpoint.pt"
    save_checkpoint(path, {"k": 1})
    before = path.read_bytes()
    with pytest.raises(ValueError, match=r"^state: state\['trainer'\]\['hook'\] is a .*function"):
        save_checkpoint(path, {"trainer": {"hook": lambda: None}})
    with pytest.raises(ValueError, match="^state: .*reserved key"):
        save_checkpoint(path, {"a": {"__mixedrl_encoded__": "ndarray"}})
    with pytest.raises(ValueError, match="^state: .*dtype <U1"):
        save_checkpoint(path, {"a": np.array(["x"])})
    assert path.read_bytes() == before  # nothing written


def test_malformed_marks_are_a_clear_error(tmp_path: Path) -> None:
    path = tmp_path / "checkpoint.pt"
    torch.save({"format": V2, "state": {"a": {"__mixedrl_encoded__": "ndarray", "data": "not a tensor"}}}, path)
    with pytest.raises(ValueError, match=f"^checkpoint: {re.escape(str(path))} .*'ndarray'"):
        load_checkpoint(path)
    torch.save({"format": "mixedrl-checkpoint-v9", "state": {}}, path)
    with pytest.raises(ValueError, match="^checkpoint: .*not a mixedrl-checkpoint-v2 file"):
        load_checkpoint(path)


@pytest.mark.parametrize("state", [
    {"trainer": {"noise": {"mean": np.array([0.5, -1.0]), "count": 3}, "w": torch.arange(3.0)}},  # numpy objects
    {"k": 4, "w": torch.ones(2)},  # plain data only
], ids=["numpy", "plain"])
def test_old_v1_checkpoint_is_refused_naming_the_release_that_reads_it(tmp_path: Path, state: dict) -> None:
    path = tmp_path / "checkpoint.pt"
    torch.save({"format": V1, "state": state}, path)  # what the v1 save_checkpoint wrote
    before = path.read_bytes()
    with pytest.raises(ValueError, match=f"^checkpoint: {re.escape(str(path))} is a {V1} file, written by mixedrl "
                                         f"before {V2}.*mixedrl 0.1.0 from git commit b510485"):
        load_checkpoint(path)
    assert path.read_bytes() == before
    assert not hasattr(mixedrl.checkpoint, "convert_checkpoint")
