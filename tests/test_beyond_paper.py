"""experiments.analysis.beyond_paper (the command line experiments/analysis/beyond_paper.py): the studies beyond the paper (docs/beyond.rst).

Without Ray: the study specs (valid, training settings left to TrainConfig's defaults), the split of a
study into main / shared / witness sweeps (the same runs as the spec, up to the shared key), the reduced
spec, the TOML writer, and the table's arithmetic. Marked ``sweep``: the reduced prior-mismatch study end
to end on the local process pool, then the shipped table checked against the runs' own results.
"""

from __future__ import annotations

import json
import shutil
import statistics
from pathlib import Path

import pytest

from mixedrl.config import ONE_STEP_LEARNER, TrainConfig
from mixedrl.sweep import expand, load_spec, parse_spec
from experiments.analysis import beyond_paper as BP

ROOT = Path(__file__).resolve().parents[1]




def _comparable(cfg: TrainConfig, drop: str | None = None) -> dict:
    data = cfg.to_dict()
    if drop == "task.prior_force_mean":
        data["task"].pop("prior_force_mean")
    elif drop is not None:
        section, name = drop.split(".") if "." in drop else (None, drop)
        (data[section] if section else data).pop(name)
    return data


# ----------------------------------------------------------------------------------------------------
# the specs and their parts
# ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(BP.STUDIES))
def test_study_specs_leave_training_settings_to_the_defaults(name: str) -> None:
    """Only the experiment (``task.*``) and the one-step learner's settings the study was trained with
    (:data:`mixedrl.config.ONE_STEP_LEARNER`, pinned), never other training settings."""
    spec = load_spec(ROOT / BP.STUDIES[name].spec)
    pinned = {f"algorithm.{k}": v for k, v in ONE_STEP_LEARNER.items()}
    assert all(key.startswith("task.") or spec.base[key] == pinned.get(key, object()) for key in spec.base), spec.base
    assert set(pinned) <= set(spec.base)
    assert all(key.startswith("task.") or key == "algorithm.ibe_case" for key in spec.grid), spec.grid
    assert len(spec.seeds) == 5 and "oracle" in spec.methods and "mixed" in spec.methods
    defaults = TrainConfig(task="dlc", algorithm=ONE_STEP_LEARNER).to_dict()
    for run in expand(spec):
        data = run.config.to_dict()
        data["algorithm"].pop("ibe_case"), defaults["algorithm"].pop("ibe_case", None)
        for key in set(defaults) - {"method", "seed", "task"}:
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
    assert {(r.config.method, r.config.algorithm.ibe_case) for r in grade} == {("mixed", 2), ("mixed", 3), ("oracle", 2),
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
    full = load_spec(ROOT / BP.STUDIES["prior_mismatch"].spec)
    assert spec.seeds == (0,) and spec.base == {**full.base, "algorithm.iterations": BP.REDUCED_ITERATIONS}
    assert spec.grid == {"task.prior_force_mean": (-300.0, 0.0)} and len(expand(spec)) == 6


@pytest.mark.parametrize("name", sorted(BP.STUDIES))
def test_seed_subset_is_the_spec_runs_of_those_seeds(name: str) -> None:
    """``run --seeds``: the same run names and configs as the full spec, restricted to the seeds."""
    spec = load_spec(ROOT / BP.STUDIES[name].spec)
    sub = BP.subset_seeds(spec, [3, 1])
    assert sub.seeds == (1, 3) and sub.grid == spec.grid and sub.base == spec.base and sub.methods == spec.methods
    assert {r.name: r.config for r in expand(sub)} == {r.name: r.config for r in expand(spec)
                                                       if r.config.seed in (1, 3)}
    for bad in ([], [1, 1], [9]):
        with pytest.raises(ValueError, match="seeds"):
            BP.subset_seeds(spec, bad)


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
    summary = BP.summary_rows("prior_mismatch", rows)
    assert summary[0] == {"prior [N]": "0", "method": "mixed", "runs/failed": "3/1", "cost": "12.00 ± 2.00",
                          "cost / oracle": "1.333", "paired excess over oracle": "3.00 ± 1.00",
                          "speed_mae [m/s]": "0.1200 ± 0.0200", "lateral_mae [m]": "1.000 ± 0.000"}
    # paired by seed with the oracle: mixed at 5 N costs [12, 12, 15] more than the same seed's oracle
    assert (rows[2]["paired_excess_mean"], rows[2]["paired_seeds"]) == (13.0, 3)
    assert rows[2]["paired_excess_std"] == pytest.approx(statistics.stdev([12.0, 12.0, 15.0]), rel=1e-15)
    assert rows[1]["paired_excess_mean"] == 0.0 and rows[1]["paired_excess_std"] == 0.0


def test_disturbance_law_table_and_figure_on_synthetic_runs() -> None:
    """The law's columns, the planned noise back in newtons, the MVC fraction; the figure renders and is
    deterministic."""
    from mixedrl.tasks import task_from_config

    laws = [{"law": "gaussian"}, {"law": "student_t", "dof": 3.0}]
    records = []
    for law in laws:
        for method in ("mixed", "oracle"):
            for seed in (0, 1):
                cfg = TrainConfig(method=method, seed=seed, task={"disturbance": law}).to_dict()
                task = task_from_config(cfg["task"])
                mean = [0.0] * task.state_dim
                var = [0.0] * task.state_dim
                mean[task.noise_index] = (250.0 + seed) * task.force_scale
                var[task.noise_index] = (30.0 + seed) * task.force_scale ** 2
                records.append({"name": f"{law['law']}{method}{seed}", "point": {"task.disturbance": law},
                                "config": cfg, "method": method, "seed": seed, "error": None, "shared": False,
                                "results": {"cost": 20.0 + seed, "speed_mae": 0.01, "lateral_mae": 0.1,
                                            "final_ibe_mean": mean, "final_ibe_cov_diag": var,
                                            "mvc_held_fraction": 0.9 + 0.05 * seed}})
    rows = BP.build_table("disturbance_law", records, collapse_shared=False)
    assert [(r["law"], r["dof"], r["method"]) for r in rows] == [
        ("gaussian", None, "mixed"), ("gaussian", None, "oracle"), ("student_t", 3.0, "mixed"),
        ("student_t", 3.0, "oracle")]
    for row in rows:
        assert (row["mean_N"], row["variance_N2"]) == (261.0, 32.0)
        assert row["ibe_mean_N_mean"] == pytest.approx(250.5) and row["ibe_var_N2_mean"] == pytest.approx(30.5)
        assert row["mvc_held_fraction_mean"] == pytest.approx(0.925)
        assert len(BP._row_records("disturbance_law", row, records)) == 2
    summary = BP.summary_rows("disturbance_law", rows)
    assert summary[2]["law"] == "student_t (3 dof), var 32" and summary[2]["planned mean [N]"] == "250.5 ± 0.7"
    png = BP.make_figure("disturbance_law", rows, None, records)
    assert png.startswith(b"\x89PNG") and png == BP.make_figure("disturbance_law", rows, None, records)


def _fake_study(out: Path, seeds: list[int], grid_value: float = 0.0) -> None:
    """A finished disturbance-law-like study directory (one part, no Ray) on ``seeds``."""
    runs = []
    for seed in seeds:
        for method in ("mixed", "oracle"):
            name = f"{method}_seed{seed}"
            cfg = TrainConfig(method=method, seed=seed, task="dlc").to_dict()
            (out / "main" / "runs" / name).mkdir(parents=True)
            (out / "main" / "runs" / name / "results.json").write_text(json.dumps({"cost": 10.0 * seed + grid_value}))
            runs.append({"name": name, "point": {"task.prior_force_mean": grid_value}, "config": cfg, "error": None})
    (out / "main" / "sweep.json").write_text(json.dumps({"finished": True, "runs": runs}))
    manifest = {"study": "prior_mismatch", "parts": ["main"], "methods": ["mixed", "oracle"], "seeds": seeds,
                "shared_methods": [], "shared_key": None, "grid": {"task.prior_force_mean": [grid_value]}}
    (out / "study.json").write_text(json.dumps(manifest))


def test_collect_many_merges_disjoint_seeds_in_the_spec_order(tmp_path: Path) -> None:
    _fake_study(tmp_path / "a", [1])
    _fake_study(tmp_path / "b", [0, 2])
    manifest, records, checks = BP.collect_many([tmp_path / "a", tmp_path / "b"])
    assert manifest["seeds"] == [0, 1, 2] and checks == []
    assert [(r["method"], r["seed"]) for r in records] == [("mixed", 0), ("mixed", 1), ("mixed", 2),
                                                           ("oracle", 0), ("oracle", 1), ("oracle", 2)]
    assert [r["results"]["cost"] for r in records[:3]] == [0.0, 10.0, 20.0]
    with pytest.raises(ValueError, match="share seeds"):
        BP.collect_many([tmp_path / "a", tmp_path / "a"])
    _fake_study(tmp_path / "c", [3], grid_value=5.0)
    with pytest.raises(ValueError, match="different studies"):
        BP.collect_many([tmp_path / "a", tmp_path / "c"])
    with pytest.raises(ValueError, match="at least one"):
        BP.collect_many([])


def test_case3_vs_case2_is_paired_by_seed() -> None:
    per_seed = [{"ibe_case": c, "method": m, "seed": s, "cost": cost} for (m, c, s, cost) in [
        ("mixed", 2, 0, 40.0), ("mixed", 3, 0, 30.0), ("oracle", None, 0, 25.0),
        ("mixed", 2, 1, 50.0), ("mixed", 3, 1, 45.0), ("oracle", None, 1, 30.0),
        ("mixed", 2, 2, 50.0), ("oracle", None, 2, 30.0)]]  # seed 2: Case 3 failed, left out
    out = BP.case3_vs_case2(per_seed)
    assert out["seeds"] == [0, 1]
    assert out["relative_change"] == pytest.approx([-0.25, -0.1]) and out["ratio_to_oracle"] == pytest.approx([1.2, 1.5])
    assert out["relative_change_mean"] == pytest.approx(-0.175)
    assert out["ratio_to_oracle_std"] == pytest.approx(statistics.stdev([1.2, 1.5]))
    assert BP.case3_vs_case2(per_seed[:2]) is None


def _stub_nmpc(calls: list[float]):
    """A stand-in for validation.nmpc.run_reference: cost = |prior - 261| / 10 + seed, fails at 1000 N."""
    def runner(*, controller: str, gamma: float, horizon: float, disturbance_mean: float, seeds: tuple[int, ...],
               progress: bool) -> dict:
        assert (controller, gamma, horizon) == ("nmpc", 0.99, 2.0) and not progress
        calls.append(disturbance_mean)
        if disturbance_mean == 1000.0:
            raise RuntimeError("IPOPT: Infeasible_Problem_Detected")
        per = [{"seed": s, "lateral_mae": 0.01, "speed_mae": 0.001 * (1 + s), "lateral_max": 0.1,
                "speed_max": 0.01, "cost": abs(disturbance_mean - 261.0) / 10 + s, "terminated": 0.0,
                "solve_ms_mean": 12.3} for s in seeds]
        out = {k: statistics.mean(r[k] for r in per) for k in per[0] if k != "seed"}
        return {**out, "force_N": disturbance_mean, "per_seed": per}
    return runner


def test_nmpc_reference_is_cached_per_prior_and_settings(tmp_path: Path) -> None:
    """Each prior is driven once per settings (the cache is reused, rewritten after every prior); a
    failure is recorded, not raised; the timings are not kept (not reproducible)."""
    path, calls = tmp_path / "nmpc.json", []
    doc = BP.nmpc_reference([0.0, 261.0, 1000.0], path, [0, 1], runner=_stub_nmpc(calls))
    assert calls == [0.0, 261.0, 1000.0]
    assert json.loads(path.read_text()) == doc
    entries = {e["prior_force_mean"]: e for e in doc["entries"]}
    assert entries[1000.0]["error"].startswith("RuntimeError: IPOPT") and "result" not in entries[1000.0]
    assert entries[0.0]["result"]["cost"] == pytest.approx(26.1 + 0.5)
    assert [r["cost"] for r in entries[0.0]["result"]["per_seed"]] == [26.1, 27.1]
    assert "solve_ms_mean" not in entries[0.0]["result"]
    assert entries[0.0]["settings"] == {"controller": "nmpc", "gamma": 0.99, "horizon": 2.0, "seeds": [0, 1]}
    BP.nmpc_reference([-300.0, 0.0, 261.0], path, [0, 1], runner=_stub_nmpc(calls))
    assert calls == [0.0, 261.0, 1000.0, -300.0]  # only the new prior
    BP.nmpc_reference([0.0], path, [0], runner=_stub_nmpc(calls))  # other seeds: driven again, replaced
    doc = json.loads(path.read_text())
    assert calls[-1] == 0.0 and [e["prior_force_mean"] for e in doc["entries"]] == [-300.0, 0.0, 261.0, 1000.0]
    assert next(e for e in doc["entries"] if e["prior_force_mean"] == 0.0)["settings"]["seeds"] == [0]
    (tmp_path / "bad.json").write_text("[]")
    with pytest.raises(ValueError, match="not an NMPC cache"):
        BP.nmpc_reference([0.0], tmp_path / "bad.json", [0], runner=_stub_nmpc(calls))


def test_nmpc_rows() -> None:
    cache = {"entries": [
        {"prior_force_mean": 0.0, "settings": {}, "result": {"per_seed": [
            {"seed": 0, "cost": 10.0, "speed_mae": 0.1, "lateral_mae": 0.2},
            {"seed": 1, "cost": 14.0, "speed_mae": 0.3, "lateral_mae": 0.4}]}},
        {"prior_force_mean": 1000.0, "settings": {}, "error": "RuntimeError: x"},
        {"prior_force_mean": 5.0, "settings": {}, "result": {"per_seed": [{"seed": 0, "cost": 1.0, "speed_mae": 0.0,
                                                                           "lateral_mae": 0.0}]}}]}
    rows = BP.nmpc_rows(cache, [1000.0, 0.0, 150.0], {0.0: 8.0, 1000.0: 9.0})
    assert [(r["prior_force_mean"], r["method"], r["runs"], r["failed"]) for r in rows] == [
        (1000.0, "nmpc", 0, 1), (0.0, "nmpc", 2, 0)]  # the study's order; 5 N is not a prior of the study
    assert rows[0]["cost_mean"] is None and rows[0]["ratio_to_oracle"] is None
    assert rows[1]["cost_mean"] == 12.0 and rows[1]["cost_std"] == pytest.approx(statistics.stdev([10.0, 14.0]))
    assert rows[1]["ratio_to_oracle"] == 1.5 and rows[1]["excess_over_oracle"] == 4.0
    assert rows[1]["speed_mae_mean"] == pytest.approx(0.2)


# ----------------------------------------------------------------------------------------------------
# end to end on the local process pool
# ----------------------------------------------------------------------------------------------------
@pytest.mark.sweep
def test_reduced_prior_mismatch_end_to_end_and_shipped_table(tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                                             ) -> None:
    out, dest = tmp_path / "pm", tmp_path / "ship"
    assert BP.main(["run", "prior_mismatch", "--reduced", "--out", str(out), "--num-cpus", "2", "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "prior_mismatch: 6 runs, 0 failed" in printed, printed
    assert json.loads((out / "study.json").read_text())["parts"] == ["main", "shared", "witness"]
    assert BP.main(["ship", "prior_mismatch", "--runs", str(out), "--dest", str(dest)]) == 0
    files = {name: (dest / name).read_bytes() for name in ("table.csv", "table.json", "summary.csv", "figure.png")}
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
    # a cached NMPC reference (here a stub) is shipped as one row per prior after the learned methods
    BP.nmpc_reference([-300.0, 0.0], dest / BP.NMPC_FILE, [0], runner=_stub_nmpc([]))
    assert BP.main(["ship", "prior_mismatch", "--runs", str(out), "--dest", str(dest)]) == 0
    doc2 = json.loads((dest / "table.json").read_text())
    assert [(r["prior_force_mean"], r["method"]) for r in doc2["rows"]] == [
        (p, m) for p in (-300.0, 0.0) for m in ("mixed", "model", "oracle", "nmpc")]
    assert doc2["rows"][:3] == rows[:3] and doc2["nmpc"]["priors"] == [-300.0, 0.0]
    assert doc2["rows"][3]["cost_mean"] == 56.1 and doc2["rows"][3]["ratio_to_oracle"] == 56.1 / rows[2]["cost_mean"]
    assert (dest / "figure.png").read_bytes() != files["figure.png"]
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
