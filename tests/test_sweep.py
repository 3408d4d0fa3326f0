"""Tests of mixedrl.sweep: the spec, its validation, the dotted-key applier, and (marked ``sweep``) sweeps on a
local Ray cluster."""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import shutil
import sys
from pathlib import Path

import pytest
import torch

from mixedrl.config import TrainConfig
from mixedrl.runs import RunDirectory, load_checkpoint, make_trainer, train, train_batch
from mixedrl.sweep import (
    INSTALL_HINT,
    add_parser,
    apply_dotted,
    expand,
    flatten_table,
    load_spec,
    make_figure,
    parse_spec,
    plan_batches,
    run_name,
    run_sweep,
    summarize,
)
from mixedrl.cli import main as cli_main
from mixedrl.tables import bootstrap_interval


def main(argv: list[str]) -> int:
    """``mixedrl sweep ARGV`` through the command line (the handler lives in :mod:`mixedrl.cli`)."""
    return cli_main(["sweep", *argv])

BASE = """
[base]
task = "linear"
"algorithm.iterations" = 20
"algorithm.batch_size" = 32
"run.eval_every" = 10
"run.checkpoint_every" = 10
"run.eval_seeds" = 1
"""
SPEC = 'methods = ["mixed"]\nseeds = [0]\n' + BASE + '\n[grid]\n"algorithm.critic_lr" = [1e-3, 3e-3]\n'


# ----------------------------------------------------------------------------------------------------
# the dotted-key applier
# ----------------------------------------------------------------------------------------------------
def test_apply_dotted_sets_nested_fields_and_leaves_its_input_unchanged() -> None:
    data = {"a": {"b": {"c": 1, "d": 2}}, "e": [1, 2]}
    out = apply_dotted(data, {"a.b.c": 10, "e": [3], "x.y": 5, "top": "v"})
    assert out == {"a": {"b": {"c": 10, "d": 2}}, "e": [3], "x": {"y": 5}, "top": "v"}
    assert data == {"a": {"b": {"c": 1, "d": 2}}, "e": [1, 2]}
    value = [1, 2]
    out = apply_dotted({}, {"l": value})
    value.append(3)
    assert out == {"l": [1, 2]}  # values are copied, not shared


@pytest.mark.parametrize("key, message", [("e.f", "^e.f: e is 3, not a nested configuration"), ("a..b", "^a..b: empty segment"),
                                          (".a", "^.a: empty segment"), ("a.", "^a.: empty segment")])
def test_apply_dotted_rejects_bad_keys(key: str, message: str) -> None:
    data = {"a": {"b": 1}, "e": 3}
    with pytest.raises(ValueError, match=message):
        apply_dotted(data, {key: 1})
    assert data == {"a": {"b": 1}, "e": 3}


def test_flatten_table() -> None:
    assert flatten_table({"a": {"b": 1, "c": {"d": [1, 2]}}, "e": 2, "f.g": 3}) == {
        "a.b": 1, "a.c.d": [1, 2], "e": 2, "f.g": 3}


# ----------------------------------------------------------------------------------------------------
# the spec
# ----------------------------------------------------------------------------------------------------
def test_parse_spec_expands_grid_methods_and_seeds_in_order() -> None:
    spec = parse_spec('methods = ["mixed", "model"]\nseeds = [0, 3]\n' + BASE +
                      '\n[grid]\n"algorithm.critic_lr" = [1e-3, 3e-3]\n"algorithm.horizon" = [16]\n')
    runs = expand(spec)
    assert len(runs) == 2 * 1 * 2 * 2
    grid = "algorithm.critic_lr=0.001__algorithm.horizon=16"
    assert [r.name for r in runs[:4]] == [f"{grid}__mixed_seed0", f"{grid}__mixed_seed3", f"{grid}__model_seed0",
                                          f"{grid}__model_seed3"]
    last = runs[-1]
    assert last.point == {"algorithm.critic_lr": 3e-3, "algorithm.horizon": 16}
    assert last.config == TrainConfig(method="model", seed=3, task="linear",
                                      algorithm=dict(iterations=20, batch_size=32, critic_lr=3e-3, horizon=16),
                                      run=dict(eval_every=10, checkpoint_every=10, eval_seeds=1))
    assert spec == parse_spec(spec.text)  # deterministic
    assert len({r.name for r in runs}) == len(runs)


def test_spec_without_grid() -> None:
    spec = parse_spec('methods = ["oracle"]\nseeds = [1]\n[base]\ntask = "linear"\n')
    (only,) = expand(spec)
    assert only.name == "oracle_seed1" and only.point == {}
    assert only.config == TrainConfig(method="oracle", seed=1, task="linear")


@pytest.mark.parametrize("text, message", [
    ('methods = ["mixed"\nseeds = [0]', r"^spec: .* is not valid TOML"),
    ('methods = ["mixed"]\nseeds = [0]\nseed = 1', r"^spec: unknown key\(s\) \['seed'\]"),
    ('seeds = [0]', r"^methods: missing"),
    ('methods = ["mixed"]', r"^seeds: missing"),
    ('methods = []\nseeds = [0]', r"^methods: empty list"),
    ('methods = "mixed"\nseeds = [0]', r"^methods: expected a list of values, got str"),
    ('methods = ["mixed", "mixed"]\nseeds = [0]', r"^methods: duplicate value 'mixed'"),
    ('methods = ["mixed"]\nseeds = [0]\n[grid]\ncritic_lr = 1e-3', r"^grid.critic_lr: expected a list of values"),
    ('methods = ["mixed"]\nseeds = [0]\n[grid]\ncritic_lr = []', r"^grid.critic_lr: empty list"),
    ('methods = ["mixed"]\nseeds = [0]\n[grid]\ncritic_lr = [1e-3, 1e-3]', r"^grid.critic_lr: duplicate"),
    ('methods = ["mixed"]\nseeds = [0]\n[grid]\nseed = [1, 2]', r"^grid.seed: set by the spec's 'seeds'"),
    ('methods = ["mixed"]\nseeds = [0]\n[base]\nmethod = "model"', r"^base.method: set by the spec's 'methods'"),
    ('methods = ["mixed"]\nseeds = [0]\n[base]\nbatch_size = 8\n[grid]\nbatch_size = [16]',
     r"^grid.batch_size: also set in \[base\]"),
    ('methods = ["mixed"]\nseeds = [0]\nbase = 3', r"^base: expected a table"),
    ('methods = ["mixed"]\nseeds = [0]\n[base]\nbatchsize = 8', r"^base: config: unknown key\(s\) \['batchsize'\]"),
    ('methods = ["mixed"]\nseeds = [0]\n[base]\ntask.nothing = 8', r"^base: .*task"),
    ('methods = ["mixed"]\nseeds = [0]\n[grid]\ncriticlr = [1e-3]',
     r"^criticlr=0.001__mixed_seed0: config: unknown key\(s\) \['criticlr'\]"),
    ('methods = ["mixed"]\nseeds = [0]\n[grid]\n"algorithm.batch_size" = [16, 0]',
     r"^algorithm.batch_size=0__mixed_seed0: algorithm.batch_size"),
    ('methods = ["ppo"]\nseeds = [0]', r"^ppo_seed0: method: expected one of"),
    ('methods = ["mixed"]\nseeds = [-1]', r"^mixed_seed-1: seed: expected a non-negative integer"),
    ('methods = ["mixed"]\nseeds = [0]\n[grid]\ntask = ["a b", "a/b"]', r"same run name"),
])
def test_invalid_specs_are_rejected_naming_the_key(text: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        parse_spec(text)


VARIANTS = """
[variants.small]
"algorithm.batch_size" = 16

[variants.wide]
"algorithm.batch_size" = 64
"algorithm.hidden_sizes" = [32, 32]
"""


def test_variants_are_named_overrides_over_base_crossed_with_the_grid() -> None:
    spec = parse_spec('methods = ["mixed"]\nseeds = [0, 1]\n' + BASE + '\n[grid]\n"algorithm.critic_lr" = [1e-3, 3e-3]\n'
                      + VARIANTS)
    runs = expand(spec)
    assert len(runs) == 2 * 2 * 2
    assert runs[0].name == "variant=small__algorithm.critic_lr=0.001__mixed_seed0"
    assert runs[0].point == {"variant": "small", "algorithm.critic_lr": 1e-3}
    base = dict(task="linear", run=dict(eval_every=10, checkpoint_every=10, eval_seeds=1))
    assert runs[0].config == TrainConfig(method="mixed", seed=0, algorithm=dict(iterations=20, batch_size=16,
                                                                                  critic_lr=1e-3), **base)
    assert runs[-1].config == TrainConfig(method="mixed", seed=1, algorithm=dict(
        iterations=20, batch_size=64, hidden_sizes=[32, 32], critic_lr=3e-3), **base)
    assert spec.variants == {"small": {"algorithm.batch_size": 16},
                             "wide": {"algorithm.batch_size": 64, "algorithm.hidden_sizes": [32, 32]}}
    only = expand(parse_spec('methods = ["model"]\nseeds = [0]\n' + BASE + VARIANTS))
    assert [r.name for r in only] == ["variant=small__model_seed0", "variant=wide__model_seed0"]
    # a variant with its own methods and seeds
    own = expand(parse_spec('methods = ["model"]\nseeds = [0]\n' + BASE + VARIANTS +
                            'methods = ["mixed", "oracle"]\nseeds = [3, 4]\n'))
    assert [r.name for r in own] == ["variant=small__model_seed0"] + [
        f"variant=wide__{m}_seed{s}" for m in ("mixed", "oracle") for s in (3, 4)]
    assert own[-1].config == TrainConfig(method="oracle", seed=4, algorithm=dict(
        iterations=20, batch_size=64, hidden_sizes=[32, 32]), **base)


@pytest.mark.parametrize("tail, message", [
    ("variants = 3", r"^variants: expected tables"),
    ("[variants]\nsmall = 3", r"^variants.small: expected a table"),
    ("[variants.small]\nseed = 3", r"^variants.small.seed: set by the spec's 'seeds'"),
    ("[variants.small]\nmethod = 'model'", r"^variants.small.method: set by the spec's 'methods'"),
    ("[grid]\ncritic_lr = [1e-3]\n[variants.small]\ncritic_lr = 1e-2", r"^variants.small.critic_lr: also a grid key"),
    ('[variants."a b"]\nbatch_size = 8', r"^variants.a b: a variant name may hold"),
    ("[variants.small]\nbatchsize = 8", r"^variant=small__mixed_seed0: config: unknown key\(s\) \['batchsize'\]"),
    ("[variants.small]\nseeds = []", r"^variants.small.seeds: empty list"),
    ("[variants.small]\nmethods = 'mixed'", r"^variants.small.methods: expected a list"),
    ("[variants.small]\nseeds = [-2]", r"^variant=small__mixed_seed-2: seed: expected a non-negative integer"),
])
def test_invalid_variants_are_rejected_naming_the_key(tail: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        parse_spec('methods = ["mixed"]\nseeds = [0]\n' + tail)


def test_load_spec_errors(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="^spec: .* does not exist"):
        load_spec(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_bytes(b"methods = [\"mixed\"]\nseeds = [0]\n# \xff\xfe\n")
    with pytest.raises(ValueError, match="^spec: .* (not UTF-8|not valid TOML)"):
        load_spec(bad)
    good = tmp_path / "good.toml"
    good.write_text(SPEC)
    assert load_spec(good) == parse_spec(SPEC)


def test_run_name_is_deterministic_safe_and_bounded() -> None:
    assert run_name({}, "mixed", 2) == "mixed_seed2"
    assert run_name({"hidden_sizes": [64, 32], "task": "a/b c"}, "ddpg", 0) == \
        "hidden_sizes=64x32__task=a_b_c__ddpg_seed0"
    long = {f"key{i}": 1.5 for i in range(40)}
    name = run_name(long, "mixed", 0)
    assert len(name) <= 160 and name == run_name(dict(long), "mixed", 0)
    assert name != run_name({**long, "key39": 2.5}, "mixed", 0)


def test_invalid_spec_starts_nothing(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    spec = tmp_path / "spec.toml"
    spec.write_text(SPEC.replace('"algorithm.critic_lr" = [1e-3, 3e-3]', '"algorithm.critic_lr" = [1e-3, -1.0]'))
    out = tmp_path / "out"
    assert main([str(spec), "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "algorithm.critic_lr=-1.0__mixed_seed0: algorithm.critic_lr: expected a positive number" in err
    assert "Traceback" not in err and not out.exists()


def test_without_ray_address_names_the_extra_and_the_pool_needs_no_ray(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # makes ``import ray`` raise ImportError
    spec = tmp_path / "spec.toml"
    spec.write_text(SPEC)
    assert main([str(spec), "--out", str(tmp_path / "out"), "--address", "local", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert INSTALL_HINT in err and "mixedrl[sweep]" in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()
    # the local engine (here in this process) does not import Ray
    assert main([str(spec.parent / "spec.toml"), "--out", str(tmp_path / "out"), "--workers", "1",
                 "--no-progress"]) == 0
    doc = json.loads((tmp_path / "out" / "sweep.json").read_text())
    assert (doc["engine"], doc["workers"], doc["failed"]) == ("local", 1, 0)


def test_existing_sweep_needs_resume(tmp_path: Path) -> None:
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "spec.toml").write_text(SPEC)
    with pytest.raises(ValueError, match="^out: .* already holds a sweep; pass --resume"):
        run_sweep(parse_spec(SPEC), tmp_path / "out", progress=False)
    other = parse_spec(SPEC.replace("seeds = [0]", "seeds = [1]"))
    with pytest.raises(ValueError, match="^spec: differs from the sweep's"):
        run_sweep(other, tmp_path / "out", resume=True, progress=False)


def test_add_parser_and_num_cpus() -> None:
    parser = argparse.ArgumentParser(prog="mixedrl")
    add_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["sweep", "s.toml", "--out", "d", "--address", "auto", "--resume"])
    assert (args.command, args.spec, args.out, args.address, args.resume, args.no_progress, args.num_cpus) == \
        ("sweep", Path("s.toml"), Path("d"), "auto", True, False, None)
    with pytest.raises(SystemExit):
        parser.parse_args(["sweep", "s.toml"])  # --out is required
    args = parser.parse_args(["sweep", "s.toml", "--out", "d", "--workers", "3"])
    assert (args.workers, args.address, args.num_cpus) == (3, None, None)
    with pytest.raises(ValueError, match="^num_cpus: expected a positive integer"):
        run_sweep(parse_spec(SPEC), "unused", num_cpus=0)
    for bad in (0, -1, True, 1.5):
        with pytest.raises(ValueError, match="^workers: expected a positive integer"):
            run_sweep(parse_spec(SPEC), "unused", workers=bad)
    with pytest.raises(ValueError, match="^workers: .* with address"):
        run_sweep(parse_spec(SPEC), "unused", workers=2, address="auto")
    with pytest.raises(ValueError, match="^num_cpus: without address it is the older name of workers"):
        run_sweep(parse_spec(SPEC), "unused", workers=2, num_cpus=3)
    args = parser.parse_args(["sweep", "s.toml", "--out", "d", "--batch", "4"])
    assert args.batch == 4 and parser.parse_args(["sweep", "s.toml", "--out", "d"]).batch == 16
    for bad in (0, -2, True, 2.0):
        with pytest.raises(ValueError, match="^batch: expected a positive integer"):
            run_sweep(parse_spec(SPEC), "unused", batch=bad)
    assert not Path("unused").exists()


def test_summarize_means_and_sample_std_over_seeds() -> None:
    def rec(point: dict, method: str, cost: float | None, error: str | None = None) -> dict:
        results = None if error else {"cost": cost, "lateral_mae": None, "speed_mae": 1.0, "true_transitions": None,
                                      "train_seconds": 2.0, "run_dir": "x"}
        return {"point": point, "config": {"method": method}, "results": results, "error": error}

    rows = summarize([rec({"a": 1}, "mixed", 1.0), rec({"a": 1}, "mixed", 3.0), rec({"a": 1}, "model", 5.0),
                      rec({"a": 1}, "mixed", None, error="boom"), rec({"a": 2}, "mixed", 4.0)])
    assert [(r["point"], r["method"], r["runs"], r["failed"]) for r in rows] == [
        ({"a": 1}, "mixed", 2, 1), ({"a": 1}, "model", 1, 0), ({"a": 2}, "mixed", 1, 0)]
    assert rows[0]["cost_mean"] == 2.0 and rows[0]["cost_std"] == pytest.approx(2 ** 0.5)
    assert rows[1]["cost_std"] == 0.0 and rows[0]["lateral_mae_mean"] is None
    assert rows[0]["speed_mae_mean"] == 1.0
    # 95% bootstrap interval of the mean over seeds (mixedrl.tables.bootstrap_interval): inside the values'
    # range around the mean; none for one seed, the value itself when every seed agrees
    assert (rows[0]["cost_ci_low"], rows[0]["cost_ci_high"]) == bootstrap_interval([1.0, 3.0])
    assert 1.0 <= rows[0]["cost_ci_low"] < 2.0 < rows[0]["cost_ci_high"] <= 3.0
    assert (rows[1]["cost_ci_low"], rows[1]["cost_ci_high"]) == (None, None)
    assert (rows[0]["speed_mae_ci_low"], rows[0]["speed_mae_ci_high"]) == (1.0, 1.0)


def test_make_figure_plots_cost_against_the_first_grid_key(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    matplotlib = pytest.importorskip("matplotlib")
    import matplotlib.axes

    plotted: list[tuple] = []
    original = matplotlib.axes.Axes.errorbar

    def record(self, x, y, yerr=None, **kw):  # type: ignore[no-untyped-def]
        plotted.append((kw.get("label"), list(x), list(y), list(yerr)))
        return original(self, x, y, yerr=yerr, **kw)

    monkeypatch.setattr(matplotlib.axes.Axes, "errorbar", record)
    summary = [{"point": {"a": a, "b": b}, "method": m, "cost_mean": 10.0 * a + len(b) + (m == "model"),
                "cost_std": 0.5} for a in (1, 2) for b in ("x", "yy") for m in ("mixed", "model")]
    path = make_figure(tmp_path, summary, {"a": [1, 2], "b": ["x", "yy"]})
    assert path == tmp_path / "figures" / "cost_vs_a.png" and path.read_bytes()[:4] == b"\x89PNG"
    # one line per method, against a, with b held at its first value "x"
    assert plotted == [("mixed", [1.0, 2.0], [11.0, 21.0], [0.5, 0.5]), ("model", [1.0, 2.0], [12.0, 22.0], [0.5, 0.5])]
    plotted.clear()
    path = make_figure(tmp_path, summary, {"b": ["x", "yy"], "a": [1, 2]})  # categorical axis, a held at 1
    assert path == tmp_path / "figures" / "cost_vs_b.png" and path.is_file()
    assert plotted[0] == ("mixed", [0.0, 1.0], [11.0, 12.0], [0.5, 0.5])
    assert make_figure(tmp_path, [], {}) is None


# ----------------------------------------------------------------------------------------------------
# sweeps on the local process pool, in this process, and on a local Ray cluster
# ----------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def pool_sweep(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, dict]:
    """SPEC swept once on a pool of two spawned processes (the default engine): (spec path, out, sweep.json)."""
    root = tmp_path_factory.mktemp("pool")
    spec_path = root / "spec.toml"
    spec_path.write_text(SPEC)
    out = root / "full"
    assert main([str(spec_path), "--out", str(out), "--workers", "2", "--no-progress"]) == 0
    return spec_path, out, json.loads((out / "sweep.json").read_text())


def _weights(run: Path) -> dict[str, torch.Tensor]:
    state = load_checkpoint(Path(run) / "checkpoint.pt")["trainer"]
    return {f"{net}.{k}": v for net in ("actor", "critic") for k, v in state[net].items()}


def _same_weights(a: Path, b: Path) -> bool:
    wa, wb = _weights(a), _weights(b)
    return wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)


def _without_time(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in r.items() if not k.startswith("time/")} for r in rows]


_TIMES = ("train_seconds", "wall_seconds")


def _timeless(rec: dict) -> dict:
    """A row of sweep.json without its wall-clock figures."""
    out = {k: v for k, v in rec.items() if k not in _TIMES}
    out["metrics"] = {k: v for k, v in rec["metrics"].items() if k not in _TIMES}
    out["results"] = None if rec["results"] is None else {k: v for k, v in rec["results"].items() if k not in _TIMES}
    return out


def test_sweep_on_the_local_pool_equals_train_alone_and_resumes(pool_sweep, tmp_path: Path) -> None:
    spec_path, full, doc = pool_sweep
    # sweep.json: each run's full config and its figures; the CSVs and the spec copy
    runs = expand(load_spec(spec_path))
    assert [r["name"] for r in doc["runs"]] == [r.name for r in runs] == \
        ["algorithm.critic_lr=0.001__mixed_seed0", "algorithm.critic_lr=0.003__mixed_seed0"]
    assert doc["failed"] == 0 and doc["finished"] is True
    # the two runs share a batch key: one batch, so one worker of the two asked for
    assert (doc["engine"], doc["workers"], doc["address"], doc["batch"], doc["batches"]) == ("local", 1, None, 16, 1)
    for rec, sweep_run in zip(doc["runs"], runs):
        assert rec["config"] == sweep_run.config.to_dict() and rec["error"] is None
        results = RunDirectory(full / rec["results"]["run_dir"]).read_results()
        assert rec["results"]["run_dir"] == f"runs/{sweep_run.name}"
        for key in ("cost", "train_seconds"):
            assert rec["results"][key] == results[key]
        assert rec["results"]["lateral_mae"] is None  # the linear task has no course
        assert rec["results"]["true_transitions"] == results.get("true_transitions")
        assert rec["metrics"]["batch_size_runs"] == 2
    assert (full / "spec.toml").read_text() == SPEC
    assert (full / "figures" / "cost_vs_algorithm.critic_lr.png").is_file()
    with open(full / "sweep.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["name"] for r in rows] == [r.name for r in runs] and float(rows[1]["cost"]) == \
        doc["runs"][1]["results"]["cost"]
    assert [r["true_transitions"] for r in rows] == [str(rec["results"]["true_transitions"]) for rec in doc["runs"]]
    with open(full / "sweep_summary.csv") as fh:
        summary = list(csv.DictReader(fh))
    assert [(s["algorithm.critic_lr"], s["method"], s["runs"]) for s in summary] == [("0.001", "mixed", "1"),
                                                                                     ("0.003", "mixed", "1")]

    # a batch of the sweep is exactly the same configs trained by train_batch
    together = [RunDirectory(tmp_path / "together" / r.name) for r in runs]
    train_batch([make_trainer(r.config) for r in runs], together, progress=False)
    for r, d in zip(runs, together):
        swept = full / "runs" / r.name
        assert _same_weights(swept, d.path)
        assert _without_time(RunDirectory(swept).read_metrics()) == _without_time(d.read_metrics())

    # with --batch 1 a run of the sweep is exactly the same config trained alone with ``mixedrl train``
    single = tmp_path / "single"
    assert main([str(spec_path), "--out", str(single), "--batch", "1", "--workers", "1", "--no-progress"]) == 0
    first = runs[0]
    alone = tmp_path / "alone"
    (tmp_path / "config.json").write_text(json.dumps(first.config.to_dict()))
    assert cli_main(["train", "--method", "mixed", "--seed", "0", "--out", str(alone), "--config",
                     str(tmp_path / "config.json"), "--no-progress"]) == 0
    swept = single / "runs" / first.name
    assert _same_weights(swept, alone)
    assert RunDirectory(swept).read_results()["final"] == RunDirectory(alone).read_results()["final"]
    assert _without_time(RunDirectory(swept).read_metrics()) == _without_time(RunDirectory(alone).read_metrics())
    assert json.loads((single / "sweep.json").read_text())["batches"] == 2

    # resume (in this process, workers=1): the batch interrupted after 10 of 20 iterations, then the second
    # run replaced by its finished copy: the first continues beside it (restored, inactive) and ends with
    # the bits of the uninterrupted batch
    resumed = tmp_path / "resumed"
    cut = [RunDirectory(resumed / "runs" / r.name) for r in runs]
    train_batch([make_trainer(r.config) for r in runs], cut, progress=False, stop_after=10)
    partial = cut[0].read_metrics()
    assert [r["iteration"] for r in partial] == list(range(1, 11))
    shutil.rmtree(cut[1].path)
    shutil.copytree(full / "runs" / runs[1].name, cut[1].path)
    finished_results = cut[1].results_path
    stamp = finished_results.stat().st_mtime_ns
    doc2 = run_sweep(load_spec(spec_path), resumed, resume=True, progress=False, workers=1)
    assert finished_results.stat().st_mtime_ns == stamp  # skipped, not retrained
    rows2 = cut[0].read_metrics()
    assert rows2[:10] == partial  # continued from the checkpoint (a restart would rewrite the times)
    assert _same_weights(cut[0].path, full / "runs" / runs[0].name)
    assert [_timeless(a) for a in doc2["runs"]] == [_timeless(b) for b in doc["runs"]]
    assert doc2["failed"] == 0 and doc2["workers"] == 1


def test_plan_batches_groups_by_shape_spreads_over_workers_and_never_leaves_a_run_alone() -> None:
    text = ('methods = ["mixed", "model", "oracle", "ddpg"]\nseeds = [0, 1, 2, 3, 4]\n' + BASE +
            '"ddpg.batch_size" = 32\n[variants.a]\n[variants.b]\n"algorithm.batch_size" = 16\nseeds = [0]\n'
            'methods = ["mixed"]\n')
    runs = expand(parse_spec(text))
    assert len(runs) == 21
    ddpg = [i for i, r in enumerate(runs) if r.config.method == "ddpg"]
    algo2 = [i for i, r in enumerate(runs) if r.config.method != "ddpg" and r.point["variant"] == "a"]
    lone = [i for i, r in enumerate(runs) if r.point["variant"] == "b"]
    assert (len(ddpg), len(algo2), len(lone)) == (5, 15, 1)
    for workers, batch, sizes in ((1, 16, [15]), (2, 16, [8, 7]), (4, 16, [4, 4, 4, 3]), (1, 4, [4, 4, 4, 3]),
                                  (8, 16, [2, 2, 2, 2, 2, 2, 3]), (1, 14, [8, 7])):
        batches = plan_batches(runs, batch, workers)
        assert sorted(i for b in batches for i in b) == list(range(21))
        assert [b for b in batches if b[0] in ddpg] == [[i] for i in ddpg]  # DDPG trains alone by default
        ddpg_batches = [b for b in plan_batches(runs, batch, workers, ddpg=True) if b[0] in ddpg]
        # with ddpg=True: DDPG in batches of its own, as Algorithm 2
        assert sorted(i for b in ddpg_batches for i in b) == ddpg and all(len(b) >= 2 for b in ddpg_batches)
        assert len(ddpg_batches) == (1 if workers == 1 and batch >= 5 else 2)
        assert lone in batches  # another batch size: its own group, of one
        grouped = [b for b in batches if b[0] in algo2]
        assert sorted(len(b) for b in grouped) == sorted(sizes), (workers, batch)
        assert all(len(b) >= 2 for b in grouped)
        assert all(runs[i].config.algorithm.batch_size == 32 for b in grouped for i in b)
    assert plan_batches(runs, 1, 2) == [[i] for i in range(21)]
    with pytest.raises(ValueError, match="batch"):
        plan_batches(runs, 0)


def test_one_row_per_run_schema(pool_sweep) -> None:
    _, full, doc = pool_sweep
    with open(full / "sweep.csv") as fh:
        rows = list(csv.DictReader(fh))
    for rec, row in zip(doc["runs"], rows):
        results = RunDirectory(full / rec["run_dir"]).read_results()
        canonical = json.dumps(RunDirectory(full / rec["run_dir"]).read_config().to_dict(), sort_keys=True,
                               separators=(",", ":"))
        assert rec["config_hash"] == hashlib.sha256(canonical.encode()).hexdigest()
        assert (rec["method"], rec["seed"], rec["iterations"]) == ("mixed", 0, 20)
        assert rec["true_transitions"] == results["true_transitions"] and rec["run_dir"] == f"runs/{rec['name']}"
        scalars = {k: v for k, v in results.items() if isinstance(v, (int, float)) and not isinstance(v, bool)
                   and k not in ("seed", "iterations", "true_transitions", "train_seconds")}
        assert rec["metrics"] == scalars and "cost" in scalars
        assert rec["train_seconds"] == results["train_seconds"] <= rec["wall_seconds"]
        assert row["config_hash"] == rec["config_hash"] and float(row["cost"]) == results["cost"]
        assert row["lateral_mae"] == "" and row["error"] == "" and int(row["iterations"]) == 20
    assert doc["runs"][0]["config_hash"] != doc["runs"][1]["config_hash"]


@pytest.fixture(scope="module")
def local_ray():
    """One local Ray cluster for the module (starting one takes ~10 s); run_sweep reuses it."""
    ray = pytest.importorskip("ray", reason="Ray is not installed (extra 'sweep')")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


@pytest.mark.sweep
def test_sweep_on_ray_gives_the_outputs_of_the_pool(local_ray, pool_sweep, tmp_path: Path) -> None:
    spec_path, full, doc = pool_sweep
    out = tmp_path / "ray"
    assert main([str(spec_path), "--out", str(out), "--address", "local", "--no-progress"]) == 0
    ray_doc = json.loads((out / "sweep.json").read_text())
    assert ray_doc["engine"] == "ray" and ray_doc["address"] == "local"
    assert [_timeless(a) for a in ray_doc["runs"]] == [_timeless(b) for b in doc["runs"]]
    for rec in doc["runs"]:
        assert _same_weights(out / rec["run_dir"], full / rec["run_dir"])


def test_a_failed_run_is_recorded_and_does_not_stop_the_others(tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    spec_path = tmp_path / "spec.toml"
    spec_path.write_text(SPEC)
    out = tmp_path / "out"
    runs = expand(load_spec(spec_path))
    # run 1's directory holds a finished run of another config: resuming it is an error
    bad = RunDirectory(out / "runs" / runs[0].name)
    bad.write_config(runs[0].config.replace(**{"algorithm.critic_lr": 0.5}))
    bad.write_results({"cost": 1.0})
    assert main([str(spec_path), "--out", str(out), "--resume", "--workers", "2", "--no-progress"]) == 1
    assert "1 run(s) failed" in capsys.readouterr().err
    doc = json.loads((out / "sweep.json").read_text())
    assert doc["failed"] == 1
    assert doc["runs"][0]["results"] is None and doc["runs"][0]["error"].startswith("ValueError: config: differs")
    assert doc["runs"][0]["metrics"] == {} and doc["runs"][0]["wall_seconds"] is None
    assert doc["runs"][1]["error"] is None and doc["runs"][1]["results"]["cost"] == \
        RunDirectory(out / "runs" / runs[1].name).read_results()["cost"]
    assert [(s["runs"], s["failed"]) for s in doc["summary"]] == [(0, 1), (1, 0)]


def test_a_resumed_sweep_of_a_global_task_compares_the_resolved_budget(tmp_path) -> None:
    """A registered task that declares a state region trains ``region_budget`` times the spec's iterations,
    and its ``config.json`` holds that budget; resuming the sweep (a finished run, an interrupted one) compares
    the saved config with the resolved one, not with the spec's."""
    from dataclasses import dataclass

    from mixedrl.config import LinearTaskConfig, task_names
    from mixedrl.linear_task import LinearTask
    from mixedrl.sweep import run_points
    from mixedrl.tasks import register_task

    @dataclass
    class RegionLinearConfig:
        name: str = "region_linear_sweep_test"

    class RegionLinear(LinearTask):
        """The linear test bed with the box [-1, 1]^2 declared as its state region."""

        name = "region_linear_sweep_test"

        @classmethod
        def from_config(cls, config: RegionLinearConfig) -> "RegionLinear":
            return cls.from_problem(LinearTaskConfig().problem())

        def sample_region(self, n: int, generator: torch.Generator) -> torch.Tensor:
            return 2 * torch.rand(n, self.state_dim, generator=generator, dtype=torch.float64) - 1

    if "region_linear_sweep_test" not in task_names():
        register_task(RegionLinear, RegionLinearConfig)
    cfg = TrainConfig(method="mixed", seed=0, task="region_linear_sweep_test",
                      algorithm=dict(iterations=3, batch_size=16, hidden_sizes=(8,), rollout_horizon=2),
                      run=dict(eval_every=3, eval_seeds=1, checkpoint_every=4))
    done, cut = tmp_path / "done", tmp_path / "cut"
    (first,) = run_points([cfg.to_dict()], [str(done)])
    assert first["iterations"] == 12 and first["region_budget"] == 4
    assert RunDirectory(done).read_config().algorithm.iterations == 12
    assert run_points([cfg.to_dict()], [str(done)], resume=True)[0]["iterations"] == 12  # finished: read back
    train(make_trainer(cfg), RunDirectory(cut), stop_after=8, progress=False)  # checkpoints at 4 and 8
    resumed = run_points([cfg.to_dict()], [str(cut)], resume=True)[0]
    assert resumed["iterations"] == 12 and resumed["final"] == first["final"]
