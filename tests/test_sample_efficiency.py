"""Tests of experiments.analysis.sample_efficiency_lib (thresholds, table, figures, rows of our runs) and of the study script's
summary, on synthetic rows; one tiny real run of mixedrl's trainer for the rows."""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from mixedrl.runs import iterations_to_converge
from mixedrl.sweep import expand, load_spec, parse_spec, run_sweep
from experiments.analysis.sample_efficiency_lib import (
    THRESHOLD_LATERAL,
    THRESHOLD_SPEED,
    check_rows,
    choose_eval_every,
    load_runs,
    ours_config,
    plot_curves,
    reach_accuracy,
    reach_own_final,
    records_from_reproduction,
    records_from_sweep,
    rows_from_metrics,
    settled,
    summarize,
    train_ours,
    write_summary,
)

ROOT = Path(__file__).resolve().parents[1]


def row(n: int, lat: float, spd: float, cost: float, wall: float | None = None) -> dict:
    return {"true_transitions": n, "wall_seconds": float(n) / 100 if wall is None else wall, "lateral_mae": lat,
            "speed_mae": spd, "cost": cost}


def test_accuracy_needs_both_thresholds_at_the_same_evaluation() -> None:
    rows = [row(100, 0.10, 0.05, 90.0),   # lateral met, speed not
            row(200, 0.20, 0.01, 80.0),   # speed met, lateral not
            row(300, 0.151, 0.021, 70.0),  # both, on the boundary (<=)
            row(400, 0.10, 0.01, 60.0)]
    assert reach_accuracy(rows) is rows[2]
    assert reach_accuracy(rows[:2]) is None
    assert reach_accuracy(rows, lateral=0.1, speed=0.01) is rows[3]


def test_own_final_is_the_first_evaluation_within_ten_percent_of_the_last() -> None:
    rows = [row(1, 1, 1, 300.0), row(2, 1, 1, 112.0), row(3, 1, 1, 110.0), row(4, 1, 1, 150.0),
            row(5, 1, 1, 100.0)]
    assert reach_own_final(rows) is rows[2]  # 110 <= 100 + 10; 112 is not
    assert reach_own_final(rows, rtol=0.5) is rows[2 - 1]
    assert reach_own_final([row(1, 1, 1, math.inf)]) is None


def test_settled_uses_the_runs_convergence_criterion() -> None:
    costs = [300.0, 100.0, 200.0, 105.0, 100.0, 98.0]
    rows = [row(10 * (i + 1), 1, 1, c) for i, c in enumerate(costs)]
    assert settled(rows) is rows[3]  # the dip at index 1 does not count: 200 follows
    assert settled(rows)["true_transitions"] == iterations_to_converge([r["true_transitions"] for r in rows], costs)


@given(st.integers(min_value=1, max_value=200_000))
def test_about_twelve_evaluations(iterations: int) -> None:
    every = choose_eval_every(iterations)
    points = iterations // every + (iterations % every != 0)  # the run also evaluates at its last iteration
    assert points <= 12
    assert points >= (10 if iterations >= 60 else min(iterations, 6))


def test_choose_eval_every_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match="iterations"):
        choose_eval_every(0)
    with pytest.raises(ValueError, match="points"):
        choose_eval_every(10, points=0)


@pytest.mark.parametrize("rows, match", [
    ([], "non-empty"),
    ([{"true_transitions": 1}], "missing"),
    ([row(1, 1, 1, 1), row(0, 1, 1, 1)], "decrease"),
    ([row(1, 1, 1, 1, wall=2.0), row(2, 1, 1, 1, wall=1.0)], "decrease"),
    ([{**row(1, 1, 1, 1), "cost": "x"}], "cost"),
])
def test_check_rows(rows: list, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        check_rows(rows)


def runs_fixture() -> list[dict]:
    rng = np.random.default_rng(7)
    runs = []
    for method, transitions in (("mixed", [20, 40, 60]), ("model", [0, 0, 0]), ("sac", [1000, 2000, 3000])):
        for seed in (0, 1, 2):
            lat = rng.uniform(0.1, 0.3, 3)
            spd = rng.uniform(0.01, 0.05, 3)
            cost = rng.uniform(30, 90, 3)
            runs.append({"method": method, "seed": seed,
                         "rows": [row(n, lat[i], spd[i], cost[i], wall=1.0 + i + seed) for i, n in enumerate(transitions)]})
    return runs


def test_summary_statistics_per_method() -> None:
    runs = runs_fixture()
    table = summarize(runs)
    assert [e["method"] for e in table] == ["mixed", "model", "sac"]
    for entry in table:
        rs = [r for r in runs if r["method"] == entry["method"]]
        finals = [r["rows"][-1] for r in rs]
        for name, key in (("lateral", "lateral_mae"), ("speed", "speed_mae"), ("cost", "cost")):
            values = [f[key] for f in finals]
            assert entry[f"{name}_mean"] == pytest.approx(sum(values) / 3, rel=1e-12)
            mean = sum(values) / 3
            assert entry[f"{name}_std"] == pytest.approx(math.sqrt(sum((v - mean) ** 2 for v in values) / 2), rel=1e-12)
        assert entry["seeds"] == [0, 1, 2]
        assert entry["true_transitions"] == [f["true_transitions"] for f in finals]
        for r, n, w in zip(rs, entry["accuracy_transitions"], entry["accuracy_wall_seconds"]):
            hit = [x for x in r["rows"] if x["lateral_mae"] <= THRESHOLD_LATERAL and x["speed_mae"] <= THRESHOLD_SPEED]
            assert (n, w) == ((hit[0]["true_transitions"], hit[0]["wall_seconds"]) if hit else (None, None))
        assert entry["reached"] == sum(n is not None for n in entry["accuracy_transitions"])
    assert summarize(runs[:1])[0]["lateral_std"] is None  # one seed: no spread


def test_write_summary_csv_and_json(tmp_path: Path) -> None:
    table = summarize(runs_fixture())
    csv_path, json_path = write_summary(table, tmp_path / "out")
    assert json.loads(json_path.read_text()) == json.loads(json.dumps(table))
    with open(csv_path, newline="") as fh:
        lines = list(csv.DictReader(fh))
    assert [x["method"] for x in lines] == ["mixed", "model", "sac"]
    for line, entry in zip(lines, table):
        assert line["seeds"] == "0 1 2"
        assert float(line["cost_mean"]) == pytest.approx(entry["cost_mean"], rel=1e-3)
        cells = line["accuracy_transitions"].split(" ")
        assert cells == ["never" if v is None else str(v) for v in entry["accuracy_transitions"]]


def test_figure_draws_zero_transition_methods_as_horizontal_lines(tmp_path: Path) -> None:
    runs = runs_fixture()
    fig = plot_curves(runs, "true_transitions", tmp_path / "t.png")
    assert (tmp_path / "t.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    ax_cost = fig.axes[0]
    assert ax_cost.get_xscale() == "log"
    lines = [ln for ln in ax_cost.get_lines() if "0 true transitions" in str(ln.get_label())]
    assert len(lines) == 1 and "model" in lines[0].get_label()
    level = np.mean([r["rows"][-1]["cost"] for r in runs if r["method"] == "model"])
    assert np.all(np.asarray(lines[0].get_ydata(), dtype=float) == level)
    # the mixed mean curve: the mean over seeds at each evaluation
    mixed = [ln for ln in ax_cost.get_lines() if str(ln.get_label()).startswith("mixed RL (mean")]
    expected = np.mean([[x["cost"] for x in r["rows"]] for r in runs if r["method"] == "mixed"], axis=0)
    np.testing.assert_allclose(mixed[0].get_ydata(), expected, rtol=1e-12)
    # against wall time the model-driven runs are curves (their wall time is not zero)
    fig_w = plot_curves(runs, "wall_seconds")
    assert not [ln for ln in fig_w.axes[0].get_lines() if "0 true transitions" in str(ln.get_label())]
    with pytest.raises(ValueError, match="x"):
        plot_curves(runs, "iteration")


def test_load_runs_rejects_duplicates_and_bad_files(tmp_path: Path) -> None:
    a = tmp_path / "a.json"
    a.write_text(json.dumps(runs_fixture()[0]))
    b = tmp_path / "b.json"
    b.write_text(json.dumps(runs_fixture()[0]))
    assert len(load_runs([a])) == 1
    with pytest.raises(ValueError, match="two runs"):
        load_runs([a, b])
    b.write_text(json.dumps({"method": "x"}))
    with pytest.raises(ValueError, match="run record"):
        load_runs([b])


def test_ours_config_and_overrides() -> None:
    cfg = ours_config("model", 2, 1500, {"sampler.name": "dlc_course", "task.gamma": 0.98})
    assert (cfg.method, cfg.seed, cfg.algorithm.iterations, cfg.run.eval_every, cfg.run.num_threads) == ("model", 2, 1500, 125, 1)
    assert cfg.sampler.name == "dlc_course" and cfg.task.gamma == 0.98
    assert ours_config("ddpg", 0, 1500, {"run.eval_every": 50}).run.eval_every == 50
    with pytest.raises(ValueError, match="method"):
        ours_config("td3", 0, 10)
    with pytest.raises(ValueError, match="unknown"):
        ours_config("mixed", 0, 10, {"not_a_field": 1})


def test_rows_of_a_real_run_are_its_evaluations(tmp_path: Path) -> None:
    """A tiny mixed RL run on the model path: rows = the evaluation metrics rows, transitions as counted."""
    rec = train_ours("mixed", 0, 12, {"sampler.name": "dlc_course", "algorithm.batch_size": 16, "run.eval_seeds": 1},
                     out=tmp_path / "r.json")
    assert json.loads((tmp_path / "r.json").read_text()) == json.loads(json.dumps(rec))
    assert [r["iteration"] for r in rec["rows"]] == list(range(1, 13))  # eval_every = round(12 / 12) = 1
    assert rec["rows"][-1]["true_transitions"] == rec["true_transitions"] > 0
    assert rec["rows"][-1]["cost"] == rec["final"]["cost"]


def test_records_from_a_reproduction_folder(tmp_path: Path) -> None:
    """mixed/model/oracle and DDPG's longer run are read back as the study's records; the short DDPG is not."""
    from mixedrl.config import TrainConfig
    from mixedrl.runs import RunDirectory, make_trainer, train

    runs = tmp_path / "runs"
    made = {}
    for label, method in (("mixed", "mixed"), ("ddpg", "ddpg"), ("ddpg_long", "ddpg")):
        cfg = TrainConfig(method=method, seed=1, algorithm=dict(iterations=6, batch_size=16),
                          ddpg=dict(warmup=16, batch_size=16),
                          run=dict(eval_every=3, eval_seeds=1, checkpoint_every=6))
        made[label] = train(make_trainer(cfg), RunDirectory(runs / f"{label}_seed1"))
    records = records_from_reproduction(runs)
    assert sorted((r["method"], r["seed"]) for r in records) == [("ddpg", 1), ("mixed", 1)]
    by = {r["method"]: r for r in records}
    for label, method in (("mixed", "mixed"), ("ddpg_long", "ddpg")):
        assert [r["iteration"] for r in by[method]["rows"]] == [3, 6]
        assert by[method]["rows"][-1]["cost"] == made[label]["cost"]
        assert by[method]["true_transitions"] == made[label]["true_transitions"]
        assert by[method]["overrides"]["source"].endswith(f"{label}_seed1")
    with pytest.raises(FileNotFoundError, match="runs_dir"):
        records_from_reproduction(tmp_path / "nothing")

    # a reproduction trained through mixedrl sweep: DIR/sweep, labels from method and variant
    from mixedrl.sweep import parse_spec, run_sweep

    text = ('methods = ["mixed", "ddpg"]\nseeds = [1]\n[base]\n"algorithm.iterations" = 6\n'
            '"algorithm.batch_size" = 16\n"ddpg.batch_size" = 16\n"ddpg.warmup" = 16\n"run.eval_every" = 3\n'
            '"run.eval_seeds" = 1\n'
            '"run.checkpoint_every" = 6\n[variants.paper]\n[variants.ddpg_long]\nmethods = ["ddpg"]\n'
            '"algorithm.iterations" = 9\n')  # the longer DDPG run (two equal configs are refused)
    run_sweep(parse_spec(text), tmp_path / "repro" / "sweep", workers=1, progress=False)
    for where in (tmp_path / "repro", tmp_path / "repro" / "sweep"):
        records = records_from_reproduction(where)
        assert sorted((r["method"], r["seed"]) for r in records) == [("ddpg", 1), ("mixed", 1)]
        by = {r["method"]: r for r in records}
        assert by["ddpg"]["overrides"]["source"].endswith("variant=ddpg_long__ddpg_seed1")
        assert by["mixed"]["rows"][-1]["cost"] == by["mixed"]["final"]["cost"]


def test_rows_from_metrics_mapping() -> None:
    metrics = [{"iteration": 1, "data/true_transitions": 16.0, "time/elapsed_s": 0.5},
               {"iteration": 2, "data/true_transitions": 32.0, "time/elapsed_s": 1.0, "eval/cost": 9.0,
                "eval/lateral_mae": 0.2, "eval/speed_mae": 0.03}]
    assert rows_from_metrics(metrics) == [{"iteration": 2, "true_transitions": 32, "wall_seconds": 1.0,
                                           "lateral_mae": 0.2, "speed_mae": 0.03, "cost": 9.0}]
    del metrics[1]["time/elapsed_s"]
    with pytest.raises(ValueError, match="elapsed"):
        rows_from_metrics(metrics)


def _script(*argv: str) -> subprocess.CompletedProcess:
    """``experiments/analysis/sample_efficiency.py ARGV`` in a subprocess (tests do not import scripts)."""
    return subprocess.run([sys.executable, str(ROOT / "experiments" / "analysis" / "sample_efficiency.py"), *argv],
                          capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=600)


def test_script_summary(tmp_path: Path) -> None:
    for run in runs_fixture():
        kind = "peers" if run["method"] == "sac" else "ours"
        (tmp_path / kind).mkdir(exist_ok=True)
        (tmp_path / kind / f"{run['method']}_s{run['seed']}.json").write_text(json.dumps(run))
    proc = _script("summary", "--out", str(tmp_path))
    assert proc.returncode == 0, proc.stderr
    for name in ("summary.csv", "summary.json", "curves_transitions.png", "curves_wall.png"):
        assert (tmp_path / name).stat().st_size > 0
    assert [e["method"] for e in json.loads((tmp_path / "summary.json").read_text())] == ["mixed", "model", "sac"]


def test_the_spec_is_ours_config() -> None:
    """experiments/studies/sample_efficiency.toml expands to the configs :func:`ours_config` builds at 1500 iterations."""
    runs = expand(load_spec(ROOT / "experiments" / "studies" / "sample_efficiency.toml"))
    assert len(runs) == 4 * 5
    for run in runs:
        assert run.config == ours_config(run.config.method, run.config.seed, 1500), run.name


def test_records_from_a_sweep_and_the_script(tmp_path: Path) -> None:
    """The runs of a (tiny) sweep become the study's records, as a reproduction's do; the script writes them."""
    spec = parse_spec('methods = ["mixed"]\nseeds = [0]\n[base]\n"algorithm.iterations" = 6\n'
                      '"run.eval_every" = 3\n"run.eval_seeds" = 1\n"algorithm.batch_size" = 16\n')
    doc = run_sweep(spec, tmp_path / "sweep", workers=1, progress=False)
    (rec,) = records_from_sweep(tmp_path / "sweep")
    (row,) = doc["runs"]
    assert (rec["method"], rec["seed"], [r["iteration"] for r in rec["rows"]]) == ("mixed", 0, [3, 6])
    assert rec["rows"][-1]["cost"] == row["metrics"]["cost"] and rec["true_transitions"] == row["true_transitions"]
    proc = _script("from-sweep", str(tmp_path / "sweep"), "--out", str(tmp_path / "study"))
    assert proc.returncode == 0, proc.stderr
    assert json.loads((tmp_path / "study" / "ours" / "mixed_s0.json").read_text()) == json.loads(json.dumps(rec))
    with pytest.raises(FileNotFoundError, match="sweep_dir"):
        records_from_sweep(tmp_path / "nothing")
