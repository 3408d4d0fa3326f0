"""Python's :mod:`math` functions mapped over float64 arrays (the bit-exact numpy backend).

numpy's vectorised transcendental functions may differ from the C library's in the last bit, so a
batched evaluation that must reproduce the Python-float environment bit for bit
(:func:`mixedrl.envs.evaluate_courses`; docs/reproduction.rst) uses :func:`elementwise` for them.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

__all__ = ["elementwise", "LibmOps"]


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
        first = np.asarray(arrays[0], dtype=np.float64)
        if len(arrays) > 1:
            cols = np.broadcast_arrays(first, *(np.asarray(a, dtype=np.float64) for a in arrays[1:]))
            first, lists = cols[0], [c.ravel().tolist() for c in cols]
        else:
            lists = [first.ravel().tolist()]
        return np.fromiter(map(f, *lists), dtype=np.float64, count=first.size).reshape(first.shape)

    g.__name__ = getattr(f, "__name__", "elementwise")
    g.__doc__ = f"{g.__name__} of :mod:`math`, element by element (bit-identical to the Python-float call)."
    return g


class LibmOps:
    """The operations the vehicle and the reference need, on float64 arrays, bit-identical to :mod:`math`
    on each element."""

    atan2 = staticmethod(elementwise(math.atan2))
    tan = staticmethod(elementwise(math.tan))
    sin = staticmethod(elementwise(math.sin))
    cos = staticmethod(elementwise(math.cos))
    tanh = staticmethod(elementwise(math.tanh))
    atan = staticmethod(elementwise(math.atan))
    clip = staticmethod(np.clip)
