"""Expectations over the mixed model's noise, ``E g(c + xi)``, ``xi ~ N(mu, K)``: one module for all.

Defined once here for Algorithm 2 (eqs. 49 and 51), the checks of :mod:`theory` and :mod:`mixedrl.gaussian`:
the numerical support of a covariance (:data:`SUPPORT_RTOL`, :func:`support`), the nodes of a quadrature
rule on it (:func:`quadrature_nodes` in numpy, :func:`expectation_nodes` in torch; :class:`SigmaPoints`,
:class:`GaussHermite`), and ``h(x, u, xi)`` of eq. (37) (:func:`h`; :func:`h_value` for a task and a critic,
:func:`expected_cost_to_go` for a noise object). ``docs/expectation.rst`` explains the cut-off, the rules
and the error bound for dropped directions.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import torch

from mixedrl.checks import as_batch, as_vector, check_covariance, check_positive_int

__all__ = ["SUPPORT_RTOL", "support", "SigmaPoints", "GaussHermite", "quadrature_nodes", "expectation_nodes",
           "NodeCache", "expect", "weighted_sum", "gaussian_expectation", "h", "h_value", "expected_cost_to_go"]

#: Relative eigenvalue floor that defines the numerical support (range, rank) of a PSD matrix:
#: eigenvalues ``<= SUPPORT_RTOL * lambda_max`` count as 0 (the project's one cut-off; docs/expectation.rst).
SUPPORT_RTOL = 1e-6


def support(cov: np.ndarray, rtol: float = SUPPORT_RTOL) -> tuple[np.ndarray, np.ndarray]:
    """Return the eigenpairs of a symmetric PSD matrix on its numerical support.

    .. math:: \\mathcal{K} \\approx \\sum_{i=1}^{r} \\lambda_i v_i v_i^\\top,
        \\qquad \\lambda_i > \\mathrm{rtol}\\,\\lambda_{\\max}

    Parameters
    ----------
    cov : numpy.ndarray, shape (n, n)
        Symmetric positive semi-definite (not validated here: callers pass validated or symmetrised
        matrices; ``eigh`` reads one triangle).
    rtol : float
        Relative eigenvalue floor (default :data:`SUPPORT_RTOL`).

    Returns
    -------
    eigvals : numpy.ndarray, shape (r,)
        The kept eigenvalues, ascending, all ``> 0``.
    eigvecs : numpy.ndarray, shape (n, r)
        Their orthonormal eigenvectors (columns).

    Notes
    -----
    ``r = 0`` when ``lambda_max <= 0`` (a zero matrix).
    """
    lam, vec = np.linalg.eigh(cov)
    top = lam[-1] if lam.size else 0.0
    keep = lam > rtol * top if top > 0 else np.zeros_like(lam, dtype=bool)
    return lam[keep], vec[:, keep]


def psd_factor(cov: np.ndarray) -> np.ndarray:
    """Return ``A`` with ``A A^T = cov`` for a PSD ``cov`` (eigen-factor, works when singular).

    Parameters
    ----------
    cov : ndarray, shape (n, n)

    Returns
    -------
    ndarray, shape (n, n)

    Notes
    -----
    ``A = V diag(sqrt(max(lambda, 0)))`` from ``eigh`` (a Cholesky factor would fail on a rank-1 ``cov``).
    """
    lam, vec = np.linalg.eigh(cov)
    return vec * np.sqrt(np.clip(lam, 0.0, None))


@dataclass(frozen=True)
class SigmaPoints:
    """Spherical-cubature rule: ``2r`` nodes ``+- sqrt(r) e_i``, weights ``1/(2r)``; exact to degree 3."""

    def nodes(self, r: int) -> tuple[np.ndarray, np.ndarray]:
        """Return nodes (2r, r) and weights (2r,) for ``N(0, I_r)``."""
        eye = np.sqrt(r) * np.eye(r)
        return np.vstack([eye, -eye]), np.full(2 * r, 1.0 / (2 * r))


@dataclass(frozen=True)
class GaussHermite:
    """Tensor-product Gauss-Hermite rule of ``order`` points per dimension; exact to degree ``2 order - 1``.

    Parameters
    ----------
    order : int
        Points per dimension (``>= 1``). The rule has ``order ** r`` nodes.
    """

    order: int = 5

    def __post_init__(self) -> None:
        check_positive_int(self.order, "order")

    def nodes(self, r: int) -> tuple[np.ndarray, np.ndarray]:
        """Return nodes (order^r, r) and weights (order^r,) for ``N(0, I_r)``."""
        x, w = np.polynomial.hermite_e.hermegauss(self.order)
        w = w / np.sqrt(2.0 * np.pi)
        grid = np.array(list(itertools.product(x, repeat=r)), dtype=np.float64).reshape(-1, r)
        wgrid = np.array([np.prod(c) for c in itertools.product(w, repeat=r)], dtype=np.float64)
        return grid, wgrid


Rule = SigmaPoints | GaussHermite


def quadrature_nodes(mean: np.ndarray, cov: np.ndarray, rule: Rule | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Nodes ``xi_i`` and weights ``w_i`` of ``E g(xi) ~= sum_i w_i g(xi_i)``, ``xi ~ N(mean, cov)``.

    Implements the quadrature of eqs. (37), (49) and (51) on the support of ``cov``
    (:func:`support`, rank ``r``):

    .. math::

        \\hat\\xi_{\\pm i} = \\hat\\mu \\pm \\sqrt{r \\lambda_i}\\, v_i,\\quad w = \\frac{1}{2r}
        \\quad\\text{(sigma points)},\\qquad
        \\hat\\xi_j = \\hat\\mu + V \\Lambda^{1/2} z_j \\quad\\text{(Gauss-Hermite)}.

    Parameters
    ----------
    mean : numpy.ndarray
        ``mu``, shape (n,) or (B, n); a batch of means (one per state, Case 3 of the IBE) gives per-state nodes.
    cov : numpy.ndarray, shape (n, n)
        Symmetric PSD, possibly singular.
    rule : SigmaPoints or GaussHermite, optional
        Default :class:`SigmaPoints`.

    Returns
    -------
    nodes : numpy.ndarray
        Shape (P, n), or (P, B, n) for a batch of means.
    weights : numpy.ndarray
        Shape (P,), summing to 1.

    Notes
    -----
    If ``r = 0`` (``cov = 0``) the rule is the single node ``mean``.
    """
    rule = SigmaPoints() if rule is None else rule
    lam, vec = support(cov)
    r = lam.shape[0]
    centre = mean[None]
    if r == 0:
        return centre.copy(), np.ones(1)
    if isinstance(rule, SigmaPoints):
        # xi_{+-i} = mu_hat +- sqrt(r lambda_i) v_i
        half = (vec * np.sqrt(r * lam)).T
        spread, w = np.concatenate([half, -half]), np.full(2 * r, 1.0 / (2 * r))
    else:
        z, w = rule.nodes(r)
        # xi_j = mu_hat + V Lambda^{1/2} z_j
        spread = z @ (vec * np.sqrt(lam)).T
    if mean.ndim == 2:
        spread = spread[:, None, :]
    return centre + spread, w


def expectation_nodes(mean: np.ndarray, cov: np.ndarray, noise_matrix: torch.Tensor,
                      rule: str | Rule = "sigma", n_samples: int = 4, generator: torch.Generator | None = None,
                      dtype: torch.dtype = torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """Nodes and weights of the expectation over ``xi_hat ~ N(mu_hat, K_hat)`` in eqs. (49) and (51).

    Implements the integral of eq. (51),

    .. math::

        \\mathbb{E}_{\\hat\\xi}\\, g(f(x, u) + E \\hat\\xi) \\approx \\sum_i w_i\\, g(f(x, u) + d_i),
        \\qquad d_i = E\\, \\hat\\xi_i,

    with the nodes ``xi_hat_i`` of :func:`quadrature_nodes` (``rule="sigma"`` or a rule object), or
    ``n_samples`` reparameterised draws ``mu_hat + K_hat^{1/2} eps`` (``rule="samples"``, weights ``1/n``).

    Parameters
    ----------
    mean : numpy.ndarray
        ``mu_hat``, shape (noise_dim,) or (B, noise_dim); one row per state for a state-dependent mean
        (Case 3) gives per-state offsets.
    cov : numpy.ndarray, shape (noise_dim, noise_dim)
        ``K_hat``, symmetric positive semi-definite (may be singular).
    noise_matrix : torch.Tensor, shape (state_dim, noise_dim)
        ``E``, how the noise enters the state.
    rule : {"sigma", "samples"} or SigmaPoints or GaussHermite
        Quadrature rule.
    n_samples : int
        Number of draws for ``rule="samples"``.
    generator : torch.Generator, optional
        Required for ``rule="samples"``.
    dtype : torch.dtype
        Dtype of the returned tensors.

    Returns
    -------
    offsets : torch.Tensor
        ``d_i = E xi_hat_i``, shape ``(P, state_dim)``, or ``(P, B, state_dim)`` for a batch of means.
    weights : torch.Tensor
        Quadrature weights summing to 1, shape ``(P,)``.

    Raises
    ------
    ValueError
        Shapes inconsistent, non-finite input, unknown ``rule``, ``rule="samples"`` without generator or
        with a batch of means.

    Notes
    -----
    The sigma rule is exact for polynomials of degree <= 3 in ``xi``. Directions off the support are
    dropped (error bound in ``docs/expectation.rst``); if ``K_hat = 0`` the rule is the single point ``mu_hat``.
    """
    mean = np.asarray(mean, dtype=np.float64)
    cov = np.asarray(cov, dtype=np.float64)
    n = mean.shape[-1] if mean.ndim in (1, 2) else -1
    if mean.ndim not in (1, 2) or cov.shape != (n, n) or noise_matrix.shape[-1] != n:
        raise ValueError(f"mean: shapes mean {mean.shape}, cov {cov.shape}, noise_matrix "
                         f"{tuple(noise_matrix.shape)} are inconsistent")
    if not (np.isfinite(mean).all() and np.isfinite(cov).all()):
        raise ValueError("mean: mean or cov contains NaN or inf")
    cov = 0.5 * (cov + cov.T)
    if rule == "sigma" or isinstance(rule, (SigmaPoints, GaussHermite)):
        xi, w = quadrature_nodes(mean, cov, SigmaPoints() if rule == "sigma" else rule)
        xi_t = torch.as_tensor(xi, dtype=torch.float64)
    elif rule == "samples":
        if generator is None:
            raise ValueError("generator: required for rule='samples'")
        if mean.ndim != 1:
            raise ValueError("mean: rule='samples' takes one mean of shape (noise_dim,)")
        eps = torch.randn(n_samples, n, generator=generator, dtype=torch.float64)
        root = torch.as_tensor(psd_factor(cov), dtype=torch.float64)
        # xi = mu_hat + K_hat^{1/2} eps   (reparameterisation)
        xi_t, w = torch.as_tensor(mean) + eps @ root.T, np.full(n_samples, 1.0 / n_samples)
    else:
        raise ValueError(f"rule: expected 'sigma', 'samples' or a quadrature rule, got {rule!r}")
    return (xi_t @ noise_matrix.to(torch.float64).T).to(dtype), torch.as_tensor(w, dtype=dtype)


class NodeCache:
    """:func:`expectation_nodes` remembered for its last inputs (issue 44): the IBE moves ``xi_hat`` only
    now and then (and PEV, PIM and the MVC ask for the same nodes several times an iteration), so the nodes
    are recomputed only when the inputs changed.

    Calling the cache is calling :func:`expectation_nodes` with the same arguments, bit for bit: the nodes of a
    deterministic rule (``"sigma"``, :class:`SigmaPoints`, :class:`GaussHermite`) of one mean (shape
    ``(noise_dim,)``) are a function of ``(mean, cov, noise_matrix, rule, dtype)`` alone, and are reused while
    these are bitwise the same (the arrays compared by their bytes, so ``-0.0`` is not ``0.0``). Sampled nodes
    (``rule="samples"``, which draw from the generator) and a batch of means (Case 3, one per state) are
    computed every call, as before. The returned tensors are shared between calls: callers must not modify
    them in place (none does).

    Attributes
    ----------
    hits, misses : int
        Calls answered from the cache / computed (the uncached kinds not counted).
    """

    def __init__(self) -> None:
        self._key: tuple | None = None
        self._value: tuple[torch.Tensor, torch.Tensor] | None = None
        self.hits = 0
        self.misses = 0

    def __call__(self, mean: np.ndarray, cov: np.ndarray, noise_matrix: torch.Tensor, rule: str | Rule = "sigma",
                 n_samples: int = 4, generator: torch.Generator | None = None,
                 dtype: torch.dtype = torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
        """:func:`expectation_nodes` ``(mean, cov, noise_matrix, rule, n_samples, generator, dtype)``."""
        m, c = np.asarray(mean, dtype=np.float64), np.asarray(cov, dtype=np.float64)
        deterministic = isinstance(rule, (SigmaPoints, GaussHermite)) or (isinstance(rule, str) and rule == "sigma")
        if not deterministic or m.ndim != 1:
            return expectation_nodes(mean, cov, noise_matrix, rule, n_samples, generator, dtype)
        e = noise_matrix.detach()
        key = (rule, dtype, m.shape, c.shape, m.tobytes(), c.tobytes(), e.dtype, tuple(e.shape),
               e.cpu().contiguous().numpy().tobytes())
        if self._value is not None and self._key == key:
            self.hits += 1
            return self._value
        value = expectation_nodes(m, c, noise_matrix, rule, n_samples, generator, dtype)
        self._key, self._value = key, value
        self.misses += 1
        return value


def expect(g: Callable[..., Any], centers: Any, offsets: Any, weights: Any, extra: Any = None) -> Any:
    """``sum_i w_i g(c_b + d_i)`` for every row ``c_b`` of ``centers``; numpy arrays or torch tensors.

    .. math:: \\mathbb{E}\\, g(c + \\xi) \\approx \\sum_i w_i\\, g(c + d_i)

    Parameters
    ----------
    g : callable
        Batched: ``g(x)`` (M, n) -> (M,), or ``g(x, e)`` when ``extra`` is given.
    centers : array or Tensor, shape (B, n)
        The deterministic parts ``f(x, u)``.
    offsets : array or Tensor
        Nodes ``d_i``, shape (P, n), or (P, B, n) per state for a state-dependent noise.
    weights : array or Tensor
        Shape (P,), or (P, B) per state (:func:`weighted_sum`).
    extra : array or Tensor, shape (B, m), optional
        Per-row extra argument (the action ``u`` of ``l(x', u)``), repeated for every node.

    Returns
    -------
    array or Tensor, shape (B,)

    Raises
    ------
    ValueError
        ``g`` returns the wrong shape, or ``extra`` has another number of rows than ``centers``.
    """
    P, B = offsets.shape[0], centers.shape[0]
    step = offsets if offsets.ndim == 3 else offsets[:, None, :]
    points = (centers[None] + step).reshape(P * B, -1)
    if extra is None:
        values = g(points)
    else:
        if extra.shape[0] != B:
            raise ValueError(f"extra: {extra.shape[0]} rows, but centers has {B}")
        broadcast = torch.broadcast_to if isinstance(extra, torch.Tensor) else np.broadcast_to
        values = g(points, broadcast(extra[None], (P, *extra.shape)).reshape(P * B, -1))
    if tuple(values.shape) != (P * B,):
        raise ValueError(f"g: expected output shape ({P * B},), got {tuple(values.shape)}")
    if weights.ndim == 2:
        return weighted_sum(weights, values.reshape(P, B))
    return weights @ values.reshape(P, B)


def weighted_sum(weights: Any, values: Any) -> Any:
    """``sum_i w_i v_i`` with per-state weights, ``weights`` (P, B) and ``values`` (P, B[, ...]), summed in the
    order ``i = 0, 1, ..., P - 1``: each state's sum uses its own column only (the batched engine's
    quadrature, :mod:`mixedrl.algorithms.batched`; trailing nodes of weight 0 change nothing)."""
    w = weights.reshape(weights.shape + (1,) * (values.ndim - weights.ndim))
    total = w[0] * values[0]
    for i in range(1, values.shape[0]):
        total = total + w[i] * values[i]
    return total


def gaussian_expectation(
    g: Callable[..., np.ndarray],
    centers: Any,
    mean: Any,
    cov: Any,
    rule: Rule | None = None,
    extra: Any = None,
) -> np.ndarray:
    """Return ``E g(c_i + xi)`` for each row ``c_i`` of ``centers``, ``xi ~ N(mean, cov)``, by quadrature.

    .. math:: \\mathbb{E}\\, g(c + \\xi) \\approx \\sum_j w_j\\, g(c + \\hat\\xi_j)

    Parameters
    ----------
    g : callable
        Batched function: ``g(x)`` with x (M, n) -> (M,), or ``g(x, e)`` when ``extra`` is given.
    centers : array_like
        The deterministic parts ``f(x, u)``, shape (N, n) or (n,).
    mean : array_like, shape (n,)
    cov : array_like, shape (n, n)
        Symmetric PSD, possibly singular.
    rule : SigmaPoints or GaussHermite, optional
        Default :class:`SigmaPoints` (exact for polynomials of degree <= 3).
    extra : array_like, shape (N, m), optional
        Per-row extra argument (e.g. the action ``u`` of ``l(x', u)``), repeated for every node.

    Returns
    -------
    ndarray, shape (N,)

    Raises
    ------
    ValueError
        Shapes do not match, non-finite input, ``cov`` not symmetric PSD, or ``g`` returns the wrong shape.
    """
    c = as_batch(centers, "centers", np.shape(centers)[-1])
    n = c.shape[1]
    mu = as_vector(mean, "mean", n)
    K = check_covariance(cov, "cov", n)
    xi, w = quadrature_nodes(mu, K, rule)
    e = None if extra is None else np.asarray(extra, dtype=np.float64).reshape(c.shape[0], -1)
    return expect(lambda *args: np.asarray(g(*args), dtype=np.float64), c, xi, w, e)


def h(f: Callable[[Any, Any], Any], cost: Callable[[Any, Any], Any], value: Callable[[Any], Any], gamma: float,
      x: Any, u: Any, offsets: Any, weights: Any) -> Any:
    """Implements eq. (37): the expected cumulative cost of action ``u`` under a noise distribution.

    .. math::

        h(x, u, \\hat\\xi) = \\mathbb{E}_{\\hat\\xi}\\{ l(x', u) + \\gamma V^k(x') \\},
        \\qquad x' = f(x, u) + \\hat\\xi,

    the utility charged on the **next** state (eq. 2). Works on numpy arrays and on torch tensors
    (differentiable in ``u`` and in ``V``'s parameters).

    Parameters
    ----------
    f : callable
        ``f(x, u)``: (B, n), (B, m) -> (B, n).
    cost : callable
        ``l(x', u)``: (M, n), (M, m) -> (M,).
    value : callable
        ``V^k``: (M, n) -> (M,).
    gamma : float
    x : array or Tensor, shape (B, n)
    u : array or Tensor, shape (B, m)
    offsets, weights : array or Tensor
        Quadrature of the noise: shapes ``(P, n)`` (or ``(P, B, n)``, per state) and ``(P,)``
        (:func:`quadrature_nodes`, :func:`expectation_nodes`).

    Returns
    -------
    array or Tensor, shape (B,)

    Raises
    ------
    ValueError
        The batch sizes of ``x`` and ``u`` differ, or ``f``/``cost``/``value`` return wrong shapes.
    """
    if x.shape[0] != u.shape[0]:
        raise ValueError(f"u: batch size {u.shape[0]} differs from x's {x.shape[0]}")
    # f(x, u), once per state: the noise is additive
    centers = f(x, u)
    if tuple(centers.shape) != tuple(x.shape):
        raise ValueError(f"f: expected output shape {tuple(x.shape)}, got {tuple(centers.shape)}")

    def target(x_next: Any, u_rep: Any) -> Any:
        # l(x', u) + gamma V(x'),  x' = f(x, u) + xi_hat
        return cost(x_next, u_rep) + gamma * value(x_next)

    return expect(target, centers, offsets, weights, u)


def h_value(task: Any, critic: torch.nn.Module, s: torch.Tensor, u: torch.Tensor, offsets: torch.Tensor,
            weights: torch.Tensor) -> torch.Tensor:
    """Implements eq. (37) for a task and a critic on observations: :func:`h` with ``V = critic o observe``.

    .. math::

        h(x, u, \\hat\\xi) = \\mathbb{E}_{\\hat\\xi}\\{ l(x', u) + \\gamma V^k(x') \\},
        \\qquad x' = f(x, u) + \\hat\\xi.

    Parameters
    ----------
    task : Task
        The model ``f``, the utility ``l``, ``gamma``, ``observe``.
    critic : torch.nn.Module
        ``V^k``, maps observations (N, obs_dim) to (N,).
    s : torch.Tensor, shape (B, state_dim)
        States ``x``.
    u : torch.Tensor, shape (B, action_dim)
        Actions.
    offsets, weights : torch.Tensor
        Quadrature of the noise distribution (:func:`expectation_nodes`), shapes ``(P, state_dim)`` (or
        ``(P, B, state_dim)``) and ``(P,)``.

    Returns
    -------
    torch.Tensor, shape (B,)
        ``h`` per state (differentiable in ``u`` and in the critic's weights).

    Raises
    ------
    ValueError
        If the batch sizes of ``s`` and ``u`` differ.
    """
    return h(task.f, task.cost, lambda z: critic(task.observe(z)), task.gamma, s, u, offsets, weights)


def expected_cost_to_go(
    value: Callable[[np.ndarray], np.ndarray],
    f: Callable[[np.ndarray, np.ndarray], np.ndarray],
    utility: Callable[[np.ndarray, np.ndarray], np.ndarray],
    gamma: float,
    states: Any,
    actions: Any,
    noise: Any,
    rule: Rule | None = None,
) -> np.ndarray:
    """Eq. (37) for numpy callables and a noise object: :func:`h` on the nodes of :func:`quadrature_nodes`.

    .. math:: h(x, u, \\xi) = \\mathbb{E}_{\\xi}\\{ l(x', u) + \\gamma V^k(x') \\},\\qquad x' = f(x, u) + \\xi

    Parameters
    ----------
    value : callable
        ``V^k``, (N, n) -> (N,).
    f : callable
        ``f(x, u)``, (N, n), (N, m) -> (N, n).
    utility : callable
        ``l(x', u)``, (N, n), (N, m) -> (N,).
    gamma : float
    states : array_like, shape (N, n)
    actions : array_like, shape (N, m)
    noise : object
        ``.mean`` (n,), ``.cov`` (n, n) (an IBE, a :class:`mixedrl.noise.GaussianNoise`).
    rule : SigmaPoints or GaussHermite, optional
        Quadrature rule (default sigma points, exact for quadratics).

    Returns
    -------
    ndarray, shape (N,)

    Raises
    ------
    ValueError
        Shapes do not match, or a callable returns the wrong shape.
    """
    arr = np.asarray(states, dtype=np.float64)
    x = as_batch(arr, "states", arr.shape[-1] if arr.ndim else 0)
    u = np.asarray(actions, dtype=np.float64).reshape(x.shape[0], -1)
    mean = as_vector(noise.mean, "noise.mean", x.shape[1])
    cov = check_covariance(noise.cov, "noise.cov", x.shape[1])
    nodes, weights = quadrature_nodes(mean, cov, rule)

    def as_float(fn: Callable[..., Any]) -> Callable[..., np.ndarray]:
        return lambda *args: np.asarray(fn(*args), dtype=np.float64)

    return h(as_float(f), as_float(utility), as_float(value), float(gamma), x, u, nodes, weights)
