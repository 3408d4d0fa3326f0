"""The results page of the studies (``docs/results.rst``, ``experiments/analysis/results_page.py``) and the guard
of the rows it lists: every shipped row of the double lane change's precision study is re-derivable from its spec.

* the shipped page is the script's output (never edited by hand);
* every shipped row holds exactly the runs its specs expand to (method, variant and seed; the budget and the
  trained feed-forward of each), so a row is re-trained by ``mixedrl sweep`` of its specs; a retired row (its
  option retired, its specs at ``RP.RETIRED_AT``) holds its per-seed files, trained with a retired value;
* every shipped ``summary.json`` is the statistics of its shipped ``per_seed.csv`` (``seed_statistics.py``), and the
  derived files (``budgets_lq_train``, ``targets.txt``, ``win_odds.txt``) are those scripts' outputs on the
  shipped rows, byte for byte.
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from experiments.analysis import results_page as RP
from experiments.analysis import seed_statistics as SS
from mixedrl.config import RETIRED_FEEDFORWARDS
from mixedrl.sweep import expand, load_spec

ROOT = Path(__file__).resolve().parents[1]
ANALYSIS = ROOT / "experiments" / "analysis"
ROWS = RP.TWENTY_SEEDS + (RP.DDPG,) + RP.HELD_OUT
#: The twenty-seed rows of ``targets.txt`` and of ``win_odds.txt``, in their order.
TARGET_ROWS = ["seeds20", "feedforward", "feedforward_lq_train", "feedforward_lq_train_n4000",
               "feedforward_lq_train_n10000", "feedforward_lq_affine", "feedforward_lq_affine_ss",
               "feedforward_lq_affine_ss_ramp", "feedforward_lq_train_n4000_ramp",
               "feedforward_lq_affine_ss_target90", "feedforward_lq_affine_ss_ramp_target90",
               "feedforward_lq_affine_ss_target90_n4000"]
ODDS_ROWS = ["seeds20", "feedforward", "feedforward_lq_train", "feedforward_lq_train_n4000", "feedforward_lq_affine",
             "feedforward_lq_affine_ss", "feedforward_lq_affine_ss_ramp", "feedforward_lq_train_n10000",
             "feedforward_lq_train_n4000_ramp", "feedforward_lq_affine_ss_target90",
             "feedforward_lq_affine_ss_ramp_target90"]


def _script(name: str, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ANALYSIS / name), *args], capture_output=True, text=True, cwd=cwd,
                          env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=600)


def test_the_shipped_results_page_is_the_scripts_output() -> None:
    assert (ROOT / "docs" / "results.rst").read_text() == RP.render(), \
        "docs/results.rst is edited or stale: PYTHONPATH=. python experiments/analysis/results_page.py"


def test_every_shipped_result_directory_is_on_the_page() -> None:
    """No row of the study is shipped without its line on the page (and no line without its directory)."""
    shipped = {p.name for p in RP.RESULTS.iterdir() if p.is_dir()}
    assert shipped == {r.folder for r in ROWS + (RP.BUDGETS,)}


@pytest.mark.parametrize("row", [r for r in ROWS if not r.retired], ids=lambda r: r.folder)
def test_every_shipped_row_holds_the_runs_of_its_specs(row: RP.Row) -> None:
    runs = {}
    for spec in row.specs:
        for run in expand(load_spec(RP.STUDIES / f"{spec}.toml")):
            runs[(SS.row_key(run.config.method, run.point.get("variant")), run.config.seed)] = run.config
    shipped = RP.per_seed(row.folder)
    keys = [(SS.row_key(r["method"], r.get("variant")), int(r["seed"])) for r in shipped]
    assert len(keys) == len(set(keys)) and set(keys) == set(runs), row.folder
    for key, rec in zip(keys, shipped):
        cfg = runs[key]
        assert int(rec["iterations"]) == cfg.algorithm.iterations, (row.folder, key)
        assert (rec.get("trained_feedforward") or "learned") == cfg.algorithm.feedforward, (row.folder, key)


@pytest.mark.parametrize("row", [r for r in ROWS + (RP.BUDGETS,) if r.retired], ids=lambda r: r.folder)
def test_a_retired_row_keeps_its_per_seed_files_and_names_the_commit_of_its_specs(row: RP.Row) -> None:
    """A retired row's specs are gone (they cannot be expanded: their option is refused) and the page names them at
    RP.RETIRED_AT; its folder keeps its measured files, one run per (row, seed), each trained with a retired
    ``algorithm.feedforward``."""
    for spec in row.specs:
        assert not (RP.STUDIES / f"{spec}.toml").exists(), spec
        assert f"``git show {RP.RETIRED_AT}:experiments/studies/{spec}.toml``" in RP.render()
    folder = RP.RESULTS / row.folder
    if row is RP.BUDGETS:
        assert {p.name for p in folder.iterdir()} >= {"budgets.json", "budgets.txt"}
        return
    assert {p.name for p in folder.iterdir()} >= {"per_seed.csv", "summary.json", "table.txt"}
    shipped = RP.per_seed(row.folder)
    keys = [(SS.row_key(r["method"], r.get("variant")), int(r["seed"])) for r in shipped]
    assert shipped and len(keys) == len(set(keys)), row.folder
    retired_there = {value for value, commit in RETIRED_FEEDFORWARDS.items() if commit == RP.RETIRED_AT}
    assert {r["trained_feedforward"] for r in shipped} <= retired_there, row.folder


def test_a_live_rows_specs_are_in_the_studies() -> None:
    for row in ROWS + (RP.BUDGETS,):
        assert row.retired or all((RP.STUDIES / f"{s}.toml").is_file() for s in row.specs), row.folder


@pytest.mark.parametrize("row", ROWS, ids=lambda r: r.folder)
def test_every_shipped_summary_is_the_statistics_of_its_per_seed_rows(row: RP.Row) -> None:
    rows = SS.load_csv_rows(RP.RESULTS / row.folder / "per_seed.csv")
    stats = json.loads(json.dumps(SS.statistics(rows)))
    assert stats == json.loads((RP.RESULTS / row.folder / "summary.json").read_text())


def test_the_derived_files_are_their_scripts_outputs_on_the_shipped_rows(tmp_path: Path) -> None:
    """budgets_lq_train from the three budgets' per_seed.csv, targets.txt and win_odds.txt from the rows."""
    sources = [f"{d}/per_seed.csv" for d in ("feedforward_lq_train", "feedforward_lq_train_n4000",
                                               "feedforward_lq_train_n10000")]
    proc = _script("budget_plateau.py", *sources, "--dest", str(tmp_path / "budgets"), cwd=RP.RESULTS)
    assert proc.returncode == 0, proc.stderr
    for name in ("budgets.json", "budgets.txt"):
        assert (tmp_path / "budgets" / name).read_text() == (RP.RESULTS / "budgets_lq_train" / name).read_text()
    proc = _script("target_matrix.py", *TARGET_ROWS, "--out", str(tmp_path / "targets.txt"), cwd=RP.RESULTS)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "targets.txt").read_text() == (RP.RESULTS / "targets.txt").read_text()
    proc = _script("win_odds.py", *(f"{d}/per_seed.csv" for d in ODDS_ROWS), "--out", str(tmp_path / "odds.txt"),
                   cwd=RP.RESULTS)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "odds.txt").read_text() == (RP.RESULTS / "win_odds.txt").read_text()


def test_the_per_seed_speed_counts_on_the_page_are_the_csvs() -> None:
    """The page's "within 0.010 on k of 20" is counted from per_seed.csv (the figure target_matrix.py shows)."""
    for row in RP.TWENTY_SEEDS:
        with (RP.RESULTS / row.folder / "per_seed.csv").open(newline="") as fh:
            speeds = [float(r["speed_mae"]) for r in csv.DictReader(fh) if r["method"] == "mixed"]
        assert f"within 0.010 on {sum(v <= 0.010 for v in speeds)} of {len(speeds)}" in RP.measured_twenty(row)


def _ship() -> Any:
    import importlib.util
    spec = importlib.util.spec_from_file_location("ship", ROOT / "experiments" / "ship.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("spec", sorted((ROOT / "experiments" / "studies").glob("*.toml")), ids=lambda p: p.stem)
def test_every_spec_names_the_commands_that_ship_it(spec: Path) -> None:
    """experiments/ship.py SPEC: the header's first command trains the spec itself (``mixedrl sweep`` of it, the
    beyond-the-paper runner that drives that sweep, or the spec's own runner ``experiments/analysis/<name>.py``),
    and every script it names exists."""
    cmds = _ship().commands(spec)
    assert cmds, spec.name
    first = cmds[0]
    assert first[:3] == ["mixedrl", "sweep", f"experiments/studies/{spec.name}"] or \
        first[1:4] == ["experiments/analysis/beyond_paper.py", "run", spec.stem] or \
        first == ["python", f"experiments/analysis/{spec.stem}.py"], first
    for argv in cmds:
        assert argv[0] in ("mixedrl", "python"), argv
        if argv[0] == "python":
            assert (ROOT / argv[1]).is_file(), argv


def test_every_shipped_row_of_the_study_is_written_by_a_specs_commands() -> None:
    dests = {argv[argv.index("--dest") + 1] for spec in (ROOT / "experiments" / "studies").glob("*.toml")
             for argv in _ship().commands(spec) if "--dest" in argv}
    for row in ROWS + (RP.BUDGETS,):
        if row.feedforward in RETIRED_FEEDFORWARDS:  # evaluated with a since retired value: re-derived at its commit
            commit = RETIRED_FEEDFORWARDS[row.feedforward]
            headers = " ".join((RP.STUDIES / f"{s}.toml").read_text().replace("\n# ", " ") for s in row.specs)
            assert f"re-derived at commit {commit}" in headers and f"table1_seeds20/{row.folder}" in headers, row.folder
            assert f"(retired: re-derived at commit {commit})" in RP.render(), row.folder
            continue
        assert row.retired or f"experiments/results/table1_seeds20/{row.folder}" in dests, row.folder


@pytest.mark.sweep
def test_ship_runs_a_specs_header_from_the_repository_root(tmp_path: Path) -> None:
    """The commands of a (tiny) spec's header, continuation lines included, run in order: the sweep, then the
    analysis into --dest; --analysis skips the sweep."""
    spec = tmp_path / "tiny.toml"
    spec.write_text(f"# A tiny spec.\n#\n#   mixedrl sweep {spec} --out {tmp_path / 'sweep'} --workers 1\n"
                    f"#   python experiments/analysis/seed_statistics.py {tmp_path / 'sweep'} \\\n"
                    f"#       --dest {tmp_path / 'out'}\n#\n"
                    'methods = ["mixed"]\nseeds = [0, 1]\n[base]\n"algorithm.iterations" = 2\n'
                    '"algorithm.batch_size" = 16\n"run.eval_every" = 2\n"run.eval_seeds" = 1\n')
    ship = _ship()
    assert [c[:2] for c in ship.commands(spec)] == [["mixedrl", "sweep"], ["python", "experiments/analysis/seed_statistics.py"]]
    assert ship.run(spec) == 0
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["methods"]["mixed"]["seeds"] == [0, 1]
    (tmp_path / "out" / "summary.json").unlink()
    assert ship.run(spec, analysis_only=True) == 0 and (tmp_path / "out" / "summary.json").is_file()
