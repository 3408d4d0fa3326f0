"""A task's rest point and the LQ problem it linearises to: :class:`Equilibrium`, :class:`Linearisation` and
:func:`cost_hessian` (re-exported by :mod:`mixedrl.tasks`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
import torch

__all__ = ["EQUILIBRIUM_ATOL", "Equilibrium", "Linearisation", "cost_hessian"]


#: Largest ``|f(s*, u*) - s*|`` and ``|grad l|`` (relative to the state's and the cost's scale) accepted at an
#: equilibrium (float64 round-off).
EQUILIBRIUM_ATOL = 1e-9


@dataclass(frozen=True)
class Equilibrium:
    """A rest point of the noise-free model: ``f(state, action) = state`` (:meth:`mixedrl.task_base.Task.equilibrium`).

    Attributes
    ----------
    state : numpy.ndarray, shape (state_dim,)
        ``s*``, float64.
    action : numpy.ndarray, shape (action_dim,)
        ``u*``, float64.
    """

    state: np.ndarray
    action: np.ndarray


@dataclass(frozen=True)
class Linearisation:
    """The discounted LQ problem of a task at an equilibrium (:meth:`mixedrl.task_base.Task.linearisation`).

    In the coordinates ``x`` of the linearisation (``x = s - s*`` unless the task says otherwise) and
    ``v = u - u*``,

    .. math:: x' = A x + B v + E \\xi, \\qquad l(x', v) = x'^\\top Q x' + v^\\top R v,\\qquad \\gamma,

    the next-state convention of eq. (2) (EQUATIONS.md, last section). Item access ``lin["A"]`` works for
    the keys ``A``, ``B``, ``Q``, ``R``, ``E``, ``gamma``.

    The fields (float64 arrays): ``A`` (n, n), ``B`` (n, action_dim), ``Q`` (n, n, symmetric PSD), ``R``
    (action_dim, action_dim, symmetric positive definite), ``E`` (n, noise_dim: how ``xi`` enters ``x``), the
    task's ``gamma``, ``state`` (the task state at ``x = 0``, ``s*``) and ``action`` (``u*``); ``embed`` maps
    ``x`` (B, n) torch float64 to task states (B, state_dim), by default ``s* + x`` (then ``n = state_dim``).
    """

    A: np.ndarray
    B: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    E: np.ndarray
    gamma: float
    state: np.ndarray
    action: np.ndarray
    embed: Callable[[torch.Tensor], torch.Tensor] | None = field(default=None, compare=False)

    _KEYS = ("A", "B", "Q", "R", "E", "gamma")

    def __getitem__(self, key: str) -> Any:
        if key not in self._KEYS:
            raise KeyError(f"key: expected one of {list(self._KEYS)}, got {key!r}")
        return getattr(self, key)

    def to_state(self, x: torch.Tensor) -> torch.Tensor:
        """Task states of the coordinates ``x`` (B, n) -> (B, state_dim), float64 (differentiable)."""
        if self.embed is not None:
            return self.embed(x)
        return torch.as_tensor(self.state, dtype=torch.float64) + x


def cost_hessian(cost: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], x0: torch.Tensor, u0: torch.Tensor,
                 name: str, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """``Q = l_xx / 2``, ``R = l_uu / 2`` of a batched cost ``l(x', u)`` at ``(x0, u0)`` (float64, ``torch.func``),
    after checking that the gradient and the cross term ``l_xu`` vanish there.

    The quadratic part of a linearisation (:meth:`mixedrl.task_base.Task.linearisation`).

    Parameters
    ----------
    cost : callable
        ``l(x', u)``: next states (B, n) and actions (B, m), torch float64 -> (B,); differentiable.
    x0 : torch.Tensor, shape (n,)
        The next state of the expansion point, float64.
    u0 : torch.Tensor, shape (m,)
        The action of the expansion point, float64.
    name : str
        The task class's name, for the error messages.
    scale : float
        Typical magnitude of the state (``1 + max |s*|``); the tolerances are :data:`EQUILIBRIUM_ATOL` times
        ``1 + max |H| * scale``.

    Returns
    -------
    Q : numpy.ndarray, shape (n, n)
        Half the (symmetrised) Hessian in ``x'``.
    R : numpy.ndarray, shape (m, m)
        Half the (symmetrised) Hessian in ``u``.

    Raises
    ------
    ValueError
        The gradient of the cost at ``(x0, u0)`` is not zero, or the Hessian couples ``x'`` and ``u``; the
        message starts with ``cost:`` and names ``name.cost``.
    """
    n = x0.shape[0]

    def stage(z: torch.Tensor) -> torch.Tensor:
        return cost(z[None, :n], z[None, n:])[0]

    z0 = torch.cat([x0, u0])
    grad = torch.func.jacrev(stage)(z0)
    H = torch.func.hessian(stage)(z0)
    H = 0.5 * (H + H.T)
    cost_scale = 1.0 + float(H.abs().max()) * scale
    if float(grad.abs().max()) > EQUILIBRIUM_ATOL * cost_scale:
        raise ValueError(f"cost: {name}.cost has a nonzero gradient {grad.tolist()} at the equilibrium (the LQ "
                         f"yardstick needs the cost's minimum there)")
    if float(H[:n, n:].abs().max()) > EQUILIBRIUM_ATOL * cost_scale:
        raise ValueError(f"cost: {name}.cost couples the next state and the action at the equilibrium (the LQ form "
                         f"l = x'^T Q x' + u^T R u has no cross term)")
    return 0.5 * H[:n, :n].numpy(), 0.5 * H[n:, n:].numpy()
