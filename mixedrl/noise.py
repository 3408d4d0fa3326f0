"""Noise sources of the mixed model ``x' = f(x, u) + xi_hat`` (eq. 20), for Algorithms 1 and 2.

The model's only uncertain part is the noise ``xi_hat ~ N(mean, cov)``. Three sources of that noise
give three methods with one algorithm (:func:`make_noise_source`, used by Algorithm 1's LQ driver
:mod:`validation.lq` and by Algorithm 2, :class:`mixedrl.algorithms.agpi.AGPI`):

* **mixed RL**: the IBE posterior (:mod:`mixedrl.ibe`, eqs. 13-19), updated from data: Case 2 (mean and
  covariance unknown, the default), Case 1 (covariance known) or Case 3 (a state-dependent mean,
  :class:`mixedrl.ibe.LinearFeatureIBE` on the task's ``mean_features``);
* **model-driven RL**: the designer's prior ``N(mu_M, K_M)`` (eqs. 8 and 55), fixed;
* **oracle**: the true noise ``N(mu, K)`` of eq. (1), fixed; when the task's true mean depends on the
  state (a road grade: ``task.true_mean_varies``), the fixed state-dependent
  :class:`StateDependentGaussianNoise` ``N(mu(x), K)``.

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
from mixedrl.ibe import KnownCovarianceIBE, LinearFeatureIBE, UnknownCovarianceIBE

__all__ = ["NoiseSource", "StateDependentNoiseSource", "NoiseMoments", "GaussianNoise", "StateDependentGaussianNoise",
           "make_noise_source"]


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
    """Case 3 of the IBE (eq. 19, :class:`mixedrl.ibe.StateDependentIBE`, :class:`mixedrl.ibe.LinearFeatureIBE`):
    ``xi_hat ~ N(phi(x, u), K)``; or a fixed state-dependent noise (:class:`StateDependentGaussianNoise`).

    Attributes
    ----------
    learns : bool
        ``True`` for an IBE (the algorithms call ``update``), ``False`` for a fixed source (no ``update``).
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
        """Draw ``n`` samples, shape (n, dim), from ``generator`` (:func:`mixedrl.gaussian.sample_gaussian`)."""
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


class StateDependentGaussianNoise:
    """Implements the fixed state-dependent noise ``xi ~ N(m(x, u), K)`` (eq. 1 with a state-dependent mean).

    .. math:: \\xi \\sim N\\big(m(x, u), \\mathcal{K}\\big)

    The oracle of a task whose true noise mean varies with the state (the double lane change on a road
    grade, :meth:`mixedrl.tasks.Task.true_mean_at`): the truth that Case 3 of the IBE (eq. 19) estimates.

    Parameters
    ----------
    mean_fn : callable
        ``m(x, u)``: float64 tensors ``(B, n_x)``, ``(B, n_u)`` -> a tensor ``(B, n)``.
    cov : array_like, shape (n, n)
        ``K``, symmetric PSD (may be singular).

    Raises
    ------
    ValueError
        ``mean_fn`` not callable, or ``cov`` not a symmetric PSD matrix.

    Notes
    -----
    A fixed source: ``learns = False`` and no ``update``; ``state_dependent = True`` (Algorithm 2 plans
    with per-state nodes, as for Case 3).
    """

    learns = False
    state_dependent = True

    def __init__(self, mean_fn: Any, cov: Any) -> None:
        if not callable(mean_fn):
            raise ValueError(f"mean_fn: expected a callable m(x, u), got {type(mean_fn).__name__}")
        self.mean_fn = mean_fn
        self._cov = check_covariance(cov, "cov")

    @property
    def cov(self) -> np.ndarray:
        """``K``, shape (n, n) (a copy)."""
        return self._cov.copy()

    def mean_at(self, x: Any, u: Any) -> np.ndarray | torch.Tensor:
        """``m(x, u)``, shape (B, n): a float64 tensor for tensor inputs, else an ndarray."""
        as_tensor = isinstance(x, torch.Tensor)
        xt = torch.as_tensor(x, dtype=torch.float64)
        ut = torch.as_tensor(u, dtype=torch.float64)
        with torch.no_grad():
            out = self.mean_fn(xt, ut).to(torch.float64)
        if tuple(out.shape) != (xt.shape[0], self._cov.shape[0]):
            raise ValueError(f"mean_fn: returned shape {tuple(out.shape)}, expected ({xt.shape[0]}, "
                             f"{self._cov.shape[0]})")
        return out if as_tensor else out.numpy()

    def state_dict(self) -> dict[str, Any]:
        """Return ``{"cov": list of lists}`` (the mean function is fixed and not saved)."""
        return {"cov": self._cov.tolist()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore from :meth:`state_dict`; on bad input raise ``ValueError`` and leave the state unchanged."""
        if not isinstance(state, dict):
            raise ValueError(f"state: expected a dict, got {type(state).__name__}")
        check_unknown_keys(state, {"cov"}, "state")
        if "cov" not in state:
            raise ValueError("state: missing key(s) ['cov']")
        self._cov = check_covariance(state["cov"], "state['cov']", self._cov.shape[0])


def make_noise_source(method: str, task: NoiseMoments, recursion: str = "exact", covariance: str = "unknown",
                      state_dependent: bool = False) -> NoiseSource | StateDependentNoiseSource:
    """The noise distribution the algorithms plan with, by method (the mixed model of eq. 20).

    .. math:: \\hat\\xi_k \\sim N(\\hat\\mu_k, \\hat K_k):\\quad \\text{IBE posterior (mixed)},\\
        N(\\mu_M, K_M)\\ \\text{(model, eq. 55)},\\ N(\\mu, K)\\ \\text{(oracle)}

    Parameters
    ----------
    method : {"mixed", "model", "oracle"}
        ``"mixed"``: an IBE started at the prior ``(mu_M, K_M)`` (Algorithms 1 and 2's initialisation);
        ``"model"``: the prior ``N(mu_M, K_M)`` held fixed (eq. 55); ``"oracle"``: the true ``N(mu, K)``
        (``N(mu(x), K)``, :class:`StateDependentGaussianNoise`, when ``task.true_mean_varies``).
    task : object
        Supplies ``prior_mean`` (n,), ``prior_cov`` (n, n), ``true_mean`` (n,), ``true_cov`` (n, n)
        (a :class:`mixedrl.tasks.Task`, a :class:`validation.lq.LQProblem`); for Case 3 also
        ``mean_features(s, u)``, ``state_dim``, ``action_dim``; optionally ``true_mean_varies`` and
        ``true_mean_at(s, u)``.
    recursion : {"exact", "paper"}
        Recursion of the Case 2 IBE (mixed only; ``covariance="unknown"``).
    covariance : {"unknown", "known"}
        ``"unknown"``: Case 2, :class:`mixedrl.ibe.UnknownCovarianceIBE` (mean and covariance unknown,
        Algorithm 2's default); ``"known"``: Case 1, :class:`mixedrl.ibe.KnownCovarianceIBE` with the
        true ``K`` (mixed only), or Case 3 with ``state_dependent``.
    state_dependent : bool
        Mixed only, with ``covariance="known"``: Case 3 (eq. 19), :class:`mixedrl.ibe.LinearFeatureIBE`
        on the features ``task.mean_features`` (whose first column must be the constant 1), with the
        true ``K``, prior weights ``W_0`` = the prior mean on the constant feature and 0 elsewhere, and
        ``sigma_w^2`` = the largest eigenvalue of ``K_M`` (for the vehicle ``(prior_force_std T/m)^2``).

    Returns
    -------
    NoiseSource or StateDependentNoiseSource
        An IBE (``learns = True``), a :class:`GaussianNoise` or a :class:`StateDependentGaussianNoise`
        (``learns = False``).

    Raises
    ------
    ValueError
        ``method``, ``recursion`` or ``covariance`` unknown, ``recursion="paper"`` with a known
        covariance, or ``state_dependent`` with an unknown covariance.
    """
    if covariance not in ("unknown", "known"):
        raise ValueError(f"covariance: expected 'unknown' or 'known', got {covariance!r}")
    if recursion not in ("exact", "paper"):
        raise ValueError(f"recursion: expected 'exact' or 'paper', got {recursion!r}")
    if state_dependent and covariance != "known":
        raise ValueError("state_dependent: Case 3 (eq. 19) is implemented with a known covariance; "
                         "pass covariance='known'")
    if method == "mixed":
        if covariance == "known" and recursion != "exact":
            raise ValueError("recursion: 'paper' is eq. (18), a Case 2 recursion; use covariance='unknown'")
        if state_dependent:
            g = task.mean_features(torch.zeros(1, task.state_dim, dtype=torch.float64),
                                   torch.zeros(1, task.action_dim, dtype=torch.float64))
            prior_weights = np.zeros((g.shape[-1], len(task.prior_mean)))
            prior_weights[0] = task.prior_mean  # W_0^T g(x, u) = mu_M: the constant feature carries the prior
            # sigma_w^2 = the largest eigenvalue of K_M
            prior_std = float(np.sqrt(max(np.linalg.eigvalsh(np.asarray(task.prior_cov, dtype=np.float64))[-1], 0.0)))
            return LinearFeatureIBE(task.mean_features, prior_weights, task.true_cov, task.state_dim,
                                    task.action_dim, prior_std=prior_std)
        if covariance == "known":
            return KnownCovarianceIBE(task.prior_mean, task.prior_cov, task.true_cov)
        return UnknownCovarianceIBE(task.prior_mean, task.prior_cov, recursion=recursion)
    if method == "model":
        return GaussianNoise(task.prior_mean, task.prior_cov)
    if method == "oracle":
        if getattr(task, "true_mean_varies", False):
            return StateDependentGaussianNoise(task.true_mean_at, task.true_cov)
        return GaussianNoise(task.true_mean, task.true_cov)
    raise ValueError(f"method: expected 'mixed', 'model' or 'oracle', got {method!r}")
