"""The gym benchmark's harness (issue 41, item 4): statistics with known answers, the reduced study end to end."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.stats

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from experiments.analysis import gym_benchmark as gb  # noqa: E402

BACKENDS = ["numpy"] + (["rliable"] if gb.have_rliable() else [])


# ------------------------------------------------------------------------------------------ statistics
@pytest.mark.parametrize("backend", BACKENDS)
def test_iqm_and_interval_of_known_scores(backend: str) -> None:
    # 0..99: the IQM is the mean of 25..74
    scores = np.random.default_rng(0).permutation(np.arange(100.0))
    assert gb.iqm(scores) == 49.5
    # constant scores: every resample has the same IQM, the interval is the point
    est = gb.interval_estimates({"c": np.full((10, 1), 3.25)}, reps=200, backend=backend)["c"]
    assert (est["iqm"], est["lo"], est["hi"]) == (3.25, 3.25, 3.25)
    assert est["backend"] == backend


@pytest.mark.parametrize("backend", BACKENDS)
def test_bootstrap_is_stratified_by_task(backend: str) -> None:
    """Task 0 scores 0, task 1 scores 10 on every run: resampling within each task keeps the half/half
    composition, so the IQM (the middle half of the pooled scores: half 0, half 10) is 5 in every
    resample; resampling the pooled scores would not."""
    scores = np.column_stack([np.zeros(8), np.full(8, 10.0)])
    est = gb.interval_estimates({"a": scores}, reps=300, backend=backend)["a"]
    assert est["iqm"] == pytest.approx(5.0) and est["lo"] == pytest.approx(5.0) and est["hi"] == pytest.approx(5.0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_interval_width_of_normal_scores(backend: str) -> None:
    """IQM of n N(0, 1) scores: asymptotic variance of the 25%-trimmed mean,
    (int_{-c}^{c} x^2 phi + 2 (0.25) c^2) / 0.5^2 / n with c = z_0.75 (= 1.195 / n): the 95% interval is
    +-1.96 sqrt(1.195 / n) around the IQM."""
    n = 400
    x = np.random.default_rng(1).standard_normal((n, 1))
    c = scipy.stats.norm.ppf(0.75)
    inner = (2 * scipy.stats.norm.cdf(c) - 1) - 2 * c * scipy.stats.norm.pdf(c)
    var = (inner + 0.5 * c * c) / 0.25
    assert var == pytest.approx(1.195, abs=1e-3)
    half = 1.96 * math.sqrt(var / n)
    est = gb.interval_estimates({"x": x}, reps=2000, backend=backend)["x"]
    assert est["iqm"] == pytest.approx(scipy.stats.trim_mean(x, 0.25, axis=None), abs=1e-12)
    assert est["lo"] < 0 < est["hi"]
    assert (est["hi"] - est["lo"]) / 2 == pytest.approx(half, rel=0.15)


@pytest.mark.parametrize("backend", BACKENDS)
def test_probability_of_improvement(backend: str) -> None:
    a, b = np.arange(5.0)[:, None], np.arange(5.0, 10.0)[:, None]
    assert gb.probability_of_improvement(b, a) == 1.0 and gb.probability_of_improvement(a, b) == 0.0
    assert gb.probability_of_improvement(a, a) == 0.5
    # ties count half: P(X > Y) + P(X = Y) / 2
    assert gb.probability_of_improvement(np.array([[1.0], [2.0]]), np.array([[1.0], [0.0]])) == 0.875
    # X ~ N(1, 1), Y ~ N(0, 1): P(X > Y) = Phi(1 / sqrt(2))
    rng = np.random.default_rng(2)
    x, y = rng.standard_normal((400, 1)) + 1.0, rng.standard_normal((400, 1))
    est = gb.improvement_estimates({"x,y": (x, y)}, reps=500, backend=backend)["x,y"]
    truth = scipy.stats.norm.cdf(1 / math.sqrt(2))
    assert est["p"] == pytest.approx(gb.probability_of_improvement(x, y), abs=1e-12)
    assert est["p"] == pytest.approx(truth, abs=0.03)
    assert est["lo"] < truth < est["hi"]


@pytest.mark.skipif(not gb.have_rliable(), reason="rliable not installed (extra 'benchmark')")
def test_numpy_statistics_equal_rliable_definitions() -> None:
    from rliable import metrics

    rng = np.random.default_rng(3)
    x, y = rng.normal(size=(10, 2)), rng.normal(0.3, 1, size=(7, 2))
    assert gb.iqm(x) == pytest.approx(float(metrics.aggregate_iqm(x)), abs=1e-12)
    assert gb.probability_of_improvement(x, y) == pytest.approx(float(metrics.probability_of_improvement(x, y)),
                                                                abs=1e-12)
    a = gb.interval_estimates({"x": x}, reps=4000, backend="numpy")["x"]
    b = gb.interval_estimates({"x": x}, reps=4000, backend="rliable")["x"]
    assert a["iqm"] == b["iqm"]
    assert a["lo"] == pytest.approx(b["lo"], abs=0.1) and a["hi"] == pytest.approx(b["hi"], abs=0.1)


@pytest.mark.skipif(not gb.have_rliable(), reason="rliable not installed (extra 'benchmark')")
def test_rliable_intervals_are_reproducible_from_the_seed_and_leave_numpy_global_state() -> None:
    """rliable's stratified bootstrap draws from NumPy's global generator, not from its ``random_state``:
    the same seed gives the same intervals, another seed others, and the caller's global state is kept."""
    rng = np.random.default_rng(5)
    x, y = rng.normal(size=(10, 1)), rng.normal(0.3, 1, size=(10, 1))
    np.random.seed(123)
    before = np.random.get_state()[1].copy()
    runs = [(gb.interval_estimates({"x": x}, reps=2000, seed=s, backend="rliable")["x"],
             gb.improvement_estimates({"p": (x, y)}, reps=2000, seed=s, backend="rliable")["p"]) for s in (0, 0, 1)]
    assert runs[0] == runs[1]
    assert runs[0][0]["lo"] != runs[2][0]["lo"] and runs[0][1]["lo"] != runs[2][1]["lo"]
    assert np.array_equal(np.random.get_state()[1], before)


# ------------------------------------------------------------------------------------------ spec, task
def test_spec_runs() -> None:
    spec = gb.load_spec(gb.SPEC)
    runs = gb.expand_runs(spec)
    ids = [r["id"] for r in runs]
    assert len(ids) == len(set(ids))
    count = {}
    for r in runs:
        count[(r["env"], r["method"])] = count.get((r["env"], r["method"]), 0) + 1
    # 10 seeds, 3 for TD3/DDPG's 300k-step budget on MountainCarContinuous-v0
    assert count[("Pendulum-v1", "td3")] == 10 and count[("MountainCarContinuous-v0", "td3")] == 3
    assert count[("MountainCarContinuous-v0", "ddpg")] == 3 and count[("MountainCarContinuous-v0", "sac")] == 10
    assert count[("Pendulum-v1", "mixed")] == 10
    assert spec["statistics"]["pairs"] == [["mixed", "model"], ["mixed", "oracle"]]
    sac = next(r for r in runs if r["method"] == "sac" and r["env"] == "MountainCarContinuous-v0")
    assert sac["hyperparams"]["n_timesteps"] == 50000 and sac["hyperparams"]["use_sde"] is True
    reduced = gb.expand_runs(spec, reduced=True)
    assert {r["seed"] for r in reduced} == {0, 1} and all(r["reduced"] for r in reduced)


def test_mountain_car_task_is_a_task() -> None:
    import torch

    from mixedrl.envs.gym_models import MountainCarTask
    from mixedrl.task_base import check_task

    assert gb.MountainCarTask is MountainCarTask  # the package's, not a copy in the script
    task = MountainCarTask(force_mean=-0.3)
    check_task(task)
    s = torch.tensor([[-0.5, 0.0], [0.45, 0.01], [task.goal - 0.01, 0.0]], dtype=torch.float64)
    assert task.is_terminal(s).tolist() == [False, True, False]
    c = task.cost(s, torch.zeros(3, 1, dtype=torch.float64))
    assert c[1] == 0 and 0 < c[0] <= 1  # no energy lacking at the flag


# ------------------------------------------------------------------------------------------ end to end
@pytest.mark.peers
def test_reduced_study_end_to_end(tmp_path: Path) -> None:
    pytest.importorskip("stable_baselines3")
    out = tmp_path / "runs"
    assert gb.main(["--reduced", "--out", str(out), "--no-progress"]) == 0
    spec = gb.load_spec(gb.SPEC)
    runs = gb.expand_runs(spec, reduced=True)
    files = sorted(out.glob("*.json"))
    assert len(files) == len(runs) == 2 * 6 * 2  # 2 seeds; 6 methods on 2 envs
    for run in runs:
        res = json.loads((out / f"{run['id']}.json").read_text())
        assert res["config"] == json.loads(json.dumps(run))  # its full config
        rows = res["rows"]
        assert rows[0]["true_transitions"] == 0 and rows[-1]["true_transitions"] == res["true_transitions"]
        assert all(len(r["returns"]) == len(run["evaluation"]["episode_seeds"]) for r in rows)
        assert res["final_return"] == rows[-1]["return"] and math.isfinite(res["final_return"])
        if run["kind"] == "sb3":  # counted, not estimated (SAC's train_freq 32 finishes its last rollout)
            assert res["true_transitions"] >= run["reduced"]["n_timesteps"]
            built, published = res["hyperparameters"], run["hyperparams"]
            for key in ("learning_rate", "gamma", "batch_size", "tau", "ent_coef", "use_sde"):
                if key in published:
                    assert built[key] == published[key], (run["id"], key)
            if "net_arch" in published.get("policy_kwargs", {}):
                arch = built["net_arch"]
                arch = arch if isinstance(arch, list) else arch["pi"]
                assert arch == published["policy_kwargs"]["net_arch"], run["id"]
        else:  # Pendulum-v1 declares its state region: 4 x the iterations, the true drive 4 x less often
            factor = 4 if run["env"] == "Pendulum-v1" else 1
            assert res["region_budget"] == factor and res["steps"] == factor * run["reduced"]["iterations"]
            assert res["trainconfig"]["sampler"]["true_every"] == factor * 10
            # the plant's: 20 steps at every true_every-th iteration from the first, as without the factor
            expected = math.ceil(run["reduced"]["iterations"] / 10) * 20
            assert res["true_transitions"] == (expected if run["mixedrl_method"] == "mixed" else 0)
    # the same policy, the same episode seeds, the same returns: the initial policies of seed 0
    m0 = json.loads((out / "Pendulum-v1__torque1.0__model__s0.json").read_text())
    o0 = json.loads((out / "Pendulum-v1__torque1.0__oracle__s0.json").read_text())
    assert m0["rows"][0]["returns"] == o0["rows"][0]["returns"]
    results = out / "results"
    table = (results / "table.md").read_text()
    assert "| mixed |" in table and "-157.0 +- 88.7 at 20000" in table and "P(mixed > method)" in table
    assert "P(mixed > model) = " in table and "; higher on " in table  # statistics.pairs, with per-seed wins
    assert (results / "returns.png").stat().st_size > 10_000
    cells = json.loads((results / "table.json").read_text())["cells"]
    assert len(cells) == 2 and all(set(c["methods"]) == {r["method"] for r in runs if r["env"] == c["env"]}
                                   for c in cells)
    # resume: every JSON exists, nothing reruns
    before = {f.name: f.stat().st_mtime_ns for f in files}
    assert gb.main(["--reduced", "--out", str(out), "--no-progress", "--analysis-only"]) == 0
    gb.run_all(runs, out, progress=False)
    assert {f.name: f.stat().st_mtime_ns for f in out.glob("*.json")} == before
    # a JSON of another configuration is not silently reused
    changed = dict(runs[0], seed=99)
    changed["id"] = runs[0]["id"]
    with pytest.raises(ValueError, match="exists with a different configuration"):
        gb.run_one(changed, out)
