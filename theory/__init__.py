"""Empirical checks of the paper's theorems (1-4) on any model, value and policy.

* :func:`lyapunov_decrease` -- Theorem 1 / 3, eqs. (28) and (41);
* :func:`value_decrease` -- Theorem 2 / 3, eqs. (29) and (42);
* :func:`mvc` -- Theorem 3, the maximum variation condition eq. (38) with ``e_k`` of eq. (39);
* :func:`ibe_shift` -- Theorem 4, the KL divergence of eq. (45).

``theory`` imports :mod:`mixedrl`; :mod:`mixedrl` never imports ``theory``. ``python -m theory lq``
prints the checks per iteration on the shipped LQ example (:mod:`validation.lq`).
"""

from theory.checks import (
    CheckReport,
    IBEShiftReport,
    expected_cost_to_go,
    ibe_shift,
    lyapunov_decrease,
    mvc,
    value_decrease,
)
from mixedrl.expectation import GaussHermite, SigmaPoints, gaussian_expectation

__all__ = [
    "lyapunov_decrease",
    "value_decrease",
    "mvc",
    "ibe_shift",
    "CheckReport",
    "IBEShiftReport",
    "expected_cost_to_go",
    "SigmaPoints",
    "GaussHermite",
    "gaussian_expectation",
]
