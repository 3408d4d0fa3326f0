"""The random longitudinal disturbance of the double lane change: ``F_dis`` (eq. 53) and its laws.

:class:`Disturbance` is the true force the environments draw from; a run holds it as
``task.disturbance``. Its noise on ``v_x`` is ``xi = F_dis T / m`` (eq. 54).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from mixedrl.checks import check_fields

__all__ = ["DISTURBANCE_LAWS", "Disturbance"]

#: Laws of the true disturbance, all with the configured mean and variance (:class:`Disturbance`); the
#: double lane change simulates all three, the linear task only ``"gaussian"``.
DISTURBANCE_LAWS = ("gaussian", "student_t", "bumps")


@dataclass(frozen=True)
class Disturbance:
    """Random longitudinal disturbance force ``F_dis`` (eq. 53) and its noise ``xi = F_dis T / m`` (eq. 54).

    Attributes
    ----------
    law : str
        Distribution of ``F_dis`` around its mean, one of :data:`DISTURBANCE_LAWS` (see Notes). Default
        ``"gaussian"`` (the paper's).
    mean : float
        Mean force on a level road [N]. Paper: 261.
    variance : float
        Variance of ``F_dis`` [N^2]. Paper: 32.
    dof : float
        Degrees of freedom ``nu`` of the ``"student_t"`` law (> 2, so that the variance is finite);
        ignored by the other laws. Default 3.
    grade_amplitude : float
        Amplitude of an optional road grade angle [rad]; 0 (default) gives the paper's constant mean.
    grade_wavelength : float
        Wavelength of the grade along ``X`` [m]. Default 40.
    grade_phase : float
        Phase of the grade [rad]. Default 0.

    Raises
    ------
    ValueError
        An unknown ``law`` (the message lists the allowed ones), non-finite fields, a negative
        variance, a non-positive wavelength, or ``dof <= 2``.

    Notes
    -----
    With a road grade ``theta(X) = grade_amplitude * sin(2 pi X / grade_wavelength + grade_phase)`` the
    mean force is ``mean - m g sin(theta(X))``, at the state before the step (a state-dependent mean for
    Case 3, eq. 19). Independent across steps,

    .. math:: F_{dis} = \\bar F(X) + \\sigma z, \\qquad E z = 0, \\quad \\mathrm{Var}\\, z = 1,

    with the law's standardised draw ``z`` (:meth:`standard_noise`; the laws' table: docs/vehicle.rst). The
    planners model the noise as a Gaussian whatever the law.
    """

    law: str = "gaussian"
    mean: float = 261.0
    variance: float = 32.0
    dof: float = 3.0
    grade_amplitude: float = 0.0
    grade_wavelength: float = 40.0
    grade_phase: float = 0.0

    def __post_init__(self) -> None:
        if self.law not in DISTURBANCE_LAWS:
            raise ValueError(f"law: expected one of {DISTURBANCE_LAWS}, got {self.law!r}")
        check_fields(self, positive=("grade_wavelength",), nonneg=("variance",))
        if not self.dof > 2.0:
            raise ValueError(f"dof: expected a number > 2 (the Student-t variance is finite only then), "
                             f"got {self.dof!r}")

    @property
    def std(self) -> float:
        """Standard deviation of ``F_dis`` [N] (every law)."""
        return math.sqrt(self.variance)

    def standard_noise(self, generator: torch.Generator | np.random.Generator | None,
                       shape: tuple[int, ...] | None = None, *, dtype: torch.dtype = torch.float64,
                       device: str | torch.device = "cpu") -> Any:
        """Draw the law's standardised noise ``z`` (mean 0, variance 1; class Notes) from ``generator``.

        Parameters
        ----------
        generator : torch.Generator, numpy.random.Generator or None
            A :class:`torch.Generator` (or None: torch's global generator) draws a tensor; a
            :class:`numpy.random.Generator` draws a numpy array (or a float when ``shape`` is None).
        shape : tuple of int, optional
            Shape of the draw; None draws one float (numpy generators only).
        dtype, device
            Of a torch draw.

        Returns
        -------
        torch.Tensor, numpy.ndarray or float
            ``z``, of shape ``shape``.

        Raises
        ------
        ValueError
            ``generator`` is neither a torch nor a numpy generator, or ``shape`` is None with a torch one.

        Notes
        -----
        On torch the Student-t draw uses Bailey's polar method (torch has no Student-t sampler that
        takes a generator); the two-point law draws one uniform per state.
        """
        scale = math.sqrt((self.dof - 2.0) / self.dof)  # "student_t": z = t sqrt((nu - 2) / nu), variance 1
        if generator is None or isinstance(generator, torch.Generator):
            if shape is None:
                raise ValueError("shape: a torch draw needs a shape")
            if self.law == "gaussian":
                return torch.randn(tuple(shape), generator=generator, dtype=dtype, device=device)
            n = math.prod(shape)
            if self.law == "student_t":
                z = _student_t_torch(self.dof, n, generator, device) * scale
            else:  # "bumps": z = -1 or +1 with probability 1/2 each
                z = torch.where(torch.rand(n, generator=generator, dtype=torch.float64, device=device) < 0.5,
                                -1.0, 1.0).to(torch.float64)
            return z.reshape(tuple(shape)).to(dtype)
        if not isinstance(generator, np.random.Generator):
            raise ValueError(f"generator: expected a torch.Generator or a numpy.random.Generator, got "
                             f"{type(generator).__name__}")
        if self.law == "gaussian":
            return generator.standard_normal(shape)
        if self.law == "student_t":
            return generator.standard_t(self.dof, shape) * scale
        u = generator.random(shape)
        return (-1.0 if u < 0.5 else 1.0) if shape is None else np.where(u < 0.5, -1.0, 1.0)

    def mean_force(self, X: Any, m: float, g: float) -> Any:
        """Mean disturbance force at longitudinal position ``X`` [N].

        Parameters
        ----------
        X : float, numpy.ndarray or torch.Tensor, shape (...)
            Longitudinal position [m].
        m, g : float
            Vehicle mass [kg] and gravity [m/s^2].

        Returns
        -------
        float, numpy.ndarray or torch.Tensor, shape (...)
            ``mean - m g sin(theta(X))``; a float ``mean`` when there is no grade.
        """
        if self.grade_amplitude == 0.0:
            if isinstance(X, torch.Tensor):
                return torch.full_like(X, self.mean)
            if isinstance(X, np.ndarray):
                return np.full_like(X, self.mean, dtype=np.float64)
            return self.mean
        ops = torch if isinstance(X, torch.Tensor) else (np if isinstance(X, np.ndarray) else math)
        theta = self.grade_amplitude * ops.sin(2.0 * math.pi / self.grade_wavelength * X + self.grade_phase)
        return self.mean - m * g * ops.sin(theta)


def _student_t_torch(dof: float, n: int, generator: torch.Generator | None, device: str | torch.device
                     ) -> torch.Tensor:
    """``n`` Student-t draws with ``dof`` degrees of freedom (float64), Bailey's polar method
    (R. W. Bailey, Math. Comp. 62 (1994) 779-781)."""
    out = torch.empty(n, dtype=torch.float64, device=device)
    filled = 0
    while filled < n:
        need = n - filled
        # (U, V) uniform in the square, kept when inside the unit disc (probability pi / 4)
        uv = 2.0 * torch.rand(need + need // 3 + 16, 2, generator=generator, dtype=torch.float64, device=device) - 1.0
        w = (uv * uv).sum(dim=-1)
        keep = (w > 0.0) & (w <= 1.0)
        u, w = uv[keep, 0], w[keep]
        # t = U sqrt(nu (W^(-2/nu) - 1) / W)   (Bailey 1994)
        t = u * torch.sqrt(dof * (w.pow(-2.0 / dof) - 1.0) / w)
        take = min(need, t.numel())
        out[filled:filled + take] = t[:take]
        filled += take
    return out

