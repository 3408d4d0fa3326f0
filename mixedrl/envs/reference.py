"""The double-lane-change reference path ``Y_ref(X)``, ``psi_ref(X)``.

The paper gives none; this is the tanh double lane change of the predictive-steering literature,

.. math::

    Y_{ref}(X) = \\frac{d_{y1}}{2}\\,(1 + \\tanh z_1) - \\frac{d_{y2}}{2}\\,(1 + \\tanh z_2), \\quad
    z_i = \\frac{s}{l_i}\\,(X - X_i) - \\frac{s}{2}, \\quad
    \\psi_{ref}(X) = \\arctan \\frac{dY_{ref}}{dX},

with the fields of :class:`DoubleLaneChangeReference` (docs/vehicle.rst).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

from mixedrl.checks import check_fields
from mixedrl.envs.libm import LibmOps, ops_for

__all__ = ["DoubleLaneChangeReference", "LibmReference"]


@dataclass(frozen=True)
class DoubleLaneChangeReference:
    """Tanh double-lane-change path in the road-fixed frame (``X`` forward, ``Y`` to the left).

    Attributes
    ----------
    dy1 : float
        Lateral offset of the first lane change [m] (to the left). Default 4.05.
    dy2 : float
        Lateral offset of the second lane change [m] (to the right). Default 5.7.
    x1 : float
        Start of the first transition [m]. Default 27.19.
    x2 : float
        Start of the second transition [m]. Default 56.46.
    len1 : float
        Length of the first transition [m]. Default 25.
    len2 : float
        Length of the second transition [m]. Default 21.95.
    shape : float
        Steepness ``s`` of the tanh transitions [-]. Default 2.4 (``z_i`` then runs from ``-s/2`` to
        ``s/2`` over each transition).

    Raises
    ------
    ValueError
        If a field is not finite, or a length or ``shape`` is not positive.
    """

    dy1: float = 4.05
    dy2: float = 5.7
    x1: float = 27.19
    x2: float = 56.46
    len1: float = 25.0
    len2: float = 21.95
    shape: float = 2.4

    def __post_init__(self) -> None:
        check_fields(self, positive=("len1", "len2", "shape"))

    def _ops(self, X: Any) -> Any:
        return ops_for(X)

    def _terms(self, X: Any) -> tuple[Any, Any, Any]:
        """``(ops, Y_ref(X), dY_ref/dX)`` from one evaluation of the tanh terms."""
        ops = self._ops(X)
        k1 = self.shape / self.len1
        k2 = self.shape / self.len2
        # z1 = 2.4/25 (X - 27.19) - 1.2 ;  z2 = 2.4/21.95 (X - 56.46) - 1.2
        th1 = ops.tanh(k1 * (X - self.x1) - 0.5 * self.shape)
        th2 = ops.tanh(k2 * (X - self.x2) - 0.5 * self.shape)
        # Y_ref = dy1/2 (1 + tanh z1) - dy2/2 (1 + tanh z2)
        lateral = 0.5 * self.dy1 * (1.0 + th1) - 0.5 * self.dy2 * (1.0 + th2)
        # dY_ref/dX = dy1/2 (s/l1)(1 - tanh^2 z1) - dy2/2 (s/l2)(1 - tanh^2 z2)
        slope = (0.5 * self.dy1 * self.shape / self.len1 * (1.0 - th1 * th1)
                 - 0.5 * self.dy2 * self.shape / self.len2 * (1.0 - th2 * th2))
        return ops, lateral, slope

    def lateral(self, X: Any) -> Any:
        """Reference lateral position ``Y_ref(X)`` [m].

        Parameters
        ----------
        X : float, numpy.ndarray or torch.Tensor, shape (...)
            Longitudinal position [m].

        Returns
        -------
        float, numpy.ndarray or torch.Tensor, shape (...)
            ``Y_ref(X) = dy1/2 (1 + tanh z1) - dy2/2 (1 + tanh z2)``.
        """
        return self._terms(X)[1]

    def slope(self, X: Any) -> Any:
        """Path slope ``dY_ref/dX`` [-] (analytic derivative of :meth:`lateral`).

        Parameters
        ----------
        X : float, numpy.ndarray or torch.Tensor, shape (...)
            Longitudinal position [m].

        Returns
        -------
        float, numpy.ndarray or torch.Tensor, shape (...)
            ``dy1/2 (s/l1)(1 - tanh^2 z1) - dy2/2 (s/l2)(1 - tanh^2 z2)``.
        """
        return self._terms(X)[2]

    def lateral_and_heading(self, X: Any) -> tuple[Any, Any]:
        """``(Y_ref(X), psi_ref(X))`` from one evaluation of the tanh terms, each of the shape of ``X``."""
        ops, lateral, slope = self._terms(X)
        return lateral, ops.atan(slope)

    def rows(self) -> "LibmReference":
        """This reference on float64 arrays, bit-identical to its Python-float values (:class:`LibmReference`)."""
        return LibmReference(*(getattr(self, f.name) for f in fields(self)))

    def heading(self, X: Any) -> Any:
        """Reference heading ``psi_ref(X) = atan(dY_ref/dX)`` [rad].

        Parameters
        ----------
        X : float, numpy.ndarray or torch.Tensor, shape (...)
            Longitudinal position [m].

        Returns
        -------
        float, numpy.ndarray or torch.Tensor, shape (...)
            Reference heading, same type and shape as ``X``.
        """
        return self.lateral_and_heading(X)[1]


@dataclass(frozen=True)
class LibmReference(DoubleLaneChangeReference):
    """A :class:`DoubleLaneChangeReference` on float64 arrays with :mod:`math`'s ``tanh`` and ``atan``
    element by element (:class:`mixedrl.envs.libm.LibmOps`), so each element equals the Python-float
    value; it stands in for the reference in :mod:`mixedrl.envs.columns`."""

    def _ops(self, X: Any) -> Any:
        return LibmOps
