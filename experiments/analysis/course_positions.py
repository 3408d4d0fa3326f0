"""Where along the course are the course copies of the batch (docs/model_based.rst, "Where the course
rollouts really are"): the observer of ``experiments/studies/course_positions.toml``.

Every ``every`` iterations :class:`CoursePositionsObserver` records, for the course copies of the batch of
a :class:`~mixedrl.algorithms.model_data.ModelStateSampler` (``trainer.sampler.course``, their
longitudinal position ``X`` the state's entry 5):

* the quantiles 0.1, 0.5 and 0.9 of ``X`` (``positions/X_q10``, ``positions/X_median``, ``positions/X_q90``);
* the fraction of them in each part of the course (:data:`PARTS`: straight 0-20 m, first lane change
  20-52 m, second lane change 52-85 m, last straight 85-120 m), ``positions/share_A_B`` for ``[A, B)``.

The observer only reads the sampler's states (it draws nothing and changes nothing). The table is
``experiments/analysis/model_based_study.py positions``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mixedrl.config import TrainConfig
from mixedrl.runs import PeriodicObserver

__all__ = ["CoursePositionsObserver", "course_positions_observer", "position_metrics", "share_key", "PARTS",
           "QUANTILES", "EVERY"]

#: The parts of the course, ``[a, b)`` in metres of ``X``.
PARTS = ((0.0, 20.0), (20.0, 52.0), (52.0, 85.0), (85.0, 120.0))
#: The quantiles of ``X`` recorded, with the suffix of their metric.
QUANTILES = ((0.1, "q10"), (0.5, "median"), (0.9, "q90"))
#: Iterations between records in ``experiments/studies/course_positions.toml``.
EVERY = 100
#: The entry of the state that is the longitudinal position ``X``.
X_INDEX = 5


def share_key(a: float, b: float) -> str:
    """The metric name of the share of the course copies with ``a <= X < b`` (``positions/share_20_52``)."""
    return f"positions/share_{a:.0f}_{b:.0f}"


def position_metrics(X: np.ndarray) -> dict[str, float]:
    """The metrics of the module docstring for the positions ``X`` (1-D) of the course copies.

    Parameters
    ----------
    X : numpy.ndarray
        The longitudinal positions of the course copies.

    Returns
    -------
    dict
        ``positions/X_q10``, ``positions/X_median``, ``positions/X_q90`` (NaN when ``X`` is empty) and
        ``positions/share_A_B`` for every part of :data:`PARTS` (0 when ``X`` is empty).
    """
    X = np.asarray(X).reshape(-1)  # its own dtype: the quantiles of the former script, bit for bit
    q = np.quantile(X, [p for p, _ in QUANTILES]) if X.size else np.full(len(QUANTILES), np.nan)
    out = {f"positions/X_{name}": float(v) for (_, name), v in zip(QUANTILES, q)}
    for a, b in PARTS:
        out[share_key(a, b)] = float(((X >= a) & (X < b)).mean()) if X.size else 0.0
    return out


class CoursePositionsObserver(PeriodicObserver):
    """The positions of the module docstring as ``positions/...`` metrics of every ``every``-th row
    (default :data:`EVERY`; a :class:`mixedrl.runs.PeriodicObserver`)."""

    def __init__(self, every: int = EVERY) -> None:
        super().__init__(every)

    def record(self, trainer: Any) -> dict[str, float]:
        """The positions of the course copies after iteration ``trainer.k``.

        Raises
        ------
        ValueError
            The trainer's sampler has no course copies (``sampler.states`` and ``sampler.course``).
        """
        sampler = getattr(trainer, "sampler", None)
        if sampler is None or not hasattr(sampler, "course") or not hasattr(sampler, "states"):
            raise ValueError(f"CoursePositionsObserver: the trainer's sampler ({type(sampler).__name__}) has no "
                             f"course copies (sampler.name = \"dlc_course\")")
        X = sampler.states[sampler.course, X_INDEX].detach().cpu().numpy()
        return position_metrics(X)


def course_positions_observer(config: TrainConfig) -> CoursePositionsObserver:
    """The ``observer`` of ``experiments/studies/course_positions.toml``: a record every :data:`EVERY` iterations."""
    return CoursePositionsObserver(EVERY)
