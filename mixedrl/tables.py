"""Statistics and CSV of result tables, shared by the sweep, the studies' scripts and the validation."""

from __future__ import annotations

import csv
import io
from typing import Any, Iterable, Sequence

import numpy as np

__all__ = ["mean_std", "bootstrap_interval", "paired_interval", "csv_text"]


def mean_std(values: Sequence[float], one: float | None = 0.0) -> tuple[float | None, float | None]:
    """Mean and sample standard deviation (``ddof=1``) of ``values``.

    Parameters
    ----------
    values : sequence of float, shape (n,)
        One figure per seed.
    one : float or None
        The standard deviation reported for a single value.

    Returns
    -------
    (float or None, float or None)
        ``(None, None)`` for no values.
    """
    arr = np.asarray(list(values), dtype=float)
    if arr.size == 0:
        return None, None
    return float(arr.mean()), (float(arr.std(ddof=1)) if arr.size > 1 else one)


def bootstrap_interval(values: Sequence[float], confidence: float = 0.95, n_resamples: int = 9999,
                       seed: int = 0) -> tuple[float | None, float | None]:
    """Percentile-bootstrap confidence interval of the mean of ``values`` (:func:`scipy.stats.bootstrap`).

    Parameters
    ----------
    values : sequence of float, shape (n,)
        One figure per seed.
    confidence : float
        Confidence level in (0, 1).
    n_resamples : int
        Bootstrap resamples.
    seed : int
        Seed of the resampling (the interval is deterministic).

    Returns
    -------
    (float or None, float or None)
        ``(low, high)``; ``(None, None)`` for fewer than two values (no interval), and ``(m, m)`` when every
        value equals ``m``.

    Raises
    ------
    ValueError
        ``confidence`` not in (0, 1).
    """
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence: expected a number in (0, 1), got {confidence!r}")
    arr = np.asarray(list(values), dtype=float)
    if arr.size < 2:
        return None, None
    if np.all(arr == arr[0]):
        return float(arr[0]), float(arr[0])
    from scipy.stats import bootstrap

    res = bootstrap((arr,), np.mean, confidence_level=confidence, n_resamples=n_resamples, method="percentile",
                    random_state=np.random.default_rng(seed))
    return float(res.confidence_interval.low), float(res.confidence_interval.high)


def paired_interval(a: Sequence[float], b: Sequence[float], statistic: str = "difference",
                    confidence: float = 0.95, n_resamples: int = 9999,
                    seed: int = 0) -> tuple[float, float | None, float | None]:
    """A paired comparison of ``a`` and ``b`` (the same seeds in the same order) and its percentile-bootstrap
    interval (:func:`scipy.stats.bootstrap` with ``paired=True``).

    Parameters
    ----------
    a, b : sequence of float, shape (n,)
    statistic : {"difference", "ratio"}
        ``mean(a - b)``, or ``mean(a) / mean(b)``.
    confidence, n_resamples, seed
        As for :func:`bootstrap_interval`.

    Returns
    -------
    (float, float or None, float or None)
        The statistic and ``(low, high)``; no interval (``None``) for fewer than two seeds.

    Raises
    ------
    ValueError
        ``a`` and ``b`` of different lengths or empty, a non-finite value, an unknown ``statistic``, or
        ``confidence`` not in (0, 1).
    """
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence: expected a number in (0, 1), got {confidence!r}")
    x, y = np.asarray(list(a), dtype=float), np.asarray(list(b), dtype=float)
    if x.ndim != 1 or x.shape != y.shape or x.size == 0:
        raise ValueError(f"b: expected as many values as a ({x.size}), got {y.size}")
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise ValueError("a, b: non-finite value")
    stat = {"difference": lambda u, v, axis=-1: np.mean(u - v, axis=axis),
            "ratio": lambda u, v, axis=-1: np.mean(u, axis=axis) / np.mean(v, axis=axis)}.get(statistic)
    if stat is None:
        raise ValueError(f"statistic: expected 'difference' or 'ratio', got {statistic!r}")
    value = float(stat(x, y))
    if x.size < 2:
        return value, None, None
    if np.all(x - y == (x - y)[0]) and statistic == "difference":
        return value, value, value
    from scipy.stats import bootstrap

    res = bootstrap((x, y), stat, paired=True, vectorized=True, confidence_level=confidence,
                    n_resamples=n_resamples, method="percentile", random_state=np.random.default_rng(seed))
    return value, float(res.confidence_interval.low), float(res.confidence_interval.high)


def csv_text(rows: Iterable[dict[str, Any]], columns: Sequence[str] = ()) -> str:
    """CSV of dict rows, ``\\n``-terminated.

    Parameters
    ----------
    rows : iterable of dict
        One dict per row.
    columns : sequence of str
        Columns that come first (present even when no row has them); then the rows' other keys, in order
        of appearance.

    Returns
    -------
    str
        Header and rows; ``None`` is an empty cell, a float its ``repr`` (round-trips exactly).
    """
    rows = list(rows)
    keys = list(dict.fromkeys([*columns, *(key for row in rows for key in row)]))
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(keys)
    writer.writerows([row.get(key) for key in keys] for row in rows)
    return out.getvalue()
