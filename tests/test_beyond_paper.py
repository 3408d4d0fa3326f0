"""scripts/beyond_paper.py: the studies beyond the paper (docs/beyond.rst).

Without Ray: the study specs (valid, training settings left to TrainConfig's defaults), the split of a
study into main / shared / witness sweeps (the same runs as the spec, up to the shared key), the reduced
spec, the TOML writer, and the table's arithmetic. Marked ``sweep``: the reduced prior-mismatch study end
to end on a local Ray cluster, then the shipped table checked against the runs' own results.
"""

from __future__ import annotations

import importlib.util
import json
import shutil
import statistics
import sys
from pathlib import Path
from types import ModuleType

import pytest

from mixedrl.config import TrainConfig
from mixedrl.sweep import expand, load_spec, parse_spec

ROOT = Path(__file__).resolve().parents[1]


def _driver() -> ModuleType:
    spec = importlib.util.spec_from_file_location("beyond_paper", ROOT / "scripts" / "beyond_paper.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("beyond_paper", module)
    spec.loader.exec_module(module)
    return module


BP = _driver()


def _comparable(cfg: TrainConfig, drop: str | None = None) -> dict:
    data = cfg.to_dict()
    if drop == "task.prior_force_mean":
        data["task"].pop("prior_force_mean")
    elif drop is not None:
        data.pop(drop)
    return data


# ----------------------------------------------------------------------------------------------------
# the specs and their parts
# ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(BP.STUDIES))
def test_study_specs_leave_training_settings_to_the_defaults(name: str) -> None:
    spec = load_spec(ROOT / BP.STUDIES[name].spec)
    assert all(key.startswith("task.") for key in spec.base), spec.base  # only the experiment, never training
    assert all(key.startswith("task.") or key == "ibe_case" for key in spec.grid), spec.grid
    assert len(spec.seeds) == 5 and "oracle" in spec.methods and "mixed" in spec.methods
    defaults = TrainConfig().to_dict()
    for run in expand(spec):
        data = run.config.to_dict()
        for key in set(defaults) - {"method", "seed", "task", "ibe_case"}:
            assert data[key] == defaults[key], (run.name, key)


def test_the_studies_cover_the_requested_grids() -> None:
    pm = load_spec(ROOT / BP.STUDIES["prior_mismatch"].spec)
    assert pm.grid == {"task.prior_force_mean": (-300.0, 0.0, 150.0, 261.0, 400.0, 600.0, 1000.0)}
    assert pm.methods == ("mixed", "model", "oracle") and pm.seeds == (0, 1, 2, 3, 4)
    laws = [run.config.task.disturbance for run in expand(load_spec(ROOT / BP.STUDIES["disturbance_law"].spec))]
    assert {(d.law, d.variance, d.mean) for d in laws} == {("gaussian", 32.0, 261.0), ("student_t", 32.0, 261.0),
                                                          ("bumps", 32.0, 261.0), ("gaussian", 320.0, 261.0)}
    assert {d.dof for d in laws if d.law == "student_t"} == {3.0}
    grade = expand(load_spec(ROOT / BP.STUDIES["road_grade"].spec))
    assert {(r.config.method, r.config.ibe_case) for r in grade} == {("mixed", 2), ("mixed", 3), ("oracle", 2),
                                                                      ("oracle", 3)}
    assert all(r.config.task.disturbance.grade_amplitude == 0.02 for r in grade)


@pytest.mark.parametrize("name", sorted(BP.STUDIES))
def test_spec_text_round_trips(name: str) -> None:
    spec = load_spec(ROOT / BP.STUDIES[name].spec)
    again = parse_spec(BP.spec_text(list(spec.methods), list(spec.seeds), spec.base,
                                    {k: list(v) for k, v in spec.grid.items()}, "a comment\nover two lines"))
    assert (again.methods, again.seeds, again.base, again.grid) == (spec.methods, spec.seeds, spec.base, spec.grid)
    assert [r.config for r in expand(again)] == [r.config for r in expand(spec)]


@pytest.mark.parametrize("name", ["prior_mismatch", "road_grade"])
def test_the_parts_are_the_spec_runs_with_the_shared_method_once_per_seed(name: str) -> None:
    """main = the spec's runs of the other methods, config for config; shared = one run per seed of the
    shared method, equal to each of the spec's runs of that method but for the shared key; witness = the
    first seed at the key's last value."""
    study = BP.STUDIES[name]
    spec = load_spec(ROOT / study.spec)
    (method, key), = study.shared.items()
    parts = BP.study_parts(spec, study.shared)
    assert list(parts) == ["main", "shared", "witness"]
    runs = expand(spec)
    main = {r.name: r.config for r in expand(parts["main"])}
    assert main == {r.name: r.config for r in runs if r.config.method != method}
    shared = expand(parts["shared"])
    assert sorted(r.config.seed for r in shared) == list(spec.seeds)
    by_seed = {r.config.seed: _comparable(r.config, key) for r in shared}
    for r in runs:
        if r.config.method == method:
            assert _comparable(r.config, key) == by_seed[r.config.seed]
    witness = expand(parts["witness"])
    assert [(r.config.method, r.config.seed) for r in witness] == [(method, spec.seeds[0])]
    assert _comparable(witness[0].config, key) == by_seed[spec.seeds[0]]
    assert witness[0].config.to_dict() != shared[0].config.to_dict()  # the key differs
    assert BP.study_parts(spec, {}) == {"main": spec}
    no_share = BP.study_parts(load_spec(ROOT / BP.STUDIES["disturbance_law"].spec), {})
    assert list(no_share) == ["main"]


def test_reduced_spec() -> None:
    spec = BP.reduce_spec(load_spec(ROOT / BP.STUDIES["prior_mismatch"].spec))
    assert spec.seeds == (0,) and spec.base == {"iterations": BP.REDUCED_ITERATIONS}
    assert spec.grid == {"task.prior_force_mean": (-300.0, 0.0)} and len(expand(spec)) == 6


def test_table_arithmetic_on_synthetic_runs() -> None:
    """Mean, sample std over seeds, ratio and excess over the oracle at the same point, recomputed here
    with the statistics module."""
    costs = {("mixed", 0.0): [10.0, 12.0, 14.0], ("oracle", 0.0): [8.0, 9.0, 10.0],
             ("mixed", 5.0): [20.0, 21.0, 25.0], ("oracle", 5.0): [8.0, 9.0, 10.0]}
    records = []
    for (method, prior), values in costs.items():
        for seed, cost in enumerate(values):
            cfg = TrainConfig(method=method, seed=seed, task={"prior_force_mean": prior}).to_dict()
            records.append({"name": f"{method}{prior}{seed}", "point": {"task.prior_force_mean": prior}, "config": cfg,
                            "method": method, "seed": seed, "error": None, "shared": method == "oracle",
                            "results": {"cost": cost, "speed_mae": cost / 100, "lateral_mae": 1.0}})
    records.append({**records[0], "name": "failed", "error": "RuntimeError: x", "results": None})
    rows = BP.build_table("prior_mismatch", records, collapse_shared=False)
    assert [(r["method"], r["prior_force_mean"]) for r in rows] == list(costs)
    for row in rows:
        values = costs[(row["method"], row["prior_force_mean"])]
        oracle = statistics.mean(costs[("oracle", row["prior_force_mean"])])
        assert row["cost_mean"] == pytest.approx(statistics.mean(values), rel=1e-15)
        assert row["cost_std"] == pytest.approx(statistics.stdev(values), rel=1e-15)
        assert row["ratio_to_oracle"] == pytest.approx(statistics.mean(values) / oracle, rel=1e-15)
        assert row["excess_over_oracle"] == pytest.approx(statistics.mean(values) - oracle, rel=1e-15)
        assert row["runs"] == 3 and row["shared_run"] == (row["method"] == "oracle")
    assert rows[0]["failed"] == 1 and sum(r["failed"] for r in rows) == 1


# ----------------------------------------------------------------------------------------------------
# end to end on a local Ray cluster
# ----------------------------------------------------------------------------------------------------
@pytest.mark.sweep
def test_reduced_prior_mismatch_end_to_end_and_shipped_table(tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                                             ) -> None:
    pytest.importorskip("ray")
    out, dest = tmp_path / "pm", tmp_path / "ship"
    assert BP.main(["run", "prior_mismatch", "--reduced", "--out", str(out), "--num-cpus", "2", "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "prior_mismatch: 6 runs, 0 failed" in printed, printed
    assert json.loads((out / "study.json").read_text())["parts"] == ["main", "shared", "witness"]
    assert BP.main(["ship", "prior_mismatch", "--runs", str(out), "--dest", str(dest)]) == 0
    files = {name: (dest / name).read_bytes() for name in ("table.csv", "table.json", "figure.png")}
    assert files["figure.png"].startswith(b"\x89PNG")
    doc = json.loads(files["table.json"])
    assert doc["reduced"] and doc["shared"]["witness"][0]["identical"]
    rows = doc["rows"]
    assert [(r["prior_force_mean"], r["method"]) for r in rows] == [
        (p, m) for p in (-300.0, 0.0) for m in ("mixed", "model", "oracle")]
    # every figure is the run's own results.json (one seed: the mean is the value, the std 0)
    for row in rows:
        part = "shared" if row["method"] == "oracle" else "main"
        name = f"{row['method']}_seed0" if part == "shared" else \
            f"task.prior_force_mean={row['prior_force_mean']}__{row['method']}_seed0"
        results = json.loads((out / part / "runs" / name / "results.json").read_text())
        assert (row["cost_mean"], row["speed_mae_mean"]) == (results["cost"], results["speed_mae"])
        assert row["cost_std"] == 0.0
        assert row["shared_run"] == (part == "shared")
        oracle = next(r for r in rows if r["method"] == "oracle" and r["prior_force_mean"] == row["prior_force_mean"])
        assert row["ratio_to_oracle"] == row["cost_mean"] / oracle["cost_mean"]
        assert row["excess_over_oracle"] == row["cost_mean"] - oracle["cost_mean"]
    witness = json.loads((out / "witness" / "runs" / "oracle_seed0" / "results.json").read_text())
    assert witness["cost"] == rows[2]["cost_mean"]  # the oracle at the other prior: the same run, proven
    # deterministic: shipping again gives the same bytes
    assert BP.main(["ship", "prior_mismatch", "--runs", str(out), "--dest", str(dest)]) == 0
    assert {name: (dest / name).read_bytes() for name in files} == files
    # a witness that differs from the shared run (the oracle would depend on the prior) is refused
    bad = tmp_path / "bad"
    shutil.copytree(out, bad)
    path = bad / "witness" / "runs" / "oracle_seed0" / "results.json"
    data = json.loads(path.read_text())
    data["cost"] += 1e-9
    path.write_text(json.dumps(data))
    capsys.readouterr()
    assert BP.main(["ship", "prior_mismatch", "--runs", str(bad), "--dest", str(tmp_path / "bad_ship")]) == 2
    assert "--no-share" in capsys.readouterr().err
    assert not (tmp_path / "bad_ship").exists()
