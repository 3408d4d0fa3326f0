"""Sweeps: a grid of ordinary training runs (config fields x variants x methods x seeds), executed on a local
process pool or on Ray (``mixedrl sweep``; docs/sweeps.rst: the spec, the engines, the outputs, resuming).

:mod:`mixedrl.sweep_spec` parses and expands the spec and :mod:`mixedrl.sweep_engines` trains the batches
(:func:`plan_batches`); this module writes the sweep directory and re-exports every public name of both."""


from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import logging
import os
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from mixedrl import sweep_engines, sweep_spec
from mixedrl.checks import check_positive_int
from mixedrl.runs import LOCK_NAME, atomic_write_bytes, atomic_write_text, hold_lock, is_lock_file
from mixedrl.run_results import png, pyplot
from mixedrl.tables import bootstrap_interval, csv_text, mean_std
from mixedrl.sweep_spec import (MAX_RUNS, SEED_MAX, SPEC_KEYS, SweepRun, SweepSpec, apply_dotted, config_hash, expand,
                                flatten_table, format_value, load_spec, parse_spec, resolve_observer, run_name)
from mixedrl.sweep_engines import (DEFAULT_BATCH, Job, plan_batches, run_here, run_point, run_points,
                                   run_pool, run_ray)

#: The names of :mod:`mixedrl.sweep_spec`, of :mod:`mixedrl.sweep_engines` and this module's own.
__all__ = [*sweep_spec.__all__, *sweep_engines.__all__, "RESULT_KEYS", "INSTALL_HINT", "csv_rows", "run_sweep",
           "summarize", "make_figure", "add_parser", "add_arguments", "add_engine_arguments", "format_summary"]

logger = logging.getLogger(__name__)


#: The figures of each run copied into ``sweep.json`` (``None`` when a run does not report one).
RESULT_KEYS = ("lateral_mae", "speed_mae", "cost", "true_transitions", "train_seconds")
#: Figures of ``results.json`` that are columns of their own in a sweep's row, not ``metrics``.
_OWN_COLUMNS = ("seed", "iterations", "true_transitions", "train_seconds")
#: What to install when Ray is missing.
INSTALL_HINT = 'pip install -c constraints.txt "mixedrl[sweep]"'


# ----------------------------------------------------------------------------------------------------
# the sweep
# ----------------------------------------------------------------------------------------------------
#: :func:`mixedrl.tables.bootstrap_interval` of a tuple, cached (``sweep.json`` is rewritten after every run).
_interval = functools.lru_cache(maxsize=4096)(bootstrap_interval)


def summarize(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Aggregate the runs over seeds: per grid point and method, mean, std and 95% interval of each figure.

    Parameters
    ----------
    records : list of dict
        The ``runs`` of ``sweep.json``.

    Returns
    -------
    list of dict
        One row per (grid point, method), in sweep order: ``point``, ``method``, ``runs`` (finished),
        ``failed``, and ``<figure>_mean``, ``_std`` (:func:`mixedrl.tables.mean_std`), ``_ci_low``,
        ``_ci_high`` (:func:`mixedrl.tables.bootstrap_interval`) for every figure of :data:`RESULT_KEYS`
        (``None`` when no run reports it).
    """
    rows: dict[str, dict[str, Any]] = {}
    done: dict[str, list[dict[str, Any]]] = {}
    for rec in records:
        key = json.dumps([rec["point"], rec["config"]["method"]], sort_keys=True)
        row = rows.setdefault(key, {"point": rec["point"], "method": rec["config"]["method"], "runs": 0, "failed": 0})
        finished = done.setdefault(key, [])
        if rec["error"] is not None:
            row["failed"] += 1
        elif rec["results"] is not None:
            finished.append(rec["results"])
    for key, row in rows.items():
        row["runs"] = len(done[key])
        for fig in RESULT_KEYS:
            values = [r[fig] for r in done[key] if isinstance(r.get(fig), (int, float))]
            row[f"{fig}_mean"], row[f"{fig}_std"] = mean_std(values)
            row[f"{fig}_ci_low"], row[f"{fig}_ci_high"] = _interval(tuple(float(v) for v in values))
    return list(rows.values())


def _spec_doc(spec: SweepSpec) -> dict[str, Any]:
    """The spec's part of ``sweep.json`` (``variants`` only for a spec that has them)."""
    return {"methods": list(spec.methods), "seeds": list(spec.seeds), "base": spec.base,
            "grid": {k: list(v) for k, v in spec.grid.items()},
            **({"variants": spec.variants} if spec.variants else {}),
            **({} if spec.observer is None else {"observer": spec.observer})}


#: What a sweep writes into its ``--out``; anything else there is not the sweep's.
SWEEP_FILES = ("spec.toml", "sweep.json", "sweep.csv", "sweep_summary.csv", "runs", "figures")


def _check_out(out: Path, spec: SweepSpec, runs: list[SweepRun], resume: bool) -> None:
    """Refuse an ``out`` that is a file or a dangling link, holds files not this sweep's, or holds a sweep
    without ``resume`` or of another spec; reads only."""
    if out.is_symlink() and not out.exists():
        raise ValueError(f"out: {out} is a symbolic link that does not resolve (a loop or a missing target)")
    if out.exists() and not out.is_dir():
        raise ValueError(f"out: {out} is a file, not a directory")
    names = [n for n in sorted(os.listdir(out)) if not (n.startswith(".") and n.endswith(".tmp"))
             and not (n == LOCK_NAME and is_lock_file(out / n))] if out.is_dir() else []
    if not names:
        return
    foreign = [n for n in names if n not in SWEEP_FILES]
    if (out / "runs").is_dir():
        own = {r.name for r in runs}
        foreign += [f"runs/{n}" for n in sorted(os.listdir(out / "runs")) if n not in own]
    if foreign:
        shown = ", ".join(foreign[:3]) + (", ..." if len(foreign) > 3 else "")
        raise ValueError(f"out: {out} holds files that are not this sweep's ({shown}); choose a new --out")
    if not resume:
        raise ValueError(f"out: {out} already holds a sweep; pass --resume to continue it, or choose a new --out")
    saved_spec = out / "spec.toml"
    if saved_spec.is_file():
        saved = parse_spec(saved_spec.read_text(encoding="utf-8"), str(saved_spec), force=True)
        if dataclasses.replace(saved, text="") != dataclasses.replace(spec, text=""):
            raise ValueError(f"spec: differs from the sweep's {saved_spec}; resume with the same spec or use a new "
                             f"--out")
    doc_path = out / "sweep.json"
    if doc_path.is_file():
        try:
            doc = json.loads(doc_path.read_text(encoding="utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ValueError(f"out: {doc_path} is not a sweep's JSON ({exc}); choose a new --out") from None
        mine = json.loads(json.dumps(_spec_doc(spec)))
        if not isinstance(doc, dict) or {k: doc.get(k) for k in mine} != mine:
            raise ValueError(f"spec: differs from the sweep recorded in {doc_path}; resume with the same spec or "
                             f"use a new --out")


def make_figure(out: str | Path, summary: list[dict[str, Any]], grid: dict[str, Sequence[Any]]) -> Path | None:
    """Plot the course cost (mean ± std over seeds) against the first grid key, one line per method, the
    other grid keys at their first value.

    Parameters
    ----------
    out : str or pathlib.Path
        The sweep directory; the figure goes to ``out/figures/cost_vs_<key>.png``.
    summary : list of dict
        :func:`summarize`'s rows.
    grid : dict
        The spec's grid.

    Returns
    -------
    pathlib.Path or None
        The figure's path; ``None`` without a grid or without matplotlib.
    """
    if not grid:
        return None
    plt = pyplot()
    if plt is None:
        logger.info("matplotlib not installed: no sweep figure")
        return None
    key = next(iter(grid))
    values = list(grid[key])
    others = {k: v[0] for k, v in grid.items() if k != key}
    numeric = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)
    xs = values if numeric else list(range(len(values)))
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    for method in dict.fromkeys(row["method"] for row in summary):
        pts = [(x, row["cost_mean"], row["cost_std"] or 0.0) for x, v in zip(xs, values) for row in summary
               if row["method"] == method and row["point"] == {**others, key: v} and row["cost_mean"] is not None]
        if pts:
            arr = np.asarray(pts, dtype=float)
            ax.errorbar(arr[:, 0], arr[:, 1], yerr=arr[:, 2], marker="o", capsize=3, label=method)
    if not numeric:
        ax.set_xticks(xs, [str(v) for v in values])
    ax.set_xlabel(key + ("" if not others else f"  ({', '.join(f'{k}={v}' for k, v in others.items())})"))
    ax.set_ylabel("course cost (mean ± std over seeds)")
    ax.legend()
    path = Path(out) / "figures" / f"cost_vs_{format_value(key)}.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, png(fig, dpi=120))
    return path


def _record(sweep_run: SweepRun, results: dict[str, Any] | None, error: str | None,
            wall_seconds: float | None = None) -> dict[str, Any]:
    """One row of ``sweep.json``'s ``runs`` (docs/sweeps.rst, "One row per run")."""
    config = sweep_run.config.to_dict()
    run_dir = str(Path("runs") / sweep_run.name)
    got = {} if results is None else results
    return {"name": sweep_run.name, "point": sweep_run.point, "config": config,
            "config_hash": config_hash(config), "method": sweep_run.config.method, "seed": sweep_run.config.seed,
            "iterations": None if results is None else results.get("iterations", config["algorithm"]["iterations"]),
            "true_transitions": got.get("true_transitions"),
            "metrics": {k: v for k, v in got.items()
                        if isinstance(v, (int, float)) and not isinstance(v, bool) and k not in _OWN_COLUMNS},
            "train_seconds": got.get("train_seconds"), "wall_seconds": wall_seconds, "run_dir": run_dir,
            "results": None if results is None else {**{k: got.get(k) for k in RESULT_KEYS}, "run_dir": run_dir},
            "error": error}


def csv_rows(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The rows of ``sweep.csv``: per run the fields of its ``sweep.json`` row but ``config``, grid values
    and metrics one column each.

    Parameters
    ----------
    records : list of dict
        The ``runs`` of ``sweep.json``.
    """
    return [{"name": rec["name"], **rec["point"], "method": rec["config"]["method"], "seed": rec["config"]["seed"],
             "config_hash": rec.get("config_hash"), "iterations": rec.get("iterations"),
             **dict.fromkeys(RESULT_KEYS), "true_transitions": rec.get("true_transitions"),
             **(rec.get("metrics") or {}),
             "train_seconds": rec.get("train_seconds"), "wall_seconds": rec.get("wall_seconds"),
             "run_dir": rec.get("run_dir"), "error": rec["error"]} for rec in records]


def run_sweep(spec: SweepSpec, out: str | Path, address: str | None = None, num_cpus: int | None = None,
              resume: bool = False, progress: bool = True, workers: int | None = None,
              batch: int = DEFAULT_BATCH, batch_ddpg: bool = False) -> dict[str, Any]:
    """Run every run of ``spec`` (on a local process pool, or on Ray with ``address``) and write the sweep's
    outputs into ``out``.

    Parameters
    ----------
    spec : SweepSpec
        From :func:`load_spec` / :func:`parse_spec`.
    out : str or pathlib.Path
        The sweep directory (on a shared file system for a multi-node cluster).
    address : str, optional
        Run on Ray: an existing cluster (``"auto"``, ``"HOST:6379"``, ``"ray://HOST:10001"``; an already
        initialised Ray is used as it is) or ``"local"`` (a local cluster of ``num_cpus`` CPUs). ``None``:
        the local process pool.
    num_cpus : int, optional
        With ``address="local"``: CPUs of the local Ray cluster (default ``os.cpu_count()``). Without
        ``address``: another name of ``workers``.
    resume : bool
        Skip finished runs, resume interrupted ones from their checkpoints.
    progress : bool
        tqdm progress bar over runs.
    workers : int, optional
        Processes of the local pool (default ``os.cpu_count()``); ``1`` trains in this process.
    batch : int
        Most runs trained as one computation (:func:`plan_batches`); ``1``: every run alone, as
        ``mixedrl train``.
    batch_ddpg : bool
        Batch the DDPG runs too (``ddpg`` of :func:`plan_batches`); default: each DDPG run alone.

    Returns
    -------
    dict
        The content of ``sweep.json``; ``failed`` counts the runs that raised.

    Raises
    ------
    ImportError
        ``address`` is given and Ray is not installed (the message names the extra to install).
    mixedrl.runs.RunLockedError
        Another sweep driver is running in ``out`` (the message names its pid and host); nothing is written.
    ValueError
        ``out`` holds a sweep and ``resume`` is false, or one of another spec; ``out`` holds files not this
        sweep's (anything but :data:`SWEEP_FILES` and the spec's run directories); ``num_cpus``,
        ``workers`` or ``batch`` not a positive integer; ``workers`` with ``address``, or ``workers`` and
        ``num_cpus`` that differ. Nothing is started or written.
    """
    out = Path(os.path.realpath(out))
    runs = expand(spec)
    for value, name in ((num_cpus, "num_cpus"), (workers, "workers"), (batch, "batch")):
        if value is not None:
            check_positive_int(value, name)
    if address is not None and workers is not None:
        raise ValueError("workers: the local process pool's size; with address the runs go to Ray (use num_cpus "
                         "for a local Ray cluster)")
    if address is None and workers is not None and num_cpus is not None and workers != num_cpus:
        raise ValueError(f"num_cpus: without address it is the older name of workers; got workers={workers} and "
                         f"num_cpus={num_cpus}")
    _check_out(out, spec, runs, resume)
    ray = None
    if address is not None:
        try:
            import ray
        except ImportError:
            raise ImportError(f"mixedrl sweep --address needs Ray: {INSTALL_HINT}") from None
    n_workers = workers or num_cpus or os.cpu_count() or 1

    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"out: cannot create the directory {out} ({exc.strerror or exc})") from None
    # one driver per sweep directory, the only writer of sweep.json
    with hold_lock(out / LOCK_NAME, "out"):
        _check_out(out, spec, runs, resume)  # again under the lock: another driver may have written meanwhile
        started = ray is not None and not ray.is_initialized()
        if started and address == "local":
            ray.init(num_cpus=num_cpus or os.cpu_count() or 1, include_dashboard=False, log_to_driver=False)
        elif started:
            ray.init(address=address, log_to_driver=False)
        try:
            (out / "runs").mkdir(parents=True, exist_ok=True)
            atomic_write_text(out / "spec.toml", spec.text)
            t0 = time.perf_counter()
            parallel = (int(ray.cluster_resources().get("CPU", 1)) if ray is not None else n_workers)
            batches = plan_batches(runs, batch, max(1, parallel), ddpg=batch_ddpg)
            # the longest first (largest budget, then largest batch)
            batches.sort(key=lambda b: (-max(runs[i].config.algorithm.iterations for i in b), -len(b), b[0]))
            jobs: list[Job] = [([runs[i].config.to_dict() for i in b], [str(out / "runs" / runs[i].name) for i in b],
                                 resume, spec.observer) for b in batches]
            records = [_record(r, None, None) for r in runs]
            if ray is not None:
                extra: dict[str, Any] = {"engine": "ray", "ray_version": ray.__version__, "address": address}
                finished = run_ray(jobs, ray)
            else:
                n_workers = min(n_workers, len(jobs))
                extra = {"engine": "local", "workers": n_workers, "address": None}
                finished = run_here(jobs) if n_workers == 1 else run_pool(jobs, n_workers)
            extra.update({"batch": batch, "batches": len(batches)})

            def write(complete: bool) -> None:
                summary = summarize(records)
                doc = {**_spec_doc(spec), **extra, "failed": failed, "finished": complete,
                       "wall_seconds": time.perf_counter() - t0, "runs": records, "summary": summary}
                atomic_write_text(out / "sweep.json", json.dumps(doc, indent=2, allow_nan=True) + "\n")
                atomic_write_text(out / "sweep.csv", csv_text(csv_rows(records)))
                atomic_write_text(out / "sweep_summary.csv", csv_text(
                    [{**row["point"], **{k: v for k, v in row.items() if k != "point"}} for row in summary]))

            from tqdm.auto import tqdm

            failed = 0
            with tqdm(total=len(runs), desc="sweep (runs)", disable=not progress) as bar:
                for j, outcomes, error, wall in finished:
                    if error is not None:
                        logger.error("batch of %s failed: %s", ", ".join(runs[i].name for i in batches[j]), error)
                    for k, i in enumerate(batches[j]):
                        results, run_error = (None, error) if outcomes is None else outcomes[k]
                        if run_error is not None:
                            failed += 1
                            if outcomes is not None:
                                logger.error("run %s failed: %s", runs[i].name, run_error)
                        records[i] = _record(runs[i], results, run_error, None if results is None else wall)
                    write(False)
                    bar.update(len(batches[j]))
                    if failed:
                        bar.set_postfix(failed=failed)
            write(True)
        finally:
            if started:
                ray.shutdown()
        doc = json.loads((out / "sweep.json").read_text())
        make_figure(out, doc["summary"], spec.grid)
        return doc



# ----------------------------------------------------------------------------------------------------
# command line
# ----------------------------------------------------------------------------------------------------
def add_arguments(p: argparse.ArgumentParser) -> None:
    """Add the options of ``mixedrl sweep`` to ``p`` (``spec``, ``--out``, ``--workers``, ``--force`` and
    :func:`add_engine_arguments`)."""
    p.add_argument("spec", type=Path, help="sweep spec (TOML: methods, seeds, [base], [grid], [variants.NAME])")
    p.add_argument("--out", type=Path, required=True, help="sweep directory (shared by every node of a cluster)")
    p.add_argument("--workers", type=int, default=None,
                   help="processes of the local pool (default: all CPUs; 1 runs in this process)")
    p.add_argument("--force", action="store_true",
                   help=f"accept a spec of more than {MAX_RUNS} runs (mixedrl.sweep.MAX_RUNS)")
    add_engine_arguments(p)


def add_engine_arguments(p: argparse.ArgumentParser) -> None:
    """Add the engine's options shared by ``mixedrl sweep`` and the study drivers to ``p``."""
    p.add_argument("--address", default=None,
                   help="run on Ray: join a cluster (e.g. 'auto' or HOST:6379) or 'local' to start one; "
                        "default: the local process pool")
    p.add_argument("--num-cpus", type=int, default=None,
                   help="CPUs of the local Ray cluster of --address local (default: all); without --address, "
                        "the processes of the local pool")
    p.add_argument("--batch", type=int, default=DEFAULT_BATCH,
                   help=f"most runs trained as one computation (default {DEFAULT_BATCH}; 1: every run alone, "
                        f"as mixedrl train)")
    p.add_argument("--batch-ddpg", action="store_true",
                   help="batch the DDPG runs too (default: each DDPG run alone; docs: Sweeps)")
    p.add_argument("--resume", action="store_true", help="skip finished runs, resume interrupted ones")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def add_parser(subparsers: Any) -> None:
    """Add the ``sweep`` sub-command to ``mixedrl``'s sub-parsers (``argparse`` ``add_subparsers()``)."""
    add_arguments(subparsers.add_parser(
        "sweep", help="run a grid of training runs (config x methods x seeds) on a process pool or Ray",
        description=__doc__.split("\n", 1)[0]))


def format_summary(doc: dict[str, Any], out: str | Path) -> str:
    """The summary of a finished sweep as text: per grid point and method the runs, failures and course
    cost (mean ± std), then the paths of ``sweep.json`` and the summary CSV.

    Parameters
    ----------
    doc : dict
        The content of ``sweep.json`` (as returned by :func:`run_sweep`).
    out : str or pathlib.Path
        The sweep directory.

    Returns
    -------
    str
        The text printed by ``mixedrl sweep``.
    """
    lines = []
    for row in doc["summary"]:
        point = ", ".join(f"{k}={v}" for k, v in row["point"].items())
        cost = "n/a" if row["cost_mean"] is None else f"{row['cost_mean']:.6g} ± {row['cost_std']:.3g}"
        lines.append(f"{point + '  ' if point else ''}{row['method']:<7} runs {row['runs']}  failed {row['failed']}  "
                     f"cost {cost}")
    lines.append(f"\nsweep: {Path(out) / 'sweep.json'}   table: {Path(out) / 'sweep_summary.csv'}")
    return "\n".join(lines)
