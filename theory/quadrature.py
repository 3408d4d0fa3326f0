"""Gaussian expectations ``E g(c + xi)``, ``xi ~ N(mu, K)``, by a stated quadrature rule (re-export).

The rules, the support cut-off and :func:`gaussian_expectation` live in :mod:`mixedrl.expectation`, the
one expectation module that Algorithm 2 uses too; this module keeps the old import path
(``theory.quadrature.SigmaPoints`` etc.). See ``docs/expectation.rst``.
"""

from mixedrl.expectation import GaussHermite, SigmaPoints, gaussian_expectation  # noqa: F401

__all__: list[str] = []  # re-exports only; documented in mixedrl.expectation
