"""Iterative Bayesian estimator (IBE) of the additive model noise, eqs. (8)-(19).

The analytical model (eq. (8)) is ``x' = f(x, u) + xi``, ``xi ~ N(mu_M, K_M)`` a priori. Data triples
give residuals ``xi_j = x_{j+1} - f(x_j, u_j)`` (eq. (10), :func:`residuals`), and the IBE fuses the
designer's prior with them:

* Case 1, :class:`KnownCovarianceIBE` and :func:`map_mean_known_cov`: ``K`` known, eqs. (14)-(16).
* Case 2, :class:`UnknownCovarianceIBE` and :func:`map_mean_cov`: ``mu`` and ``K`` unknown, eqs. (17)-(18).
* Case 3, :class:`StateDependentIBE`: state-dependent mean ``mu = phi(x, u; w)``, eq. (19);
  :class:`LinearFeatureIBE`: the same for a ``phi`` linear in ``w`` (fixed features), solved in closed form.

Each Case is a module (:mod:`mixedrl.ibe.case1`, :mod:`mixedrl.ibe.case2`, :mod:`mixedrl.ibe.case3`);
:mod:`mixedrl.ibe.common` holds eq. (10) and the checks all three apply. Every name above can be
imported from this package.

Every estimator refuses bad input (and any update whose posterior would not be finite and symmetric PSD)
with a ``ValueError`` naming the argument, its state unchanged; its public state is read-only
(:class:`mixedrl.ibe.common.ReadOnlyField`). Cases 1 and 2 use the *covariance (Kalman) form* of eq. (15),

.. math::
    \\hat\\mu = \\mu_M + \\mathcal{K}_M (N\\mathcal{K}_M + \\mathcal{K})^{-1}
    \\Big(\\sum_j \\xi_j - N\\mu_M\\Big), \\qquad
    \\Psi_N^{-1} = \\mathcal{K}_M (N\\mathcal{K}_M + \\mathcal{K})^{-1} \\mathcal{K},

which inverts only ``S = N K_M + K`` (:func:`mixedrl.gaussian.solve_psd`), never the possibly singular
``K`` or ``K_M``. ``docs/ibe.rst`` ("How inverses are computed, and why", "Bad input never poisons the
estimate") gives the details.
"""

from __future__ import annotations

from mixedrl.ibe.case1 import KnownCovarianceIBE, map_mean_known_cov
from mixedrl.ibe.case2 import FIXED_POINT_MAX_ITER, FIXED_POINT_RTOL, UnknownCovarianceIBE, map_mean_cov
from mixedrl.ibe.case3 import LinearFeatureIBE, StateDependentIBE
from mixedrl.ibe.common import residuals

__all__ = ["residuals", "map_mean_known_cov", "map_mean_cov", "KnownCovarianceIBE", "UnknownCovarianceIBE",
           "StateDependentIBE", "LinearFeatureIBE", "FIXED_POINT_RTOL", "FIXED_POINT_MAX_ITER"]
