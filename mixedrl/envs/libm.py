"""The backends of the vehicle and reference formulas: Python floats, numpy, torch, and :mod:`math` mapped
over float64 arrays (the bit-exact numpy backend).

numpy's vectorised transcendental functions may differ from the C library's in the last bit, so a
batched evaluation that must reproduce the Python-float environment bit for bit
(:func:`mixedrl.envs.evaluate_courses`; docs/reproduction.rst) uses :func:`elementwise` for them.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np
import torch

__all__ = ["elementwise", "LibmOps", "MathOps", "NumpyOps", "TorchOps", "ops_for"]


def elementwise(f: Callable[..., float]) -> Callable[..., np.ndarray]:
    """``f`` (a function of Python floats) applied element by element to float64 arrays of one shape.

    Parameters
    ----------
    f : callable
        A :mod:`math` function of one or more floats.

    Returns
    -------
    callable
        ``g(*arrays) -> numpy.ndarray`` of the arrays' (broadcast) shape, ``g(x)[i] == f(x[i])`` exactly.
    """

    def g(*arrays: np.ndarray) -> np.ndarray:
        cols = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in arrays))
        return np.fromiter(map(f, *(c.ravel().tolist() for c in cols)), dtype=np.float64,
                           count=cols[0].size).reshape(cols[0].shape)

    g.__name__ = getattr(f, "__name__", "elementwise")
    g.__doc__ = f"{g.__name__} of :mod:`math`, element by element (bit-identical to the Python-float call)."
    return g


class MathOps:
    """The operations on Python floats (:mod:`math`)."""

    atan2, tan, sin, cos, tanh, atan = (staticmethod(getattr(math, n)) for n in ("atan2", "tan", "sin", "cos",
                                                                                "tanh", "atan"))

    @staticmethod
    def clip(x: float, lo: float, hi: float) -> float:
        return lo if x < lo else (hi if x > hi else x)


class NumpyOps:
    """The operations on numpy arrays, with ``columns`` (the last axis split) and ``stack`` (its inverse)."""

    atan2, tan, sin, cos, tanh, atan, clip = (staticmethod(f) for f in (np.arctan2, np.tan, np.sin, np.cos, np.tanh,
                                                                         np.arctan, np.clip))
    columns = staticmethod(lambda x: tuple(np.moveaxis(x, -1, 0)))
    stack = staticmethod(lambda cols: np.stack(np.broadcast_arrays(*cols), axis=-1))


class TorchOps:
    """The operations on torch tensors, with ``columns`` and ``stack`` as :class:`NumpyOps`."""

    atan2, tan, sin, cos, tanh, atan, clip = (staticmethod(f) for f in (torch.atan2, torch.tan, torch.sin, torch.cos,
                                                                         torch.tanh, torch.atan, torch.clamp))
    columns = staticmethod(lambda x: x.unbind(-1))
    stack = staticmethod(lambda cols: torch.stack(torch.broadcast_tensors(*cols), dim=-1))


def ops_for(x: Any) -> Any:
    """The backend of ``x``: torch for a tensor, numpy for an array, :mod:`math` otherwise."""
    if isinstance(x, torch.Tensor):
        return TorchOps
    return NumpyOps if isinstance(x, np.ndarray) else MathOps


class LibmOps(NumpyOps):
    """The operations the vehicle and the reference need, on float64 arrays, bit-identical to :mod:`math`
    on each element."""

    atan2, tan, sin, cos, tanh, atan = (staticmethod(elementwise(getattr(math, n)))
                                        for n in ("atan2", "tan", "sin", "cos", "tanh", "atan"))
