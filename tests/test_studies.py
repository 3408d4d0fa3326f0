"""The study specs under ``experiments/studies/``: each is valid, and expands to the configs the studies' old builders
(Python dicts of flat, pre-section keys in the scripts) trained, so moving a study to a spec changed no run.

The old designs below are those of ``experiments/analysis/model_based_study.py`` as it was before the move (its
``DESIGNS``; run ``job`` built ``TrainConfig().replace(method, seed, iterations, eval_every=max(100, n // 5),
checkpoint_every=n, num_threads=1, **design)``), written with the dotted keys the flat ones moved to
(mixedrl 0.1.0 read the flat form; the translation was checked equal there: ``state_source = "model"`` is
``sampler.name = "dlc_course"``, ``model_course_horizon`` set both ``sampler.course_horizon`` and
``sampler.true_horizon``).
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mixedrl.config import ONE_STEP_LEARNER, TrainConfig
from mixedrl.runs import RunDirectory
from mixedrl.sweep import expand, load_spec, parse_spec, run_sweep

ROOT = Path(__file__).resolve().parents[1]
#: The sweep specs (``mixedrl sweep``); a spec run by its own script (its header's command
#: ``python experiments/analysis/<name>.py``, e.g. the Gymnasium benchmark) is tested with that script.
STUDIES = sorted(p for p in (ROOT / "experiments" / "studies").glob("*.toml")
                 if f"python experiments/analysis/{p.stem}.py" not in p.read_text())

_MODEL = {"sampler.name": "dlc_course", "sampler.course_starts": "start", "sampler.true_envs": 1,
          "sampler.true_steps": 20, "sampler.true_every": 10, "sampler.course_horizon": 2000,
          "sampler.true_horizon": 2000, "sampler.kick_scale": 1.0, "algorithm.batch_weighting": "uniform",
          "algorithm.lr_decay_iterations": 0}
_G = {**_MODEL, "sampler.course_fraction": 0.75, "sampler.course_start": 500, "sampler.box": 3.0,
      "sampler.kick_prob": 0.01}
_M = {**_G, "algorithm.lr_decay_iterations": 1500, "algorithm.batch_weighting": "relative",
      "algorithm.batch_weight_offset": 1.0}
OLD_DESIGNS: dict[str, dict[str, Any]] = {
    "A": {**_MODEL, "sampler.course_fraction": 0.5, "sampler.course_start": 0, "sampler.box": 4.0,
          "sampler.kick_prob": 0.0},
    "C": {**_MODEL, "sampler.course_fraction": 0.0, "sampler.course_start": 0, "sampler.box": math.inf,
          "sampler.kick_prob": 0.0},
    "G": _G,
    "I": {**_G, "algorithm.lr_decay_iterations": 1500, "algorithm.actor_lr": 1e-3},
    "K": {**_G, "algorithm.lr_decay_iterations": 1500, "algorithm.batch_size": 1024},
    "M": _M,
    "S": {**_M, "sampler.course_starts": "along"},
    "T": {**_M, "sampler.course_starts": "loop"},
}


@pytest.mark.parametrize("path", STUDIES, ids=[p.stem for p in STUDIES])
def test_every_study_spec_is_valid(path: Path) -> None:
    runs = expand(load_spec(path))
    assert runs and len({r.name for r in runs}) == len(runs)


def _old_config(design: str, method: str, seed: int, iterations: int) -> TrainConfig:
    return TrainConfig(algorithm=ONE_STEP_LEARNER).replace(method=method, seed=seed,
                                                        **_budget(iterations, max(100, iterations // 5)),
                                 **OLD_DESIGNS[design])


def _budget(iterations: int, eval_every: int) -> dict[str, int]:
    """The old scripts' ``iterations``, ``eval_every``, ``checkpoint_every = iterations`` and one thread."""
    return {"algorithm.iterations": iterations, "run.eval_every": eval_every, "run.checkpoint_every": iterations,
            "run.num_threads": 1}


def test_model_based_spec_reproduces_the_old_designs() -> None:
    runs = {r.name: r for r in expand(load_spec(ROOT / "experiments" / "studies" / "model_based.toml"))}
    assert len(runs) == 22 * 3 * 5
    checked = 0
    for name, run in runs.items():
        variant = run.point["variant"]
        design, _, budget = variant.partition("_n")
        if design not in OLD_DESIGNS:
            continue
        expected = _old_config(design, run.config.method, run.config.seed, int(budget or 1500))
        assert run.config == expected, name
        checked += 1
    assert checked == (len(OLD_DESIGNS) + 4) * 15  # the designs above, and M and S at two more budgets
    # the designs differ from each other (a variant that silently took the defaults would not)
    configs = {run.point["variant"]: run.config for run in runs.values() if run.config.seed == 0
               and run.config.method == "mixed"}
    assert len({c.to_json() if hasattr(c, "to_json") else str(c.to_dict()) for c in configs.values()}) == 22


@pytest.mark.studies
def test_model_based_study_ships_a_sweep_directory(tmp_path: Path) -> None:
    """The script only analyses: a (tiny) sweep of two variants, shipped through the command line."""
    spec = parse_spec('methods = ["model"]\nseeds = [0]\n[base]\n"algorithm.iterations" = 10\n'
                      '"run.eval_every" = 5\n"run.eval_seeds" = 1\n[variants.S]\n"sampler.course_starts" = "along"\n'
                      '[variants.S_n20]\n"sampler.course_starts" = "along"\n"algorithm.iterations" = 20\n')
    doc = run_sweep(spec, tmp_path / "sweep", workers=1, progress=False)
    dest = tmp_path / "ship"
    proc = subprocess.run([sys.executable, str(ROOT / "experiments" / "analysis" / "model_based_study.py"), "ship",
                           str(tmp_path / "sweep"), "--dest", str(dest)], capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=600)
    assert proc.returncode == 0, proc.stderr
    for row in doc["runs"]:
        n = row["iterations"]
        rec = json.loads((dest / "per_run" / "S" / f"model_s0_n{n}.json").read_text())
        assert (rec["cost"], rec["true_transitions"], rec["config_hash"]) == (
            row["metrics"]["cost"], row["true_transitions"], row["config_hash"])
        assert [e["iteration"] for e in rec["evals"]] == list(range(5, n + 1, 5))
        assert len(rec["u0"]) == 2 and "prior_world" in rec
    summary = json.loads((dest / "summary.json").read_text())
    assert [(r["tag"], r["iterations"], r["cost_mean"]) for r in summary] == [
        ("S", row["iterations"], row["metrics"]["cost"]) for row in doc["runs"]]


#: ``experiments/analysis/preview_study.py``'s candidates and designs before the move (its ``CANDIDATES``, ``DESIGNS``).
OLD_PREVIEW = {"none": [], "P12": [2.0, 4.0, 6.0, 8.0, 10.0, 12.0],
               "P24": [3.0, 6.0, 9.0, 12.0, 15.0, 18.0, 21.0, 24.0], "P6": [1.5, 3.0, 4.5, 6.0]}
OLD_PREVIEW_DESIGNS = {"M": "start", "S": "along"}


def test_preview_spec_reproduces_the_old_config_of() -> None:
    runs = expand(load_spec(ROOT / "experiments" / "studies" / "preview.toml"))
    assert len(runs) == (len(OLD_PREVIEW) * len(OLD_PREVIEW_DESIGNS) + 3 + 1) * 5
    for run in runs:
        design, candidate = run.point["variant"].split("_", 1)
        candidate, _, budget = candidate.partition("_n")
        n = int(budget or 1500)
        if candidate == "P12s":
            continue  # test_preview_spec_p12s_is_the_old_patched_obs_scale
        # the old config_of(candidate, method, seed, iterations=n, design=design)
        old = TrainConfig(task="dlc", algorithm=ONE_STEP_LEARNER).replace(method=run.config.method, seed=run.config.seed, **_budget(n, max(100, n // 5)),
                                    **{"sampler.course_starts": OLD_PREVIEW_DESIGNS[design],
                                       "task.preview_distances": OLD_PREVIEW[candidate]})
        assert run.config == old, run.name


def test_preview_spec_p12s_is_the_old_patched_obs_scale() -> None:
    """M_P12s: P12 under design M with ``task.obs_scale`` set; the task it builds has the observation scale the
    old ``make_task("P12s", cfg)`` patched in after building (``cat(obs_scale[:5], preview_scale(task))``)."""
    import torch

    from mixedrl.tasks import task_from_config
    from validation.preview import preview_scale

    runs = [r for r in expand(load_spec(ROOT / "experiments" / "studies" / "preview.toml")) if r.point["variant"] == "M_P12s"]
    assert len(runs) == 5
    for run in runs:
        old = TrainConfig(task="dlc", algorithm=ONE_STEP_LEARNER).replace(method=run.config.method, seed=run.config.seed, **_budget(1500, 300),
                                    **{"sampler.course_starts": "start", "task.preview_distances": OLD_PREVIEW["P12"]})
        assert run.config.replace(**{"task.obs_scale": None}) == old, run.name
        task, plain = task_from_config(run.config.task), task_from_config(old.task)
        assert torch.equal(task.obs_scale, torch.cat([plain.obs_scale[:5], preview_scale(plain)]))
        assert not torch.equal(task.obs_scale, plain.obs_scale)


@pytest.mark.studies
def test_preview_study_ships_a_sweep_directory(tmp_path: Path) -> None:
    """preview_study.py only analyses: a (tiny) sweep of one variant of its spec's form, shipped through the
    command line into per-run files and the summary."""
    spec = parse_spec('methods = ["mixed"]\nseeds = [0]\n[base]\n"algorithm.iterations" = 10\n"run.eval_every" = 5\n'
                      '"run.eval_seeds" = 1\n[variants.S_P6]\n"task.preview_distances" = [1.5, 3.0, 4.5, 6.0]\n')
    doc = run_sweep(spec, tmp_path / "sweep", workers=1, progress=False)
    dest = tmp_path / "ship"
    proc = subprocess.run([sys.executable, str(ROOT / "experiments" / "analysis" / "preview_study.py"), "ship", str(tmp_path / "sweep"),
                           "--dest", str(dest)], capture_output=True, text=True, cwd=ROOT,
                          env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=600)
    assert proc.returncode == 0, proc.stderr
    (row,) = doc["runs"]
    rec = json.loads((dest / "per_run" / "S" / "P6" / "mixed_s0_n10.json").read_text())
    assert (rec["cost"], rec["config_hash"], rec["preview_distances"]) == (
        row["metrics"]["cost"], row["config_hash"], [1.5, 3.0, 4.5, 6.0])
    assert len(rec["obs_scale"]) == 9 and [e["iteration"] for e in rec["evals"]] == [5, 10]
    (summary,) = json.loads((dest / "summary.json").read_text())
    assert (summary["design"], summary["candidate"], summary["cost_mean"]) == ("S", "P6", row["metrics"]["cost"])


def test_reproduction_spec_is_the_reproductions_run_config() -> None:
    from validation.reproduce import run_config

    runs = expand(load_spec(ROOT / "experiments" / "studies" / "reproduction.toml"))
    assert len(runs) == 7 * 5  # four methods, DDPG's longer budget, mixed and model-driven with the paper preset
    labels = []
    for run in runs:
        label = {"ddpg_long": "ddpg_long", "paper_preset": f"{run.config.method}_paper"}.get(
            run.point["variant"], run.config.method)
        assert run.config == run_config(label, run.config.seed), run.name
        labels.append(label)
    assert sorted(set(labels)) == ["ddpg", "ddpg_long", "mixed", "mixed_paper", "model", "model_paper", "oracle"]


def test_the_reproductions_spec_is_the_shipped_spec_with_the_theory_observer() -> None:
    from validation.reproduce import reproduction_spec, run_config

    shipped = load_spec(ROOT / "experiments" / "studies" / "reproduction.toml")
    ours = reproduction_spec(5)
    assert [(r.name, r.config) for r in expand(ours)] == [(r.name, r.config) for r in expand(shipped)]
    assert ours.observer == shipped.observer == "validation.reproduce:theory_observer"
    quick = reproduction_spec(2, quick=True)
    assert quick.observer == "validation.reproduce:quick_theory_observer"
    for run in expand(quick):
        label = {"ddpg_long": "ddpg_long", "paper_preset": f"{run.config.method}_paper"}.get(
            run.point["variant"], run.config.method)
        assert run.config == run_config(label, run.config.seed, quick=True), run.name


def test_the_theory_observer_reads_the_run_and_changes_none_of_its_numbers(tmp_path: Path) -> None:
    """A batch of two runs (the reproduction's quick config cut to 60 iterations, a batch of 32 states and
    4-step model rollouts) with the theory observer and without: the same rows bit for bit, plus the theory
    checks every 50th iteration."""
    from validation.reproduce import run_config

    short = {"algorithm.iterations": 60, "algorithm.batch_size": 32, "algorithm.rollout_horizon": 4,
             "run.eval_every": 30, "run.checkpoint_every": 30}
    config = run_config("mixed", 0, quick=True).replace(**short)
    text = 'methods = ["mixed", "oracle"]\nseeds = [0]\n[base]\n' + "".join(
        f'"{k}" = {json.dumps(v)}\n' for k, v in {**short, "run.eval_seeds": 1, "ddpg.warmup": 500}.items())
    plain = parse_spec(text)
    observed = parse_spec('observer = "validation.reproduce:quick_theory_observer"\n' + text)
    assert expand(plain)[0].config == config
    docs = [run_sweep(spec, tmp_path / name, workers=1, progress=False)
            for name, spec in (("plain", plain), ("observed", observed))]
    for a, b in zip(*(d["runs"] for d in docs)):
        rows_a = RunDirectory(tmp_path / "plain" / a["run_dir"]).read_metrics()
        rows_b = RunDirectory(tmp_path / "observed" / b["run_dir"]).read_metrics()
        theory = [r["iteration"] for r in rows_b if "theory/lyapunov" in r]
        assert theory == [1, 51]  # before iterations k = 0 and 50
        strip = [{k: v for k, v in r.items() if not k.startswith(("theory/", "time/"))} for r in rows_b]
        assert strip == [{k: v for k, v in r.items() if not k.startswith("time/")} for r in rows_a]
        for key in ("lateral_mae", "speed_mae", "cost", "iterations_to_converge", "mvc_held_fraction"):
            assert a["metrics"][key] == b["metrics"][key], key
    with pytest.raises(ValueError, match="^observer: .*no callable 'nothing'"):
        parse_spec('observer = "validation.reproduce:nothing"\n' + text)
    with pytest.raises(ValueError, match="^observer: cannot import"):
        parse_spec('observer = "no_such_module:f"\n' + text)
    with pytest.raises(ValueError, match="^observer: expected"):
        parse_spec('observer = 3\n' + text)


@pytest.mark.studies
def test_long_training_spec_and_its_observer_only_reads_the_runs() -> None:
    from experiments.analysis.long_training_observer import LongTrainingObserver
    from mixedrl.runs import make_trainer, train_batch

    runs = expand(load_spec(ROOT / "experiments" / "studies" / "long_training.toml"))
    assert [(r.config.method, r.config.seed, r.config.algorithm.iterations) for r in runs] == \
        [("mixed", 0, 10000), ("oracle", 0, 10000)]
    # the old script's config: TrainConfig(method, seed=0, iterations=10000, eval_every=10000)
    for r in runs:
        # ... with the one-step learner of its time (ONE_STEP_LEARNER, the spec's pins)
        old = TrainConfig(method=r.config.method, seed=0, task="dlc",
                          algorithm={**ONE_STEP_LEARNER, "iterations": 10000}, run={"eval_every": 10000})
        assert r.config.replace(**{"run.checkpoint_every": old.run.checkpoint_every}) == old
    small = [r.config.replace(**{"algorithm.iterations": 6, "run.eval_every": 100, "run.checkpoint_every": 100,
                                 "run.eval_seeds": 1, "algorithm.batch_size": 64}) for r in runs]
    plain = train_batch([make_trainer(c) for c in small], progress=False)
    seen = train_batch([make_trainer(c) for c in small], progress=False,
                       observers=[LongTrainingObserver(3), LongTrainingObserver(3)])
    for a, b in zip(plain, seen):
        recorded = [r["iteration"] for r in b["metrics"] if "long/J_train" in r]
        assert recorded == [3, 6]
        assert all(np.isfinite(r["long/J_train"]) and "long/dax_de_y" in r for r in b["metrics"] if "long/J_train" in r)
        strip = [{k: v for k, v in r.items() if not k.startswith(("long/", "time/"))} for r in b["metrics"]]
        assert strip == [{k: v for k, v in r.items() if not k.startswith("time/")} for r in a["metrics"]]
        assert a["final"] == b["final"]


def _old_precision_config(method: str, seed: int, iterations: int = 1500) -> TrainConfig:
    """``experiments/analysis/precision_study.py``'s ``run`` before the move (its ``bellman1`` runs): the
    placeholder ``task="linear"`` config it trained ``PendulumTask()`` with, its task the pendulum's."""
    cfg = TrainConfig(method=method, task="linear", seed=seed,
                      algorithm={**ONE_STEP_LEARNER, "iterations": iterations, "batch_size": 256, "horizon": 100,
                                 "batch_weighting": "relative", "lr_decay_iterations": iterations},
                      sampler={"name": "model_rollouts", "true_horizon": 100, "box": 3.0}, run={"eval_every": 300})
    return TrainConfig.from_dict({**cfg.to_dict(), "task": {"name": "pendulum"}})


def test_precision_spec_reproduces_the_old_script_configs() -> None:
    from mixedrl.envs.pendulum import PendulumTask
    from mixedrl.tasks import task_from_config

    runs = expand(load_spec(ROOT / "experiments" / "studies" / "precision_pendulum.toml"))
    assert len(runs) == 3 * 3
    seen = set()
    for run in runs:
        assert run.point["variant"] == "bellman1"
        assert run.config == _old_precision_config(run.config.method, run.config.seed), run.name
        task = task_from_config(run.config.task)
        assert isinstance(task, PendulumTask) and vars(task).keys() == vars(PendulumTask()).keys()
        assert all(np.array_equal(np.asarray(getattr(task, k)), np.asarray(v)) for k, v in vars(PendulumTask()).items())
        seen.add((run.config.method, run.config.seed))
    assert seen == {(m, s) for m in ("mixed", "model", "oracle") for s in (0, 1, 2)}


@pytest.mark.studies
def test_precision_study_ships_a_sweep_directory(tmp_path: Path) -> None:
    """precision_study.py only analyses: a tiny pendulum sweep (2 iterations) of the spec's form, shipped
    through the command line into the table."""
    spec = parse_spec('methods = ["mixed"]\nseeds = [0]\n[base]\n"task.name" = "pendulum"\n'
                      '"algorithm.iterations" = 2\n"algorithm.batch_size" = 16\n"run.eval_every" = 2\n'
                      '"run.eval_seeds" = 1\n[variants.bellman1]\n')
    doc = run_sweep(spec, tmp_path / "sweep", workers=1, progress=False)
    dest = tmp_path / "ship"
    proc = subprocess.run([sys.executable, str(ROOT / "experiments" / "analysis" / "precision_study.py"), "ship",
                           str(tmp_path / "sweep"), "--dest", str(dest)], capture_output=True, text=True, cwd=ROOT,
                          env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=600)
    assert proc.returncode == 0, proc.stderr
    (row,) = doc["runs"]
    (rec,) = json.loads((dest / "rows.json").read_text())
    results = json.loads((tmp_path / "sweep" / row["run_dir"] / "results.json").read_text())
    assert (rec["variant"], rec["method"], rec["iterations"]) == ("bellman1", "mixed", 2)
    assert (rec["cost"], rec["theta"]) == (row["metrics"]["cost"], results["final"]["mean_state_0"])
    # the IBE estimate of the loaded checkpoint is the run's final one (0.05 / 1 = xi per N m of the default)
    assert rec["tau_hat"] == pytest.approx(results["final_ibe_mean"][0] / 0.05, rel=1e-12)
    assert rec["tau_hat"] != 0.0  # mixed RL moved off the prior's 0
    table = (dest / "table.md").read_text().splitlines()
    assert table[0].startswith("variant | method | seed | cost") and table[2].startswith("bellman1 | mixed | 0 | ")
    assert table[2] in proc.stdout


@pytest.mark.studies
def test_analyses_with_the_lq_feedforward_evaluate_the_same_checkpoints_again(tmp_path: Path) -> None:
    """precision_study.py and seed_statistics.py --feedforward lq_ss: each run's final actor evaluated again with
    the LQ feed-forward (its action near the optimum's steady state is the optimum's there for the run's own noise
    mean), the learned actor's own error kept beside it; the retired ``lq`` is refused."""
    spec = parse_spec('methods = ["mixed", "model"]\nseeds = [0]\n[base]\n"task.name" = "pendulum"\n'
                      '"algorithm.iterations" = 2\n"algorithm.batch_size" = 16\n"run.eval_every" = 2\n'
                      '"run.eval_seeds" = 1\n')
    run_sweep(spec, tmp_path / "sweep", workers=1, progress=False)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([sys.executable, str(ROOT / "experiments" / "analysis" / "precision_study.py"), "ship", str(tmp_path / "sweep"),
                           "--feedforward", "lq_ss", "--dest", str(tmp_path / "pend")], capture_output=True,
                          text=True, cwd=ROOT, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr
    rows = json.loads((tmp_path / "pend" / "rows.json").read_text())
    assert {r["feedforward"] for r in rows} == {"lq_ss"}
    assert "Summary (feedforward = lq_ss)" in proc.stdout
    assert json.loads((tmp_path / "pend" / "summary.json").read_text())[""]["methods"].keys() == {"mixed", "model"}
    proc = subprocess.run([sys.executable, str(ROOT / "experiments" / "analysis" / "seed_statistics.py"), str(tmp_path / "sweep"),
                           "--feedforward", "lq_ss", "--dest", str(tmp_path / "stats")], capture_output=True, text=True,
                          cwd=ROOT, env=env, timeout=600)
    assert proc.returncode == 2 and "has no course errors" in proc.stderr  # Table I's analysis, not the pendulum's
    spec = parse_spec('methods = ["mixed", "model"]\nseeds = [0, 1]\n[base]\n"algorithm.iterations" = 2\n'
                      '"algorithm.batch_size" = 16\n"run.eval_every" = 2\n"run.eval_seeds" = 1\n')
    run_sweep(spec, tmp_path / "dlc", workers=1, progress=False)
    for ff in ([], ["--feedforward", "lq_ss"]):
        proc = subprocess.run([sys.executable, str(ROOT / "experiments" / "analysis" / "seed_statistics.py"), str(tmp_path / "dlc"),
                               *ff, "--dest", str(tmp_path / f"stats{len(ff)}")], capture_output=True, text=True,
                              cwd=ROOT, env=env, timeout=600)
        assert proc.returncode == 0, proc.stderr
    learned, shifted = (list(csv.DictReader((tmp_path / f"stats{n}" / "per_seed.csv").open())) for n in (0, 2))
    for a, b in zip(learned, shifted):
        assert float(a["ax_error"]) == float(b["ax_error_learned"])  # the learned actor's own error kept beside
        assert b["lateral_mae"] != a["lateral_mae"]  # evaluated again, with the shifted policy
    proc = subprocess.run([sys.executable, str(ROOT / "experiments" / "analysis" / "seed_statistics.py"),
                           str(tmp_path / "dlc"), "--feedforward", "lq", "--dest", str(tmp_path / "stats_lq")],
                          capture_output=True, text=True, cwd=ROOT, env=env, timeout=600)
    assert proc.returncode == 2 and "invalid choice: 'lq'" in proc.stderr  # retired
    assert "algorithm.feedforward = 'lq_ss'" in (tmp_path / "stats2" / "table.txt").read_text()


def _run_script(name: str, *args: object) -> subprocess.CompletedProcess:
    """``python experiments/analysis/NAME ARGS`` from the repository root, with the repository on the path."""
    return subprocess.run([sys.executable, str(ROOT / "experiments" / "analysis" / name), *map(str, args)], capture_output=True,
                          text=True, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=600)


@pytest.mark.studies
def test_precision_study_lqr_yardstick_is_the_lq_optimums_affine_policy(tmp_path: Path) -> None:
    """precision_study.py ship --lqr on a pendulum sweep: the LQR is evaluated on each run's own evaluation seeds
    and summarised per method; the yardstick policy has the optimum's action and gain at the equilibrium."""
    spec = parse_spec('methods = ["mixed", "oracle"]\nseeds = [0, 1]\n[base]\n"task.name" = "pendulum"\n'
                      '"algorithm.iterations" = 2\n"algorithm.batch_size" = 16\n'
                      '"run.eval_every" = 2\n"run.eval_seeds" = 1\n')
    run_sweep(spec, tmp_path / "sweep", workers=1, progress=False)
    proc = _run_script("precision_study.py", "ship", tmp_path / "sweep", "--lqr", "--dest", tmp_path / "pend")
    assert proc.returncode == 0, proc.stderr
    rows = json.loads((tmp_path / "pend" / "rows.json").read_text())
    yard = json.loads((tmp_path / "pend" / "summary.json").read_text())[""]["lqr_evaluated"]
    by_seed = {r["seed"]: r["lqr_evaluated"]["true_mean"]["cost"] for r in rows}
    assert by_seed[0] != by_seed[1]  # each run's own evaluation seeds
    assert yard["true_mean"]["cost_mean"] == pytest.approx(np.mean(list(by_seed.values())), rel=1e-12)
    assert yard["methods"].keys() == {"mixed", "oracle"} and yard["methods"]["oracle"]["true_mean"]["n"] == 2
    # the yardstick policy is the LQ optimum's affine policy: its action and gain at the equilibrium
    import importlib.util
    mod_spec = importlib.util.spec_from_file_location("precision_study", ROOT / "experiments" / "analysis" / "precision_study.py")
    mod = importlib.util.module_from_spec(mod_spec)
    mod_spec.loader.exec_module(mod)
    from mixedrl.envs.pendulum import PendulumTask
    from mixedrl.precision import policy_gap
    task = PendulumTask()
    gap = policy_gap(task, mod.LQRPolicy(task, task.true_mean), task.true_mean)
    assert max(abs(e) for e in gap["action_error"]) < 1e-6 and gap["gain_error_rel"] < 1e-6
    prior = policy_gap(task, mod.LQRPolicy(task, task.prior_mean), task.true_mean)
    assert max(abs(e) for e in prior["action_error"]) > 0.1  # the prior's LQR has another feed-forward


@pytest.mark.studies
def test_custom_defaults_spec_varies_only_the_two_settings_and_its_script_ships_the_table(tmp_path: Path) -> None:
    """experiments/studies/custom_defaults.toml: each variant differs from the generic defaults of its task only in
    algorithm.batch_weighting and sampler.box; experiments/analysis/custom_defaults.py turns a tiny sweep of that form into
    the table (per variant and method, the paired difference against uniform_inf)."""
    runs = expand(load_spec(ROOT / "experiments" / "studies" / "custom_defaults.toml"))
    assert len(runs) == 80
    for r in runs:
        generic = TrainConfig(method=r.config.method, seed=r.config.seed, task=r.config.task.name,
                              algorithm={**ONE_STEP_LEARNER, "batch_weighting": r.config.algorithm.batch_weighting},
                              sampler={"box": r.config.sampler.box}, run={"eval_every": 300})
        assert r.config.to_dict() == generic.to_dict(), r.name
    spec = parse_spec('methods = ["mixed"]\nseeds = [0, 1]\n[base]\n"task.name" = "pendulum"\n'
                      '"algorithm.iterations" = 2\n"algorithm.batch_size" = 16\n"run.eval_every" = 2\n'
                      '"run.eval_seeds" = 1\n[variants.pendulum_uniform_inf]\n"algorithm.batch_weighting" = "uniform"\n'
                      '"sampler.box" = "inf"\n[variants.pendulum_relative_box3]\n')
    doc = run_sweep(spec, tmp_path / "sweep", workers=1, progress=False)
    proc = _run_script("custom_defaults.py", tmp_path / "sweep", "--dest", tmp_path / "ship")
    assert proc.returncode == 0, proc.stderr
    rows = json.loads((tmp_path / "ship" / "rows.json").read_text())
    assert sorted((r["variant"], r["seed"]) for r in rows) == [("relative_box3", 0), ("relative_box3", 1),
                                                              ("uniform_inf", 0), ("uniform_inf", 1)]
    costs = {(r["point"]["variant"], r["seed"]): r["metrics"]["cost"] for r in doc["runs"]}
    for r in rows:
        assert r["cost"] == costs[(f"pendulum_{r['variant']}", r["seed"])]
    lines = (tmp_path / "ship" / "table.md").read_text().splitlines()
    assert lines[2].startswith("| pendulum | mixed | relative_box3 |") and "/2 |" in lines[2]  # paired: 2 seeds
    assert lines[3].startswith("| pendulum | mixed | uniform_inf |") and lines[3].endswith("| - | - |")
    assert _run_script("custom_defaults.py", tmp_path / "nothing").returncode == 2


def test_ddpg_seeds20_spec_is_the_reproductions_ddpg_on_more_seeds() -> None:
    """experiments/studies/table1_seeds20_ddpg.toml: its ``ddpg_long`` runs of seeds 0-4 are exactly the
    reproduction's (so the shipped Table I's longer-DDPG rows are five of its twenty seeds) in every setting DDPG
    reads; its ``paper`` runs are DDPG at the one-step learner's 1500 iterations, the reproduction's at the
    library's budget; seeds 0-19 each once per variant."""
    reads = ("iterations", "horizon", "hidden_sizes", "value_output", "lr_decay_to", "lr_decay_iterations")

    def ddpg_view(config: TrainConfig) -> dict:
        data = config.to_dict()
        data["algorithm"] = {k: data["algorithm"][k] for k in reads}
        return data

    ours = expand(load_spec(ROOT / "experiments" / "studies" / "table1_seeds20_ddpg.toml"))
    repro = [r for r in expand(load_spec(ROOT / "experiments" / "studies" / "reproduction.toml")) if r.config.method == "ddpg"]
    assert len(ours) == 40 and len(repro) == 10
    key = {(r.point["variant"], r.config.seed): r.config for r in ours}
    assert sorted(s for v, s in key if v == "ddpg_long") == list(range(20))
    for r in repro:
        mine = key[(r.point["variant"], r.config.seed)]
        if r.point["variant"] == "ddpg_long":
            assert ddpg_view(mine) == ddpg_view(r.config), r.name
        else:
            assert (mine.algorithm.iterations, r.config.algorithm.iterations) == (1500, TrainConfig().algorithm.iterations)
            assert ddpg_view(mine.replace(**{"algorithm.iterations": r.config.algorithm.iterations})) == \
                ddpg_view(r.config), r.name


def test_seed_statistics_keys_variants_apart_and_reads_its_own_csv_back(tmp_path: Path) -> None:
    """seed_statistics.py: a sweep's variants are separate rows (``ddpg[paper]``, not one merged ``ddpg``),
    mixed RL is paired with each of them seed by seed, and a shipped ``per_seed.csv`` read back as a source
    gives the same figures as the sweep it came from (the 20-seed DDPG rows beside the shipped Algorithm-2
    rows)."""
    algo2 = parse_spec('methods = ["mixed"]\nseeds = [0, 1]\n[base]\n"algorithm.iterations" = 2\n'
                       '"algorithm.batch_size" = 16\n"run.eval_every" = 2\n"run.eval_seeds" = 1\n')
    ddpg = parse_spec('methods = ["ddpg"]\nseeds = [0, 1]\n[base]\n"algorithm.iterations" = 2\n"ddpg.envs" = 2\n'
                      '"ddpg.warmup" = 8\n"ddpg.batch_size" = 8\n"run.eval_every" = 2\n"run.eval_seeds" = 1\n'
                      '[variants.short]\n[variants.longer]\n"algorithm.iterations" = 3\n')
    run_sweep(algo2, tmp_path / "a2", workers=1, progress=False)
    doc = run_sweep(ddpg, tmp_path / "ddpg", workers=1, progress=False)
    assert _run_script("seed_statistics.py", tmp_path / "a2", "--dest", tmp_path / "first").returncode == 0
    proc = _run_script("seed_statistics.py", tmp_path / "first" / "per_seed.csv", tmp_path / "ddpg",
                       "--dest", tmp_path / "both")
    assert proc.returncode == 0, proc.stderr
    first = json.loads((tmp_path / "first" / "summary.json").read_text())
    both = json.loads((tmp_path / "both" / "summary.json").read_text())
    assert both["methods"]["mixed"] == first["methods"]["mixed"]  # the csv round trip is exact
    assert set(both["methods"]) == {"mixed", "ddpg[short]", "ddpg[longer]"}
    cost = {(r["point"]["variant"], r["seed"]): r["metrics"]["cost"] for r in doc["runs"]}
    mixed = {int(r["seed"]): float(r["cost"]) for r in csv.DictReader((tmp_path / "first" / "per_seed.csv").open())}
    for variant in ("short", "longer"):
        assert both["methods"][f"ddpg[{variant}]"]["cost"]["mean"] == pytest.approx(
            np.mean([cost[(variant, s)] for s in (0, 1)]), rel=1e-12)
        pair = both["pairs"][f"mixed-ddpg[{variant}]"]["cost"]
        assert pair["wins"] == sum(mixed[s] < cost[(variant, s)] for s in (0, 1))
        assert pair["difference"] == pytest.approx(np.mean([mixed[s] - cost[(variant, s)] for s in (0, 1)]), rel=1e-12)
    assert f"Rows from {tmp_path / 'ddpg'}: ddpg[longer], ddpg[short]" in proc.stdout
    again = _run_script("seed_statistics.py", tmp_path / "first" / "per_seed.csv", tmp_path / "a2",
                        "--dest", tmp_path / "x")
    assert again.returncode == 2 and "also come from an earlier source" in again.stderr


def _per_seed_csv(path: Path, iterations: int, costs: dict[str, list[float]], left: dict[str, list[int]] = {},
                  speed: dict[str, list[float]] = {}) -> Path:
    """A ``per_seed.csv`` as seed_statistics.py writes it, with the given course costs (and speed errors) per
    method and seed."""
    rows = [{"method": m, "seed": s, "lateral_mae": 0.1, "speed_mae": speed[m][s] if m in speed else 0.01,
             "cost": c, "ax_error": 0.0,
             "delta_error": 0.0, "left_road": float(s in left.get(m, [])), "iterations": iterations}
            for m, cs in costs.items() for s, c in enumerate(cs)]
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    return path


@pytest.mark.studies
def test_budget_plateau_measures_the_rise_of_the_mean_and_the_diverged_seeds(tmp_path: Path) -> None:
    """budget_plateau.py: the ratio of mean costs from one budget to the next (paired over the seeds), the
    5% target met or missed on it, a seed whose cost rose by more than 50% or that left the road named as
    diverged, and errors for sources it cannot order."""
    a = _per_seed_csv(tmp_path / "a" / "per_seed.csv", 1500, {"mixed": [20.0, 22.0, 24.0, 26.0],
                                                              "model": [30.0, 30.0, 30.0, 30.0]})
    b = _per_seed_csv(tmp_path / "b" / "per_seed.csv", 4000, {"mixed": [20.0, 22.0, 24.0, 26.0 * 1.6],
                                                              "model": [31.0, 31.0, 31.0, 31.0]})
    c = _per_seed_csv(tmp_path / "c" / "per_seed.csv", 10000, {"mixed": [20.0, 22.0, 24.0, 26.0 * 1.6],
                                                               "model": [31.0, 31.0, 31.0, 31.0]},
                      left={"model": [2]})
    proc = _run_script("budget_plateau.py", b, a, c, "--dest", tmp_path / "out")  # any order: sorted by budget
    assert proc.returncode == 0, proc.stderr
    doc = json.loads((tmp_path / "out" / "budgets.json").read_text())
    assert doc["budgets"] == [1500, 4000, 10000] and list(doc["rows"]) == ["mixed", "model"]
    mixed, model = doc["rows"]["mixed"]["steps"], doc["rows"]["model"]["steps"]
    assert mixed[0]["mean_ratio"] == pytest.approx((20 + 22 + 24 + 41.6) / 92.0, rel=1e-12)
    assert (mixed[0]["diverged_seeds"], mixed[0]["plateau_met"]) == ([3], False)  # +17% mean, seed 3 +60%
    assert (mixed[1]["mean_ratio"], mixed[1]["diverged_seeds"], mixed[1]["plateau_met"]) == (1.0, [], True)
    assert (model[0]["mean_ratio"], model[0]["rose_on"], model[0]["plateau_met"]) == (pytest.approx(31 / 30), 4, True)
    assert (model[1]["diverged_seeds"], model[1]["plateau_met"]) == ([2], False)  # left the road
    assert doc["rows"]["mixed"]["per_budget"]["4000"]["worst_seed"] == 3
    assert "MISSED" in proc.stdout and "diverged [3]" in proc.stdout
    twice = _run_script("budget_plateau.py", a, a, "--dest", tmp_path / "x")
    assert twice.returncode == 2 and "of the budget of 1500 iterations also come from an earlier" in twice.stderr
    assert _run_script("budget_plateau.py", a, "--dest", tmp_path / "x").returncode == 2


@pytest.mark.studies
def test_win_odds_is_the_normal_model_of_the_paired_speed_difference(tmp_path: Path) -> None:
    """win_odds.py: p = Phi(mean(d) / std(d)) of d = model - mixed, P(Binomial(20, p) >= 18), and mixed RL's
    mean + 1.8675 std, computed here from the definitions on hand-made figures."""
    from scipy import stats

    mixed = [0.010, 0.012, 0.009, 0.011, 0.008]
    model = [0.014, 0.013, 0.015, 0.010, 0.016]
    path = _per_seed_csv(tmp_path / "s" / "per_seed.csv", 1500, {"mixed": [1.0] * 5, "model": [1.0] * 5},
                         speed={"mixed": mixed, "model": model})
    proc = _run_script("win_odds.py", path, "--out", tmp_path / "odds.txt")
    assert proc.returncode == 0, proc.stderr
    d = np.subtract(model, mixed)
    p = stats.norm.cdf(d.mean() / d.std(ddof=1))
    worst = np.mean(mixed) + 1.8675 * np.std(mixed, ddof=1)
    text = (tmp_path / "odds.txt").read_text()
    assert f"wins 4 of 5   p {p:.3f}   P18 {stats.binom.sf(17, 20, p):.2f}" in text
    assert f"expected worst of 20 {worst:.4f}" in text
    only = _per_seed_csv(tmp_path / "m" / "per_seed.csv", 1500, {"mixed": [1.0] * 5})
    bad = _run_script("win_odds.py", only, "--out", tmp_path / "x.txt")
    assert bad.returncode == 2 and "needs the rows of mixed and model-driven RL" in bad.stderr


def _course_run(root: Path, method: str, seed: int, losses: list[float], speed: dict[int, float],
                start: int = 4, variant: str = "") -> None:
    """A run directory as a sweep leaves it, with the given critic losses (iterations 1, 2, ...) and
    evaluations, its course sampler switching at ``start`` (a spec's ``variant`` in its name)."""
    run = root / "runs" / ((f"variant={variant}__" if variant else "") + f"{method}_seed{seed}")
    run.mkdir(parents=True)
    (run / "config.json").write_text(json.dumps({"method": method, "seed": seed, "sampler": {
        "name": "dlc_course", "course_start": start}}))
    with (run / "metrics.csv").open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["iteration", "train/critic_loss", "eval/speed_mae"])
        for k, loss in enumerate(losses, start=1):
            writer.writerow([k, loss, speed.get(k, "")])


@pytest.mark.studies
def test_course_switch_measures_the_critics_rise_against_the_speed_error(tmp_path: Path) -> None:
    """course_switch.py: rise = the largest critic loss over the 3 w iterations after course_start (ramp 0) over the
    median of the w before; change = last evaluation - the one at course_start; Spearman's rho of the two
    (computed here from the definitions); errors naming the run that cannot be measured."""
    from scipy import stats

    rises = {0: 2.0, 1: 8.0, 2: 4.0, 3: 16.0}
    changes = {0: 0.001, 1: 0.004, 2: 0.002, 3: 0.010}
    for s, r in rises.items():  # w = 2: before = median(loss at 3, 4) = 1; the peak r at 7 (9 r at 11: outside)
        _course_run(tmp_path / "sw", "mixed", s, [5.0, 5.0, 1.0, 1.0, 1.5, 1.0, r, 1.0, 1.0, 1.0, 9.0 * r, 1.0],
                    {4: 0.01, 12: 0.01 + changes[s]})
    proc = _run_script("course_switch.py", tmp_path / "sw", "--dest", tmp_path / "out", "--window", "2")
    assert proc.returncode == 0, proc.stderr
    doc = json.loads((tmp_path / "out" / "course_switch.json").read_text())
    got = {r["seed"]: r for r in doc["runs"]}
    for s in rises:
        assert (got[s]["rise"], got[s]["peak_iteration"]) == (max(1.5, rises[s]), 7 if rises[s] > 1.5 else 5)
        assert got[s]["change"] == pytest.approx(changes[s], rel=1e-9)
    rho = stats.spearmanr([got[s]["rise"] for s in rises], [changes[s] for s in rises]).statistic
    assert doc["pooled"]["change"]["rho"] == pytest.approx(rho) and rho == pytest.approx(1.0)
    assert "Mixed RL seed 3" in proc.stdout.splitlines()[-4]  # the worst final speed error listed first
    _course_run(tmp_path / "bad", "mixed", 0, [1.0] * 10, {6: 0.01, 10: 0.01})
    _course_run(tmp_path / "bad", "mixed", 1, [1.0] * 10, {4: 0.01, 10: 0.01})
    _course_run(tmp_path / "bad", "mixed", 2, [1.0] * 10, {4: 0.01, 10: 0.01})
    bad = _run_script("course_switch.py", tmp_path / "bad", "--dest", tmp_path / "x", "--window", "2")
    assert bad.returncode == 2 and "mixed_seed0: no evaluation at the course start (iteration 4)" in bad.stderr


@pytest.mark.studies
def test_course_switch_keeps_variants_apart(tmp_path: Path) -> None:
    """Runs of a spec's variants are separate rows (``method[variant]``) with their median and largest rise, taken
    over the 3 w iterations after course_start."""
    # w = 2, start 4: before = 1; the window is iterations 5-10 (a peak at 11 is outside it)
    losses = [1.0, 1.0, 1.0, 1.0, 2.0, 1.0, 1.0, 1.0, 1.0, 1.0, 6.0, 1.0]
    for s in (0, 1, 2):
        _course_run(tmp_path / "sw", "mixed", s, losses, {4: 0.01, 12: 0.02}, variant="switch")
        _course_run(tmp_path / "sw", "mixed", s, losses[:8] + [6.0] + losses[9:], {4: 0.01, 12: 0.02},
                    variant="late")
    proc = _run_script("course_switch.py", tmp_path / "sw", "--dest", tmp_path / "out", "--window", "2")
    assert proc.returncode == 0, proc.stderr
    doc = json.loads((tmp_path / "out" / "course_switch.json").read_text())
    assert list(doc["methods"]) == ["mixed[late]", "mixed[switch]"]
    assert (doc["methods"]["mixed[switch]"]["median_rise"], doc["methods"]["mixed[switch]"]["max_rise"]) == (2.0, 2.0)
    assert (doc["methods"]["mixed[late]"]["median_rise"], doc["methods"]["mixed[late]"]["max_rise"]) == (6.0, 6.0)
    assert {r["peak_iteration"] for r in doc["runs"] if r["row"] == "mixed[late]"} == {9}


@pytest.mark.studies
def test_budget_plateau_compares_a_row_over_the_budgets_it_was_measured_at(tmp_path: Path) -> None:
    """budget_plateau.py with a row missing at one budget (an unfinished sweep read with --partial): the row
    is compared over its measured budgets only and shown as "not run" at the other; the other rows keep
    every step."""
    a = _per_seed_csv(tmp_path / "a" / "per_seed.csv", 1500, {"mixed": [20.0, 22.0], "model": [30.0, 30.0]})
    b = _per_seed_csv(tmp_path / "b" / "per_seed.csv", 4000, {"mixed": [18.0, 20.0], "model": [31.0, 33.0]})
    c = _per_seed_csv(tmp_path / "c" / "per_seed.csv", 10000, {"mixed": [19.0, 21.0]})
    proc = _run_script("budget_plateau.py", a, b, c, "--dest", tmp_path / "out")
    assert proc.returncode == 0, proc.stderr
    doc = json.loads((tmp_path / "out" / "budgets.json").read_text())
    mixed, model = doc["rows"]["mixed"], doc["rows"]["model"]
    assert [(s["from"], s["to"]) for s in mixed["steps"]] == [(1500, 4000), (4000, 10000)]
    assert mixed["steps"][1]["mean_ratio"] == pytest.approx(40.0 / 38.0, rel=1e-12)
    assert [(s["from"], s["to"]) for s in model["steps"]] == [(1500, 4000)] and "10000" not in model["per_budget"]
    assert proc.stdout.splitlines()[5].startswith("Model-driven RL") and proc.stdout.splitlines()[5].endswith("not run")


@pytest.mark.studies
def test_budget_plateau_merges_the_sources_of_one_budget(tmp_path: Path) -> None:
    """budget_plateau.py with two sources of one budget, each of its own rows (two methods shipped in a
    per_seed.csv, the third run later): the rows are merged into that budget and compared as if they came
    from one source."""
    a = _per_seed_csv(tmp_path / "a" / "per_seed.csv", 1500, {"mixed": [20.0, 22.0], "oracle": [30.0, 30.0]})
    b = _per_seed_csv(tmp_path / "b" / "per_seed.csv", 4000, {"mixed": [18.0, 20.0]})
    c = _per_seed_csv(tmp_path / "c" / "per_seed.csv", 4000, {"oracle": [33.0, 31.5]})
    proc = _run_script("budget_plateau.py", a, b, c, "--dest", tmp_path / "out")
    assert proc.returncode == 0, proc.stderr
    doc = json.loads((tmp_path / "out" / "budgets.json").read_text())
    assert doc["budgets"] == [1500, 4000]
    assert doc["rows"]["oracle"]["steps"][0]["mean_ratio"] == pytest.approx(64.5 / 60.0, rel=1e-12)
    assert doc["rows"]["mixed"]["steps"][0]["mean_ratio"] == pytest.approx(38.0 / 42.0, rel=1e-12)


@pytest.mark.studies
def test_seed_statistics_refuses_an_unfinished_sweep_unless_partial(tmp_path: Path) -> None:
    """A sweep with runs that have no results yet is refused by name, with the way out (--partial); with
    --partial the unfinished runs are skipped, not read."""
    sweep = tmp_path / "sw"
    sweep.mkdir()
    runs = [{"name": f"mixed_seed{s}", "method": "mixed", "seed": s, "point": {}, "run_dir": f"runs/mixed_seed{s}",
             "results": None, "error": None} for s in (0, 1)]
    (sweep / "sweep.json").write_text(json.dumps({"runs": runs}))
    proc = _run_script("seed_statistics.py", sweep, "--dest", tmp_path / "out")
    assert proc.returncode == 2 and "2 runs have no results yet (mixed_seed0, mixed_seed1" in proc.stderr
    assert "--partial" in proc.stderr
    partial = _run_script("seed_statistics.py", sweep, "--dest", tmp_path / "out", "--partial")
    assert partial.returncode == 2 and "no finished run" in partial.stderr  # nothing read, nothing written
    assert not (tmp_path / "out").exists()


def _speed_anatomy_module() -> Any:
    import importlib.util
    sys.path.insert(0, str(ROOT / "experiments" / "analysis"))
    try:
        spec = importlib.util.spec_from_file_location("speed_anatomy", ROOT / "experiments" / "analysis" / "speed_anatomy.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
    finally:
        sys.path.remove(str(ROOT / "experiments" / "analysis"))
    return mod


def test_speed_anatomy_splits_the_course_mean_by_stretch_and_prices_the_target() -> None:
    """speed_anatomy.anatomy: the stretches' contributions add up to the course mean |v_x - 12|, each is its
    stretch's sum over N, the speed part of the cost is T q_v sum dv^2, and target_buys is the share of the
    cost lost by scaling the speed error down to 0.010 m/s."""
    from mixedrl.envs import DoubleLaneChangeModel
    from mixedrl.envs.evaluation import TrackingResult
    sa = _speed_anatomy_module()
    cfg = DoubleLaneChangeModel().config
    n = 120
    X = np.linspace(0.0, 119.0, n + 1)
    dv = np.where(X < cfg.reference.x1, 0.01, np.where(X < cfg.reference.x2 + cfg.reference.len2, -0.03, 0.02))
    states = np.zeros((n + 1, 6))
    states[:, 5] = X
    costs = np.full(n, 0.5)
    r = TrackingResult(0.0, float(np.abs(dv[1:]).mean()), 0.0, 0.0, float(costs.sum()), False, n, X, states,
                       states[:, :5], np.zeros((n, 2)), np.zeros(n + 1), dv, np.zeros(n), costs)
    rec = sa.anatomy([r], cfg)
    d = dv[1:]
    assert rec["before"] == pytest.approx(0.01 * np.sum(X[1:] < cfg.reference.x1) / n)
    assert rec["changes"] + rec["before"] + rec["after"] == pytest.approx(rec["speed_mae"])
    assert rec["speed_mae"] == pytest.approx(np.abs(d).mean()) and rec["speed_mae"] > 0.01
    assert rec["speed_share"] == pytest.approx(cfg.dt * 45.0 * np.sum(d * d) / 60.0)
    assert rec["target_buys"] == pytest.approx(rec["speed_share"] * (1 - (0.01 / rec["speed_mae"]) ** 2))
    small = sa.anatomy([dataclasses.replace(r, speed_error=dv / 10)], cfg)
    assert small["target_buys"] == 0.0 and small["speed_mae"] < 0.01
    rows = [{"speed_mae": a + b + c, "before": a, "changes": b, "after": c}
            for a, b, c in [(1, 2, 3), (1, 5, 3), (2, 1, 4), (1, 7, 2)]]
    shares = sa._variance_shares(rows)
    assert sum(shares.values()) == pytest.approx(1.0)


@pytest.mark.studies
def test_speed_anatomy_drives_each_run_again_and_the_lqr_references(tmp_path: Path) -> None:
    """speed_anatomy.py on a tiny DLC sweep: every run driven again equals its results.json (else it stops), the
    two LQR references are listed with the LQR's known course speed error, and a bad sweep is refused."""
    spec = parse_spec('methods = ["mixed", "model"]\nseeds = [0, 1, 2]\n[base]\n"algorithm.iterations" = 2\n'
                      '"algorithm.batch_size" = 16\n"run.eval_every" = 2\n"run.eval_seeds" = 1\n')
    doc = run_sweep(spec, tmp_path / "sw", workers=1, progress=False)
    proc = _run_script("speed_anatomy.py", tmp_path / "sw", "--dest", tmp_path / "out")
    assert proc.returncode == 0, proc.stderr
    out = json.loads((tmp_path / "out" / "speed_anatomy.json").read_text())
    runs = [r for r in out["records"] if r["seed"] is not None]
    assert len(runs) == 6
    for r in runs:
        (row,) = [x for x in doc["runs"] if (x["method"], x["seed"]) == (r["method"], r["seed"])]
        assert r["speed_mae"] == pytest.approx(row["metrics"]["speed_mae"], rel=1e-12)
        assert r["before"] + r["changes"] + r["after"] == pytest.approx(r["speed_mae"])
    refs = {r["method"]: r for r in out["records"] if r["seed"] is None}
    assert set(refs) == {"LQR, gamma=0.99, true mean", "LQR, gamma=0.99, prior mean"}
    # docs/_static/references (scripts/references.py, other seeds): 0.0088 and 0.0130 m/s
    assert refs["LQR, gamma=0.99, true mean"]["speed_mae"] == pytest.approx(0.00876, abs=2e-4)
    assert refs["LQR, gamma=0.99, prior mean"]["speed_mae"] == pytest.approx(0.01296, abs=2e-4)
    assert out["summary"]["mixed"]["runs"] == 3 and "Mixed RL" in proc.stdout
    (tmp_path / "empty").mkdir()
    bad = _run_script("speed_anatomy.py", tmp_path / "empty", "--dest", tmp_path / "x")
    assert bad.returncode != 0 and "sweep.json" in bad.stderr


@pytest.mark.studies
def test_target_matrix_reads_each_rows_targets_and_counts_the_seeds_within_the_speed_target(tmp_path: Path) -> None:
    """target_matrix.py: one line per seed_statistics.py output directory, each target's figure and met / NO as
    summary.json has it, the seeds within 0.010 m/s counted from per_seed.csv; a directory without them refused."""
    d = tmp_path / "row_a"
    d.mkdir()
    targets = {"mixed_action_at_origin_le_0.01_every_seed": {"measured": 2e-5, "met": True},
               "mixed_speed_le_0.010_every_seed": {"measured": 0.0131, "met": False},
               "mixed_lateral_le_0.151_every_seed": {"measured": 0.104, "met": True},
               "model_over_mixed_speed_ge_1.5": {"measured": 1.42, "met": False},
               "paired_speed_difference_ci_excludes_0": {"measured": [-0.0048, -0.0033], "met": True},
               "mixed_better_on_speed_on_ge_90pct_of_seeds": {"measured": "19 of 20", "met": True},
               "mixed_cost_within_5pct_of_oracle": {"measured": {"mixed_over_oracle": 1.01, "ci": [0.98, 1.04]},
                                                    "met": True}}
    (d / "summary.json").write_text(json.dumps({"targets": targets}))
    speeds = [0.008, 0.0131, 0.0099, 0.0100, 0.011]
    (d / "per_seed.csv").write_text("method,seed,speed_mae\n" + "".join(f"mixed,{i},{s}\n" for i, s in enumerate(speeds))
                                    + "model,0,0.001\n")
    proc = _run_script("target_matrix.py", d, "--out", tmp_path / "t.txt")
    assert proc.returncode == 0, proc.stderr
    (line,) = [x for x in (tmp_path / "t.txt").read_text().splitlines() if x.startswith("row_a")]
    assert "NO 3 of 5, worst 0.0131" in line and "met 0.1040" in line and "NO 1.420" in line
    assert "met [-0.0048, -0.0033]" in line and "met 19 of 20" in line and "met 1.010 [0.980, 1.040]" in line
    (tmp_path / "empty").mkdir()
    bad = _run_script("target_matrix.py", tmp_path / "empty", "--out", tmp_path / "x.txt")
    assert bad.returncode != 0 and "summary.json does not exist" in bad.stderr


@pytest.mark.studies
def test_learner_targets_trains_the_missing_runs_in_parallel_and_resumes(tmp_path: Path) -> None:
    """learner_targets.py --jobs 2 --settings paper: the pool trains each missing run once (its per_run JSON), the
    table holds the chosen setting only, and a second call reads the runs back (the same rows, nothing trained)."""
    spec = tmp_path / "spec.toml"
    spec.write_text('systems = ["linear"]\nsettings = ["default", "paper"]\nmethods = ["mixed"]\nseeds = [0, 1]\n'
                    'iterations = 3\n')
    args = ["--spec", spec, "--dest", tmp_path / "out", "--settings", "paper", "--jobs", "2"]
    first = _run_script("learner_targets.py", *args)
    assert first.returncode == 0, first.stderr
    files = sorted(p.name for p in (tmp_path / "out" / "per_run").iterdir())
    assert files == ["linear_mixed_paper_0.json", "linear_mixed_paper_1.json"]
    rows = json.loads((tmp_path / "out" / "rows.json").read_text())
    assert [(r["setting"], r["seed"]) for r in rows] == [("paper", 0), ("paper", 1)]
    stamps = [p.stat().st_mtime_ns for p in sorted((tmp_path / "out" / "per_run").iterdir())]
    again = _run_script("learner_targets.py", *args)
    assert again.returncode == 0, again.stderr
    assert json.loads((tmp_path / "out" / "rows.json").read_text()) == rows
    assert [p.stat().st_mtime_ns for p in sorted((tmp_path / "out" / "per_run").iterdir())] == stamps
    bad = _run_script("learner_targets.py", "--spec", spec, "--dest", tmp_path / "x", "--settings", "papers")
    assert bad.returncode != 0 and "--settings" in bad.stderr


@pytest.mark.studies
def test_learner_targets_runs_an_override_setting_on_its_systems_only(tmp_path: Path) -> None:
    """A setting of the spec's ``[overrides]`` table trains the defaults with its ``algorithm.*`` settings (saved in
    each run's config), on the systems ``[setting_systems]`` names, with per-run files ending in its name."""
    spec = tmp_path / "spec.toml"
    spec.write_text('systems = ["linear", "pendulum"]\nsettings = ["default", "wide"]\nmethods = ["model"]\n'
                    'seeds = [0]\niterations = 3\n[overrides.wide]\nfeedforward_width = 0.5\n'
                    '[setting_systems]\nwide = ["linear"]\n')
    proc = _run_script("learner_targets.py", "--spec", spec, "--dest", tmp_path / "out", "--settings", "wide")
    assert proc.returncode == 0, proc.stderr
    assert sorted(p.name for p in (tmp_path / "out" / "per_run").iterdir()) == ["linear_model_0_wide.json"]
    record = json.loads((tmp_path / "out" / "per_run" / "linear_model_0_wide.json").read_text())
    assert record["config"]["algorithm"]["feedforward_width"] == 0.5
    assert TrainConfig().algorithm.feedforward_width != 0.5  # the override, not the default
    assert record["row"]["setting"] == "wide"
    assert [r["setting"] for r in json.loads((tmp_path / "out" / "rows.json").read_text())] == ["wide"]
