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

Bad input
---------
Every estimator refuses, with a ``ValueError`` naming the argument and its state unchanged: residuals
(and states, actions, covariances) that are not real numbers (complex, bool, strings, objects) or not
finite; zero-dimensional noise at construction; and any update (or ``load_state_dict`` state) whose
posterior would not be finite and symmetric PSD, overflow included. The candidate posterior is
computed with floating-point warnings silenced, checked, and only then committed.

The public state (``mean``, ``cov``, ``prior_cov``, ``count``, the sufficient statistics ...) is
read-only: assigning or deleting an attribute raises ``AttributeError`` and the arrays are read-only
views, so the state changes only through ``update`` and ``load_state_dict``, which validate it
(:class:`mixedrl.ibe.common.ReadOnlyField`).

How inverses are computed
-------------------------
The vehicle task has a rank-1 true noise covariance and a prior ``K_M`` with entries ``1e-20``
(EQUATIONS.md point 5), so ``K^{-1}`` may not exist and ``K_M^{-1}`` has entries ``1e20``. Cases 1 and 2
therefore use the *covariance (Kalman) form* of eq. (15),

.. math::
    \\hat\\mu = \\mu_M + \\mathcal{K}_M (N\\mathcal{K}_M + \\mathcal{K})^{-1}
    \\Big(\\sum_j \\xi_j - N\\mu_M\\Big), \\qquad
    \\Psi_N^{-1} = \\mathcal{K}_M (N\\mathcal{K}_M + \\mathcal{K})^{-1} \\mathcal{K},

which equals eq. (15) whenever both are defined and inverts only ``S = N K_M + K``. ``S`` is
Jacobi-equilibrated and Cholesky-factored; if it is numerically singular (squared pivot of the scaled
matrix ``< 1e-13``) the eigenvalue pseudo-inverse is used (:func:`mixedrl.gaussian.solve_psd`), which
keeps the prior exactly in directions where both ``K_M`` and ``K`` vanish. Only the literal eq. (18)
(``recursion="paper"``) needs ``K_hat^{-1}`` and ``K_M^{-1}``; it uses pseudo-inverses
(:func:`mixedrl.gaussian.pinv_psd`, on the support of :func:`mixedrl.expectation.support`).
"""

from __future__ import annotations

from mixedrl.ibe.case1 import KnownCovarianceIBE, map_mean_known_cov
from mixedrl.ibe.case2 import FIXED_POINT_MAX_ITER, FIXED_POINT_RTOL, UnknownCovarianceIBE, map_mean_cov
from mixedrl.ibe.case3 import LinearFeatureIBE, StateDependentIBE
from mixedrl.ibe.common import residuals

__all__ = ["residuals", "map_mean_known_cov", "map_mean_cov", "KnownCovarianceIBE", "UnknownCovarianceIBE",
           "StateDependentIBE", "LinearFeatureIBE", "FIXED_POINT_RTOL", "FIXED_POINT_MAX_ITER"]
