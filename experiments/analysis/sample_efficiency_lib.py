"""Sample efficiency of mixed RL against its baselines and the SB3 peers (issue 10): runs, table, figures.

The study (``experiments/analysis/sample_efficiency.py``) trains every method for several seeds and records, at each
course evaluation, one *row*::

    {"true_transitions": int, "wall_seconds": float, "lateral_mae": float, "speed_mae": float, "cost": float}

(plus ``iteration`` for mixedrl's own methods). ``true_transitions`` are the transitions of the true
environment used so far (``data/true_transitions`` of a mixedrl run; counted by a wrapper for a peer, see
:mod:`validation.peers`); ``wall_seconds`` is the training time so far without the evaluations
(``time/elapsed_s`` of a run). One JSON file per run holds ``method``, ``seed``, ``config`` and ``rows``.

This module holds the logic that does not need Stable-Baselines3: training one of mixedrl's methods
(:func:`train_ours`), the thresholds (:func:`reach_accuracy`, :func:`reach_own_final`), the table
(:func:`summarize`, :func:`write_summary`) and the figures (:func:`plot_curves`).
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch

from mixedrl.checks import check_positive_int
from mixedrl.config import ONE_STEP_LEARNER, TrainConfig
from mixedrl.tables import mean_std
from mixedrl.runs import (
    CONVERGENCE_RTOL,
    RunDirectory,
    atomic_write_bytes,
    atomic_write_text,
    iterations_to_converge,
    make_trainer,
    train,
)

__all__ = [
    "ROW_KEYS",
    "OURS",
    "THRESHOLD_LATERAL",
    "THRESHOLD_SPEED",
    "FINAL_RTOL",
    "LABELS",
    "check_rows",
    "choose_eval_every",
    "first_reaching",
    "load_runs",
    "plot_curves",
    "reach_accuracy",
    "reach_own_final",
    "settled",
    "rows_from_metrics",
    "summarize",
    "ours_config",
    "train_ours",
    "records_from_reproduction",
    "write_summary",
]

#: Keys of every row (mixedrl's own methods add ``iteration``).
ROW_KEYS = ("true_transitions", "wall_seconds", "lateral_mae", "speed_mae", "cost")
#: mixedrl's own methods.
OURS = ("mixed", "model", "oracle", "ddpg")
#: The accuracy threshold [m]: the paper's Table I lateral error of mixed RL, 0.151 m.
THRESHOLD_LATERAL = 0.151
#: The accuracy threshold [m/s]: the paper's Table I speed error of mixed RL, 0.021 m/s.
THRESHOLD_SPEED = 0.021
#: "Its own final accuracy": the course cost within this fraction of the run's final cost.
FINAL_RTOL = 0.10
#: Legend names.
LABELS = {"mixed": "mixed RL", "model": "model-driven RL", "oracle": "oracle (true noise)", "ddpg": "DDPG (ours)",
          "td3": "TD3 (SB3)", "sac": "SAC (SB3)"}


def check_rows(rows: Any, where: str = "rows") -> list[dict[str, Any]]:
    """Validate evaluation rows: a non-empty list of dicts with :data:`ROW_KEYS`, counts and times not decreasing.

    Returns
    -------
    list of dict
        ``rows`` (the same dicts).

    Raises
    ------
    ValueError
        ``where: ...`` naming the first problem (empty, a missing key, a non-number, a negative or
        decreasing ``true_transitions`` or ``wall_seconds``).
    """
    if not isinstance(rows, list) or not rows:
        raise ValueError(f"{where}: expected a non-empty list of evaluation rows, got {rows!r:.80}")
    for i, row in enumerate(rows):
        if not isinstance(row, dict):
            raise ValueError(f"{where}[{i}]: expected a dict, got {type(row).__name__}")
        missing = [k for k in ROW_KEYS if k not in row]
        if missing:
            raise ValueError(f"{where}[{i}]: missing key(s) {missing}")
        for k in ROW_KEYS:
            if isinstance(row[k], bool) or not isinstance(row[k], (int, float)):
                raise ValueError(f"{where}[{i}].{k}: expected a number, got {row[k]!r}")
        if row["true_transitions"] < 0 or row["wall_seconds"] < 0:
            raise ValueError(f"{where}[{i}]: true_transitions and wall_seconds must be >= 0")
        if i and (row["true_transitions"] < rows[i - 1]["true_transitions"]
                  or row["wall_seconds"] < rows[i - 1]["wall_seconds"]):
            raise ValueError(f"{where}[{i}]: true_transitions and wall_seconds must not decrease along the run")
    return rows


def first_reaching(rows: Sequence[dict[str, Any]], predicate: Callable[[dict[str, Any]], bool]
                   ) -> dict[str, Any] | None:
    """The first row (in run order) for which ``predicate(row)`` holds, or None."""
    for row in rows:
        if predicate(row):
            return row
    return None


def reach_accuracy(rows: Sequence[dict[str, Any]], lateral: float = THRESHOLD_LATERAL,
                   speed: float = THRESHOLD_SPEED) -> dict[str, Any] | None:
    """The first evaluation at which **both** ``lateral_mae <= lateral`` and ``speed_mae <= speed`` hold.

    Returns
    -------
    dict or None
        That row (its ``true_transitions`` and ``wall_seconds`` say what it took), or None if no
        evaluation of the run meets both.
    """
    return first_reaching(rows, lambda r: r["lateral_mae"] <= lateral and r["speed_mae"] <= speed)


def reach_own_final(rows: Sequence[dict[str, Any]], rtol: float = FINAL_RTOL) -> dict[str, Any] | None:
    """The first evaluation whose course cost is within ``rtol`` of the run's final cost (its last row).

    ``cost <= final + rtol * |final|``; the last row always qualifies, so None only for an empty run or a
    non-finite final cost.
    """
    if not rows or not math.isfinite(rows[-1]["cost"]):
        return None
    bound = rows[-1]["cost"] + rtol * abs(rows[-1]["cost"])
    return first_reaching(rows, lambda r: math.isfinite(r["cost"]) and r["cost"] <= bound)


def settled(rows: Sequence[dict[str, Any]], rtol: float = CONVERGENCE_RTOL) -> dict[str, Any]:
    """The first evaluation from which the course cost *stays* within ``rtol`` of the run's final level.

    The convergence criterion of every mixedrl run (:func:`mixedrl.runs.iterations_to_converge`: final
    level = median of the last three costs), applied to the evaluation rows. Unlike
    :func:`reach_own_final` (first time within 10%), a run that was good early and then got worse is not
    counted as settled early.

    Raises
    ------
    ValueError
        ``rows`` empty.
    """
    if not rows:
        raise ValueError("rows: expected a non-empty list of evaluation rows")
    index = iterations_to_converge(list(range(len(rows))), [float(r["cost"]) for r in rows], rtol)
    return rows[index]


def choose_eval_every(iterations: int, points: int = 12) -> int:
    """An evaluation period giving about ``points`` evaluations over ``iterations``.

    ``ceil(iterations / points)``: at most ``points`` evaluations (the run also evaluates at its last
    iteration), and at least 10 of 12 once ``iterations >= 60``.

    Raises
    ------
    ValueError
        ``iterations`` or ``points`` not a positive integer.
    """
    iterations = check_positive_int(iterations, "iterations")
    return -(-iterations // check_positive_int(points, "points"))


def rows_from_metrics(metrics: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """The study's rows from a mixedrl run's metrics rows (:func:`mixedrl.runs.train`): one per evaluation.

    ``iteration`` <- ``iteration``, ``true_transitions`` <- ``data/true_transitions``, ``wall_seconds`` <-
    ``time/elapsed_s``, ``lateral_mae``/``speed_mae``/``cost`` <- ``eval/...``.

    Raises
    ------
    ValueError
        An evaluation row lacks ``data/true_transitions`` or ``time/elapsed_s``, or the rows fail
        :func:`check_rows`.
    """
    rows = []
    for m in metrics:
        if "eval/cost" not in m:
            continue
        for key in ("data/true_transitions", "time/elapsed_s", "eval/lateral_mae", "eval/speed_mae"):
            if key not in m:
                raise ValueError(f"metrics: the evaluation row of iteration {m.get('iteration')} has no {key!r}")
        count = float(m["data/true_transitions"])
        rows.append({"iteration": int(m["iteration"]),
                     "true_transitions": int(count) if math.isfinite(count) else count,
                     "wall_seconds": float(m["time/elapsed_s"]), "lateral_mae": float(m["eval/lateral_mae"]),
                     "speed_mae": float(m["eval/speed_mae"]), "cost": float(m["eval/cost"])})
    return check_rows(rows, "metrics")


def ours_config(method: str, seed: int, iterations: int, overrides: dict[str, Any] | None = None) -> TrainConfig:
    """The :class:`TrainConfig` of one of mixedrl's runs in the study.

    ``TrainConfig(task="dlc", algorithm=ONE_STEP_LEARNER).replace(method=..., seed=..., algorithm.iterations=..., run.eval_every=choose_eval_every(
    iterations), run.num_threads=1, **overrides)`` (``overrides``: dotted keys, ``run.eval_every`` among them).

    Raises
    ------
    ValueError
        ``method`` not one of :data:`OURS`, or an invalid/unknown override (from :class:`TrainConfig`).
    """
    if method not in OURS:
        raise ValueError(f"method: expected one of {OURS}, got {method!r}")
    iterations = int(iterations)
    overrides = dict(overrides or {})
    base = {"method": method, "seed": seed, "algorithm.iterations": iterations,
            "run.eval_every": choose_eval_every(iterations), "run.num_threads": 1}
    # the one-step learner the study was run with (experiments/studies/sample_efficiency.toml pins it)
    return TrainConfig(task="dlc", algorithm=ONE_STEP_LEARNER).replace(**{**base, **overrides})


def train_ours(method: str, seed: int, iterations: int, overrides: dict[str, Any] | None = None,
               out: str | Path | None = None) -> dict[str, Any]:
    """Train one of mixedrl's methods (:func:`mixedrl.runs.train`, in memory) and return the study's record.

    Parameters
    ----------
    method : {"mixed", "model", "oracle", "ddpg"}
    seed, iterations : int
    overrides : dict, optional
        ``TrainConfig`` fields (dotted keys allowed), see :func:`ours_config`.
    out : str or pathlib.Path, optional
        Write the record as JSON there (atomically, parents created).

    Returns
    -------
    dict
        ``method``, ``seed``, ``config`` (the run's ``TrainConfig.to_dict()``), ``overrides``, ``rows``
        (:func:`rows_from_metrics`), ``true_transitions``, ``train_seconds``, ``final`` (the run's final
        evaluation).

    Raises
    ------
    ValueError
        As :func:`ours_config`.
    """
    cfg = ours_config(method, seed, iterations, overrides)
    torch.set_num_threads(1)
    results = train(make_trainer(cfg), None, progress=False)
    record = {"method": method, "seed": int(seed), "config": cfg.to_dict(), "overrides": dict(overrides or {}),
              "rows": rows_from_metrics(results["metrics"]), "true_transitions": results.get("true_transitions"),
              "train_seconds": results["train_seconds"],
              "final": {k: results[k] for k in ("lateral_mae", "speed_mae", "cost") if k in results}}
    if out is not None:
        path = Path(out)
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(path, json.dumps(record, indent=1) + "\n")
    return record


#: Reproduction run labels (``validation.reproduce``) -> the study's method; DDPG's curve is its longer run.
REPRODUCTION_LABELS = {"mixed": "mixed", "model": "model", "oracle": "oracle", "ddpg_long": "ddpg"}


def records_from_reproduction(runs_dir: str | Path) -> list[dict[str, Any]]:
    """The study's records of the runs of a reproduction (``mixedrl reproduce``), without training again.

    Parameters
    ----------
    runs_dir : str or pathlib.Path
        A reproduction's directory (``mixedrl reproduce --out DIR``: its sweep ``DIR/sweep``, whose rows
        name each run's label by method and variant), its ``sweep`` folder, or the ``runs`` folder of a
        reproduction written before it trained through ``mixedrl sweep`` (``<label>_seed<n>/``). Each run
        has ``config.json``, ``metrics.jsonl`` and ``results.json``. Labels ``mixed``, ``model``,
        ``oracle`` and ``ddpg_long`` (DDPG with the longer budget, recorded as method ``ddpg``) are read;
        the 1500-iteration ``ddpg`` runs are a prefix of nothing (their learning rates decay over 1500
        iterations) and are skipped.

    Returns
    -------
    list of dict
        Records as :func:`train_ours` returns them (``overrides`` names the source run directory).

    Raises
    ------
    FileNotFoundError
        No run directory of a known label under ``runs_dir``.
    ValueError
        A run's metrics lack the keys :func:`rows_from_metrics` needs.
    """
    root = Path(runs_dir)
    records = []
    sweep_json = next((p for p in (root / "sweep.json", root / "sweep" / "sweep.json") if p.is_file()), None)
    if sweep_json is not None:
        rows = json.loads(sweep_json.read_text())["runs"]
        found = [("ddpg_long" if r["point"].get("variant") == "ddpg_long" else r["method"], r["seed"],
                  sweep_json.parent / r["run_dir"]) for r in rows if r["error"] is None]
    else:
        found = [(p.name.rpartition("_seed")[0], p.name.rpartition("_seed")[2], p) for p in sorted(root.glob("*_seed*"))]
    for label, seed, path in found:
        if label not in REPRODUCTION_LABELS or not (path / "results.json").is_file():
            continue
        run = RunDirectory(path)
        config, results = run.read_config(), run.read_results()
        records.append({"method": REPRODUCTION_LABELS[label], "seed": int(seed), "config": config.to_dict(),
                        "overrides": {"source": str(path)}, "rows": rows_from_metrics(run.read_metrics()),
                        "true_transitions": results.get("true_transitions"),
                        "train_seconds": results["train_seconds"],
                        "final": {k: results[k] for k in ("lateral_mae", "speed_mae", "cost") if k in results}})
    if not records:
        raise FileNotFoundError(f"runs_dir: no reproduction runs ({', '.join(REPRODUCTION_LABELS)}) under {root}")
    return records


def records_from_sweep(sweep_dir: str | Path) -> list[dict[str, Any]]:
    """The study's records of the finished runs of a sweep (``mixedrl sweep experiments/studies/sample_efficiency.toml``).

    Parameters
    ----------
    sweep_dir : str or pathlib.Path
        A sweep directory (:mod:`mixedrl.sweep`): its ``sweep.json`` rows and their run directories.

    Returns
    -------
    list of dict
        Records as :func:`train_ours` returns them (``overrides`` names the source run directory), in the
        sweep's order; failed or unfinished runs are left out.

    Raises
    ------
    FileNotFoundError
        ``sweep_dir`` holds no ``sweep.json``.
    ValueError
        A run's metrics lack the keys :func:`rows_from_metrics` needs.
    """
    root = Path(sweep_dir)
    doc_path = root / "sweep.json"
    if not doc_path.is_file():
        raise FileNotFoundError(f"sweep_dir: {doc_path} does not exist (run mixedrl sweep ... --out {root})")
    records = []
    for row in json.loads(doc_path.read_text())["runs"]:
        if row["error"] is not None or row["results"] is None:
            continue
        run = RunDirectory(root / row["run_dir"])
        config, results = run.read_config(), run.read_results()
        records.append({"method": config.method, "seed": config.seed, "config": config.to_dict(),
                        "overrides": {"source": str(run.path)}, "rows": rows_from_metrics(run.read_metrics()),
                        "true_transitions": results.get("true_transitions"),
                        "train_seconds": results["train_seconds"],
                        "final": {k: results[k] for k in ("lateral_mae", "speed_mae", "cost") if k in results}})
    return records


def load_runs(paths: Sequence[str | Path]) -> list[dict[str, Any]]:
    """Read per-run JSON files (of :func:`train_ours` or :func:`validation.peers.train_peer`).

    Raises
    ------
    ValueError
        A file is not JSON, lacks ``method``/``seed``/``rows``, or its rows fail :func:`check_rows`;
        two files hold the same method and seed.
    """
    runs, seen = [], set()
    for p in paths:
        try:
            run = json.loads(Path(p).read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"paths: {p} is not valid JSON ({exc})") from None
        if not isinstance(run, dict) or not {"method", "seed", "rows"} <= set(run):
            raise ValueError(f"paths: {p} is not a run record (needs 'method', 'seed', 'rows')")
        check_rows(run["rows"], f"{p}: rows")
        key = (run["method"], run["seed"])
        if key in seen:
            raise ValueError(f"paths: two runs of method {key[0]!r} seed {key[1]} ({p})")
        seen.add(key)
        runs.append(run)
    return runs


def _aligned(runs: Sequence[dict[str, Any]]) -> bool:
    """True if the runs evaluated at the same true-transition counts (the same schedule): their means per
    evaluation are then meaningful (``x`` = the mean over seeds, e.g. of the wall time)."""
    grids = [[row["true_transitions"] for row in r["rows"]] for r in runs]
    return bool(grids) and all(g == grids[0] for g in grids)


def _method_order(method: str) -> tuple[int, str]:
    order = [*OURS, "td3", "sac"]
    return (order.index(method) if method in order else len(order), method)


def summarize(runs: Sequence[dict[str, Any]], lateral: float = THRESHOLD_LATERAL, speed: float = THRESHOLD_SPEED,
              rtol: float = FINAL_RTOL) -> list[dict[str, Any]]:
    """The study's table: one entry per method, over its seeds.

    Returns
    -------
    list of dict
        Per method: ``method``, ``seeds``; the final evaluation (last row) as ``lateral_mean``,
        ``lateral_std``, ``speed_mean``, ``speed_std``, ``cost_mean``, ``cost_std`` (std over seeds with
        ``ddof=1``; None for one seed); ``true_transitions`` (final count per seed), ``wall_seconds`` (final
        training time per seed); per seed, the ``true_transitions`` and ``wall_seconds`` at the first
        evaluation meeting the accuracy threshold (:func:`reach_accuracy`; None = never) as
        ``accuracy_transitions``, ``accuracy_wall_seconds``, and within ``rtol`` of its own final cost
        (:func:`reach_own_final`) as ``own_final_transitions``, ``own_final_wall_seconds``, and from which
        it stays there (:func:`settled`) as ``settled_transitions``, ``settled_wall_seconds``; ``reached``
        (seeds meeting the threshold at some evaluation); the thresholds used.
    """
    groups: dict[str, list[dict[str, Any]]] = {}
    for run in runs:
        groups.setdefault(str(run["method"]), []).append(run)
    table = []
    for method in sorted(groups, key=_method_order):
        rs = sorted(groups[method], key=lambda r: r["seed"])
        finals = [r["rows"][-1] for r in rs]
        acc = [reach_accuracy(r["rows"], lateral, speed) for r in rs]
        own = [reach_own_final(r["rows"], rtol) for r in rs]
        stay = [settled(r["rows"], rtol) for r in rs]
        entry: dict[str, Any] = {"method": method, "seeds": [r["seed"] for r in rs]}
        for name, key in (("lateral", "lateral_mae"), ("speed", "speed_mae"), ("cost", "cost")):
            entry[f"{name}_mean"], entry[f"{name}_std"] = mean_std([f[key] for f in finals], one=None)
        entry["true_transitions"] = [f["true_transitions"] for f in finals]
        entry["wall_seconds"] = [f["wall_seconds"] for f in finals]
        entry["accuracy_transitions"] = [None if a is None else a["true_transitions"] for a in acc]
        entry["accuracy_wall_seconds"] = [None if a is None else a["wall_seconds"] for a in acc]
        entry["own_final_transitions"] = [None if a is None else a["true_transitions"] for a in own]
        entry["own_final_wall_seconds"] = [None if a is None else a["wall_seconds"] for a in own]
        entry["settled_transitions"] = [a["true_transitions"] for a in stay]
        entry["settled_wall_seconds"] = [a["wall_seconds"] for a in stay]
        entry["reached"] = sum(a is not None for a in acc)
        entry["threshold"] = {"lateral_mae": lateral, "speed_mae": speed, "own_final_rtol": rtol}
        table.append(entry)
    return table


def _cell(value: Any) -> str:
    if value is None:
        return "never"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def write_summary(table: Sequence[dict[str, Any]], out_dir: str | Path) -> tuple[Path, Path]:
    """Write ``summary.csv`` (lists as space-separated cells, ``never`` for None) and ``summary.json``.

    Both atomically, into ``out_dir`` (created if needed).

    Returns
    -------
    tuple of pathlib.Path
        The CSV and JSON paths.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    columns = [k for k in table[0] if k != "threshold"] if table else []
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(columns)
    for entry in table:
        writer.writerow([" ".join(_cell(v) for v in entry[c]) if isinstance(entry[c], list) else
                         ("" if entry[c] is None else _cell(entry[c])) for c in columns])
    csv_path, json_path = out / "summary.csv", out / "summary.json"
    atomic_write_text(csv_path, buffer.getvalue())
    atomic_write_text(json_path, json.dumps(list(table), indent=1) + "\n")
    return csv_path, json_path


def plot_curves(runs: Sequence[dict[str, Any]], x: str = "true_transitions", path: str | Path | None = None,
                lateral: float = THRESHOLD_LATERAL, speed: float = THRESHOLD_SPEED) -> Any:
    """Course cost, lateral and speed error against ``x`` (log axis), one colour per method.

    Each seed is a thin line; the mean over seeds is a thick line where the seeds share their ``x`` grid.
    With ``x="true_transitions"``, a method whose runs use no true transition (model-driven RL, the
    oracle on the model path) is drawn as a dashed horizontal line at its mean final value, labelled
    "0 true transitions". Points at ``x = 0`` of other methods cannot be shown on the log axis and are
    left out. The accuracy thresholds are dotted grey lines.

    Parameters
    ----------
    runs : sequence of dict
        Run records (``method``, ``seed``, ``rows``).
    x : {"true_transitions", "wall_seconds"}
    path : str or pathlib.Path, optional
        Save the figure there (PNG, atomically).

    Returns
    -------
    matplotlib.figure.Figure

    Raises
    ------
    ValueError
        ``x`` not one of the two keys.
    """
    if x not in ("true_transitions", "wall_seconds"):
        raise ValueError(f"x: expected 'true_transitions' or 'wall_seconds', got {x!r}")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = (("cost", "course cost (eq. 54, summed)"), ("lateral_mae", "lateral error [m]"),
              ("speed_mae", "speed error [m/s]"))
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    groups: dict[str, list[dict[str, Any]]] = {}
    for run in runs:
        groups.setdefault(str(run["method"]), []).append(run)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, method in enumerate(sorted(groups, key=_method_order)):
        rs, colour, label = groups[method], colours[i % len(colours)], LABELS.get(method, method)
        zero = x == "true_transitions" and all(row[x] == 0 for r in rs for row in r["rows"])
        for ax, (key, _) in zip(axes, panels):
            first = ax is axes[0]  # the methods' legend is on the first panel
            if zero:
                level = float(np.mean([r["rows"][-1][key] for r in rs]))
                ax.axhline(level, color=colour, ls="--", lw=1.8,
                           label=f"{label}: 0 true transitions" if first else None)
                continue
            for r in rs:
                pts = [(row[x], row[key]) for row in r["rows"] if row[x] > 0]
                if pts:
                    ax.plot(*zip(*pts), color=colour, lw=0.7, alpha=0.35)
            if _aligned(rs):
                mx = np.mean([[row[x] for row in r["rows"]] for r in rs], axis=0)
                my = np.mean([[row[key] for row in r["rows"]] for r in rs], axis=0)
                keep = mx > 0
                ax.plot(mx[keep], my[keep], color=colour, lw=2.0, marker="o", ms=3,
                        label=f"{label} (mean of {len(rs)} seed{'s' if len(rs) > 1 else ''})" if first else None)
            elif first:
                ax.plot([], [], color=colour, lw=2.0, label=f"{label} ({len(rs)} seeds, evaluation grids differ)")
    for ax, (key, title) in zip(axes, panels):
        if key == "lateral_mae":
            ax.axhline(lateral, color="grey", ls=":", lw=1, label=f"{lateral} m")
        if key == "speed_mae":
            ax.axhline(speed, color="grey", ls=":", lw=1, label=f"{speed} m/s")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("true-environment transitions" if x == "true_transitions" else
                      "training wall time [s] (evaluations excluded)")
        ax.set_title(title)
        ax.grid(True, which="both", alpha=0.3)
    for ax in axes[1:]:
        ax.legend(fontsize=7, loc="best")
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 3) or 1, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.06 * math.ceil(len(labels) / 3), 1, 1))
    if path is not None:
        buffer = io.BytesIO()
        fig.savefig(buffer, format="png", dpi=120)
        atomic_write_bytes(path, buffer.getvalue())
    return fig
