"""Empirical checks of the paper's theorems (1-4) on any model, value and policy.

* :func:`lyapunov_decrease` -- Theorem 1 / 3, eqs. (28) and (41);
* :func:`value_decrease` -- Theorem 2 / 3, eqs. (29) and (42);
* :func:`mvc` -- Theorem 3, the maximum variation condition eq. (38) with ``e_k`` of eq. (39);
* :func:`ibe_shift` -- Theorem 4, the KL divergence of eq. (45);
* :func:`gamma_condition` -- Theorem 1's condition on gamma, eq. (27) (:mod:`theory.premises`);
* :func:`prior_full_rank` -- Lemma 2's full-rank premise on the prior (:mod:`theory.premises`).

``theory`` imports only :mod:`mixedrl`; :mod:`mixedrl` never imports ``theory``. ``python -m validation.theory_lq``
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
from theory.premises import PriorRankReport, gamma_condition, prior_full_rank

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
    "gamma_condition",
    "prior_full_rank",
    "PriorRankReport",
]
