"""Sweeps: a grid of ordinary training runs (config fields x variants x methods x seeds), executed on a local
process pool or on Ray.

::

    mixedrl sweep SPEC.toml --out DIR [--workers N] [--force] [--batch N] [--address ADDR] [--num-cpus N]
                  [--resume] [--no-progress]

A spec is a small TOML file::

    methods = ["mixed", "model"]          # TrainConfig.method of the runs
    seeds = [0, 1, 2]                     # TrainConfig.seed of the runs

    [base]                                # TrainConfig fields shared by every run, as dotted keys
    "algorithm.iterations" = 600
    "run.eval_seeds" = 1
    "task.prior_force_mean" = 150

    [grid]                                # dotted key -> list of values: the cartesian product
    "algorithm.critic_lr" = [1e-3, 3e-3]
    "algorithm.batch_size" = [256, 512]

    [variants.short]                      # optional: named designs that are not a product, each a table of
    "algorithm.horizon" = 8               # fields applied over [base] (not method, seed or a grid key)
    [variants.long]
    "algorithm.horizon" = 32
    seeds = [0]                           # a variant may have its own methods / seeds lists

and optionally ``observer = "module:function"`` (top level): ``function(config)`` returns the
:class:`mixedrl.runs.IterationObserver` of each run (the reproduction's theory checks).

It expands to ``len(variants or [one]) x len(grid product) x len(methods) x len(seeds)`` runs (a variant's own
``methods`` / ``seeds`` replace the spec's for its runs). Every run is an
ordinary run directory (:class:`mixedrl.runs.RunDirectory`) under ``DIR/runs/``, trained by
:func:`mixedrl.runs.make_trainer` and :func:`mixedrl.runs.train_batch`. The runs are trained in batches
(:func:`plan_batches`: runs with equal :func:`mixedrl.algorithms.batched.batch_key`, at most ``--batch`` per
batch, default :data:`DEFAULT_BATCH`; Algorithm-2 runs in :class:`~mixedrl.algorithms.batched.BatchedAGPI`;
DDPG runs alone, or with ``--batch-ddpg`` in :class:`~mixedrl.algorithms.batched_ddpg.BatchedDDPG`, never
with Algorithm-2 runs): a run of a batch ends
with exactly the weights and metrics of the same config in any other batch of two or more, and with
``--batch 1`` every run trains alone, with exactly the weights and metrics of ``mixedrl train``.

Before anything starts, the spec is checked (TOML syntax, top-level keys, non-empty lists without
duplicates, variant tables, no TOML dates, seeds below ``2**64``, at most :data:`MAX_RUNS` runs unless
``--force``) and the :class:`~mixedrl.config.TrainConfig` of **every** run is built (two runs with equal
configs are an error); any error names the offending key and nothing is started or written.

One driver writes a sweep directory: it holds ``DIR/.lock`` (:func:`mixedrl.runs.hold_lock`) from its checks
to its last write, and its pool workers end when it dies (:func:`_die_with_parent`).

Engines (the same outputs from each):

* **local process pool** (default): ``--workers N`` processes (default ``os.cpu_count()``;
  :class:`concurrent.futures.ProcessPoolExecutor` with the ``spawn`` start method, so each worker is a fresh
  interpreter), one batch per task, the longest first. ``--workers 1`` trains the batches one after the
  other in this process. ``--num-cpus`` without ``--address`` is the older name of ``--workers``.
* **Ray** (the optional extra ``sweep``) when ``--address`` is given: one Ray task per batch (``num_cpus=1``),
  gathered with ``ray.wait``. ``--address local`` starts a local cluster of ``--num-cpus`` CPUs (default
  all); any other address joins an existing cluster (``DIR`` must then be a path every node sees).

Each batch sets ``torch.set_num_threads(config.run.num_threads)``. A failed run is recorded with its
error and does not stop the others (a run whose directory is refused fails alone; a batch that raises
fails with its runs).

Outputs in ``DIR``:

* ``spec.toml``: a copy of the spec;
* ``runs/<name>/``: one run directory per run, ``<name>`` made of the variant, the grid values, method and
  seed (:func:`run_name`);
* ``sweep.json``: the spec (``methods``, ``seeds``, ``base``, ``grid``, ``variants`` and ``observer`` when it
  has them), the engine (``engine`` ``"local"`` or ``"ray"``, ``workers`` or ``ray_version``, ``address``),
  ``batch`` and ``batches``, ``failed``,
  ``finished``, ``wall_seconds``, ``runs`` and ``summary``; rewritten atomically after every finished run.
  ``runs`` holds **one row per run** (the one result schema of every study):

  * ``name``: the run's directory name
  * ``point``: its grid values (and ``variant``: the variant's name)
  * ``config``: the full ``TrainConfig.to_dict()``
  * ``config_hash``: sha256 of the canonical JSON of ``config`` (:func:`config_hash`)
  * ``method``: ``config["method"]``
  * ``seed``: ``config["seed"]``
  * ``iterations``: the training budget in iterations (``results.json``'s ``iterations``)
  * ``true_transitions``: true-environment transitions the run consumed (its budget in env steps)
  * ``metrics``: every top-level number of ``results.json`` (``lateral_mae``, ``speed_mae``, ``cost``,
    ``iterations_to_converge``, ...) but the columns above and the times
  * ``train_seconds``: training time (``results.json``)
  * ``wall_seconds``: the wall time of the run's batch in its worker: start-up, training and evaluation
  * ``run_dir``: ``runs/<name>``, relative to ``DIR``
  * ``error``: ``null``, or the failed run's exception (``Type: message``)
  * ``results``: the figures of :data:`RESULT_KEYS` and ``run_dir`` (``null`` for a failed or unfinished run;
    kept for readers of earlier sweeps)

  A failed or unfinished run has ``null`` budget, times and ``results`` and empty ``metrics``.
  ``summary``: per grid point and method, mean, sample std and 95% bootstrap interval over seeds
  (:func:`summarize`);
* ``sweep.csv``: the rows of ``runs`` flattened (:func:`csv_rows`: grid values and metrics one column each, no
  ``config``) and ``sweep_summary.csv`` (the summary);
* ``figures/cost_vs_<first grid key>.png`` when matplotlib is installed.

``--resume`` skips runs whose ``results.json`` exists and resumes interrupted runs from their
checkpoints in their batches (``train_batch(..., resume=True)``), so a resumed sweep ends with the results
of an uninterrupted one.

The statistics and CSV helpers are :mod:`mixedrl.tables`, shared with the studies' scripts."""

from __future__ import annotations

import argparse
import concurrent.futures
import ctypes
import dataclasses
import datetime
import functools
import hashlib
import importlib
import io
import itertools
import json
import logging
import multiprocessing
import os
import re
import signal
import sys
import threading
import time
import tomllib
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np

from mixedrl.config import TrainConfig, apply_overrides, flatten_table
from mixedrl.algorithms.batched import batch_key
from mixedrl.checks import check_positive_int
from mixedrl.runs import (LOCK_NAME, RunDirectory, atomic_write_bytes, atomic_write_text, check_run_directory,
                          hold_lock, is_lock_file, load_trainer, make_trainer, train_batch)
from mixedrl.tables import bootstrap_interval, csv_text, mean_std

__all__ = [
    "SPEC_KEYS",
    "RESULT_KEYS",
    "INSTALL_HINT",
    "SweepSpec",
    "SweepRun",
    "apply_dotted",
    "flatten_table",
    "parse_spec",
    "load_spec",
    "expand",
    "run_name",
    "config_hash",
    "csv_rows",
    "run_point",
    "run_points",
    "plan_batches",
    "resolve_observer",
    "DEFAULT_BATCH",
    "MAX_RUNS",
    "SEED_MAX",
    "run_sweep",
    "summarize",
    "make_figure",
    "add_parser",
    "add_arguments",
    "add_engine_arguments",
    "format_summary",
]

logger = logging.getLogger(__name__)

#: Top-level keys a spec may have (``methods`` and ``seeds`` are required).
SPEC_KEYS = ("methods", "seeds", "base", "grid", "variants", "observer")
#: Most runs trained as one computation (:func:`mixedrl.runs.train_batch`) by default: at 15 runs a batch
#: already makes 1.7x the run-iterations per second of the runs one by one (``benchmarks/batched_table.py``).
DEFAULT_BATCH = 16
#: The figures of each run copied into ``sweep.json`` (``None`` when a run does not report one).
RESULT_KEYS = ("lateral_mae", "speed_mae", "cost", "true_transitions", "train_seconds")
#: Figures of ``results.json`` that are columns of their own in a sweep's row, not ``metrics``.
_OWN_COLUMNS = ("seed", "iterations", "true_transitions", "train_seconds")
#: What to install when Ray is missing.
INSTALL_HINT = 'pip install -c constraints.txt "mixedrl[sweep]"'
#: Fields a spec sets through ``methods`` and ``seeds``, never through ``[base]`` or ``[grid]``.
_RESERVED = {"method": "methods", "seed": "seeds"}
#: Keys of a ``[variants.NAME]`` table that replace the spec's lists for that variant (not config fields).
_VARIANT_LISTS = ("methods", "seeds")
#: Longest run name before it is shortened with a hash.
_MAX_NAME = 160
#: Most runs a spec may expand to without ``force`` (``mixedrl sweep --force``): checking a spec builds every
#: run's config first (about 2 ms and 2.5 kB each), and a larger sweep is more likely a typo than a plan.
MAX_RUNS = 10_000
#: The largest seed the generators accept (``torch.Generator.manual_seed``: 64 bits).
SEED_MAX = 2**64 - 1


# ----------------------------------------------------------------------------------------------------
# the spec
# ----------------------------------------------------------------------------------------------------
#: Dotted-key overrides of a config dict: :func:`mixedrl.config.apply_overrides` (one implementation for
#: ``mixedrl train --set`` and the sweep's ``[base]`` / ``[grid]`` keys).
apply_dotted = apply_overrides


@dataclasses.dataclass(frozen=True)
class SweepSpec:
    """A parsed, checked sweep spec (see the module docstring).

    Attributes
    ----------
    methods : tuple of str
        ``TrainConfig.method`` of the runs.
    seeds : tuple of int
        ``TrainConfig.seed`` of the runs.
    base : dict
        Dotted key -> value shared by every run.
    grid : dict
        Dotted key -> tuple of values; the runs cover their cartesian product (in the spec's key order).
    text : str
        The spec's TOML text (copied to ``DIR/spec.toml``).
    variants : dict
        Variant name -> its dotted-key overrides (applied over ``base``), and optionally ``methods`` /
        ``seeds``: the variant's own lists; empty for a spec without ``[variants.NAME]`` tables. The runs
        cover variants x grid points x methods x seeds.
    observer : str or None
        ``"module:function"``: ``function(config)`` returns the :class:`mixedrl.runs.IterationObserver` of a
        run (or ``None``), for example ``"validation.reproduce:theory_observer"`` (the theory checks);
        resolved when the spec is parsed.
    """

    methods: tuple[str, ...]
    seeds: tuple[int, ...]
    base: dict[str, Any]
    grid: dict[str, tuple[Any, ...]]
    text: str = ""
    variants: dict[str, dict[str, Any]] = dataclasses.field(default_factory=dict)
    observer: str | None = None


@dataclasses.dataclass(frozen=True)
class SweepRun:
    """One run of a sweep: its directory name, its grid values and its full config."""

    name: str
    point: dict[str, Any]
    config: TrainConfig


def _check_values(value: Any, key: str) -> None:
    """Refuse a TOML date or time anywhere in ``value`` (no config field is one)."""
    if isinstance(value, (datetime.date, datetime.time)):
        raise ValueError(f"{key}: {value.isoformat()} is a TOML date or time, which no config field takes (quote it "
                         f"to make it a string)")
    if isinstance(value, dict):
        for k, v in value.items():
            _check_values(v, f"{key}.{k}")
    elif isinstance(value, list):
        for v in value:
            _check_values(v, key)


def _run_count(methods: list[Any], seeds: list[Any], grid: dict[str, tuple[Any, ...]],
               variants: dict[str, dict[str, Any]]) -> int:
    """How many runs a spec expands to (:func:`expand`), without building them."""
    points = 1
    for values in grid.values():
        points *= len(values)
    own = list(variants.values()) or [{}]
    return sum(points * len(v.get("methods", methods)) * len(v.get("seeds", seeds)) for v in own)


def _check_list(value: Any, key: str) -> list[Any]:
    if not isinstance(value, list):
        raise ValueError(f"{key}: expected a list of values, got {type(value).__name__} {value!r}")
    if not value:
        raise ValueError(f"{key}: empty list (a sweep over nothing)")
    seen: set[str] = set()
    for v in value:  # the same TOML value twice (1 and 1.0 differ here; equal configs are found by expand)
        text = f"{type(v).__name__}:{json.dumps(v, sort_keys=True, default=str)}"
        if text in seen:
            raise ValueError(f"{key}: duplicate value {v!r}")
        seen.add(text)
    return value


def parse_spec(text: str, source: str = "spec", force: bool = False) -> SweepSpec:
    """Parse and check the TOML text of a sweep spec, and build the config of every run.

    Parameters
    ----------
    text : str
        TOML with ``methods``, ``seeds``, and optionally ``[base]``, ``[grid]`` and ``[variants.NAME]``.
    source : str
        Name used in error messages (the file's path).
    force : bool
        Accept a spec of more than :data:`MAX_RUNS` runs.

    Returns
    -------
    SweepSpec

    Raises
    ------
    ValueError
        Invalid TOML (``spec: ...``), an unknown top-level key (``spec: unknown key(s) ...``), a missing,
        empty, non-list or duplicated ``methods`` / ``seeds`` / grid list (message starts with the key,
        e.g. ``grid.critic_lr: ...``), ``method`` or ``seed`` set in ``[base]`` / ``[grid]``, a field
        both in ``[base]`` and ``[grid]``, or a run whose config :meth:`TrainConfig.from_dict` rejects
        (unknown or invalid field; message starts with the run's name), a ``[variants.NAME]`` that is not a
        table, sets ``method`` / ``seed`` or a grid key, or has a ``methods`` / ``seeds`` that is not a
        non-empty list without duplicates (``variants.NAME.KEY: ...``), a TOML date or time anywhere, a
        seed beyond ``2**64 - 1``, more than :data:`MAX_RUNS` runs without ``force`` (``grid: ...``, checked
        before any config is built), or two runs with equal configs (grid values equal after their
        type is normalised, e.g. ``1`` and ``1.0`` of a float field: ``grid: ...`` naming both).
    """
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"spec: {source} is not valid TOML ({exc})") from None
    unknown = sorted(set(data) - set(SPEC_KEYS))
    if unknown:
        raise ValueError(f"spec: unknown key(s) {unknown} in {source}; allowed: {list(SPEC_KEYS)}")
    for key in ("methods", "seeds"):
        if key not in data:
            raise ValueError(f"{key}: missing from {source} (a list is required)")
    for key, value in data.items():
        _check_values(value, key)
    methods = _check_list(data["methods"], "methods")
    seeds = _check_list(data["seeds"], "seeds")
    tables: dict[str, dict[str, Any]] = {}
    for key in ("base", "grid"):
        table = data.get(key, {})
        if not isinstance(table, dict):
            raise ValueError(f"{key}: expected a table [{key}], got {type(table).__name__}")
        tables[key] = flatten_table(table)
        for field, via in _RESERVED.items():
            if field in tables[key]:
                raise ValueError(f"{key}.{field}: set by the spec's {via!r} list, not in [{key}]")
    grid = {key: tuple(_check_list(values, f"grid.{key}")) for key, values in tables["grid"].items()}
    for key in grid:
        if key in tables["base"]:
            raise ValueError(f"grid.{key}: also set in [base]; set it in one place")
    variants = _parse_variants(data.get("variants", {}), grid)
    for key, values in [("seeds", seeds)] + [(f"variants.{n}.seeds", v["seeds"]) for n, v in variants.items()
                                             if "seeds" in v]:
        big = [v for v in values if isinstance(v, int) and v > SEED_MAX]
        if big:
            raise ValueError(f"{key}: {big[0]} is out of range; a seed is an integer in [0, 2**64 - 1]")
    count = _run_count(methods, seeds, grid, variants)
    if count > MAX_RUNS and not force:
        raise ValueError(f"grid: {source} expands to {count} runs, more than the {MAX_RUNS} a sweep may have without "
                         f"--force (force=True); nothing was checked or started")
    observer = data.get("observer")
    if observer is not None:
        resolve_observer(observer)
    spec = SweepSpec(methods=tuple(methods), seeds=tuple(seeds), base=tables["base"], grid=grid, text=text,
                     variants=variants, observer=observer)
    expand(spec)  # builds (and so validates) the config of every run before anything starts
    return spec


def resolve_observer(name: Any) -> Any:
    """The observer factory a spec names: ``"module:function"`` imported, ``function(config)`` callable.

    Raises
    ------
    ValueError
        ``name`` is not a ``"module:function"`` string, the module does not import, or it has no such
        callable (the message starts with ``observer``).
    """
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z_][\w.]*:[A-Za-z_]\w*", name):
        raise ValueError(f"observer: expected \"module:function\", got {name!r}")
    module_name, attr = name.split(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ValueError(f"observer: cannot import {module_name!r} ({exc})") from None
    factory = getattr(module, attr, None)
    if not callable(factory):
        raise ValueError(f"observer: {module_name} has no callable {attr!r}")
    return factory


def _parse_variants(table: Any, grid: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Check the ``[variants.NAME]`` tables: each a table of dotted-key overrides (over ``[base]``), not
    ``method`` / ``seed`` and not a grid key; ``methods`` / ``seeds`` (lists) give the variant its own."""
    if not isinstance(table, dict):
        raise ValueError(f"variants: expected tables [variants.NAME], got {type(table).__name__}")
    variants: dict[str, dict[str, Any]] = {}
    for name, body in table.items():
        if not re.fullmatch(r"[A-Za-z0-9.+\-_]+", name):
            raise ValueError(f"variants.{name}: a variant name may hold letters, digits, '.', '+', '-', '_' only")
        if not isinstance(body, dict):
            raise ValueError(f"variants.{name}: expected a table [variants.{name}], got {type(body).__name__}")
        own = {key: _check_list(body[key], f"variants.{name}.{key}") for key in _VARIANT_LISTS if key in body}
        flat = flatten_table({k: v for k, v in body.items() if k not in _VARIANT_LISTS})
        for field, via in _RESERVED.items():
            if field in flat:
                raise ValueError(f"variants.{name}.{field}: set by the spec's {via!r} list, not in a variant")
        for key in flat:
            if key in grid:
                raise ValueError(f"variants.{name}.{key}: also a grid key; set it in one place")
        variants[name] = {**flat, **own}
    return variants


def load_spec(path: str | Path, force: bool = False) -> SweepSpec:
    """Read a spec file and :func:`parse_spec` it (``force``: as for :func:`parse_spec`).

    Raises
    ------
    ValueError
        The file does not exist, is a directory or is not UTF-8 (``spec: ...``), or :func:`parse_spec`
        rejects it.
    """
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"spec: {path} is a directory, not a spec file (TOML)")
    if not path.is_file():
        raise ValueError(f"spec: {path} does not exist")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(f"spec: {path} is not UTF-8 text ({exc})") from None
    except OSError as exc:
        raise ValueError(f"spec: cannot read {path} ({exc.strerror})") from None
    return parse_spec(text, source=str(path), force=force)


def _format_value(value: Any) -> str:
    if isinstance(value, str):
        text = value
    elif isinstance(value, (list, tuple)):
        text = "x".join(_format_value(v) for v in value)
    elif isinstance(value, dict):
        text = "_".join(f"{k}-{_format_value(v)}" for k, v in value.items())
    else:
        text = json.dumps(value)
    return re.sub(r"[^A-Za-z0-9.+\-]", "_", text)


def run_name(point: dict[str, Any], method: str, seed: int) -> str:
    """The directory name of one run: ``key=value`` of each grid value, then ``<method>_seed<S>``, joined by
    ``__`` (e.g. ``critic_lr=0.001__batch_size=256__mixed_seed0``).

    Characters other than letters, digits, ``.``, ``+`` and ``-`` in a value become ``_``; a name longer than
    160 characters is cut and ends with a hash of the full name, so it stays unique and deterministic.
    """
    parts = [f"{key}={_format_value(value)}" for key, value in point.items()] + [f"{method}_seed{seed}"]
    name = "__".join(parts)
    if len(name) > _MAX_NAME:
        digest = hashlib.sha256(name.encode()).hexdigest()[:12]
        name = f"{name[:_MAX_NAME - 14]}__{digest}"
    return name


def expand(spec: SweepSpec) -> list[SweepRun]:
    """Every run of ``spec``: variants (spec order) x grid points (cartesian product, spec order) x methods x
    seeds. A run's ``point`` holds ``variant`` (its name, for a spec with variants) and its grid values.

    Returns
    -------
    list of SweepRun
        In a fixed order (the order of ``sweep.json``).

    Raises
    ------
    ValueError
        A run's config is invalid (message starts with ``base`` or the run's name, then the field), two
        runs get the same directory name, or two runs the same config.
    """
    defaults: dict = {}  # each run takes its task's experiment configuration for what the spec leaves out
    try:
        TrainConfig.from_dict(apply_dotted(defaults, spec.base))
    except (ValueError, TypeError) as exc:
        raise ValueError(f"base: {exc}") from None
    keys = list(spec.grid)
    variants: list[str | None] = list(spec.variants) or [None]
    own = {name: spec.variants.get(name, {}) if name is not None else {} for name in variants}
    combos = [({**({} if variant is None else {"variant": variant}), **dict(zip(keys, values))}, method, seed)
              for variant in variants
              for values in itertools.product(*(spec.grid[k] for k in keys))
              for method in own[variant].get("methods", spec.methods)
              for seed in own[variant].get("seeds", spec.seeds)]
    names: dict[str, dict[str, Any]] = {}
    for point, method, seed in combos:  # every name first: a clash is reported before any config error
        name = run_name(point, method, seed)
        if name in names:
            raise ValueError(f"grid: the points {names[name]} and {point} give the same run name {name!r}")
        names[name] = point
    runs: list[SweepRun] = []
    for point, method, seed in combos:
        name = run_name(point, method, seed)
        variant = {k: v for k, v in (spec.variants.get(point.get("variant"), {}) if spec.variants else {}).items()
                   if k not in _VARIANT_LISTS}
        grid_point = {k: v for k, v in point.items() if not (spec.variants and k == "variant")}
        overrides = {**spec.base, **variant, **grid_point, "method": method, "seed": seed}
        try:
            config = TrainConfig.from_dict(apply_dotted(defaults, overrides))
        except (ValueError, TypeError) as exc:
            raise ValueError(f"{name}: {exc}") from None
        runs.append(SweepRun(name=name, point=point, config=config))
    seen: dict[str, SweepRun] = {}
    for run in runs:  # equal configs from values that differ only in type (1 and 1.0 of a float field)
        other = seen.setdefault(json.dumps(_numbers_as_floats(run.config.to_dict()), sort_keys=True), run)
        if other is not run:
            raise ValueError(f"grid: the runs {other.name} and {run.name} have the same config (points {other.point} "
                             f"and {run.point}); remove one of the equal values")
    return runs


def _numbers_as_floats(value: Any) -> Any:
    """``value`` with every integer (not bool) turned into a float: two configs that train alike compare equal."""
    if isinstance(value, dict):
        return {k: _numbers_as_floats(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_numbers_as_floats(v) for v in value]
    if isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    return value


# ----------------------------------------------------------------------------------------------------
# one run (executed in this process, a pool worker or a Ray worker)
# ----------------------------------------------------------------------------------------------------
def config_hash(config: TrainConfig | dict[str, Any]) -> str:
    """The sha256 (hex) of a run's configuration: of the canonical JSON of ``TrainConfig.to_dict()`` (keys
    sorted, no whitespace), so two runs with equal configs have equal hashes wherever they ran.

    Parameters
    ----------
    config : TrainConfig or dict
        The config, or its ``to_dict()``.
    """
    data = config.to_dict() if isinstance(config, TrainConfig) else config
    text = json.dumps(data, sort_keys=True, separators=(",", ":"), allow_nan=True)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def run_point(config: dict[str, Any], path: str, resume: bool = False) -> dict[str, Any]:
    """Train one run of a sweep into ``path`` alone: exactly ``mixedrl train`` (``--batch 1``).

    Parameters
    ----------
    config : dict
        ``TrainConfig.to_dict()`` of the run.
    path : str
        The run directory.
    resume : bool
        If the run has ``results.json``, return it without training; else continue from its checkpoint.

    Returns
    -------
    dict
        The run's results (the content of ``results.json``).

    Raises
    ------
    ValueError
        ``resume`` and the run directory holds a different config.
    """
    return run_points([config], [path], resume)[0]


def run_points(configs: list[dict[str, Any]], paths: list[str], resume: bool = False,
               observer: str | None = None) -> list[dict[str, Any]]:
    """Train the runs of one batch of a sweep, each into its path; the body of a pool or Ray task.

    :func:`mixedrl.runs.make_trainer` for each run, then :func:`mixedrl.runs.train_batch` (one run:
    :func:`mixedrl.runs.train`, which is ``mixedrl train``), which sets
    ``torch.set_num_threads(config.run.num_threads)``.

    Parameters
    ----------
    configs : list of dict
        ``TrainConfig.to_dict()`` of each run (several: they must share a
        :func:`mixedrl.algorithms.batched.batch_key`).
    paths : list of str
        The run directories.
    resume : bool
        A run with ``results.json`` is returned without training; the others continue from their
        checkpoints, in one batch. When a single run of a batch is left, the batch's last finished run
        is restored from its checkpoint beside it (in memory, not rewritten) so that it keeps the
        batched arithmetic of the uninterrupted sweep.
    observer : str, optional
        The spec's ``observer`` (:func:`resolve_observer`).

    Returns
    -------
    list of dict
        Per run its results (the content of its ``results.json``).

    Raises
    ------
    ValueError
        A run directory is refused (``resume`` and another config, or foreign files; the others of the
        batch have trained), or ``configs`` and ``paths`` of different lengths.
    """
    outcomes = _train_points(configs, paths, resume, observer)
    for results, error in outcomes:
        if error is not None:
            raise ValueError(error)
    return [results for results, _ in outcomes]


def _train_points(configs: list[dict[str, Any]], paths: list[str], resume: bool,
                  observer: str | None) -> list[tuple[dict[str, Any] | None, str | None]]:
    """:func:`run_points`, per run ``(results, None)`` or ``(None, error text)``: a run whose directory is
    refused (another config, foreign files) fails alone, the others of its batch train."""
    if len(configs) != len(paths):
        raise ValueError(f"paths: {len(paths)} paths for {len(configs)} configs")
    cfgs = [TrainConfig.from_dict(c) for c in configs]
    dirs = [RunDirectory(p) for p in paths]
    outcomes: list[tuple[dict[str, Any] | None, str | None]] = [(None, None)] * len(cfgs)
    todo, finished = [], []
    for i, (cfg, run_dir) in enumerate(zip(cfgs, dirs)):
        try:
            if resume and run_dir.results_path.is_file():
                if run_dir.read_config().to_dict() != cfg.to_dict():
                    raise ValueError(f"config: differs from the saved {run_dir.config_path}; resume with the same "
                                     f"spec")
                outcomes[i] = (run_dir.read_results(), None)
                finished.append(i)
            else:
                check_run_directory(run_dir, cfg, resume)
                todo.append(i)
        except Exception as exc:  # noqa: BLE001 - this run fails, the batch's others train
            outcomes[i] = (None, _error_text(exc))
    if not todo:
        return outcomes
    factory = None if observer is None else resolve_observer(observer)
    trainers = [make_trainer(cfgs[i]) for i in todo]
    run_dirs: list[RunDirectory | None] = [dirs[i] for i in todo]
    observers = [None if factory is None else factory(cfgs[i]) for i in todo]
    if len(todo) == 1 and finished:
        # the batch's other runs finished: one of them, restored and inactive, keeps this run batched
        j = finished[0]
        companion = make_trainer(cfgs[j])
        load_trainer(companion, dirs[j].checkpoint_path)
        trainers.append(companion)
        run_dirs.append(None)
        observers.append(None)
    trained = train_batch(trainers, run_dirs, resume=resume, progress=False, observers=observers)
    for i, res in zip(todo, trained):
        outcomes[i] = (res, None)
    return outcomes


def _timed_run_points(configs: list[dict[str, Any]], paths: list[str], resume: bool,
                      observer: str | None) -> tuple[list[tuple[dict[str, Any] | None, str | None]], float]:
    """:func:`_train_points` and its wall time in seconds (start-up, training and evaluation of the batch)."""
    t0 = time.perf_counter()
    outcomes = _train_points(configs, paths, resume, observer)
    return outcomes, time.perf_counter() - t0


def plan_batches(runs: Sequence[SweepRun], batch: int = DEFAULT_BATCH, workers: int = 1,
                 ddpg: bool = False) -> list[list[int]]:
    """Group a sweep's runs into batches trained as one computation each.

    Runs with equal :func:`mixedrl.algorithms.batched.batch_key` (the kind of algorithm, Algorithm 2 or
    DDPG, the task, the network shapes and batch size; method, seed, budget and learning rates may differ)
    form a group; DDPG runs only with ``ddpg=True``, otherwise each trains alone (measured on 2 cores, five
    DDPG runs in one batch do 1.01-1.12 times the work per second of five alone, and a batch of the long
    runs on one worker would leave the other idle: docs/algorithm2.rst). A
    group of ``n`` runs is split into ``c`` batches of near-equal size, ``c`` the smallest number with at
    most ``batch`` runs each, raised up to ``workers`` while every batch keeps two runs or more (so
    that the workers share the work). A batch never holds a single run of a larger group: a run's bits
    then depend only on whether its group has one run (or ``batch = 1``: every run alone, as
    ``mixedrl train``), not on ``batch`` or ``workers`` (the batched engine gives a run the same bits in
    any batch of two or more, :mod:`mixedrl.algorithms.batched`, :mod:`mixedrl.algorithms.batched_ddpg`).

    Parameters
    ----------
    runs : sequence of SweepRun
    batch : int
        Most runs per batch (``>= 1``).
    workers : int
        Processes that will train the batches.
    ddpg : bool
        Batch the DDPG runs too (:class:`mixedrl.algorithms.batched_ddpg.BatchedDDPG`); default: each alone.

    Returns
    -------
    list of list of int
        Indices into ``runs``, each batch in the runs' order, batches in the order of their first run.
    """
    _check_count(batch, "batch")
    _check_count(workers, "workers")
    groups: dict[Any, list[int]] = {}
    alone: list[list[int]] = []
    for i, r in enumerate(runs):
        key = batch_key(r.config) if batch > 1 and (ddpg or r.config.method != "ddpg") else None
        if key is None:
            alone.append([i])
        else:
            groups.setdefault(key, []).append(i)
    batches = list(alone)
    for members in groups.values():
        n = len(members)
        count = max(-(-n // batch), min(workers, n // 2)) if n > 1 else 1
        while count > 1 and n // count < 2:
            count -= 1
        size, extra = divmod(n, count)
        start = 0
        for c in range(count):
            stop = start + size + (1 if c < extra else 0)
            batches.append(members[start:stop])
            start = stop
    return sorted(batches, key=lambda b: b[0])


# ----------------------------------------------------------------------------------------------------
# the sweep
# ----------------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=4096)
def _interval(values: tuple[float, ...]) -> tuple[float | None, float | None]:
    """:func:`mixedrl.tables.bootstrap_interval`, cached: ``sweep.json`` is rewritten after every finished run,
    and only the group of that run has new values (one interval costs tens of milliseconds)."""
    return bootstrap_interval(values)


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
        ``failed``, and ``<figure>_mean`` / ``<figure>_std`` / ``<figure>_ci_low`` / ``<figure>_ci_high``
        for every figure of :data:`RESULT_KEYS` (:func:`mixedrl.tables.mean_std`: sample std, ``ddof=1``, 0
        for one seed; :func:`mixedrl.tables.bootstrap_interval`: the seeded 95% percentile-bootstrap
        interval of the mean, ``None`` for fewer than two seeds; all ``None`` when no run reports the
        figure).
    """
    groups: dict[str, dict[str, Any]] = {}
    for rec in records:
        key = json.dumps([rec["point"], rec["config"]["method"]], sort_keys=True)
        group = groups.setdefault(key, {"point": rec["point"], "method": rec["config"]["method"], "done": [],
                                        "failed": 0})
        if rec["error"] is not None:
            group["failed"] += 1
        elif rec["results"] is not None:
            group["done"].append(rec["results"])
    rows = []
    for group in groups.values():
        row: dict[str, Any] = {"point": group["point"], "method": group["method"], "runs": len(group["done"]),
                               "failed": group["failed"]}
        for fig in RESULT_KEYS:
            values = [r[fig] for r in group["done"] if isinstance(r.get(fig), (int, float))]
            row[f"{fig}_mean"], row[f"{fig}_std"] = mean_std(values)
            row[f"{fig}_ci_low"], row[f"{fig}_ci_high"] = _interval(tuple(float(v) for v in values))
        rows.append(row)
    return rows


def _spec_doc(spec: SweepSpec) -> dict[str, Any]:
    """The spec's part of ``sweep.json`` (``variants`` only for a spec that has them)."""
    doc = {"methods": list(spec.methods), "seeds": list(spec.seeds), "base": spec.base,
           "grid": {k: list(v) for k, v in spec.grid.items()}}
    if spec.variants:
        doc["variants"] = spec.variants
    if spec.observer is not None:
        doc["observer"] = spec.observer
    return doc


#: What a sweep writes into its ``--out``; anything else there is not the sweep's.
SWEEP_FILES = ("spec.toml", "sweep.json", "sweep.csv", "sweep_summary.csv", "runs", "figures")


def _check_out(out: Path, spec: SweepSpec, runs: list[SweepRun], resume: bool) -> None:
    """Refuse an ``out`` that is a file, a symbolic link leading nowhere, holds anything but this sweep's
    files, or holds a sweep without ``resume`` or of a different spec; reads only."""
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


def _write_outputs(out: Path, spec: SweepSpec, records: list[dict[str, Any]], extra: dict[str, Any]) -> None:
    summary = summarize(records)
    doc = {**_spec_doc(spec), **extra, "runs": records, "summary": summary}
    atomic_write_text(out / "sweep.json", json.dumps(doc, indent=2, allow_nan=True) + "\n")
    atomic_write_text(out / "sweep.csv", csv_text(csv_rows(records)))
    table = [{**row["point"], **{k: v for k, v in row.items() if k != "point"}} for row in summary]
    atomic_write_text(out / "sweep_summary.csv", csv_text(table))


def make_figure(out: str | Path, summary: list[dict[str, Any]], grid: dict[str, Sequence[Any]]) -> Path | None:
    """Plot the course cost against the first grid key, one line per method (mean ± std over seeds).

    Other grid keys are held at their first value. Numeric values go on a numeric axis, others on
    categories.

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
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        logger.info("matplotlib not installed: no sweep figure")
        return None
    key = next(iter(grid))
    values = list(grid[key])
    others = {k: v[0] for k, v in grid.items() if k != key}
    numeric = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)
    xs = values if numeric else list(range(len(values)))
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    methods = list(dict.fromkeys(row["method"] for row in summary))
    for method in methods:
        pts = []
        for x, v in zip(xs, values):
            target = {**others, key: v}
            for row in summary:
                if row["method"] == method and row["point"] == target and row["cost_mean"] is not None:
                    pts.append((x, row["cost_mean"], row["cost_std"] or 0.0))
        if pts:
            arr = np.asarray(pts, dtype=float)
            ax.errorbar(arr[:, 0], arr[:, 1], yerr=arr[:, 2], marker="o", capsize=3, label=method)
    if not numeric:
        ax.set_xticks(xs, [str(v) for v in values])
    ax.set_xlabel(key + ("" if not others else f"  ({', '.join(f'{k}={v}' for k, v in others.items())})"))
    ax.set_ylabel("course cost (mean ± std over seeds)")
    ax.legend()
    fig.tight_layout()
    path = Path(out) / "figures" / f"cost_vs_{_format_value(key)}.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=120)
    plt.close(fig)
    atomic_write_bytes(path, buffer.getvalue())
    return path


def _record(sweep_run: SweepRun, results: dict[str, Any] | None, error: str | None,
            wall_seconds: float | None = None) -> dict[str, Any]:
    """One row of ``sweep.json``'s ``runs`` (the schema of the module docstring)."""
    config = sweep_run.config.to_dict()
    figures = None
    metrics: dict[str, Any] = {}
    if results is not None:
        figures = {k: results.get(k) for k in RESULT_KEYS}
        figures["run_dir"] = str(Path("runs") / sweep_run.name)
        metrics = {k: v for k, v in results.items()
                   if isinstance(v, (int, float)) and not isinstance(v, bool) and k not in _OWN_COLUMNS}
    return {"name": sweep_run.name, "point": sweep_run.point, "config": config,
            "config_hash": config_hash(config), "method": sweep_run.config.method, "seed": sweep_run.config.seed,
            "iterations": None if results is None else results.get("iterations", config["algorithm"]["iterations"]),
            "true_transitions": None if results is None else results.get("true_transitions"),
            "metrics": metrics,
            "train_seconds": None if results is None else results.get("train_seconds"),
            "wall_seconds": wall_seconds, "run_dir": str(Path("runs") / sweep_run.name),
            "results": figures, "error": error}


def csv_rows(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The rows of ``sweep.csv``: per run its name, grid values, method, seed, config hash, budget, metrics
    (one column each), times, run directory and error.

    Parameters
    ----------
    records : list of dict
        The ``runs`` of ``sweep.json``.
    """
    rows = []
    for rec in records:
        row = {"name": rec["name"], **rec["point"], "method": rec["config"]["method"],
               "seed": rec["config"]["seed"], "config_hash": rec.get("config_hash"),
               "iterations": rec.get("iterations"), "true_transitions": rec.get("true_transitions")}
        row.update({k: None for k in RESULT_KEYS})
        row.update(rec.get("metrics") or {})
        row.update({"train_seconds": rec.get("train_seconds"), "wall_seconds": rec.get("wall_seconds"),
                    "run_dir": rec.get("run_dir"), "error": rec["error"]})
        rows.append(row)
    return rows


def _error_text(exc: BaseException) -> str:
    cause = getattr(exc, "cause", None)  # ray.exceptions.RayTaskError wraps the run's own exception
    err = cause if isinstance(cause, BaseException) else exc
    return f"{type(err).__name__}: {err}"


#: A job: one batch of runs, ``(configs, paths, resume, observer)`` (the arguments of :func:`run_points`).
_Job = tuple[list[dict[str, Any]], list[str], bool, "str | None"]
#: A finished job as the executors report it: (index, per run (results, error text) or None, error text of
#: the whole batch or None, wall seconds).
_Done = tuple[int, "list[tuple[dict[str, Any] | None, str | None]] | None", "str | None", "float | None"]


def _run_here(jobs: list[_Job]) -> Iterator[_Done]:
    """Run the jobs one after the other in this process (``workers=1``)."""
    for i, job in enumerate(jobs):
        try:
            results, wall = _timed_run_points(*job)
            yield i, results, None, wall
        except Exception as exc:  # noqa: BLE001 - one failed batch must not stop the others
            yield i, None, _error_text(exc), None


def _watch_parent(parent: int) -> None:
    """End this process as soon as its parent is no longer ``parent`` (it died: this process was re-parented)."""
    while os.getppid() == parent:
        time.sleep(0.5)
    os._exit(1)


def _die_with_parent(parent: int) -> None:
    """The initializer of a pool worker: the worker ends when the sweep driver (``parent``) dies, however it
    dies (``kill -9`` included), instead of training on without anyone to record its runs.

    On Linux the kernel sends the worker ``SIGKILL`` when the driver ends (``prctl(PR_SET_PDEATHSIG)``);
    everywhere, a daemon thread also polls the parent's pid. A run killed so is resumed by ``--resume``.
    """
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL), 0, 0, 0)  # 1: PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            pass  # no prctl: the thread below does it
    if os.getppid() != parent:  # the driver died before the signal was armed
        os._exit(1)
    threading.Thread(target=_watch_parent, args=(parent,), name="watch-sweep-driver", daemon=True).start()


def _run_pool(jobs: list[_Job], workers: int) -> Iterator[_Done]:
    """Run the jobs on a local pool of ``workers`` processes (``spawn``: a fresh interpreter each, no state
    inherited from this one; each ends if this process dies, :func:`_die_with_parent`), yielding them as they
    finish."""
    context = multiprocessing.get_context("spawn")
    with concurrent.futures.ProcessPoolExecutor(max_workers=workers, mp_context=context, initializer=_die_with_parent,
                                                initargs=(os.getpid(),)) as pool:
        futures = {pool.submit(_timed_run_points, *job): i for i, job in enumerate(jobs)}
        try:
            for future in concurrent.futures.as_completed(futures):
                try:
                    results, wall = future.result()
                    yield futures[future], results, None, wall
                except Exception as exc:  # noqa: BLE001 - one failed batch must not stop the others
                    yield futures[future], None, _error_text(exc), None
        finally:
            for future in futures:
                future.cancel()


def _run_ray(jobs: list[_Job], ray: Any) -> Iterator[_Done]:
    """Run the jobs as Ray tasks (one task per batch, ``num_cpus=1`` each) on the initialised cluster,
    yielding them as they finish (``ray.wait``)."""
    task = ray.remote(num_cpus=1)(_timed_run_points)
    refs = {task.remote(*job): i for i, job in enumerate(jobs)}
    pending = list(refs)
    while pending:
        done, pending = ray.wait(pending, num_returns=1)
        try:
            results, wall = ray.get(done[0])
            yield refs[done[0]], results, None, wall
        except Exception as exc:  # noqa: BLE001 - one failed batch must not stop the others
            yield refs[done[0]], None, _error_text(exc), None


def _check_count(value: Any, name: str) -> None:
    """:func:`mixedrl.checks.check_positive_int`, ``None`` allowed (the option's default)."""
    if value is not None:
        check_positive_int(value, name)


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
        The sweep directory (on a shared file system when ``address`` names a multi-node cluster).
    address : str, optional
        Run on Ray: the address of an existing cluster (``"auto"``, ``"HOST:6379"``, ``"ray://HOST:10001"``)
        or ``"local"`` (start a local cluster of ``num_cpus`` CPUs). When Ray is already initialised in this
        process, that cluster is used. ``None`` (default): the local process pool.
    num_cpus : int, optional
        With ``address="local"``: CPUs of the local Ray cluster (default ``os.cpu_count()``). Without
        ``address``: the older name of ``workers`` (giving both with different values is an error).
        Ignored when joining a running cluster.
    resume : bool
        Skip finished runs, resume interrupted ones from their checkpoints.
    progress : bool
        tqdm progress bar over runs.
    workers : int, optional
        Processes of the local pool (default ``os.cpu_count()``; each run is single-threaded unless its
        config sets ``run.num_threads``). ``1`` runs the batches one after the other in this process. Not
        used with ``address``.
    batch : int
        Most runs trained as one computation (:func:`plan_batches`; on Ray a task is a batch). ``1``:
        every run alone, exactly as ``mixedrl train`` would.
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
        ``out`` already holds a sweep and ``resume`` is false, ``resume`` with a different spec in
        ``out/spec.toml`` or ``out/sweep.json``, ``out`` holds files that are not this sweep's (anything
        but :data:`SWEEP_FILES`, or a run directory the spec does not name), ``num_cpus`` or ``workers``
        not a positive integer, ``workers`` with ``address``, or ``workers`` and ``num_cpus`` that differ
        without ``address``, ``batch`` not a positive integer. Nothing is started or written.
    """
    out = Path(os.path.realpath(out))
    runs = expand(spec)
    _check_count(num_cpus, "num_cpus")
    _check_count(workers, "workers")
    _check_count(batch, "batch")
    if address is not None and workers is not None:
        raise ValueError("workers: the local process pool's size; with address the runs go to Ray (use num_cpus "
                         "for a local Ray cluster)")
    if address is None and workers is not None and num_cpus is not None and workers != num_cpus:
        raise ValueError(f"num_cpus: without address it is the older name of workers; got workers={workers} and "
                         f"num_cpus={num_cpus}")
    saved_spec = out / "spec.toml"
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
    # one driver per sweep directory (the only writer of sweep.json): another driver, running or resuming
    # beside this one, is refused while this one lives; the kernel releases the lock however it dies
    with hold_lock(out / LOCK_NAME, "out"):
        _check_out(out, spec, runs, resume)  # again under the lock: another driver may have written meanwhile
        started = False
        if ray is not None and not ray.is_initialized():
            if address == "local":
                ray.init(num_cpus=num_cpus or os.cpu_count() or 1, include_dashboard=False, log_to_driver=False)
            else:
                ray.init(address=address, log_to_driver=False)
            started = True
        try:
            (out / "runs").mkdir(parents=True, exist_ok=True)
            atomic_write_text(saved_spec, spec.text)
            t0 = time.perf_counter()
            parallel = (int(ray.cluster_resources().get("CPU", 1)) if ray is not None else n_workers)
            batches = plan_batches(runs, batch, max(1, parallel), ddpg=batch_ddpg)
            # the longest first (the largest budget, then the largest batch), so that no long job starts last
            batches.sort(key=lambda b: (-max(runs[i].config.algorithm.iterations for i in b), -len(b), b[0]))
            jobs: list[_Job] = [([runs[i].config.to_dict() for i in b], [str(out / "runs" / runs[i].name) for i in b],
                                 resume, spec.observer) for b in batches]
            records: list[dict[str, Any] | None] = [None] * len(runs)
            if ray is not None:
                extra: dict[str, Any] = {"engine": "ray", "ray_version": ray.__version__, "address": address}
                finished = _run_ray(jobs, ray)
            else:
                n_workers = min(n_workers, len(jobs))
                extra = {"engine": "local", "workers": n_workers, "address": None}
                finished = _run_here(jobs) if n_workers == 1 else _run_pool(jobs, n_workers)
            extra.update({"batch": batch, "batches": len(batches)})

            def current() -> list[dict[str, Any]]:
                return [rec if rec is not None else _record(r, None, None) for rec, r in zip(records, runs)]

            bar = None
            if progress:
                from tqdm.auto import tqdm

                bar = tqdm(total=len(runs), desc="sweep (runs)")
            failed = 0
            try:
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
                    _write_outputs(out, spec, current(), {**extra, "failed": failed, "finished": False,
                                                           "wall_seconds": time.perf_counter() - t0})
                    if bar is not None:
                        bar.update(len(batches[j]))
                        if failed:
                            bar.set_postfix(failed=failed)
            finally:
                if bar is not None:
                    bar.close()
            doc_extra = {**extra, "failed": failed, "finished": True, "wall_seconds": time.perf_counter() - t0}
            _write_outputs(out, spec, current(), doc_extra)
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
    """The options of ``mixedrl sweep`` (positional ``spec``, ``--out``, ``--workers``, ``--force``, ``--address``,
    ``--num-cpus``, ``--resume``, ``--no-progress``)."""
    p.add_argument("spec", type=Path, help="sweep spec (TOML: methods, seeds, [base], [grid], [variants.NAME])")
    p.add_argument("--out", type=Path, required=True, help="sweep directory (shared by every node of a cluster)")
    p.add_argument("--workers", type=int, default=None,
                   help="processes of the local pool (default: all CPUs; 1 runs in this process)")
    p.add_argument("--force", action="store_true",
                   help=f"accept a spec of more than {MAX_RUNS} runs (mixedrl.sweep.MAX_RUNS)")
    add_engine_arguments(p)


def add_engine_arguments(p: argparse.ArgumentParser) -> None:
    """The engine's options shared by ``mixedrl sweep`` and the study drivers: ``--address``, ``--num-cpus``,
    ``--batch``, ``--resume``, ``--no-progress``."""
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
    p = subparsers.add_parser("sweep", help="run a grid of training runs (config x methods x seeds) on a process pool or Ray",
                              description=__doc__.split("\n", 1)[0])
    add_arguments(p)


def format_summary(doc: dict[str, Any], out: str | Path) -> str:
    """The summary of a finished sweep as text: one line per grid point x method (runs, failures, course cost
    mean ± std over seeds), then where ``sweep.json`` and the summary CSV are.

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
