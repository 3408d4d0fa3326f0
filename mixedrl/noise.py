"""Noise sources for the mixed model, and the mixed model itself (eq. 20).

Algorithm 1 uses a model ``x' = f(x, u) + xi_hat`` whose only uncertain part is the noise
``xi_hat ~ N(mean, cov)``. Three sources of that noise give three methods with one algorithm:

* **mixed RL**: the IBE posterior (:mod:`mixedrl.ibe`, eqs. 13-18), updated from data;
* **model-driven RL**: the designer's prior ``N(mu_M, K_M)`` (eqs. 8 and 55), fixed;
* **oracle**: the true noise ``N(mu, K)`` of eq. (1), fixed.

:class:`GaussianNoise` is the fixed source. It has the same face as the IBE objects (``.mean``,
``.cov``, ``.sample(n, generator)``, ``state_dict()`` / ``load_state_dict()``) but no ``update``.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
import torch

from mixedrl._checks import as_batch, as_vector, check_covariance, check_unknown_keys
from mixedrl.gaussian import sample_gaussian

__all__ = ["GaussianNoise", "MixedModel"]


class GaussianNoise:
    """Implements the fixed noise of eq. (55) (prior model) and of eq. (1) (oracle): ``xi ~ N(mean, cov)``.

    .. math:: \\xi \\sim N(\\mu, \\mathcal{K})

    Parameters
    ----------
    mean : array_like, shape (n,)
    cov : array_like, shape (n, n)
        Symmetric PSD (may be singular).

    Raises
    ------
    ValueError
        ``mean`` or ``cov`` of the wrong shape, not finite, or ``cov`` not symmetric PSD.

    Notes
    -----
    For model-driven RL (eq. 55) the paper uses the prior ``N(mu_M, K_M)`` as the noise, although
    ``K_M`` is the prior covariance *of the mean* (EQUATIONS.md point 4); this class does not
    distinguish: it is a Gaussian with the given moments.
    """

    def __init__(self, mean: Any, cov: Any) -> None:
        self._mean = as_vector(mean, "mean")
        self._cov = check_covariance(cov, "cov", self._mean.shape[0])

    @property
    def dim(self) -> int:
        """Noise dimension ``n``."""
        return self._mean.shape[0]

    @property
    def mean(self) -> np.ndarray:
        """Mean, shape (n,) (a copy)."""
        return self._mean.copy()

    @property
    def cov(self) -> np.ndarray:
        """Covariance, shape (n, n) (a copy)."""
        return self._cov.copy()

    def sample(self, n: int, generator: np.random.Generator | torch.Generator) -> np.ndarray | torch.Tensor:
        """Draw ``n`` samples, shape (n, dim), from the given generator (see :func:`mixedrl.gaussian.sample_gaussian`)."""
        return sample_gaussian(self._mean, self._cov, n, generator)

    def state_dict(self) -> dict[str, Any]:
        """Return ``{"mean": list, "cov": list of lists}`` (JSON-serialisable)."""
        return {"mean": self._mean.tolist(), "cov": self._cov.tolist()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore from :meth:`state_dict`; on bad input raise ``ValueError`` and leave the state unchanged."""
        if not isinstance(state, dict):
            raise ValueError(f"state: expected a dict, got {type(state).__name__}")
        check_unknown_keys(state, {"mean", "cov"}, "state")
        if set(state) != {"mean", "cov"}:
            raise ValueError(f"state: missing key(s) {sorted({'mean', 'cov'} - set(state))}")
        mean = as_vector(state["mean"], "state['mean']", self.dim)
        cov = check_covariance(state["cov"], "state['cov']", self.dim)
        self._mean, self._cov = mean, cov

    def __repr__(self) -> str:
        return f"GaussianNoise(mean={self._mean.tolist()}, cov={self._cov.tolist()})"


class MixedModel:
    """Implements eq. (20): the mixed model ``x' = f(x, u) + xi_hat``, ``xi_hat ~ N(noise.mean, noise.cov)``.

    .. math:: x' = f(x, u) + \\hat\\xi_k, \\qquad \\hat\\xi_k \\sim N(\\hat\\mu_k, \\hat K_k)

    Parameters
    ----------
    f : callable
        Deterministic dynamics ``f(x, u)``: x (N, n), u (N, m) -> (N, n); the same ``f`` as the true
        system (eq. 1) and the prior model (eq. 8).
    noise : object
        Any noise source with ``.mean`` (n,), ``.cov`` (n, n) and ``.sample(N, generator)``: an IBE
        object (mixed RL), or a :class:`GaussianNoise` (prior or oracle). The model reads the noise's
        *current* moments at every call, so an IBE update changes the model's predictions at once.

    Raises
    ------
    ValueError
        ``f`` is not callable.
    """

    def __init__(self, f: Callable[[np.ndarray, np.ndarray], np.ndarray], noise: Any) -> None:
        if not callable(f):
            raise ValueError("f: must be callable f(x, u)")
        self.f = f
        self.noise = noise

    def mean_next(self, x: Any, u: Any) -> np.ndarray:
        """Return ``E x' = f(x, u) + mean``, shape (N, n)."""
        return np.asarray(self.f(x, u)) + self.noise.mean

    def sample_next(self, x: Any, u: Any, generator: np.random.Generator) -> np.ndarray:
        """Return one sample ``x' = f(x, u) + xi_hat`` per row, shape (N, n)."""
        fx = np.asarray(self.f(x, u))
        fx = as_batch(fx, "f(x, u)", fx.shape[-1])
        return fx + np.asarray(self.noise.sample(fx.shape[0], generator))
