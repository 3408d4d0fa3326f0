"""Noise sources of the mixed model ``x' = f(x, u) + xi_hat`` (eq. 20), for Algorithms 1 and 2.

The model's only uncertain part is the noise ``xi_hat ~ N(mean, cov)``. Three sources of that noise
give three methods with one algorithm (:func:`make_noise_source`, used by Algorithm 1's LQ driver
:mod:`validation.lq` and by Algorithm 2, :class:`mixedrl.algorithms.agpi.AGPI`):

* **mixed RL**: the IBE posterior (:mod:`mixedrl.ibe`, eqs. 13-18), updated from data;
* **model-driven RL**: the designer's prior ``N(mu_M, K_M)`` (eqs. 8 and 55), fixed;
* **oracle**: the true noise ``N(mu, K)`` of eq. (1), fixed.

The algorithms depend only on the protocols :class:`NoiseSource` (moments ``mean``, ``cov``) and
:class:`StateDependentNoiseSource` (Case 3 of the IBE, eq. 19: a mean ``mean_at(x, u)``). Whether a
source learns is an attribute, ``learns``: the algorithms call ``update`` only when it is true, and a
fixed source (:class:`GaussianNoise`) has no ``update`` at all, so a call by mistake fails loudly
instead of silently doing nothing.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np
import torch

from mixedrl.checks import as_vector, check_covariance, check_unknown_keys
from mixedrl.gaussian import sample_gaussian
from mixedrl.ibe import KnownCovarianceIBE, UnknownCovarianceIBE

__all__ = ["NoiseSource", "StateDependentNoiseSource", "NoiseMoments", "GaussianNoise", "make_noise_source"]


class NoiseSource(Protocol):
    """What the algorithms need from the noise ``xi_hat_k ~ N(mean, cov)`` of the mixed model (eq. 20).

    Attributes
    ----------
    learns : bool
        ``True`` for an IBE (the algorithms feed it residuals with ``update``), ``False`` for a fixed
        source (it then need not have ``update``).
    state_dependent : bool
        ``False`` here; see :class:`StateDependentNoiseSource`.
    """

    learns: bool
    state_dependent: bool

    @property
    def mean(self) -> np.ndarray:
        """``mu_hat_k``, shape (n,)."""
        ...

    @property
    def cov(self) -> np.ndarray:
        """``K_hat_k``, shape (n, n)."""
        ...

    def update(self, xi: Any) -> Any:
        """Absorb residuals ``xi^D`` (N, n) of eq. (10): ``xi_hat_k -> xi_hat_{k+1}`` (eq. 13)."""
        ...

    def state_dict(self) -> dict[str, Any]:
        """The full state (for checkpoints)."""
        ...

    def load_state_dict(self, state: dict[str, Any]) -> Any:
        """Restore :meth:`state_dict`."""
        ...


class StateDependentNoiseSource(Protocol):
    """Case 3 of the IBE (eq. 19, :class:`mixedrl.ibe.StateDependentIBE`): ``xi_hat ~ N(phi(x, u), K)``.

    Attributes
    ----------
    learns : bool
        ``True``.
    state_dependent : bool
        ``True``: Algorithm 2 plans with per-state nodes ``mean_at(x, u) +- sqrt(r lambda_i) v_i``.
    """

    learns: bool
    state_dependent: bool

    @property
    def cov(self) -> np.ndarray:
        """``K``, shape (n, n)."""
        ...

    def mean_at(self, x: Any, u: Any) -> Any:
        """``phi(x, u; w_hat)``, shape (B, n) for x (B, n_x), u (B, n_u)."""
        ...

    def update(self, x: Any, u: Any, xi: Any) -> Any:
        """Absorb transitions ``(x, u)`` with residuals ``xi`` (eq. 19)."""
        ...

    def state_dict(self) -> dict[str, Any]:
        """The full state (for checkpoints)."""
        ...

    def load_state_dict(self, state: dict[str, Any]) -> Any:
        """Restore :meth:`state_dict`."""
        ...


class NoiseMoments(Protocol):
    """Where :func:`make_noise_source` reads the prior and the truth: a task or an LQ problem."""

    prior_mean: np.ndarray
    prior_cov: np.ndarray
    true_mean: np.ndarray
    true_cov: np.ndarray


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
    distinguish: it is a Gaussian with the given moments. A fixed source: ``learns = False`` and no
    ``update`` (see the module docstring).
    """

    learns = False
    state_dependent = False

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


def make_noise_source(method: str, task: NoiseMoments, recursion: str = "exact", covariance: str = "unknown"
                      ) -> NoiseSource:
    """The noise distribution the algorithms plan with, by method (the mixed model of eq. 20).

    .. math:: \\hat\\xi_k \\sim N(\\hat\\mu_k, \\hat K_k):\\quad \\text{IBE posterior (mixed)},\\
        N(\\mu_M, K_M)\\ \\text{(model, eq. 55)},\\ N(\\mu, K)\\ \\text{(oracle)}

    Parameters
    ----------
    method : {"mixed", "model", "oracle"}
        ``"mixed"``: an IBE started at the prior ``(mu_M, K_M)`` (Algorithms 1 and 2's initialisation);
        ``"model"``: the prior ``N(mu_M, K_M)`` held fixed (eq. 55); ``"oracle"``: the true ``N(mu, K)``.
    task : object
        Supplies ``prior_mean`` (n,), ``prior_cov`` (n, n), ``true_mean`` (n,), ``true_cov`` (n, n)
        (a :class:`mixedrl.tasks.Task`, a :class:`validation.lq.LQProblem`).
    recursion : {"exact", "paper"}
        Recursion of the Case 2 IBE (mixed only; ``covariance="unknown"``).
    covariance : {"unknown", "known"}
        ``"unknown"``: Case 2, :class:`mixedrl.ibe.UnknownCovarianceIBE` (mean and covariance unknown,
        Algorithm 2's default); ``"known"``: Case 1, :class:`mixedrl.ibe.KnownCovarianceIBE` with the
        true ``K`` (mixed only).

    Returns
    -------
    NoiseSource
        An IBE (``learns = True``) or a :class:`GaussianNoise` (``learns = False``).

    Raises
    ------
    ValueError
        ``method``, ``recursion`` or ``covariance`` unknown, or ``recursion="paper"`` with a known
        covariance.
    """
    if covariance not in ("unknown", "known"):
        raise ValueError(f"covariance: expected 'unknown' or 'known', got {covariance!r}")
    if recursion not in ("exact", "paper"):
        raise ValueError(f"recursion: expected 'exact' or 'paper', got {recursion!r}")
    if method == "mixed":
        if covariance == "known":
            if recursion != "exact":
                raise ValueError("recursion: 'paper' is eq. (18), a Case 2 recursion; use covariance='unknown'")
            return KnownCovarianceIBE(task.prior_mean, task.prior_cov, task.true_cov)
        return UnknownCovarianceIBE(task.prior_mean, task.prior_cov, recursion=recursion)
    if method == "model":
        return GaussianNoise(task.prior_mean, task.prior_cov)
    if method == "oracle":
        return GaussianNoise(task.true_mean, task.true_cov)
    raise ValueError(f"method: expected 'mixed', 'model' or 'oracle', got {method!r}")
