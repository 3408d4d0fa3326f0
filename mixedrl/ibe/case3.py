"""Case 3 of the IBE: a state-dependent mean ``mu = phi(x, u; w)``, eq. (19).

* :class:`~mixedrl.ibe.StateDependentIBE`: any ``phi`` (a ``torch.nn.Module``), refitted by L-BFGS on every residual
  kept so far; :meth:`~mixedrl.ibe.StateDependentIBE.negative_log_posterior` is eq. (19).
* :class:`~mixedrl.ibe.LinearFeatureIBE`: ``phi = W^T g(x, u)`` with fixed features, solved in closed form from the
  sufficient statistics ``(N, G, S)``.

Both take the noise covariance ``K`` as known.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from mixedrl.checks import (as_vector, check_finite, check_nonnegative_int, check_number, check_positive_int,
                            check_unknown_keys)
from mixedrl.expectation import support
from mixedrl.gaussian import sample_gaussian
from mixedrl.ibe.common import (
    PosteriorGuard,
    ReadOnlyFields,
    check_dimension,
    check_posterior,
    check_state,
    real_array,
    real_batch,
    real_covariance,
)

__all__ = ["StateDependentIBE", "LinearFeatureIBE"]


def _whitening(noise_cov: np.ndarray) -> torch.Tensor:
    """``W`` with ``W W^T = K^+`` on the support of ``K``, so that ``r^T K^+ r = |r W|^2``."""
    lam, vec = support(noise_cov)
    return torch.as_tensor(vec / np.sqrt(lam))


class _StateDependentMean(ReadOnlyFields):
    """What the two Case 3 estimators share: a known ``K`` and a mean ``mean_at(x, u)`` of batches ``(x, u)``."""

    #: The mean is ``mean_at(x, u)``: Algorithm 2 plans with per-state nodes.
    state_dependent = True

    def _probe(self, fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]) -> torch.Tensor:
        """``fn`` at one zero state and action (to check the shape of its output)."""
        with torch.no_grad():
            return fn(torch.zeros((1, self.state_dim), dtype=torch.float64),
                      torch.zeros((1, self.action_dim), dtype=torch.float64))

    @staticmethod
    def _batch(value: Any, name: str, dim: int) -> torch.Tensor:
        """One sample or a batch of real numbers as a float64 ``(N, dim)`` tensor (a copy)."""
        return torch.as_tensor(real_batch(value.detach() if isinstance(value, torch.Tensor) else value, name, dim,
                                          copy=True))

    def _inputs(self, x: Any, u: Any, xi: Any | None = None) -> tuple[torch.Tensor, ...]:
        """``x``, ``u`` (and ``xi``) as float64 ``(N, .)`` tensors; ``ValueError`` naming one whose rows differ
        from ``x``'s."""
        out = [self._batch(x, "x", self.state_dim), self._batch(u, "u", self.action_dim)]
        if xi is not None:
            out.append(self._batch(xi, "xi", self.dim))
        for name, t in zip(("u", "xi"), out[1:]):
            if t.shape[0] != out[0].shape[0]:
                raise ValueError(f"{name}: {t.shape[0]} rows, but x has {out[0].shape[0]}")
        return tuple(out)

    def _mean(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def mean_at(self, x: Any, u: Any) -> np.ndarray | torch.Tensor:
        """The posterior mean ``phi(x, u; w_hat)`` (``phi(x, u; w_0)``, the prior, before any data).

        Parameters
        ----------
        x : array_like or Tensor, shape (B, n_x) or (n_x,)
        u : array_like or Tensor, shape (B, n_u) or (n_u,)

        Returns
        -------
        ndarray or Tensor, shape (B, n) or (n,)
            A float64 tensor if ``x`` is a tensor, else an ndarray.

        Raises
        ------
        ValueError
            Wrong shapes or NaN/inf.
        """
        xb, ub = self._inputs(x, u)
        with torch.no_grad():
            out = self._mean(xb, ub)
        out = out[0] if np.ndim(x) == 1 else out
        return out.clone() if isinstance(x, torch.Tensor) else out.numpy().copy()


class StateDependentIBE(_StateDependentMean):
    """Implements eq. (19): Case 3 IBE with a state-dependent mean ``mu = phi(x, u; w)``.

    .. math::
        \\mathcal{L}(w) = \\frac12\\sum_{j=1}^N \\big(\\xi_j - \\phi(x_j, u_j; w)\\big)^T \\mathcal{K}^{+}
        \\big(\\xi_j - \\phi(x_j, u_j; w)\\big) + \\frac{1}{2\\sigma_w^2}\\lVert w - w_0\\rVert^2 + C

    the negative log posterior (EQUATIONS.md point 1) with Gaussian prior ``w ~ N(w_0, sigma_w^2 I)``.

    Parameters
    ----------
    phi : torch.nn.Module
        ``forward(x, u)`` maps ``(B, n_x)`` and ``(B, n_u)`` tensors to ``(B, n)``. Its parameters at
        construction are the prior mean ``w_0``; they are converted to float64.
    noise_cov : array_like, shape (n, n)
        Known noise covariance ``K`` (symmetric PSD).
    state_dim : int
        ``n_x``.
    action_dim : int
        ``n_u``.
    prior_std : float
        ``sigma_w > 0``.
    max_iter : int
        L-BFGS iterations per :meth:`update` (full batch, strong-Wolfe line search; deterministic).

    Attributes
    ----------
    count : int
        Number of residuals seen.

    Raises
    ------
    ValueError
        Bad covariance (not real numbers, zero-dimensional, not symmetric PSD), non-positive
        ``prior_std``/``max_iter``/dimensions, ``phi`` not a module.

    Notes
    -----
    ``K^{+}`` is the pseudo-inverse on the support of ``K`` (:func:`mixedrl.expectation.support`): noise-free
    directions are set by the prior on ``w`` alone. ``K`` is known (the paper leaves Case 3's unspecified).
    Every update refits on all data so far, warm-started from the current ``w`` (deterministic; seed the
    module's initialisation); see ``docs/ibe.rst``, Case 3.
    """

    _KIND = "StateDependentIBE"
    _FIELDS = ("phi", "state_dim", "action_dim", "prior_std", "max_iter")

    def __init__(
        self,
        phi: torch.nn.Module,
        noise_cov: Any,
        state_dim: int,
        action_dim: int,
        prior_std: float = 1.0,
        max_iter: int = 200,
    ) -> None:
        if not isinstance(phi, torch.nn.Module):
            raise ValueError(f"phi: expected a torch.nn.Module, got {type(phi).__name__}")
        self._commit(noise_cov=real_covariance(noise_cov, "noise_cov"),
                     state_dim=check_positive_int(state_dim, "state_dim"),
                     action_dim=check_positive_int(action_dim, "action_dim"),
                     prior_std=check_number(prior_std, "prior_std", positive=True),
                     max_iter=check_positive_int(max_iter, "max_iter"), phi=phi.double(), count=0)
        self._prior_w = [p.detach().clone() for p in self.phi.parameters()]
        self._whiten = _whitening(self.noise_cov)
        self._x, self._u, self._xi = (torch.zeros((0, d), dtype=torch.float64)
                                      for d in (self.state_dim, self.action_dim, self.dim))
        out = self._probe(self.phi)
        if tuple(out.shape) != (1, self.dim):
            raise ValueError(f"phi: returned shape {tuple(out.shape)} for one input, expected (1, {self.dim})")

    def negative_log_posterior(self) -> torch.Tensor:
        """Implements eq. (19) as a negative log posterior on the data seen so far (constant dropped)."""
        pred = self.phi(self._x, self._u)
        # (xi_j - phi(x_j, u_j; w))^T K^+ (xi_j - phi(x_j, u_j; w))
        white = (self._xi - pred) @ self._whiten
        nll = 0.5 * torch.sum(white * white)
        # -log p(w) = |w - w_0|^2 / (2 sigma_w^2)
        prior = sum(torch.sum((p - p0) ** 2) for p, p0 in zip(self.phi.parameters(), self._prior_w))
        return nll + 0.5 * prior / self.prior_std**2

    def update(self, x: Any, u: Any, xi: Any) -> StateDependentIBE:
        """Add transitions ``(x, u, xi)`` and refit ``w`` by minimising eq. (19); returns ``self``.

        Parameters
        ----------
        x : array_like, shape (N, n_x) or (n_x,)
        u : array_like, shape (N, n_u) or (n_u,)
        xi : array_like, shape (N, n) or (n,)
            Residuals (eq. (10)) of those transitions.

        Raises
        ------
        ValueError
            Wrong shapes, not real numbers, NaN/inf, or a fit that ends with non-finite parameters or a
            non-finite eq. (19); the estimator is then unchanged.
        """
        xb, ub, xib = self._inputs(x, u, xi)
        if xb.shape[0] == 0:
            return self
        saved = [p.detach().clone() for p in self.phi.parameters()]
        old = (self._x, self._u, self._xi, self.count)
        self._x, self._u, self._xi = torch.cat([self._x, xb]), torch.cat([self._u, ub]), torch.cat([self._xi, xib])
        self._commit(count=self.count + xb.shape[0])
        opt = torch.optim.LBFGS(self.phi.parameters(), lr=1.0, max_iter=self.max_iter, tolerance_grad=1e-12,
                                tolerance_change=1e-15, history_size=50, line_search_fn="strong_wolfe")

        def closure() -> torch.Tensor:
            opt.zero_grad()
            loss = self.negative_log_posterior()
            loss.backward()
            return loss

        try:
            opt.step(closure)
            with torch.no_grad():
                ok = (all(bool(torch.isfinite(p).all()) for p in self.phi.parameters())
                      and bool(torch.isfinite(self.negative_log_posterior())))
        except RuntimeError:
            ok = False
        if not ok:
            with torch.no_grad():
                for p, s in zip(self.phi.parameters(), saved):
                    p.copy_(s)
            self._x, self._u, self._xi = old[:3]
            self._commit(count=old[3])
            raise ValueError("xi: update rejected: fitting eq. (19) gave non-finite parameters or a non-finite "
                             "negative log posterior (residuals too large for float64?)")
        return self

    def _mean(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return self.phi(x, u)

    def sample(self, n: int, generator: np.random.Generator | torch.Generator, x: Any,
               u: Any) -> np.ndarray | torch.Tensor:
        """Draw ``xi_hat ~ N(phi(x, u; w_hat), K)`` at one state-action pair.

        Parameters
        ----------
        n : int
        generator : numpy.random.Generator or torch.Generator
        x : array_like, shape (n_x,)
        u : array_like, shape (n_u,)

        Returns
        -------
        ndarray or Tensor, shape (n, d)

        Raises
        ------
        ValueError
            Bad ``n``, ``generator``, ``x`` or ``u``.
        """
        x = as_vector(real_array(x, "x"), "x", self.state_dim)
        u = as_vector(real_array(u, "u"), "u", self.action_dim)
        return sample_gaussian(self.mean_at(x, u), self.noise_cov, n, generator)

    def state_dict(self) -> dict[str, Any]:
        """Return a copy of the full state: parameters, prior, data, covariance."""
        return {
            **self._state("noise_cov", "prior_std", "max_iter", "count"),
            "params": [p.detach().numpy().copy() for p in self.phi.parameters()],
            "prior_params": [p.numpy().copy() for p in self._prior_w],
            "x": self._x.numpy().copy(),
            "u": self._u.numpy().copy(),
            "xi": self._xi.numpy().copy(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> StateDependentIBE:
        """Restore a state from :meth:`state_dict`; validate everything first.

        Raises
        ------
        ValueError
            Not a dict, unknown/missing keys, other kind, wrong shapes, NaN/inf, bad covariance.
            The estimator is then left unchanged.
        """
        n = self.dim
        if not isinstance(state, dict):
            raise ValueError(f"state_dict: expected a dict, got {type(state).__name__}")
        check_unknown_keys(state, {"kind", "noise_cov", "prior_std", "max_iter", "count", "params", "prior_params",
                                   "x", "u", "xi"}, "state_dict")
        count = check_nonnegative_int(state.get("count"), "state_dict: count")
        shapes = [tuple(p.shape) for p in self.phi.parameters()]
        spec: dict[str, Any] = {
            "kind": "str", "noise_cov": (n, n), "prior_std": "float", "max_iter": "int", "count": "int",
            "x": (int(count), self.state_dim), "u": (int(count), self.action_dim), "xi": (int(count), n),
        }
        flat = {k: v for k, v in state.items() if k not in ("params", "prior_params")}
        for key in ("params", "prior_params"):
            val = state.get(key)
            if not isinstance(val, (list, tuple)) or len(val) != len(shapes):
                raise ValueError(f"state_dict: {key} must be a list of {len(shapes)} arrays")
            for i, (arr, shp) in enumerate(zip(val, shapes)):
                spec[f"{key}.{i}"], flat[f"{key}.{i}"] = shp, arr
        st = check_state(flat, spec, self._KIND, psd=("noise_cov",))
        check_number(st["prior_std"], "state_dict: prior_std", positive=True)
        check_positive_int(st["max_iter"], "state_dict: max_iter")
        whiten = _whitening(st["noise_cov"])
        with torch.no_grad():
            for i, p in enumerate(self.phi.parameters()):
                p.copy_(torch.as_tensor(st[f"params.{i}"]))
        self._prior_w = [torch.as_tensor(st[f"prior_params.{i}"]).clone() for i in range(len(shapes))]
        self._commit(noise_cov=st["noise_cov"], prior_std=st["prior_std"], max_iter=st["max_iter"], count=st["count"])
        self._whiten = whiten
        self._x, self._u, self._xi = (torch.as_tensor(st[k]).clone() for k in ("x", "u", "xi"))
        return self


class LinearFeatureIBE(_StateDependentMean):
    """Implements eq. (19) in closed form: Case 3 IBE with a mean linear in its parameters.

    .. math::
        \\phi(x, u; W) = W^T g(x, u), \\qquad
        \\mathcal{L}(W) = \\frac12\\sum_{j=1}^N \\big(\\xi_j - W^T g_j\\big)^T \\mathcal{K}^{+}
        \\big(\\xi_j - W^T g_j\\big) + \\frac{1}{2\\sigma_w^2}\\lVert W - W_0\\rVert_F^2 + C

    with fixed features ``g(x, u)`` (``p`` of them) and weights ``W`` (``p x n``). ``L`` is quadratic in
    ``W``, so its minimiser (the posterior mode, and mean, of eq. 19) is exact: with
    ``K^+ = sum_i v_i v_i^T / lambda_i`` on the support of ``K``, ``G = sum_j g_j g_j^T`` and
    ``S = sum_j g_j xi_j^T``,

    .. math::
        \\big(G + \\tfrac{\\lambda_i}{\\sigma_w^2} I\\big)\\, W v_i = S v_i + \\tfrac{\\lambda_i}{\\sigma_w^2} W_0 v_i
        \\quad \\text{(each support direction } v_i\\text{)}, \\qquad W v = W_0 v \\ \\text{(} v \\perp
        \\text{support)}.

    The state is the sufficient statistics ``(N, G, S)``, so an update costs the same at every residual;
    :class:`StateDependentIBE` is the general form (``docs/ibe.rst``, Case 3).

    Parameters
    ----------
    features : callable
        ``g(x, u)``: float64 tensors ``(B, n_x)``, ``(B, n_u)`` -> a float64 tensor ``(B, p)``. Fixed
        (it holds no learned state; it is not saved by :meth:`state_dict`).
    prior_weights : array_like, shape (p, n)
        ``W_0``, the prior mean of the weights.
    noise_cov : array_like, shape (n, n)
        The known noise covariance ``K`` (symmetric PSD, may be singular).
    state_dim, action_dim : int
        ``n_x``, ``n_u``.
    prior_std : float
        ``sigma_w > 0``: prior ``vec(W) ~ N(vec(W_0), sigma_w^2 I)``.

    Attributes
    ----------
    count : int
        Number of residuals seen.

    Raises
    ------
    ValueError
        Bad covariance or prior weights (not real numbers, or no feature or noise dimension),
        non-positive ``prior_std``/dimensions, ``features`` not callable or returning a wrong shape.

    Notes
    -----
    As for :class:`StateDependentIBE`, ``K`` is known and ``W`` stays at the prior off its support. Any split
    of the data into batches gives the same ``W`` up to the rounding of ``G`` and ``S``.
    """

    _KIND = "LinearFeatureIBE"
    _FIELDS = ("features", "state_dim", "action_dim", "prior_std", "prior_weights", "weights", "gram", "cross")

    def __init__(self, features: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], prior_weights: Any,
                 noise_cov: Any, state_dim: int, action_dim: int, prior_std: float = 1.0) -> None:
        if not callable(features):
            raise ValueError(f"features: expected a callable g(x, u), got {type(features).__name__}")
        self._commit(features=features, state_dim=check_positive_int(state_dim, "state_dim"),
                     action_dim=check_positive_int(action_dim, "action_dim"))
        w0 = np.array(real_array(prior_weights, "prior_weights"), dtype=np.float64)
        if w0.ndim != 2:
            raise ValueError(f"prior_weights: expected a (p, n) matrix, got shape {w0.shape}")
        check_dimension(w0.shape[0], "prior_weights (rows: features)")
        check_dimension(w0.shape[1], "prior_weights (columns: noise)")
        check_finite(w0, "prior_weights")
        self._commit(noise_cov=real_covariance(noise_cov, "noise_cov", w0.shape[1]),
                     prior_std=check_number(prior_std, "prior_std", positive=True))
        g = self._probe(features)
        if tuple(g.shape) != (1, w0.shape[0]):
            raise ValueError(f"features: returned shape {tuple(g.shape)} for one input, expected (1, {w0.shape[0]}) "
                             f"(one feature per row of prior_weights)")
        self._commit(prior_weights=w0, count=0, gram=np.zeros((w0.shape[0], w0.shape[0])), cross=np.zeros(w0.shape),
                     weights=w0.copy())
        self._support = support(self.noise_cov)

    @property
    def num_features(self) -> int:
        """Number ``p`` of features."""
        return self.prior_weights.shape[0]

    def _solve(self, gram: np.ndarray, cross: np.ndarray) -> np.ndarray:
        lam, vec = self._support
        w0 = self.prior_weights
        weights = w0.copy()
        eye = np.eye(self.num_features)
        for lam_i, v in zip(lam, vec.T):
            ridge = lam_i / self.prior_std**2
            # (G + lambda_i / sigma_w^2 I) W v_i = S v_i + lambda_i / sigma_w^2 W_0 v_i
            chol = np.linalg.cholesky(gram + ridge * eye)
            rhs = cross @ v + ridge * (w0 @ v)
            wv = np.linalg.solve(chol.T, np.linalg.solve(chol, rhs))
            # replace the v_i-component of W (the prior's W_0 v_i) by the solution
            weights += np.outer(wv - w0 @ v, v)
        return weights

    def _features(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            g = self.features(x, u)
        if tuple(g.shape) != (x.shape[0], self.num_features):
            raise ValueError(f"features: returned shape {tuple(g.shape)}, expected ({x.shape[0]}, {self.num_features})")
        return g.to(torch.float64)

    def update(self, x: Any, u: Any, xi: Any) -> LinearFeatureIBE:
        """Add transitions ``(x, u, xi)`` and re-solve eq. (19) exactly; returns ``self``.

        Parameters
        ----------
        x : array_like, shape (N, n_x) or (n_x,)
        u : array_like, shape (N, n_u) or (n_u,)
        xi : array_like, shape (N, n) or (n,)
            Residuals (eq. (10)) of those transitions.

        Raises
        ------
        ValueError
            Wrong shapes, not real numbers, NaN/inf in the data or in the features, or statistics or
            weights that would not be finite (``G`` not symmetric PSD); the estimator is then unchanged.
        """
        xb, ub = self._batch(x, "x", self.state_dim), self._batch(u, "u", self.action_dim)
        xib = real_batch(xi, "xi", self.dim)
        if not xb.shape[0] == ub.shape[0] == xib.shape[0]:
            raise ValueError(f"xi: x, u and xi need the same number of rows, got {xb.shape[0]}, {ub.shape[0]}, "
                             f"{xib.shape[0]}")
        if xb.shape[0] == 0:
            return self
        g = self._features(xb, ub).numpy()
        check_finite(g, "features(x, u)")
        with PosteriorGuard("xi"):
            # G = sum_j g_j g_j^T ;  S = sum_j g_j xi_j^T
            gram, cross = self.gram + g.T @ g, self.cross + g.T @ xib
            check_posterior("x", (), (gram,))
            check_posterior("xi", (cross,))
            weights = self._solve(gram, cross)
        check_posterior("xi", (weights,))
        self._commit(gram=gram, cross=cross, weights=weights, count=self.count + xb.shape[0])
        return self

    def _mean(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        # phi(x, u; W_hat) = W_hat^T g(x, u)
        return self._features(x, u) @ torch.tensor(self.weights)

    def state_dict(self) -> dict[str, Any]:
        """Return a copy of the full state: prior, covariance, sufficient statistics (not the features)."""
        return self._state("noise_cov", "prior_std", "prior_weights", "count", "gram", "cross")

    def load_state_dict(self, state: dict[str, Any]) -> LinearFeatureIBE:
        """Restore a state from :meth:`state_dict` (same features); validate everything first.

        Raises
        ------
        ValueError
            Not a dict, unknown/missing keys, other kind, wrong shapes, NaN/inf, bad covariance or
            ``prior_std``. The estimator is then left unchanged.
        """
        p, n = self.prior_weights.shape
        spec = {"kind": "str", "noise_cov": (n, n), "prior_std": "float", "prior_weights": (p, n), "count": "int",
                "gram": (p, p), "cross": (p, n)}
        st = check_state(state, spec, self._KIND, psd=("noise_cov",))
        check_number(st["prior_std"], "state_dict: prior_std", positive=True)
        real_covariance(st["gram"], "state_dict: gram", p)  # checked, kept as saved
        new = LinearFeatureIBE(self.features, st["prior_weights"], st["noise_cov"], self.state_dim, self.action_dim,
                               st["prior_std"])
        with PosteriorGuard("state_dict"):
            weights = new._solve(st["gram"], st["cross"])
        check_posterior("state_dict", (weights,))
        new._commit(gram=st["gram"], cross=st["cross"], count=st["count"], weights=weights)
        self.__dict__.update(new.__dict__)
        return self
