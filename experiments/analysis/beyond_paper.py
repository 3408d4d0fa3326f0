"""Studies beyond the paper (docs/beyond.rst; the command line is ``experiments/analysis/beyond_paper.py``): run them as sweeps (a local process pool, or Ray with
``--address``), ship their tables and figures.

Each study is a sweep spec in ``experiments/studies/<study>.toml`` (:mod:`mixedrl.sweep`)::

    PYTHONPATH=. python experiments/analysis/beyond_paper.py run STUDY [--reduced] [--out DIR] [--num-cpus N]
                                                          [--address ADDR] [--resume] [--no-share] [--no-progress]
                                                          [--seeds S ...]
    PYTHONPATH=. python experiments/analysis/beyond_paper.py ship STUDY [--runs DIR [DIR ...]] [--dest DIR]
    PYTHONPATH=. python experiments/analysis/beyond_paper.py nmpc [--dest DIR] [--seeds S ...] [--progress]

``run`` trains the study into ``--out`` (default ``runs/beyond/<study>``; with ``--reduced``
``runs/beyond/<study>_reduced``) with :func:`mixedrl.sweep.run_sweep`, the engine of ``mixedrl sweep``.
``--reduced`` is a smoke test: the first seed only, 100 iterations, the first two values of the first
grid key.

A method that does not read a grid key (the oracle does not use the prior mean, nor the IBE's Case) is
trained once per seed instead of once per grid point, *if the engine proves it identical*: the sweep is
split into parts, each a sweep directory of ``--out``::

    main/      the other methods on the whole grid
    shared/    the shared method(s), every seed, the key at its first grid value
    witness/   the shared method(s), the first seed, the key at its last grid value

and ``ship`` refuses to reuse the shared runs unless the witness run ends with exactly the results and
the weights (actor and critic, bit for bit) of the shared run of the same seed. ``--no-share`` runs the
spec as it is (one part, ``main/``). ``study.json`` in ``--out`` records the parts.

``ship`` reads the parts' ``sweep.json`` and every run's ``results.json`` (and, for the road grade, its
checkpoint) and writes ``table.csv``, ``table.json`` and ``figure.png`` into ``--dest`` (default
``experiments/results/beyond/<study>``), atomically, with ``summary.csv``, the docs' table (the main figures,
rounded, ``mean ± std``); the same runs give the same bytes.

``nmpc`` drives the NMPC reference (:func:`validation.nmpc.run_reference`, gamma 0.99, 2 s horizon) once
per prior mean of the prior-mismatch study, predicting with that prior mean, and caches the results in
``--dest/nmpc.json`` (default ``experiments/results/beyond/prior_mismatch``; written after every prior, a prior
already there with the same settings is not driven again). ``ship prior_mismatch`` adds the cached priors
as rows ``method = "nmpc"`` (``runs`` = noise courses) and as a reference line of the figure.
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mixedrl.config import TrainConfig
from mixedrl.tables import csv_text, mean_std
from mixedrl.runs import atomic_write_bytes, atomic_write_text, load_checkpoint, make_trainer
from mixedrl.sweep import DEFAULT_BATCH, SweepSpec, add_engine_arguments, format_summary, load_spec, parse_spec, run_sweep
from mixedrl.tasks import task_from_config

ROOT = Path(__file__).resolve().parents[2]
#: Iterations of a ``--reduced`` run.
REDUCED_ITERATIONS = 100
#: The NMPC reference of the prior-mismatch study: :func:`validation.nmpc.run_reference` settings.
NMPC_SETTINGS: dict[str, Any] = {"controller": "nmpc", "gamma": 0.99, "horizon": 2.0}
#: The NMPC cache of the prior-mismatch study, in its ``--dest``.
NMPC_FILE = "nmpc.json"
#: The figures of an NMPC result kept in the cache (the timings are not: they are not reproducible).
NMPC_FIGURES = ("lateral_mae", "speed_mae", "lateral_max", "speed_max", "cost", "terminated")


@dataclasses.dataclass(frozen=True)
class Study:
    """A study: its spec, the methods trained once for every value of a grid key, and its table's shape."""

    spec: str
    #: method -> the grid key it does not read (trained at one value, reused for all)
    shared: dict[str, str]
    #: one row for a shared method instead of one per value of its key (the key is meaningless for it)
    collapse_shared: bool
    description: str


STUDIES: dict[str, Study] = {
    "prior_mismatch": Study(
        "experiments/studies/prior_mismatch.toml", {"oracle": "task.prior_force_mean"}, False,
        "Designer's prior mean of the disturbance force (eq. 55) against the true 261 N."),
    "disturbance_law": Study(
        "experiments/studies/disturbance_law.toml", {}, False,
        "True disturbance law: Gaussian, Student-t (3 dof), two-point, Gaussian with 10x the variance; "
        "the planners assume a Gaussian."),
    "road_grade": Study(
        "experiments/studies/road_grade.toml", {"oracle": "algorithm.ibe_case"}, True,
        "Road grade (a state-dependent mean): Case-2 IBE (one mean) against Case-3 IBE (eq. 19, a Fourier "
        "series along the course) and the oracle (the true mean at every state)."),
}


# ----------------------------------------------------------------------------------------------------
# deriving the parts of a study (TOML text, validated by mixedrl.sweep.parse_spec)
# ----------------------------------------------------------------------------------------------------
def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isfinite(value):
            return repr(value)
        return "nan" if math.isnan(value) else "inf" if value > 0 else "-inf"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{json.dumps(str(k))} = {_toml_value(v)}" for k, v in value.items()) + " }"
    raise ValueError(f"value: cannot write {value!r} as TOML")


def spec_text(methods: list[str], seeds: list[int], base: dict[str, Any], grid: dict[str, list[Any]],
              comment: str = "") -> str:
    """The TOML text of a sweep spec (every key quoted: dotted keys stay one key)."""
    lines = [f"# {line}" for line in comment.splitlines()]
    lines += [f"methods = {_toml_value(methods)}", f"seeds = {_toml_value(seeds)}", "", "[base]"]
    lines += [f"{json.dumps(k)} = {_toml_value(v)}" for k, v in base.items()]
    lines += ["", "[grid]"]
    lines += [f"{json.dumps(k)} = {_toml_value(list(v))}" for k, v in grid.items()]
    return "\n".join(lines) + "\n"


def reduce_spec(spec: SweepSpec) -> SweepSpec:
    """The ``--reduced`` spec: the first seed, ``REDUCED_ITERATIONS`` iterations, two grid points (the
    first two values of the first grid key, the other keys at their first value)."""
    grid = {k: list(v[:2]) if i == 0 else list(v[:1]) for i, (k, v) in enumerate(spec.grid.items())}
    text = spec_text(list(spec.methods), list(spec.seeds[:1]), {**spec.base, "algorithm.iterations": REDUCED_ITERATIONS}, grid,
                     "reduced by experiments/analysis/beyond_paper.py (--reduced)")
    return parse_spec(text, "reduced spec")


def subset_seeds(spec: SweepSpec, seeds: list[int]) -> SweepSpec:
    """The spec on a subset of its seeds (``run --seeds``: a study cut short, reported as such).

    Raises
    ------
    ValueError
        ``seeds`` is empty, repeats a seed, or names a seed the spec does not have.
    """
    if not seeds or len(set(seeds)) != len(seeds) or not set(seeds) <= set(spec.seeds):
        raise ValueError(f"seeds: expected distinct seeds among the spec's {list(spec.seeds)}, got {seeds!r}")
    kept = [s for s in spec.seeds if s in seeds]  # the spec's order
    return parse_spec(spec_text(list(spec.methods), kept, dict(spec.base), {k: list(v) for k, v in spec.grid.items()},
                                f"the spec on seeds {kept} only (experiments/analysis/beyond_paper.py run --seeds)"), "seed subset")


def study_parts(spec: SweepSpec, shared: dict[str, str]) -> dict[str, SweepSpec]:
    """Split ``spec`` into ``main`` / ``shared`` / ``witness`` sweeps (module docstring); ``{"main": spec}``
    when no method of the spec is shared.

    Raises
    ------
    ValueError
        A shared method is keyed on a field that is not a grid key of the spec, or two shared methods
        on different keys.
    """
    used = {m: k for m, k in shared.items() if m in spec.methods}
    if not used:
        return {"main": spec}
    keys = set(used.values())
    if len(keys) != 1 or next(iter(keys)) not in spec.grid:
        raise ValueError(f"shared: {used} must name one grid key of the spec ({list(spec.grid)})")
    key = next(iter(keys))
    values = list(spec.grid[key])
    others = {k: list(v) for k, v in spec.grid.items() if k != key}
    methods = [m for m in spec.methods if m in used]
    rest = [m for m in spec.methods if m not in used]
    parts: dict[str, SweepSpec] = {}
    if rest:
        parts["main"] = parse_spec(spec_text(rest, list(spec.seeds), dict(spec.base),
                                             {k: list(v) for k, v in spec.grid.items()},
                                             f"part 'main' of the study: methods {rest}"), "main part")
    parts["shared"] = parse_spec(spec_text(methods, list(spec.seeds), {**spec.base, key: values[0]}, others,
                                           f"part 'shared': {methods} at {key} = {values[0]!r}, reused for every "
                                           f"value of {key}"), "shared part")
    if len(values) > 1:
        parts["witness"] = parse_spec(spec_text(methods, list(spec.seeds[:1]), {**spec.base, key: values[-1]}, others,
                                                f"part 'witness': {methods} at {key} = {values[-1]!r}; must equal "
                                                f"the shared runs"), "witness part")
    return parts


# ----------------------------------------------------------------------------------------------------
# run
# ----------------------------------------------------------------------------------------------------
def run_study(name: str, out: Path, reduced: bool = False, share: bool = True, address: str | None = None,
              num_cpus: int | None = None, resume: bool = False, progress: bool = True,
              seeds: list[int] | None = None, batch: int = DEFAULT_BATCH) -> dict[str, Any]:
    """Train the study ``name`` into ``out`` (its parts, in order); return ``{part: sweep.json}``.

    ``seeds`` (optional) trains only those seeds of the spec (:func:`subset_seeds`); ``study.json`` records
    them and ``ship`` reports the table as covering them only.
    """
    study = STUDIES[name]
    spec = load_spec(ROOT / study.spec)
    spec_seeds = list(spec.seeds)
    if reduced:
        spec = reduce_spec(spec)
    if seeds is not None:
        spec = subset_seeds(spec, list(seeds))
    shared = study.shared if share else {}
    parts = study_parts(spec, shared)
    key = next(iter(shared.values()), None) if "shared" in parts else None
    manifest = {"study": name, "spec": study.spec, "reduced": reduced, "parts": list(parts),
                "methods": list(spec.methods), "seeds": list(spec.seeds),
                "shared_methods": [m for m in shared if m in spec.methods] if key else [], "shared_key": key,
                "grid": {k: list(v) for k, v in spec.grid.items()}}
    if seeds is not None:
        manifest["spec_seeds"] = spec_seeds  # a study cut short: the seeds it was meant to have
    if num_cpus is not None and (isinstance(num_cpus, bool) or not isinstance(num_cpus, int) or num_cpus < 1):
        raise ValueError(f"num_cpus: expected a positive integer, got {num_cpus!r}")
    out.mkdir(parents=True, exist_ok=True)
    if (out / "study.json").is_file():
        if not resume:
            raise ValueError(f"out: {out} already holds a study; pass --resume to continue it, or choose a new --out")
        if json.loads((out / "study.json").read_text()) != manifest:
            raise ValueError(f"out: {out} holds this study with other parts or options (--reduced, --no-share); "
                             f"resume it with the same options, or choose a new --out")
    atomic_write_text(out / "study.json", json.dumps(manifest, indent=2) + "\n")
    docs = {}
    for part, part_spec in parts.items():  # the engine of mixedrl sweep: the local pool, or Ray with address
        docs[part] = run_sweep(part_spec, out / part, address=address, num_cpus=num_cpus, resume=resume,
                               progress=progress, batch=batch)
    return docs


# ----------------------------------------------------------------------------------------------------
# ship
# ----------------------------------------------------------------------------------------------------
def _load_part(out: Path, part: str) -> dict[str, Any]:
    path = out / part / "sweep.json"
    if not path.is_file():
        raise ValueError(f"runs: {path} does not exist (run the study first)")
    doc = json.loads(path.read_text())
    if not doc.get("finished"):
        raise ValueError(f"runs: the sweep {out / part} has not finished (resume it with --resume)")
    return doc


def _run_records(out: Path, part: str, doc: dict[str, Any]) -> list[dict[str, Any]]:
    records = []
    for rec in doc["runs"]:
        run_dir = out / part / "runs" / rec["name"]
        results = json.loads((run_dir / "results.json").read_text()) if rec["error"] is None else None
        records.append({"part": part, "name": rec["name"], "point": rec["point"], "config": rec["config"],
                        "method": rec["config"]["method"], "seed": rec["config"]["seed"], "results": results,
                        "error": rec["error"], "run_dir": run_dir})
    return records


def _same_weights(a: Path, b: Path) -> bool:
    ta, tb = load_checkpoint(a / "checkpoint.pt")["trainer"], load_checkpoint(b / "checkpoint.pt")["trainer"]
    for net in ("actor", "critic"):
        if ta[net].keys() != tb[net].keys() or not all(torch.equal(ta[net][k], tb[net][k]) for k in ta[net]):
            return False
    return True


def check_witness(shared: list[dict[str, Any]], witness: list[dict[str, Any]], key: str) -> list[dict[str, Any]]:
    """Compare every witness run with the shared run of the same method and seed: the same ``results.json``
    (but ``train_seconds``) and bit-identical actor and critic weights.

    Returns
    -------
    list of dict
        One entry per comparison (method, seed, both values of ``key``).

    Raises
    ------
    ValueError
        A witness run failed, has no shared counterpart, or differs from it: the shared method depends
        on ``key`` after all, and the study must be run with ``--no-share``.
    """
    checks = []
    for w in witness:
        twin = [s for s in shared if s["method"] == w["method"] and s["seed"] == w["seed"]]
        if w["results"] is None or len(twin) != 1 or twin[0]["results"] is None:
            raise ValueError(f"witness: no finished shared run to compare {w['name']} with")
        s = twin[0]
        strip = [{k: v for k, v in r["results"].items() if k != "train_seconds"} for r in (s, w)]
        if strip[0] != strip[1] or not _same_weights(s["run_dir"], w["run_dir"]):
            raise ValueError(f"witness: {w['method']} seed {w['seed']} differs between {key} = "
                             f"{_get(s['config'], key)!r} and {_get(w['config'], key)!r}: the {w['method']} runs "
                             f"depend on {key}; run the study with --no-share")
        checks.append({"method": w["method"], "seed": w["seed"], "key": key, "values": [_get(s["config"], key),
                                                                                       _get(w["config"], key)],
                       "identical": True})
    return checks


def _get(config: dict[str, Any], dotted: str) -> Any:
    node: Any = config
    for part in dotted.split("."):
        node = node[part]
    return node


def collect(out: Path, replicate: bool = True) -> tuple[dict[str, Any], list[dict[str, Any]], list[dict[str, Any]]]:
    """The study's manifest, its run records and the witness checks.

    The shared runs (``shared = True``) are copied to every value of their key when ``replicate``, else
    kept once (at the key's first value).
    """
    manifest = json.loads((out / "study.json").read_text())
    docs = {part: _load_part(out, part) for part in manifest["parts"]}
    parts = {part: _run_records(out, part, doc) for part, doc in docs.items()}
    records = [{**r, "shared": False} for r in parts.get("main", [])]
    checks: list[dict[str, Any]] = []
    key = manifest["shared_key"]
    if key is not None:
        checks = check_witness(parts["shared"], parts.get("witness", []), key)
        values = manifest["grid"][key] if replicate else manifest["grid"][key][:1]
        for value in values:
            for r in parts["shared"]:
                records.append({**r, "point": {**r["point"], key: value}, "shared": True})
    return manifest, sorted(records, key=_record_order(manifest, replicate)), checks


def _record_order(manifest: dict[str, Any], replicate: bool) -> Any:
    """The sort key of the spec's order: grid point, method, seed (collapsed shared runs last)."""
    grid, methods = manifest["grid"], manifest["methods"]

    def order(r: dict[str, Any]) -> tuple[Any, ...]:
        return (r["shared"] and not replicate, *(grid[k].index(r["point"][k]) for k in grid),
                methods.index(r["method"]), r["seed"])

    return order


def collect_many(outs: list[Path], replicate: bool = True
                 ) -> tuple[dict[str, Any], list[dict[str, Any]], list[dict[str, Any]]]:
    """:func:`collect` over several run directories of one study trained on disjoint seeds (``run
    --seeds`` into different ``--out``): their records and witness checks together, in the spec's order,
    the manifest with the union of the seeds.

    Raises
    ------
    ValueError
        No directory, the directories hold different studies or options, or share a seed.
    """
    if not outs:
        raise ValueError("runs: expected at least one run directory")
    manifests, records, checks = [], [], []
    for out in outs:
        m, r, c = collect(out, replicate)
        manifests.append(m)
        records += r
        checks += c
    strip = [{k: v for k, v in m.items() if k not in ("seeds", "spec_seeds")} for m in manifests]
    if any(x != strip[0] for x in strip[1:]):
        raise ValueError(f"runs: {[str(o) for o in outs]} hold different studies or options")
    seeds = [s for m in manifests for s in m["seeds"]]
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"runs: {[str(o) for o in outs]} share seeds ({sorted(seeds)})")
    manifest = {**manifests[0], "seeds": sorted(seeds)}
    return manifest, sorted(records, key=_record_order(manifest, replicate)), checks


def _xi_to_force(config: dict[str, Any]) -> tuple[float, int]:
    task = task_from_config(config["task"])
    return task.force_scale, task.noise_index


def _point_columns(name: str, record: dict[str, Any], collapse: bool) -> dict[str, Any]:
    """The grid point of a run as table columns (from its config and its point); a collapsed shared run
    has no value for its shared key."""
    config = record["config"]
    if name == "prior_mismatch":
        return {"prior_force_mean": float(record["point"]["task.prior_force_mean"])}
    if name == "disturbance_law":
        d = config["task"]["disturbance"]
        return {"law": d["law"], "dof": d["dof"] if d["law"] == "student_t" else None, "mean_N": d["mean"],
                "variance_N2": d["variance"]}
    return {"ibe_case": None if (collapse and record["shared"]) else record["point"]["algorithm.ibe_case"]}


def course_mean_force(run_dir: Path, config: dict[str, Any], X: np.ndarray) -> np.ndarray:
    """The mean force [N] the run's final planning noise assigns along the course at positions ``X``, on
    the reference at 12 m/s (its checkpoint restored): ``mu_hat`` for Case 2, ``phi(x, pi(x))`` for Case 3,
    the true mean for the oracle of a grade."""
    trainer = make_trainer(TrainConfig.from_dict(config))
    trainer.load_state_dict(load_checkpoint(run_dir / "checkpoint.pt")["trainer"])
    task = trainer.task
    ref = task.model.config.reference
    Xt = torch.as_tensor(X, dtype=torch.float64)
    s = torch.zeros(len(X), task.state_dim, dtype=torch.float64)
    s[:, 2], s[:, 3], s[:, 4], s[:, 5] = 12.0, ref.heading(Xt), ref.lateral(Xt), Xt
    if trainer.noise.state_dependent:
        with torch.no_grad():
            u = trainer.actor(task.observe(s.float())).double()
        mean = np.asarray(trainer.noise.mean_at(s, u))[:, task.noise_index]
    else:
        mean = np.full(len(X), float(np.asarray(trainer.noise.mean)[task.noise_index]))
    return np.asarray(mean, dtype=float) / task.force_scale


def build_table(name: str, records: list[dict[str, Any]], collapse_shared: bool,
                course: dict[str, np.ndarray] | None = None) -> list[dict[str, Any]]:
    """One row per grid point and method, in the order of the records: the number of finished and failed
    runs, whether the runs are shared, the mean and std over seeds of the course cost and the mean
    absolute speed and lateral errors (and the study's own figures), and the ratio and the excess of the
    mean cost over the oracle's at the same point (the one oracle row when the shared runs are collapsed).
    """
    groups: dict[str, dict[str, Any]] = {}
    for r in records:
        cols = _point_columns(name, r, collapse_shared)
        key = json.dumps([cols, r["method"]], sort_keys=True)
        group = groups.setdefault(key, {"cols": cols, "method": r["method"], "shared": r["shared"], "runs": [],
                                        "failed": 0})
        if r["error"] is not None:
            group["failed"] += 1
        else:
            group["runs"].append(r)
    rows: list[dict[str, Any]] = []
    by_seed: list[dict[int, float]] = []  # each row's cost per seed
    for group in groups.values():
        runs = group["runs"]
        row: dict[str, Any] = {**group["cols"], "method": group["method"], "runs": len(runs), "failed": group["failed"],
                               "shared_run": group["shared"]}
        for fig in ("cost", "speed_mae", "lateral_mae"):
            row[f"{fig}_mean"], row[f"{fig}_std"] = mean_std([x["results"][fig] for x in runs])
        if name == "disturbance_law":
            ibe_mean, ibe_var, held = [], [], []
            for x in runs:
                scale, i = _xi_to_force(x["config"])
                # xi = F T / m on v_x: back to newtons (and N^2)
                ibe_mean.append(x["results"]["final_ibe_mean"][i] / scale)
                ibe_var.append(x["results"]["final_ibe_cov_diag"][i] / scale**2)
                held.append(x["results"]["mvc_held_fraction"])
            row["ibe_mean_N_mean"], row["ibe_mean_N_std"] = mean_std(ibe_mean)
            row["ibe_var_N2_mean"], row["ibe_var_N2_std"] = mean_std(ibe_var)
            row["mvc_held_fraction_mean"], row["mvc_held_fraction_std"] = mean_std(held)
        if name == "road_grade" and course is not None:
            rms = [float(np.sqrt(np.mean((course[x["name"]] - course["truth"]) ** 2))) for x in runs]
            row["mean_force_rms_error_N_mean"], row["mean_force_rms_error_N_std"] = mean_std(rms)
        rows.append(row)
        by_seed.append({x["seed"]: x["results"]["cost"] for x in runs})
    oracle = {json.dumps(r_cols(r), sort_keys=True): (r["cost_mean"], seeds) for r, seeds in zip(rows, by_seed)
              if r["method"] == "oracle"}
    single = next(iter(oracle.values())) if collapse_shared and len(oracle) == 1 else (None, {})
    for row, seeds in zip(rows, by_seed):
        ref, ref_seeds = oracle.get(json.dumps(r_cols(row), sort_keys=True), single)
        ok = ref is not None and row["cost_mean"] is not None and ref > 0
        row["ratio_to_oracle"] = row["cost_mean"] / ref if ok else None
        row["excess_over_oracle"] = row["cost_mean"] - ref if ok else None
        # paired by seed: the same seed's oracle run (the seeds finished by both)
        paired = [seeds[s] - ref_seeds[s] for s in sorted(seeds) if s in ref_seeds]
        row["paired_excess_mean"], row["paired_excess_std"] = mean_std(paired)
        row["paired_seeds"] = len(paired)
    return rows


def per_seed_costs(name: str, records: list[dict[str, Any]], collapse_shared: bool) -> list[dict[str, Any]]:
    """One entry per finished run: its point columns, method, seed and final course figures (the
    table's raw data, for paired comparisons across grid points)."""
    out = []
    for r in records:
        if r["results"] is None:
            continue
        out.append({**_point_columns(name, r, collapse_shared), "method": r["method"], "seed": r["seed"],
                    **{k: r["results"][k] for k in ("cost", "speed_mae", "lateral_mae")}})
    return out


def case3_vs_case2(per_seed: list[dict[str, Any]]) -> dict[str, Any] | None:
    """Road grade: mixed RL's Case-3 course cost against Case 2's and the oracle's, paired by seed.

    Returns
    -------
    dict or None
        ``seeds`` (finished by Case 2, Case 3 and the oracle), the per-seed ``relative_change`` of Case 3's
        cost from Case 2's (``c3 / c2 - 1``) and ``ratio_to_oracle`` (``c3 / oracle``), each with its mean
        and sample std; None when no seed has the three runs.
    """
    cost = {(e["method"], e["ibe_case"], e["seed"]): e["cost"] for e in per_seed}
    seeds = sorted(s for (m, c, s) in cost if (m, c) == ("mixed", 2) and ("mixed", 3, s) in cost
                   and ("oracle", None, s) in cost)
    if not seeds:
        return None
    change = [cost[("mixed", 3, s)] / cost[("mixed", 2, s)] - 1.0 for s in seeds]
    ratio = [cost[("mixed", 3, s)] / cost[("oracle", None, s)] for s in seeds]
    out: dict[str, Any] = {"seeds": seeds, "relative_change": change, "ratio_to_oracle": ratio}
    out["relative_change_mean"], out["relative_change_std"] = mean_std(change)
    out["ratio_to_oracle_mean"], out["ratio_to_oracle_std"] = mean_std(ratio)
    return out


def r_cols(row: dict[str, Any]) -> dict[str, Any]:
    """The point columns of a table row (every column before ``method``)."""
    out = {}
    for k, v in row.items():
        if k == "method":
            break
        out[k] = v
    return out


def _pm(row: dict[str, Any], key: str, digits: int) -> str:
    """``mean ± std`` of ``key`` in a table row, rounded ("" when there is no value)."""
    mean, std = row.get(f"{key}_mean"), row.get(f"{key}_std")
    if mean is None:
        return ""
    return f"{mean:.{digits}f} ± {std:.{digits}f}" if std is not None else f"{mean:.{digits}f}"


def summary_rows(name: str, rows: list[dict[str, Any]]) -> list[dict[str, str]]:
    """The rows of the docs' table (``summary.csv``): the table's main figures, rounded, ``mean ± std``.

    Every value comes from ``rows`` (:func:`build_table`); the runs column reads ``finished/failed``.
    """
    out = []
    for row in rows:
        if name == "prior_mismatch":
            head = {"prior [N]": f"{row['prior_force_mean']:g}"}
        elif name == "disturbance_law":
            head = {"law": _law_label(row)}
        else:
            head = {}
        label = _grade_label(row) if name == "road_grade" else row["method"]
        ratio = row.get("ratio_to_oracle")
        item = {**head, "method": label, "runs/failed": f"{row['runs']}/{row['failed']}",
                "cost": _pm(row, "cost", 2), "cost / oracle": "" if ratio is None else f"{ratio:.3f}",
                "paired excess over oracle": _pm(row, "paired_excess", 2) if row.get("paired_seeds") else "",
                "speed_mae [m/s]": _pm(row, "speed_mae", 4), "lateral_mae [m]": _pm(row, "lateral_mae", 3)}
        if name == "disturbance_law":
            item["planned mean [N]"] = _pm(row, "ibe_mean_N", 1)
            item["planned var [N²]"] = _pm(row, "ibe_var_N2", 1)
            item["MVC held"] = _pm(row, "mvc_held_fraction", 3)
        if name == "road_grade":
            item["mean force RMS error [N]"] = _pm(row, "mean_force_rms_error_N", 1)
        out.append(item)
    return out


def make_figure(name: str, rows: list[dict[str, Any]], course: dict[str, np.ndarray] | None,
                records: list[dict[str, Any]]) -> bytes:
    """The study's figure as PNG bytes (deterministic: no metadata)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = list(dict.fromkeys(r["method"] for r in rows))
    fig, axes = plt.subplots(1, 2, figsize=(10.5, 3.9))
    if name == "prior_mismatch":
        for ax, fig_key, label in ((axes[0], "cost", "course cost"), (axes[1], "speed_mae", "mean |v_x - 12| [m/s]")):
            learned = [m for m in methods if m != "nmpc"]
            for method in methods:
                pts = sorted((r["prior_force_mean"], r[f"{fig_key}_mean"], r[f"{fig_key}_std"]) for r in rows
                             if r["method"] == method and r[f"{fig_key}_mean"] is not None)
                if not pts:
                    continue
                arr = np.asarray(pts, dtype=float)
                if method == "nmpc":  # a reference, not learned: one course per prior
                    ax.plot(arr[:, 0], arr[:, 1], color="k", ls="--", marker="s", ms=4, label="NMPC with the prior mean")
                    continue
                j = learned.index(method)
                off = (j - (len(learned) - 1) / 2) * 18.0  # side by side, not on top of each other
                ax.errorbar(arr[:, 0] + off, arr[:, 1], yerr=arr[:, 2], marker="o", capsize=3, color=f"C{j}",
                            label=method)
                for r in rows:  # every seed, hollow
                    if r["method"] == method:
                        vals = [x["results"][fig_key] for x in _row_records(name, r, records)]
                        ax.plot([r["prior_force_mean"] + off] * len(vals), vals, "o", mfc="none", ms=4,
                                color=f"C{j}", alpha=0.6)
            ax.axvline(261.0, color="0.5", ls="--", lw=1)
            ax.set_xlabel("prior mean of F_dis [N] (truth 261 N, dashed)")
            ax.set_ylabel(label)
            ax.set_title("mean ± std over seeds; hollow: each seed", fontsize=9)
        axes[0].legend(fontsize=8)
    elif name == "disturbance_law":
        labels = list(dict.fromkeys(_law_label(r) for r in rows))
        width = 0.8 / max(len(methods), 1)
        for ax, fig_key, label in ((axes[0], "cost", "course cost"), (axes[1], "speed_mae", "mean |v_x - 12| [m/s]")):
            for j, method in enumerate(methods):
                xs, ys, es = [], [], []
                for i, lab in enumerate(labels):
                    for r in rows:
                        if r["method"] == method and _law_label(r) == lab and r[f"{fig_key}_mean"] is not None:
                            xs.append(i + (j - (len(methods) - 1) / 2) * width)
                            ys.append(r[f"{fig_key}_mean"])
                            es.append(r[f"{fig_key}_std"])
                            _seed_dots(ax, xs[-1], [x["results"][fig_key] for x in _row_records(name, r, records)],
                                       width / 4, "one seed" if (i, j) == (0, 0) else None)
                ax.bar(xs, ys, width=width, yerr=es, capsize=3, label=method, color=f"C{j}")
            ax.set_xticks(range(len(labels)), [lab.replace(", ", "\n") for lab in labels], fontsize=8)
            ax.set_ylabel(label)
            ax.set_title("bars: mean ± std over seeds; dots: each seed", fontsize=9)
            ax.margins(y=0.3)  # room for the legend above the bars
        axes[0].legend(fontsize=8, ncol=4, loc="upper center")
    else:
        labels = [(_grade_label(r), r) for r in rows]
        xs = np.arange(len(labels))
        axes[0].bar(xs, [r["cost_mean"] or 0.0 for _, r in labels], yerr=[r["cost_std"] or 0.0 for _, r in labels],
                    capsize=3, color=[f"C{i}" for i in range(len(labels))])
        axes[0].set_xticks(xs, [lab for lab, _ in labels], fontsize=8)
        for i, (_, r) in enumerate(labels):  # every seed's cost, on its bar
            _seed_dots(axes[0], i, [x["results"]["cost"] for x in _row_records(name, r, records)], 0.15,
                       "one seed" if i == 0 else None)
        axes[0].set_ylabel("course cost (bar: mean ± std over seeds)")
        axes[0].legend(fontsize=8)
        if course is not None:
            X = course["X"]
            axes[1].plot(X, course["truth"], color="0.6", lw=5, label="true mean")
            for i, (lab, r) in enumerate(labels):
                curves = [course[x["name"]] for x in _row_records(name, r, records) if x["method"] != "oracle"]
                if curves:
                    axes[1].plot(X, np.mean(curves, axis=0), color=f"C{i}", ls="--" if i else "-",
                                 label=f"{lab} (mean over seeds)")
            axes[1].set_xlabel("X along the course [m]")
            axes[1].set_ylabel("mean of F_dis the run plans with [N]")
            axes[1].legend(fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, metadata={"Software": None})
    plt.close(fig)
    return buf.getvalue()


def _row_records(name: str, row: dict[str, Any], records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The finished runs of a table row: its method at its grid point (as :func:`build_table` groups them)."""
    collapse = STUDIES[name].collapse_shared
    return [x for x in records if x["results"] is not None and x["method"] == row["method"]
            and _point_columns(name, x, collapse) == r_cols(row)]


def _seed_dots(ax: Any, x: float, costs: list[float], half_width: float, label: str | None) -> None:
    """Every seed's value as a black dot at ``x`` (spread over ``x ± half_width``)."""
    xs = x + np.linspace(-half_width, half_width, len(costs)) if len(costs) > 1 else [x] * len(costs)
    ax.plot(xs, costs, "o", color="k", ms=3, label=label, zorder=3)


def _law_label(row: dict[str, Any]) -> str:
    law = row["law"] if row["law"] != "student_t" else f"student_t ({row['dof']:g} dof)"
    return f"{law}, var {row['variance_N2']:g}"


def _grade_label(row: dict[str, Any]) -> str:
    return "oracle" if row["method"] == "oracle" else f"{row['method']}, Case {row['ibe_case']}"


def ship_study(name: str, runs: Path | list[Path], dest: Path) -> dict[str, Any]:
    """Write ``table.csv``, ``table.json``, ``summary.csv`` and ``figure.png`` of the study's runs in ``runs``
    (one directory, or several trained on disjoint seeds: :func:`collect_many`) into ``dest`` (and, for
    the prior mismatch, the NMPC rows of ``dest/nmpc.json`` if it exists)."""
    study = STUDIES[name]
    manifest, records, checks = collect_many([runs] if isinstance(runs, Path) else list(runs),
                                             replicate=not study.collapse_shared)
    if manifest["study"] != name:
        raise ValueError(f"runs: {runs} holds the study {manifest['study']!r}, not {name!r}")
    course = None
    if name == "road_grade":
        X = np.linspace(0.0, 120.0, 241)
        first = next(r for r in records if r["results"] is not None)
        task = task_from_config(first["config"]["task"])
        d, params = task.model.config.disturbance, task.model.config.params
        # the true mean force along the course: mean - m g sin(theta(X))
        course = {"X": X, "truth": np.asarray(d.mean_force(X, params.m, params.g), dtype=float)}
        for r in records:
            if r["results"] is not None and r["name"] not in course:
                course[r["name"]] = course_mean_force(r["run_dir"], r["config"], X)
    rows = build_table(name, records, study.collapse_shared, course)
    per_seed = per_seed_costs(name, records, study.collapse_shared)
    nmpc = None
    if name == "prior_mismatch" and (dest / NMPC_FILE).is_file():
        cache = _load_nmpc_cache(dest / NMPC_FILE)
        priors = [float(p) for p in manifest["grid"]["task.prior_force_mean"]]
        oracle = {r["prior_force_mean"]: r["cost_mean"] for r in rows if r["method"] == "oracle"}
        extra = {r["prior_force_mean"]: r for r in nmpc_rows(cache, priors, oracle)}
        merged = []
        for i, row in enumerate(rows):  # each prior's NMPC row after that prior's learned methods
            merged.append(row)
            last = i + 1 == len(rows) or rows[i + 1]["prior_force_mean"] != row["prior_force_mean"]
            if last and row["prior_force_mean"] in extra:
                merged.append(extra[row["prior_force_mean"]])
        rows = merged
        nmpc = {"file": NMPC_FILE, "settings": sorted({json.dumps(e["settings"], sort_keys=True)
                                                       for e in cache["entries"]}),
                "priors": sorted(extra), "generated_by": "experiments/analysis/beyond_paper.py nmpc"}
    doc = {
        "study": name,
        "description": study.description,
        "spec": study.spec,
        "reduced": manifest["reduced"],
        "seeds": manifest["seeds"],
        **({"spec_seeds": manifest["spec_seeds"]} if "spec_seeds" in manifest else {}),
        "generated_by": f"experiments/analysis/beyond_paper.py ship {name}",
        "statistics": "mean and sample standard deviation (ddof=1) over seeds; ratio_to_oracle and "
                      "excess_over_oracle compare the mean course cost with the oracle's at the same point; "
                      "paired_excess_* is the mean and std over seeds of the cost minus the same seed's oracle "
                      "cost (paired_seeds seeds)",
        "shared": {"methods": manifest["shared_methods"], "key": manifest["shared_key"], "witness": checks},
        **({"nmpc": nmpc} if nmpc is not None else {}),
        "rows": rows,
        "per_seed": per_seed,
        **({"case3_vs_case2": case3_vs_case2(per_seed)} if name == "road_grade" else {}),
    }
    dest.mkdir(parents=True, exist_ok=True)
    atomic_write_text(dest / "table.csv", csv_text(rows))
    atomic_write_text(dest / "summary.csv", csv_text(summary_rows(name, rows)))
    atomic_write_text(dest / "table.json", json.dumps(doc, indent=2, sort_keys=False) + "\n")
    atomic_write_bytes(dest / "figure.png", make_figure(name, rows, course, records))
    return doc



# ----------------------------------------------------------------------------------------------------
# the NMPC reference of the prior-mismatch study
# ----------------------------------------------------------------------------------------------------
def _nmpc_settings(seeds: list[int]) -> dict[str, Any]:
    return {**NMPC_SETTINGS, "seeds": [int(s) for s in seeds]}


def _load_nmpc_cache(path: Path) -> dict[str, Any]:
    if not path.is_file():
        return {"generated_by": "experiments/analysis/beyond_paper.py nmpc", "entries": []}
    doc = json.loads(path.read_text())
    if not isinstance(doc, dict) or not isinstance(doc.get("entries"), list):
        raise ValueError(f"nmpc: {path} is not an NMPC cache of experiments/analysis/beyond_paper.py (no 'entries' list)")
    return doc


def nmpc_reference(priors: list[float], path: Path, seeds: list[int], runner: Any = None,
                   progress: bool = False) -> dict[str, Any]:
    """Drive the NMPC with each prior mean in ``priors`` (or reuse the cache ``path``) and return the cache.

    Parameters
    ----------
    priors : list of float
        Prior means of the disturbance force [N]; the NMPC predicts with each one.
    path : Path
        The cache (JSON, ``{"entries": [...]}``), rewritten atomically after every prior. An entry with
        the same prior and the same settings (:data:`NMPC_SETTINGS` and ``seeds``) is reused.
    seeds : list of int
        Noise seeds, one course each (as :func:`validation.nmpc.run_reference`).
    runner : callable, optional
        ``runner(**kwargs) -> dict``; default :func:`validation.nmpc.run_reference` (tests pass a stub).
    progress : bool, optional
        Show the NMPC's progress bar.

    Returns
    -------
    dict
        The cache: ``entries``, one per prior driven (the study's order), each with ``prior_force_mean``,
        ``settings``, ``wall_seconds`` and either ``result`` (:data:`NMPC_FIGURES`, their ``per_seed``
        values, ``force_N``) or ``error`` (an IPOPT failure, say).
    """
    if runner is None:
        from validation.nmpc import run_reference as runner
    settings = _nmpc_settings(seeds)
    doc = _load_nmpc_cache(path)
    for prior in priors:
        prior = float(prior)
        if any(e.get("prior_force_mean") == prior and e.get("settings") == settings for e in doc["entries"]):
            continue
        t0 = time.perf_counter()
        entry: dict[str, Any] = {"prior_force_mean": prior, "settings": settings}
        try:
            res = runner(**NMPC_SETTINGS, disturbance_mean=prior, seeds=tuple(settings["seeds"]), progress=progress)
        except Exception as exc:  # noqa: BLE001 - an IPOPT failure is a result of the study, recorded
            entry["error"] = f"{type(exc).__name__}: {exc}"
        else:
            entry["result"] = {**{k: float(res[k]) for k in NMPC_FIGURES}, "force_N": float(res["force_N"]),
                               "per_seed": [{"seed": int(r["seed"]), **{k: float(r[k]) for k in NMPC_FIGURES}}
                                            for r in res["per_seed"]]}
        entry["wall_seconds"] = round(time.perf_counter() - t0, 1)
        others = [e for e in doc["entries"] if e.get("prior_force_mean") != prior]
        doc["entries"] = sorted(others + [entry], key=lambda e: float(e["prior_force_mean"]))
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(path, json.dumps(doc, indent=2) + "\n")
    return doc


def nmpc_rows(cache: dict[str, Any], priors: list[float], oracle_cost: dict[float, float]) -> list[dict[str, Any]]:
    """The table rows ``method = "nmpc"`` of the cached priors that are in ``priors`` (their order).

    ``runs`` counts the noise courses (one NMPC, nothing trained); the std is over those courses (0 for
    one); ``ratio_to_oracle`` / ``excess_over_oracle`` compare its cost with ``oracle_cost[prior]``.
    A cached failure is a row with ``failed = 1`` and no figures.
    """
    by_prior: dict[float, dict[str, Any]] = {}
    for e in cache.get("entries", []):
        by_prior[float(e["prior_force_mean"])] = e
    rows = []
    for prior in priors:
        e = by_prior.get(float(prior))
        if e is None:
            continue
        per = e.get("result", {}).get("per_seed", [])
        row: dict[str, Any] = {"prior_force_mean": float(prior), "method": "nmpc", "runs": len(per),
                               "failed": 0 if "result" in e else 1, "shared_run": False}
        for fig in ("cost", "speed_mae", "lateral_mae"):
            row[f"{fig}_mean"], row[f"{fig}_std"] = mean_std([r[fig] for r in per])
        ref = oracle_cost.get(float(prior))
        ok = ref is not None and row["cost_mean"] is not None and ref > 0
        row["ratio_to_oracle"] = row["cost_mean"] / ref if ok else None
        row["excess_over_oracle"] = row["cost_mean"] - ref if ok else None
        rows.append(row)
    return rows


# ----------------------------------------------------------------------------------------------------
# command line
# ----------------------------------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="train the study (the engine of mixedrl sweep)")
    run.add_argument("study", choices=sorted(STUDIES))
    run.add_argument("--reduced", action="store_true",
                     help=f"first seed, {REDUCED_ITERATIONS} iterations, two grid points (a smoke test)")
    run.add_argument("--out", type=Path, default=None, help="default runs/beyond/<study>[_reduced]")
    add_engine_arguments(run)  # --address, --num-cpus, --resume, --no-progress: as mixedrl sweep
    run.add_argument("--no-share", action="store_true", help="train every method at every grid point")
    run.add_argument("--seeds", type=int, nargs="+", default=None,
                     help="train only these seeds of the spec (a study cut short; recorded in study.json)")
    ship = sub.add_parser("ship", help="write the study's table and figure")
    ship.add_argument("study", choices=sorted(STUDIES))
    ship.add_argument("--runs", type=Path, nargs="+", default=None,
                      help="default runs/beyond/<study>; several: one study trained on disjoint seeds")
    ship.add_argument("--dest", type=Path, default=None, help="default experiments/results/beyond/<study>")
    nm = sub.add_parser("nmpc", help="drive the NMPC with each prior mean of the prior-mismatch study (cached)")
    nm.add_argument("--dest", type=Path, default=None, help="default experiments/results/beyond/prior_mismatch")
    nm.add_argument("--seeds", type=int, nargs="+", default=[0], help="noise seeds, one course each (default 0)")
    nm.add_argument("--progress", action="store_true")
    args = parser.parse_args(argv)
    try:
        if args.command == "run":
            out = args.out or Path("runs/beyond") / (args.study + ("_reduced" if args.reduced else ""))
            t0 = time.perf_counter()
            docs = run_study(args.study, out, reduced=args.reduced, share=not args.no_share, address=args.address,
                             num_cpus=args.num_cpus, resume=args.resume, progress=not args.no_progress,
                             seeds=args.seeds, batch=args.batch)
            for part, doc in docs.items():
                print(f"[{part}]")
                print(format_summary(doc, out / part))
            failed = sum(doc["failed"] for doc in docs.values())
            print(f"\n{args.study}: {sum(len(d['runs']) for d in docs.values())} runs, {failed} failed, "
                  f"{time.perf_counter() - t0:.1f} s")
            return 1 if failed else 0
        if args.command == "nmpc":
            dest = args.dest or Path("experiments/results/beyond/prior_mismatch")
            priors = list(load_spec(ROOT / STUDIES["prior_mismatch"].spec).grid["task.prior_force_mean"])
            cache = nmpc_reference(priors, dest / NMPC_FILE, args.seeds, progress=args.progress)
            for e in cache["entries"]:
                res = e.get("result")
                print(f"prior {e['prior_force_mean']:g} N: " + (e["error"] if res is None else
                      f"cost {res['cost']:.3f}, speed_mae {res['speed_mae']:.4f}, lateral_mae {res['lateral_mae']:.4f}"
                      f" ({e['wall_seconds']} s)"))
            print(f"cached in {dest / NMPC_FILE}")
            return 0
        runs = args.runs or [Path("runs/beyond") / args.study]
        dest = args.dest or Path("experiments/results/beyond") / args.study
        doc = ship_study(args.study, runs, dest)
        print(csv_text(doc["rows"]), end="")
        print(f"shipped to {dest}: table.csv, table.json, summary.csv, figure.png")
        return 0
    except (ValueError, ImportError) as exc:
        print(f"beyond_paper.py: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
