"""Algorithm 1 of the paper: mixed RL by policy iteration, as a loop of three named steps.

.. code-block:: text

    Initialise IBE:  mu_hat_0 = mu_M, K_hat_0 = K_M           (the noise source, before any data)
    repeat  k = 0, 1, ...
        IBE  (eq. 13/20):  update the noise with the residuals xi^D_k    -> ibe_step
        PEV  (eq. 21):     V^k = E_{xi_hat_k}{ l(x', pi^k(x)) + gamma V^k(x') }   -> pev_step
        PIM  (eq. 22):     pi^{k+1} = argmin_u E_{xi_hat_k}{ l(x', u) + gamma V^k(x') }  -> pim_step
    until |V^{k+1} - V^k| <= eps and |pi^{k+1} - pi^k| <= eps

The value and policy representations are pluggable: PEV is any callable ``evaluate(policy, noise) ->
value`` and PIM any callable ``improve(value, noise) -> policy`` (exact ones for linear dynamics are
:class:`mixedrl.pev.ExactPEV` / :class:`mixedrl.pim.ExactPIM`; the steps :func:`mixedrl.pev.pev_step`
and :func:`mixedrl.pim.pim_step` are re-exported here). The noise source
(:class:`mixedrl.noise.NoiseSource`, made by :func:`mixedrl.noise.make_noise_source`) is pluggable too,
and is the only difference between the three methods:

* mixed RL: an IBE object (:mod:`mixedrl.ibe`) and a ``collect(policy, k)`` callable that returns the
  residuals (eq. 10) of fresh transitions of the true system under ``pi^k``;
* model-driven RL: :class:`mixedrl.noise.GaussianNoise` with the prior (eq. 55), ``collect=None``;
* oracle: :class:`mixedrl.noise.GaussianNoise` with the true noise, ``collect=None``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from mixedrl.checks import check_number, check_positive_int
from mixedrl.noise import NoiseSource
from mixedrl.pev import pev_step
from mixedrl.pim import pim_step

__all__ = [
    "Iteration",
    "PolicyIterationResult",
    "ibe_step",
    "policy_iteration",
]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Iteration:
    """One pass of Algorithm 1 (iteration ``k``).

    Attributes
    ----------
    k : int
        Iteration index.
    noise_mean : ndarray, shape (n,)
        ``mu_hat_k`` used by PEV and PIM at this iteration (after the IBE step).
    noise_cov : ndarray, shape (n, n)
        ``K_hat_k``.
    samples : int
        Total number of residuals the noise source has been given so far (0 for fixed sources).
    policy : object
        ``pi^k``, the policy that was evaluated.
    value : object
        ``V^k``, its value under the mixed model (eq. 21).
    next_policy : object
        ``pi^{k+1}`` from PIM (eq. 22).
    """

    k: int
    noise_mean: np.ndarray
    noise_cov: np.ndarray
    samples: int
    policy: Any
    value: Any
    next_policy: Any


@dataclass
class PolicyIterationResult:
    """Outcome of :func:`policy_iteration`: the last policy and value, and every :class:`Iteration`."""

    policy: Any
    value: Any
    history: list[Iteration] = field(default_factory=list)
    converged: bool = False


def ibe_step(noise: Any, residuals: np.ndarray | None) -> None:
    """Implements eq. (13) inside eq. (20): update the noise of the mixed model with new residuals.

    .. math:: [\\hat\\mu_k, \\hat K_k] = \\mathrm{IBE}(\\hat\\mu_{k-1}, \\hat K_{k-1}, \\xi^D_k)

    Parameters
    ----------
    noise : NoiseSource
        The noise source. When ``residuals`` is given it must learn (``learns = True``: an IBE).
    residuals : ndarray, shape (N, n), or None
        ``xi^D_j = x_{j+1} - f(x_j, u_j)`` (eq. 10) of the transitions collected at this iteration;
        ``None`` for a fixed noise source (model-driven RL, oracle): the step is then the identity.

    Raises
    ------
    ValueError
        ``residuals`` are given but ``noise`` does not learn (``learns`` false or missing); errors of
        the IBE's own input checks propagate unchanged (they leave the IBE state unchanged).
    """
    if residuals is None:
        return
    if not getattr(noise, "learns", False):
        raise ValueError("noise: residuals were collected but this noise source does not learn (not an IBE)")
    noise.update(residuals)


def policy_iteration(
    noise: NoiseSource,
    evaluate: Callable[[Any, Any], Any],
    improve: Callable[[Any, Any], Any],
    initial_policy: Any,
    iterations: int,
    collect: Callable[[Any, int], np.ndarray] | None = None,
    tol: float | None = None,
    callback: Callable[[Iteration], None] | None = None,
) -> PolicyIterationResult:
    """Implements Algorithm 1: repeat IBE -> PEV (eq. 21) -> PIM (eq. 22).

    .. math::
        [\\hat\\mu_k, \\hat K_k] = \\mathrm{IBE}(\\hat\\mu_{k-1}, \\hat K_{k-1}, \\xi^D_k),\\quad
        V^k = \\mathrm{PEV}(\\pi^k; \\hat\\xi_k),\\quad
        \\pi^{k+1} = \\mathrm{PIM}(V^k; \\hat\\xi_k)

    Parameters
    ----------
    noise : object
        Noise source, already initialised (an IBE starts at ``mu_hat_0 = mu_M``, ``K_hat_0 = K_M``).
        It is updated in place by the IBE step.
    evaluate : callable
        PEV, ``evaluate(policy, noise) -> value``.
    improve : callable
        PIM, ``improve(value, noise) -> policy``.
    initial_policy : object
        ``pi^0`` (must be admissible: for LQ, stabilising).
    iterations : int
        Maximum number of iterations (``>= 1``).
    collect : callable or None
        ``collect(policy, k) -> residuals`` of shape (N, n): eq. (10) on transitions of the true system
        under ``pi^k`` (mixed RL). ``None`` for a fixed noise source.
    tol : float or None
        Algorithm 1's stopping rule: stop when ``value.distance(previous value) <= tol`` and
        ``next_policy.distance(policy) <= tol`` (the representations must then have ``distance``).
        ``None`` runs all ``iterations`` (the default, used for mixed RL since the noise keeps changing).
    callback : callable or None
        Called with each :class:`Iteration` as soon as it is complete.

    Returns
    -------
    PolicyIterationResult
        ``policy`` = the last ``pi^{k+1}``, ``value`` = the last ``V^k``, ``history`` of every iteration.

    Raises
    ------
    ValueError
        ``iterations`` not a positive integer, ``tol`` negative, or propagated from a step.

    Notes
    -----
    The paper's stopping rule is kept but optional. ``samples`` in each :class:`Iteration` is read
    from ``noise.count`` when present (the IBE's number of residuals), else 0.
    """
    iterations = check_positive_int(iterations, "iterations")
    if tol is not None:
        check_number(tol, "tol", nonneg=True)
    policy = initial_policy
    history: list[Iteration] = []
    value = None
    for k in range(iterations):
        # IBE: [mu_k, K_k] = IBE(mu_{k-1}, K_{k-1}, xi^D_k)   (eq. 13, mixed model eq. 20)
        residuals = None if collect is None else collect(policy, k)
        ibe_step(noise, residuals)
        # PEV: V^k(x) = E_{xi_k}{ l(x', pi^k(x)) + gamma V^k(x') }   (eq. 21)
        new_value = pev_step(evaluate, policy, noise)
        # PIM: pi^{k+1}(x) = argmin_pi E_{xi_k}{ l(x', pi(x)) + gamma V^k(x') }   (eq. 22)
        next_policy = pim_step(improve, new_value, noise)
        record = Iteration(k=k, noise_mean=np.array(noise.mean, dtype=np.float64),
                           noise_cov=np.array(noise.cov, dtype=np.float64), samples=int(getattr(noise, "count", 0)),
                           policy=policy, value=new_value, next_policy=next_policy)
        history.append(record)
        if callback is not None:
            callback(record)
        logger.debug("iteration %d done (samples=%d)", k, record.samples)
        stop = tol is not None and value is not None and new_value.distance(value) <= tol and \
            next_policy.distance(policy) <= tol
        value, policy = new_value, next_policy
        if stop:
            return PolicyIterationResult(policy=policy, value=value, history=history, converged=True)
    return PolicyIterationResult(policy=policy, value=value, history=history)
