"""Vehicle body dynamics of the double-lane-change task: eq. (53) with the Fiala tire (docs/vehicle.rst).

One formula, evaluated on Python floats, numpy arrays and torch tensors, so the environment and the
planning model share ``f``; it takes the state ``x = [v_y, r, v_x, phi, y]`` or the tracking state
``s = [v_y, r, v_x, phi, Y, X]`` (with ``dX/dt = v_x cos(phi) - v_y sin(phi)``) and ``u = [delta, a_x]``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Callable, overload

import numpy as np
import torch

from mixedrl.checks import check_fields, check_finite, check_number
from mixedrl.envs.libm import LibmOps, MathOps, TorchOps, ops_for

__all__ = ["VehicleParams", "VehicleDynamics", "fiala_lateral_force", "STATE_NAMES", "TRACKING_STATE_NAMES",
           "ACTION_NAMES", "VX_INDEX"]

logger = logging.getLogger(__name__)

#: Names of the paper's state components (eq. 53), in order.
STATE_NAMES = ("v_y", "r", "v_x", "phi", "y")
#: Names of the tracking state (eq. 53 plus the longitudinal position ``X``), in order.
TRACKING_STATE_NAMES = ("v_y", "r", "v_x", "phi", "Y", "X")
#: Names of the input components (eq. 53), in order.
ACTION_NAMES = ("delta", "a_x")
#: Index of ``v_x``: the component on which the disturbance ``F_dis / m`` acts.
VX_INDEX = 2


@dataclass(frozen=True)
class VehicleParams:
    """Vehicle and tire parameters of the paper's experiment (Section "Numerical Experiments").

    Attributes
    ----------
    m : float
        Vehicle mass [kg]. Paper: 1500.
    I_z : float
        Yaw moment of inertia about the centre of gravity [kg m^2]. Paper: 2420 (printed as N/rad).
    a : float
        Distance from the centre of gravity to the front axle [m]. Paper: 1.14.
    b : float
        Distance from the centre of gravity to the rear axle [m]. Paper: 1.40.
    C_f : float
        Front axle cornering stiffness [N/rad]. Paper: 88000.
    C_r : float
        Rear axle cornering stiffness [N/rad]. Paper: 94000.
    mu : float
        Tire-road friction coefficient [-]. Paper: 1.0.
    g : float
        Gravitational acceleration [m/s^2] for the static axle loads (not in the paper). 9.81.

    Raises
    ------
    ValueError
        If a parameter is not a finite positive number (the message starts with its name).
    """

    m: float = 1500.0
    I_z: float = 2420.0
    a: float = 1.14
    b: float = 1.40
    C_f: float = 88000.0
    C_r: float = 94000.0
    mu: float = 1.0
    g: float = 9.81

    def __post_init__(self) -> None:
        check_fields(self, positive=True)

    @property
    def L(self) -> float:
        """Wheelbase ``a + b`` [m]."""
        return self.a + self.b

    @property
    def F_zf(self) -> float:
        """Static front axle load ``m g b / (a + b)`` [N]."""
        return self.m * self.g * self.b / self.L

    @property
    def F_zr(self) -> float:
        """Static rear axle load ``m g a / (a + b)`` [N]."""
        return self.m * self.g * self.a / self.L


def _tire(C: float, mu: float, F_z: float) -> tuple[float, float, float, float]:
    """Fiala coefficients of one axle, ``(C, c2, c3, alpha_sl)``: ``F = -C t + c2 |t| t - c3 t^3``,
    ``t = tan(clip(alpha, +-alpha_sl))``."""
    return C, C * C / (3.0 * mu * F_z), C**3 / (27.0 * mu * mu * F_z * F_z), math.atan(3.0 * mu * F_z / C)


def _fiala(ops: Any, alpha: Any, tire: tuple[float, float, float, float]) -> Any:
    C, c2, c3, alpha_sl = tire
    # Clipping to +-alpha_sl gives the piecewise law exactly (zero slope there), with no branch.
    t = ops.tan(ops.clip(alpha, -alpha_sl, alpha_sl))
    # F_y = -C tan(a) + C^2 / (3 mu F_z) |tan(a)| tan(a) - C^3 / (27 mu^2 F_z^2) tan(a)^3
    return t * (-C + c2 * abs(t) - c3 * t * t)


def fiala_lateral_force(alpha: np.ndarray | torch.Tensor | float, C: float, mu: float, F_z: float
                        ) -> np.ndarray | torch.Tensor | float:
    """Fiala lateral tire force (Hsu 2009), as used in eq. (53).

    .. math::

        F_y(\\alpha) = \\begin{cases}
            -C \\tan\\alpha + \\dfrac{C^2}{3 \\mu F_z} |\\tan\\alpha| \\tan\\alpha
            - \\dfrac{C^3}{27 \\mu^2 F_z^2} \\tan^3\\alpha, & |\\alpha| < \\alpha_{sl}, \\\\
            -\\mu F_z \\operatorname{sign}\\alpha, & |\\alpha| \\ge \\alpha_{sl},
        \\end{cases}
        \\qquad \\alpha_{sl} = \\arctan\\frac{3 \\mu F_z}{C}.

    Parameters
    ----------
    alpha : float, numpy.ndarray or torch.Tensor, shape (...)
        Slip angle [rad], any shape.
    C : float
        Cornering stiffness [N/rad], > 0.
    mu : float
        Friction coefficient [-], > 0.
    F_z : float
        Normal load [N], > 0.

    Returns
    -------
    float, numpy.ndarray or torch.Tensor, shape (...)
        Lateral force [N], same type and shape as ``alpha``.

    Raises
    ------
    ValueError
        If ``C``, ``mu`` or ``F_z`` is not a finite positive number.

    Examples
    --------
    >>> from mixedrl.envs.vehicle import fiala_lateral_force
    >>> round(float(fiala_lateral_force(1.0, C=88000.0, mu=1.0, F_z=8000.0)), 6)  # saturated: -mu F_z
    -8000.0
    """
    for name, value in (("C", C), ("mu", mu), ("F_z", F_z)):
        check_number(value, name, positive=True)
    if isinstance(alpha, np.ndarray):
        alpha = alpha.astype(np.float64, copy=False)
    elif not isinstance(alpha, torch.Tensor):
        alpha = float(alpha)
    return _fiala(ops_for(alpha), alpha, _tire(float(C), float(mu), float(F_z)))


ArrayLike = Any


class VehicleDynamics:
    """Eq. (53) with the Fiala tire, in continuous time and discretised with step ``dt``.

    Parameters
    ----------
    params : VehicleParams, optional
        Vehicle parameters; default: the paper's values.
    dt : float, optional
        Sampling time ``T`` [s]; the paper uses ``1/200``.
    scheme : {"euler", "rk4"}, optional
        Discretisation of the deterministic part ``f`` (see :meth:`__call__`). Default ``"euler"``.
    compile : bool, optional
        If True, the batched torch step ``__call__`` is fused with :func:`torch.compile` at the first
        torch call; it returns a non-contiguous ``(..., n)`` view. On failure a warning is logged and the
        eager code is used. Default False.

    Raises
    ------
    ValueError
        If ``params`` is not a :class:`VehicleParams`, ``dt`` is not finite positive, or ``scheme`` is
        unknown.
    """

    def __init__(self, params: VehicleParams | None = None, dt: float = 1.0 / 200.0, scheme: str = "euler",
                 compile: bool = False) -> None:
        params = VehicleParams() if params is None else params
        if not isinstance(params, VehicleParams):
            raise ValueError(f"params: expected VehicleParams, got {type(params).__name__}")
        check_number(dt, "dt", positive=True)
        if scheme not in ("euler", "rk4"):
            raise ValueError(f"scheme: expected 'euler' or 'rk4', got {scheme!r}")
        self.params = params
        self.dt = float(dt)
        self.scheme = scheme
        self.compile = bool(compile)
        self._k = (params.a, params.b, 1.0 / params.m, 1.0 / params.I_z, _tire(params.C_f, params.mu, params.F_zf),
                   _tire(params.C_r, params.mu, params.F_zr))
        self._compiled: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None
        self._compile_failed = False

    def __repr__(self) -> str:
        return (f"VehicleDynamics(params={self.params!r}, dt={self.dt!r}, scheme={self.scheme!r}, "
                f"compile={self.compile})")

    # --- validation ---
    def _prepare(self, x: Any, u: Any, f_dis: Any) -> tuple[Any, Any, Any]:
        is_torch = isinstance(x, torch.Tensor)
        if is_torch or isinstance(u, torch.Tensor):
            if not (is_torch and isinstance(u, torch.Tensor)):
                raise ValueError("x: x and u must both be torch tensors or both be numpy arrays")
            if not x.is_floating_point():
                raise ValueError(f"x: expected a floating-point tensor, got {x.dtype}")
            if u.dtype != x.dtype:
                raise ValueError(f"u: dtype {u.dtype} differs from x's dtype {x.dtype}")
        else:
            x = np.asarray(x, dtype=np.float64)
            u = np.asarray(u, dtype=np.float64)
        if x.ndim < 1 or x.shape[-1] not in (5, 6):
            raise ValueError(f"x: expected shape (..., 5) or (..., 6), got {tuple(x.shape)}")
        if u.ndim < 1 or u.shape[-1] != 2:
            raise ValueError(f"u: expected shape (..., 2), got {tuple(u.shape)}")
        if is_torch:
            if isinstance(f_dis, torch.Tensor) and f_dis.dtype != x.dtype:
                raise ValueError(f"f_dis: dtype {f_dis.dtype} differs from x's dtype {x.dtype}")
            return x, u, f_dis
        check_finite(x, "x")
        check_finite(u, "u")
        f_dis = np.asarray(f_dis, dtype=np.float64)
        check_finite(f_dis, "f_dis")
        return x, u, f_dis

    # --- continuous time ---
    def _rhs(self, ops: Any, cols: tuple[Any, ...], delta: Any, ax: Any, f_dis: Any) -> tuple[Any, ...]:
        """Right-hand side of eq. (53) (plus ``dX/dt`` for 6 columns) on one backend (:meth:`derivatives`)."""
        a, b, inv_m, inv_iz, front, rear = self._k
        vy, r, vx, phi = cols[:4]
        # alpha_f = atan((v_y + a r) / v_x) - delta ;  alpha_r = atan((v_y - b r) / v_x)   (atan2 == atan for v_x > 0)
        alpha_f = ops.atan2(vy + a * r, vx) - delta
        alpha_r = ops.atan2(vy - b * r, vx)
        fyf = _fiala(ops, alpha_f, front)
        fyr = _fiala(ops, alpha_r, rear)
        cos_d, sin_d, cos_p, sin_p = ops.cos(delta), ops.sin(delta), ops.cos(phi), ops.sin(phi)
        fyf_cos = fyf * cos_d
        d = ((fyf_cos + fyr) * inv_m - vx * r,  # dv_y/dt = (F_yf cos(delta) + F_yr) / m - v_x r
             (a * fyf_cos - b * fyr) * inv_iz,  # dr/dt = (a F_yf cos(delta) - b F_yr) / I_z
             # dv_x/dt = a_x + v_y r - F_yf sin(delta) / m + F_dis / m
             ax + vy * r - fyf * sin_d * inv_m + f_dis * inv_m,
             r,  # dphi/dt = r
             vx * sin_p + vy * cos_p,  # dy/dt = v_x sin(phi) + v_y cos(phi)
             # dX/dt = v_x cos(phi) - v_y sin(phi)   (road-fixed longitudinal position; not part of eq. 53)
             vx * cos_p - vy * sin_p)
        return d if len(cols) == 6 else d[:5]

    @overload
    def derivatives(self, x: torch.Tensor, u: torch.Tensor, f_dis: float | torch.Tensor = 0.0) -> torch.Tensor: ...
    @overload
    def derivatives(self, x: np.ndarray, u: np.ndarray, f_dis: float | np.ndarray = 0.0) -> np.ndarray: ...

    def derivatives(self, x: ArrayLike, u: ArrayLike, f_dis: ArrayLike = 0.0) -> ArrayLike:
        """Time derivative of the state: implements eq. (53) with the Fiala tire.

        .. math::

            \\dot x = \\begin{bmatrix}
                (F_{yf}\\cos\\delta + F_{yr}) / m - v_x r \\\\
                (a F_{yf}\\cos\\delta - b F_{yr}) / I_z \\\\
                a_x + v_y r - F_{yf}\\sin\\delta / m + F_{dis} / m \\\\
                r \\\\
                v_x \\sin\\phi + v_y \\cos\\phi
            \\end{bmatrix},
            \\quad
            \\begin{aligned}
            F_{yf} &= F_y^{\\rm Fiala}(\\alpha_f;\\, C_f, \\mu, F_{zf}),&
            \\alpha_f &= \\arctan\\frac{v_y + a r}{v_x} - \\delta, \\\\
            F_{yr} &= F_y^{\\rm Fiala}(\\alpha_r;\\, C_r, \\mu, F_{zr}),&
            \\alpha_r &= \\arctan\\frac{v_y - b r}{v_x},
            \\end{aligned}

        with :func:`fiala_lateral_force` and, for a 6-component tracking state, the extra row
        :math:`\\dot X = v_x \\cos\\phi - v_y \\sin\\phi`.

        Parameters
        ----------
        x : numpy.ndarray or torch.Tensor, shape (..., 5) or (..., 6)
            State ``[v_y, r, v_x, phi, y]`` or tracking state ``[v_y, r, v_x, phi, Y, X]``.
        u : numpy.ndarray or torch.Tensor, shape (..., 2)
            Input ``[delta, a_x]`` [rad, m/s^2]; leading dimensions broadcast against ``x``'s.
        f_dis : float, numpy.ndarray or torch.Tensor, shape () or (...), optional
            Longitudinal disturbance force ``F_dis`` [N]; default 0 (the deterministic part).

        Returns
        -------
        numpy.ndarray or torch.Tensor, shape (..., 5) or (..., 6)
            ``dx/dt`` in the units of ``x`` per second; same backend and dtype as ``x``.

        Raises
        ------
        ValueError
            Wrong last dimension; ``x`` and ``u`` of different backends or dtypes; a non-floating tensor;
            NaN/inf on the numpy path (on torch, NaN propagates).

        Notes
        -----
        ``atan`` is computed as ``atan2``, equal for ``v_x > 0``; the model is meaningless for
        ``v_x <= 0``. Normal loads are static (no load transfer), as in the paper.
        """
        x, u, f_dis = self._prepare(x, u, f_dis)
        ops = ops_for(x)
        return ops.stack(self._rhs(ops, ops.columns(x), u[..., 0], u[..., 1], f_dis))

    # --- discrete time ---
    def _step_cols(self, ops: Any, cols: tuple[Any, ...], delta: Any, ax: Any) -> tuple[Any, ...]:
        dt = self.dt
        if self.scheme == "euler":
            # x_{t+1} = x_t + T * xdot(x_t, u_t)   (forward Euler; F_dis enters as T F_dis / m = xi, eq. 54)
            d = self._rhs(ops, cols, delta, ax, 0.0)
            return tuple(c + dt * dc for c, dc in zip(cols, d))
        # classical Runge-Kutta 4 with u held constant over the step (zero-order hold)
        k1 = self._rhs(ops, cols, delta, ax, 0.0)
        k2 = self._rhs(ops, tuple(c + 0.5 * dt * k for c, k in zip(cols, k1)), delta, ax, 0.0)
        k3 = self._rhs(ops, tuple(c + 0.5 * dt * k for c, k in zip(cols, k2)), delta, ax, 0.0)
        k4 = self._rhs(ops, tuple(c + dt * k for c, k in zip(cols, k3)), delta, ax, 0.0)
        return tuple(c + dt / 6.0 * (a + 2.0 * b + 2.0 * e + d)
                     for c, a, b, e, d in zip(cols, k1, k2, k3, k4))

    def _kernel_component_major(self, xt: torch.Tensor, ut: torch.Tensor) -> torch.Tensor:
        # xt: (n, ...) and ut: (2, ...) component-major; returns the next state as (n, ...).
        out = self._step_cols(TorchOps, xt.unbind(0), ut[0], ut[1])
        return torch.stack(torch.broadcast_tensors(*out), dim=0)

    def step_scalar(self, x: tuple[float, ...] | list[float], u: tuple[float, float] | list[float]
                    ) -> tuple[float, ...]:
        """Deterministic step ``f`` on Python floats (the Gymnasium environment's fast path).

        Parameters
        ----------
        x : sequence of float, length 5 or 6
            State or tracking state (see :meth:`derivatives`).
        u : sequence of float, length 2
            Input ``[delta, a_x]``.

        Returns
        -------
        tuple of float, length 5 or 6
            The next state ``f(x, u)``.

        Raises
        ------
        ValueError
            If the lengths are wrong. (No NaN scan: callers validate.)
        """
        if len(x) not in (5, 6) or len(u) != 2:
            raise ValueError(f"x: expected 5 or 6 floats and u 2 floats, got {len(x)} and {len(u)}")
        return self._step_cols(MathOps, tuple(x), u[0], u[1])

    def step_rows(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, ...]:
        """Deterministic step ``f`` on float64 rows, bit-identical to :meth:`step_scalar` on each row.

        The transcendental functions are :mod:`math`'s, element by element
        (:class:`mixedrl.envs.libm.LibmOps`); :func:`mixedrl.envs.evaluate_courses` relies on this.

        Parameters
        ----------
        x : numpy.ndarray, shape (N, 5) or (N, 6), float64
            States or tracking states (see :meth:`derivatives`).
        u : numpy.ndarray, shape (N, 2), float64
            Inputs ``[delta, a_x]``.

        Returns
        -------
        tuple of numpy.ndarray
            The 5 or 6 columns of ``f(x, u)``, each shape (N,).

        Raises
        ------
        ValueError
            Wrong shapes. (No NaN scan: callers validate.)
        """
        if not isinstance(x, np.ndarray) or x.ndim != 2 or x.shape[1] not in (5, 6):
            raise ValueError(f"x: expected a numpy array of shape (N, 5) or (N, 6), got {np.shape(x)}")
        if not isinstance(u, np.ndarray) or u.shape != (x.shape[0], 2):
            raise ValueError(f"u: expected a numpy array of shape ({x.shape[0]}, 2), got {np.shape(u)}")
        return self._step_cols(LibmOps, tuple(x[:, i] for i in range(x.shape[1])), u[:, 0], u[:, 1])

    @overload
    def __call__(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor: ...
    @overload
    def __call__(self, x: np.ndarray, u: np.ndarray) -> np.ndarray: ...

    def __call__(self, x: ArrayLike, u: ArrayLike) -> ArrayLike:
        """Deterministic part ``f`` of the discretised system: implements eq. (54)'s ``f(x_t, u_t)``.

        With the default forward-Euler scheme,

        .. math::

            x_{t+1} = f(x_t, u_t) + \\xi_t, \\qquad
            f(x_t, u_t) = x_t + T\\, \\dot x(x_t, u_t)\\big|_{F_{dis} = 0}, \\qquad
            \\xi_t = \\big[0, 0, F_{dis} T / m, 0, 0\\big]^\\top,

        i.e. forward Euler on eq. (53) with ``F_dis`` held over the step.

        Parameters
        ----------
        x : numpy.ndarray or torch.Tensor, shape (..., 5) or (..., 6)
            State or tracking state (see :meth:`derivatives`).
        u : numpy.ndarray or torch.Tensor, shape (..., 2)
            Input ``[delta, a_x]`` (not clipped here; the environments clip to their action bounds).

        Returns
        -------
        numpy.ndarray or torch.Tensor, shape (..., 5) or (..., 6)
            ``f(x, u)``, same backend and dtype as ``x``; differentiable in torch.

        Raises
        ------
        ValueError
            As :meth:`derivatives`.

        Notes
        -----
        Only under forward Euler is the additive ``xi`` on ``v_x`` alone the discretised ``F_dis / m``
        (docs/vehicle.rst gives the reasons for the scheme). With ``scheme="rk4"`` the environments add
        the same ``xi`` after ``f``.
        """
        x, u, _ = self._prepare(x, u, 0.0)
        ops = ops_for(x)
        if ops is TorchOps and self.compile and not self._compile_failed:
            # component-major copies, made outside the compiled graph, let inductor emit SIMD code
            # (docs/vehicle.rst, "Fused batched step"); the result is a (..., n) view of that buffer
            if self._compiled is None:
                self._compiled = torch.compile(self._kernel_component_major, dynamic=None)
            try:
                return self._compiled(x.movedim(-1, 0).contiguous(), u.movedim(-1, 0).contiguous()).movedim(0, -1)
            except Exception as exc:  # noqa: BLE001 - any backend failure falls back to the eager path
                self._compile_failed = True
                logger.warning("torch.compile of VehicleDynamics failed (%s); using eager torch", exc)
        return ops.stack(self._step_cols(ops, ops.columns(x), u[..., 0], u[..., 1]))
