"""Sweep specifications (docs/sweeps.rst, "Writing a spec"): their parsing, checks and expansion into runs
(:mod:`mixedrl.sweep` executes them and re-exports every public name of this module)."""

from __future__ import annotations

import dataclasses
import datetime
import hashlib
import importlib
import itertools
import json
import math
import re
import tomllib
from pathlib import Path
from typing import Any

from mixedrl.config import TrainConfig, apply_overrides, flatten_table

__all__ = ["SPEC_KEYS", "SweepSpec", "SweepRun", "apply_dotted", "flatten_table", "parse_spec", "load_spec",
           "resolve_observer", "expand", "run_name", "config_hash", "MAX_RUNS", "SEED_MAX"]

#: Top-level keys a spec may have (``methods`` and ``seeds`` are required).
SPEC_KEYS = ("methods", "seeds", "base", "grid", "variants", "observer")
#: Fields a spec sets through ``methods`` and ``seeds``, never through ``[base]`` or ``[grid]``.
_RESERVED = {"method": "methods", "seed": "seeds"}
#: Keys of a ``[variants.NAME]`` table that replace the spec's lists for that variant (not config fields).
_VARIANT_LISTS = ("methods", "seeds")
#: Longest run name before it is shortened with a hash.
_MAX_NAME = 160
#: Most runs a spec may expand to without ``force`` (``mixedrl sweep --force``).
MAX_RUNS = 10_000
#: The largest seed the generators accept (``torch.Generator.manual_seed``: 64 bits).
SEED_MAX = 2**64 - 1


#: Dotted-key overrides of a config dict (:func:`mixedrl.config.apply_overrides`).
apply_dotted = apply_overrides


@dataclasses.dataclass(frozen=True)
class SweepSpec:
    """A parsed, checked sweep spec.

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
        Variant name -> its dotted-key overrides (over ``base``) and optionally its own ``methods`` /
        ``seeds``; empty without ``[variants.NAME]`` tables.
    observer : str or None
        ``"module:function"``: ``function(config)`` returns a run's :class:`mixedrl.runs.IterationObserver`
        (or ``None``).
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


def _check_list(value: Any, key: str) -> list[Any]:
    if not isinstance(value, list):
        raise ValueError(f"{key}: expected a list of values, got {type(value).__name__} {value!r}")
    if not value:
        raise ValueError(f"{key}: empty list (a sweep over nothing)")
    seen: set[str] = set()
    for v in value:  # 1 and 1.0 differ here; equal configs are found by expand
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
        The message starts with the offending key (``spec``, ``methods``, ``grid.KEY``,
        ``variants.NAME.KEY``, a run's name, ...): invalid TOML or an unknown top-level key; a missing,
        empty, non-list or duplicated list; ``method`` / ``seed`` in a table; a field in two places; a
        TOML date or time; a seed beyond ``2**64 - 1``; more than :data:`MAX_RUNS` runs without
        ``force``; a run whose config is invalid; two runs with equal configs.
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
    points = math.prod(map(len, grid.values()))
    count = sum(points * len(v.get("methods", methods)) * len(v.get("seeds", seeds))
                for v in list(variants.values()) or [{}])
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
    """Check the ``[variants.NAME]`` tables (overrides over ``[base]``, no ``method`` / ``seed`` or grid key;
    optional own ``methods`` / ``seeds`` lists)."""
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


def format_value(value: Any) -> str:
    if isinstance(value, str):
        text = value
    elif isinstance(value, (list, tuple)):
        text = "x".join(format_value(v) for v in value)
    elif isinstance(value, dict):
        text = "_".join(f"{k}-{format_value(v)}" for k, v in value.items())
    else:
        text = json.dumps(value)
    return re.sub(r"[^A-Za-z0-9.+\-]", "_", text)


def run_name(point: dict[str, Any], method: str, seed: int) -> str:
    """The directory name of one run: ``key=value`` of each grid value, then ``<method>_seed<S>``, joined by
    ``__`` (e.g. ``critic_lr=0.001__batch_size=256__mixed_seed0``).

    Other characters than letters, digits, ``.``, ``+`` and ``-`` in a value become ``_``; a name longer
    than 160 characters is cut and ends with a hash of the full name (unique and deterministic).
    """
    name = "__".join([f"{key}={format_value(value)}" for key, value in point.items()] + [f"{method}_seed{seed}"])
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
        A run's config is invalid (message starts with ``base`` or the run's name), or two runs get the
        same directory name or the same config.
    """
    try:
        TrainConfig.from_dict(apply_dotted({}, spec.base))  # each run takes its task's defaults for the rest
    except (ValueError, TypeError) as exc:
        raise ValueError(f"base: {exc}") from None
    keys = list(spec.grid)
    combos = [({} if variant is None else {"variant": variant}, own, dict(zip(keys, values)), method, seed)
              for variant, own in list(spec.variants.items()) or [(None, {})]
              for values in itertools.product(*(spec.grid[k] for k in keys))
              for method in own.get("methods", spec.methods)
              for seed in own.get("seeds", spec.seeds)]
    names: dict[str, dict[str, Any]] = {}
    for label, _, grid_point, method, seed in combos:  # every name first: a clash is reported before a config error
        point = {**label, **grid_point}
        name = run_name(point, method, seed)
        if name in names:
            raise ValueError(f"grid: the points {names[name]} and {point} give the same run name {name!r}")
        names[name] = point
    runs: list[SweepRun] = []
    for name, (_, own, grid_point, method, seed) in zip(names, combos):
        overrides = {**spec.base, **{k: v for k, v in own.items() if k not in _VARIANT_LISTS}, **grid_point,
                     "method": method, "seed": seed}
        try:
            config = TrainConfig.from_dict(apply_dotted({}, overrides))
        except (ValueError, TypeError) as exc:
            raise ValueError(f"{name}: {exc}") from None
        runs.append(SweepRun(name=name, point=names[name], config=config))
    seen: dict[str, SweepRun] = {}
    for run in runs:  # equal configs from values that differ only in type (1 and 1.0 of a float field)
        as_floats = json.loads(json.dumps(run.config.to_dict()), parse_int=float)
        other = seen.setdefault(json.dumps(as_floats, sort_keys=True), run)
        if other is not run:
            raise ValueError(f"grid: the runs {other.name} and {run.name} have the same config (points {other.point} "
                             f"and {run.point}); remove one of the equal values")
    return runs


def config_hash(config: TrainConfig | dict[str, Any]) -> str:
    """The sha256 (hex) of the canonical JSON (keys sorted, no whitespace) of ``TrainConfig.to_dict()``.

    Parameters
    ----------
    config : TrainConfig or dict
        The config, or its ``to_dict()``.
    """
    data = config.to_dict() if isinstance(config, TrainConfig) else config
    text = json.dumps(data, sort_keys=True, separators=(",", ":"), allow_nan=True)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()
