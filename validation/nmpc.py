"""Reference controllers for the double lane change: NMPC, the whole-course optimum and LQR.

The LQ case has its exact answer (the DARE, :mod:`validation.lq`); the double lane change has none. This
module gives the yardsticks a vehicle-control engineer would use, all on the package's *own* model:

* **NMPC** -- receding-horizon nonlinear MPC (CasADi + IPOPT, multiple shooting, warm start by shifting
  the previous solution). The prediction model is the shared deterministic ``f`` of eqs. (53)-(54)
  (forward Euler, ``T = 1/200``, Fiala tires) rewritten in CasADi symbols (:func:`casadi_tracking_model`;
  a test holds it to the torch model to ``1e-12``) plus a *given* disturbance mean on ``v_x``; the
  stage cost is eq. (54) charged on the next state (eq. 2), discounted by ``gamma**k`` or not, and the
  reference path over the horizon is known (preview):

  .. math::

      \\min_{u_0..u_{N-1}} \\sum_{k=0}^{N-1} \\gamma^k\\, l(s_{k+1}, u_k)
      \\quad \\text{s.t.}\\quad s_{k+1} = f(s_k, u_k) + \\bar\\xi\\, e_{v_x},\\ s_0 = s,\\
      |u_k| \\le \\bar u,

  with ``xi_bar = F_bar T / m`` and ``F_bar`` the true mean (261 N), the prior's (150 N), zero, or any
  force. The first input is applied; the problem is re-solved every ``period`` steps.
  Without preview (``preview=False``) the prediction replaces the path by its tangent line at the
  car's current ``X``: the controller knows what ``e_y`` and ``e_phi`` tell (and the tangent's heading),
  nothing of the path ahead (:class:`VehicleNMPC`).
* **whole-course optimum** -- the same problem over the whole course (2000 steps, ``gamma = 1``) solved
  once from the start with the true mean, applied open loop: the physical limit of the course cost.
* **LQR** -- the discounted LQ optimum (EQUATIONS.md, last section) of the linearisation of ``f`` at
  12 m/s on the straight, on the paper's relative state ``[v_y, r, v_x - 12, e_phi, e_y]`` (no preview),
  with the disturbance mean compensated by the affine term ``l0``: ``u = -L x - l0``.

Every controller drives the reproduction's course through :func:`mixedrl.envs.evaluate_tracking` (the
same true environment, noise seeds, start and metrics as ``DoubleLaneChangeTask.evaluate``).
:func:`run_reference` is the public entry; :func:`reference_rows` gives the rows of the "references,
not learned" block; ``python -m validation.nmpc --out DIR`` writes them as JSON.

CasADi is an optional dependency (``pip install -c constraints.txt -e ".[nmpc]"``); it is imported
lazily inside the functions that need it, so this module (and the LQR) imports without it.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch
from tqdm.auto import tqdm

from mixedrl.checks import check_nonnegative_int, check_positive_int
from mixedrl.envs import DoubleLaneChangeConfig, DoubleLaneChangeModel, TrackingResult, evaluate_tracking
from mixedrl.runs import atomic_write_text
from mixedrl.tasks import DoubleLaneChangeTask
from mixedrl.lq import discounted_lq_optimum

__all__ = [
    "CONTROLLERS",
    "NMPCSolveError",
    "CasadiTrackingModel",
    "casadi_tracking_model",
    "ShootingSolution",
    "RecedingHorizon",
    "VehicleNMPC",
    "CourseOptimum",
    "AffineLQR",
    "discounted_lqr",
    "linearise_straight",
    "straight_lqr",
    "force_mean",
    "drive",
    "run_reference",
    "REFERENCE_SETTINGS",
    "reference_row",
    "reference_rows",
    "jsonable",
    "main",
]

logger = logging.getLogger(__name__)

#: The reference controllers of :func:`run_reference`.
CONTROLLERS = ("nmpc", "lqr", "optimum")
#: Named disturbance means of :func:`force_mean`.
MEAN_NAMES = ("true", "prior", "zero")
#: IPOPT options of every solve (tight tolerances; quiet).
IPOPT_OPTIONS: dict[str, Any] = {"print_level": 0, "sb": "yes", "tol": 1e-9, "max_iter": 500}
#: Extra IPOPT options of the warm-started solves (primal-dual start from the shifted solution, small
#: barrier parameter: 3 IPOPT iterations per NMPC step instead of 6 on the double lane change).
IPOPT_WARM_OPTIONS: dict[str, Any] = {"warm_start_init_point": "yes", "mu_init": 1e-6,
                                      "warm_start_bound_push": 1e-9, "warm_start_mult_bound_push": 1e-9}


def _casadi() -> Any:
    """Import CasADi lazily, with an error that says how to install it."""
    try:
        import casadi
    except ImportError as exc:  # pragma: no cover - exercised only without the extra
        raise ImportError("casadi: the NMPC references need CasADi; install the extra: "
                          "pip install -c constraints.txt -e '.[nmpc]'") from exc
    return casadi


class NMPCSolveError(RuntimeError):
    """IPOPT did not solve an optimal-control problem; the message names the control step and the status.

    Attributes
    ----------
    step : int
        Control step (index of the applied input) at which the solve failed.
    status : str
        IPOPT's return status (e.g. ``"Maximum_Iterations_Exceeded"``).
    """

    def __init__(self, step: int, status: str) -> None:
        super().__init__(f"step {step}: IPOPT failed with status {status!r} (no fallback input is used)")
        self.step = step
        self.status = status


# ----------------------------------------------------------------------------------------------------
# The package's model in CasADi symbols
# ----------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CasadiTrackingModel:
    """The double-lane-change model of :class:`~mixedrl.envs.DoubleLaneChangeModel` as CasADi functions.

    Attributes
    ----------
    step : casadi.Function
        ``(s[6], u[2]) -> f(s, u)[6]``: eq. (53) discretised (the config's scheme), no noise.
    cost : casadi.Function
        ``(s_next[6], u[2]) -> l(s_next, u)``: eq. (54) on the next state.
    lateral : casadi.Function
        ``X -> Y_ref(X)``.
    heading : casadi.Function
        ``X -> psi_ref(X)``.
    config : DoubleLaneChangeConfig
    """

    step: Any
    cost: Any
    lateral: Any
    heading: Any
    config: DoubleLaneChangeConfig


def _fiala_sym(ca: Any, alpha: Any, C: float, mu: float, F_z: float) -> Any:
    # alpha_sl = atan(3 mu F_z / C); F_y = -C t + C^2/(3 mu F_z) |t| t - C^3/(27 mu^2 F_z^2) t^3, t = tan(clip(alpha))
    alpha_sl = math.atan(3.0 * mu * F_z / C)
    c2 = C * C / (3.0 * mu * F_z)
    c3 = C**3 / (27.0 * mu * mu * F_z * F_z)
    t = ca.tan(ca.fmin(ca.fmax(alpha, -alpha_sl), alpha_sl))
    return t * (-C + c2 * ca.fabs(t) - c3 * t * t)


def casadi_tracking_model(config: DoubleLaneChangeConfig | dict[str, Any] | None = None) -> CasadiTrackingModel:
    """Implements eqs. (53)-(54) in CasADi symbols: the same ``f`` and cost as the torch model.

    .. math::

        s_{t+1} = s_t + T\\,\\dot s(s_t, u_t), \\qquad
        l(s', u) = T\\,\\big(45 (v_x' - 12)^2 + 60 (Y' - Y_{ref}(X'))^2 + 800\\,\\delta^2 + a_x^2\\big),

    with ``s = [v_y, r, v_x, phi, Y, X]``, ``\\dot s`` eq. (53) with the Fiala tire (see
    :meth:`mixedrl.envs.VehicleDynamics.derivatives`) plus ``dX/dt = v_x cos(phi) - v_y sin(phi)``, and
    the tanh reference of :class:`~mixedrl.envs.DoubleLaneChangeReference`.

    Parameters
    ----------
    config : DoubleLaneChangeConfig or dict, optional
        The task (default: the paper's). Every number is read from it.

    Returns
    -------
    CasadiTrackingModel

    Raises
    ------
    ImportError
        CasADi is not installed.
    ValueError
        Invalid ``config``.

    Notes
    -----
    The Fiala law is written, as in the torch model, as the polynomial of ``tan(clip(alpha))``; IPOPT
    sees a function with a continuous first derivative (the second jumps at saturation and at
    ``alpha = 0`` through ``|t|``), which it handles in practice. ``tests/test_nmpc.py`` checks the two
    models agree to ``1e-12`` on random states, in and beyond the saturation branch.
    """
    ca = _casadi()
    cfg = DoubleLaneChangeModel(config).config
    p, ref = cfg.params, cfg.reference
    F_zf, F_zr = p.F_zf, p.F_zr

    X = ca.SX.sym("X")
    # z_i = s/l_i (X - X_i) - s/2 ; Y_ref = dy1/2 (1 + tanh z1) - dy2/2 (1 + tanh z2) ; psi_ref = atan(dY_ref/dX)
    th1 = ca.tanh(ref.shape / ref.len1 * (X - ref.x1) - 0.5 * ref.shape)
    th2 = ca.tanh(ref.shape / ref.len2 * (X - ref.x2) - 0.5 * ref.shape)
    y_ref = 0.5 * ref.dy1 * (1.0 + th1) - 0.5 * ref.dy2 * (1.0 + th2)
    slope = (0.5 * ref.dy1 * ref.shape / ref.len1 * (1.0 - th1 * th1)
             - 0.5 * ref.dy2 * ref.shape / ref.len2 * (1.0 - th2 * th2))
    lateral = ca.Function("lateral", [X], [y_ref], ["X"], ["Y_ref"])
    heading = ca.Function("heading", [X], [ca.atan(slope)], ["X"], ["psi_ref"])

    s = ca.SX.sym("s", 6)
    u = ca.SX.sym("u", 2)

    def rhs(state: Any) -> Any:
        vy, r, vx, phi = state[0], state[1], state[2], state[3]
        delta, ax = u[0], u[1]
        # alpha_f = atan((v_y + a r)/v_x) - delta ; alpha_r = atan((v_y - b r)/v_x)
        fyf = _fiala_sym(ca, ca.atan2(vy + p.a * r, vx) - delta, p.C_f, p.mu, F_zf)
        fyr = _fiala_sym(ca, ca.atan2(vy - p.b * r, vx), p.C_r, p.mu, F_zr)
        fyf_cos = fyf * ca.cos(delta)
        return ca.vertcat(
            (fyf_cos + fyr) * (1.0 / p.m) - vx * r,                 # dv_y/dt
            (p.a * fyf_cos - p.b * fyr) * (1.0 / p.I_z),            # dr/dt
            ax + vy * r - fyf * ca.sin(delta) * (1.0 / p.m),        # dv_x/dt (F_dis = 0: the mean enters as xi)
            r,                                                       # dphi/dt
            vx * ca.sin(phi) + vy * ca.cos(phi),                     # dY/dt
            vx * ca.cos(phi) - vy * ca.sin(phi),                     # dX/dt
        )

    dt = cfg.dt
    if cfg.scheme == "euler":
        # s' = s + T sdot(s, u)
        s_next = s + dt * rhs(s)
    else:  # "rk4", zero-order hold on u (as VehicleDynamics)
        k1 = rhs(s)
        k2 = rhs(s + 0.5 * dt * k1)
        k3 = rhs(s + 0.5 * dt * k2)
        k4 = rhs(s + dt * k3)
        s_next = s + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    step = ca.Function("f", [s, u], [s_next], ["s", "u"], ["s_next"])
    e_y = s[4] - lateral(s[5])
    dv = s[2] - cfg.v_des
    cost_expr = dt * (cfg.q_speed * dv * dv + cfg.q_lateral * e_y * e_y
                      + cfg.r_steer * u[0] * u[0] + cfg.r_accel * u[1] * u[1])
    cost = ca.Function("l", [s, u], [cost_expr], ["s_next", "u"], ["l"])
    return CasadiTrackingModel(step=step, cost=cost, lateral=lateral, heading=heading, config=cfg)


# ----------------------------------------------------------------------------------------------------
# The generic NMPC core: multiple shooting on any CasADi (step, cost)
# ----------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ShootingSolution:
    """One solve of :class:`RecedingHorizon`.

    Attributes
    ----------
    u : numpy.ndarray, shape (N, nu)
        Optimal inputs ``u_0 .. u_{N-1}``.
    x : numpy.ndarray, shape (N + 1, nx)
        Predicted states ``x_0 .. x_N``.
    objective : float
        Discounted cost of the plan.
    status : str
        IPOPT's return status.
    iterations : int
        IPOPT iterations.
    solve_ms : float
        Wall time of the solver call [ms].
    """

    u: np.ndarray
    x: np.ndarray
    objective: float
    status: str
    iterations: int
    solve_ms: float


class RecedingHorizon:
    """Implements the finite-horizon optimal-control problem behind eq. (2), by multiple shooting.

    .. math::

        \\min_{x_{0..N},\\,u_{0..N-1}} \\sum_{k=0}^{N-1} \\gamma^k\\, l(x_{k+1}, u_k)
        \\quad\\text{s.t.}\\quad x_0 = \\hat x,\\quad x_{k+1} = f(x_k, u_k),\\quad
        u_{\\min} \\le u_k \\le u_{\\max},

    the truncation of eq. (2)'s discounted sum at ``N`` steps (no terminal cost), with the utility on the
    next state. Works on any CasADi dynamics; the vehicle is one instance (:class:`VehicleNMPC`).

    Parameters
    ----------
    step : casadi.Function
        ``(x[nx], u[nu]) -> x_next[nx]`` (including any known mean of the noise).
    cost : casadi.Function
        ``(x_next[nx], u[nu]) -> scalar``, or ``(x_next[nx], u[nu], theta[n_theta]) -> scalar`` with a
        parameter vector ``theta`` fixed for one solve and given to :meth:`solve` (e.g. the reference path
        the controller assumes, :class:`VehicleNMPC` without preview).
    horizon_steps : int
        ``N`` >= 1.
    gamma : float, optional
        Discount in (0, 1]; default 1.
    u_min, u_max : array_like, shape (nu,), optional
        Input bounds (default unbounded).
    ipopt_options : dict, optional
        Overrides of :data:`IPOPT_OPTIONS` (e.g. ``{"max_iter": 1}``).
    warm_start : bool, optional
        Build the warm-start solver (:data:`IPOPT_WARM_OPTIONS`) now, so that no solve is timed with its
        construction. Default True; without it, it is built at the first warm solve.

    Raises
    ------
    ValueError
        Bad ``horizon_steps``, ``gamma``, bounds, or a ``step``/``cost`` of the wrong signature.
    ImportError
        CasADi is not installed.

    Notes
    -----
    Warm start: after a solve at control step ``k0``, the next solve at step ``k1`` starts IPOPT from the
    previous primal-dual solution shifted by ``k1 - k0`` stages (the tail filled by repeating the last
    input and simulating ``step``), with its first state replaced by the measured one. A solve that IPOPT
    does not finish (any status but ``Solve_Succeeded`` / ``Solved_To_Acceptable_Level``) raises
    :class:`NMPCSolveError`; there is no fallback input.
    """

    def __init__(self, step: Any, cost: Any, *, horizon_steps: int, gamma: float = 1.0, u_min: Any = None,
                 u_max: Any = None, ipopt_options: dict[str, Any] | None = None, warm_start: bool = True) -> None:
        ca = _casadi()
        horizon_steps = check_positive_int(horizon_steps, "horizon_steps")
        gamma = _check_gamma(gamma)
        if not (isinstance(step, ca.Function) and step.n_in() == 2 and step.n_out() == 1):
            raise ValueError("step: expected a casadi.Function (x, u) -> x_next")
        if not (isinstance(cost, ca.Function) and cost.n_in() in (2, 3) and cost.n_out() == 1):
            raise ValueError("cost: expected a casadi.Function (x_next, u) -> scalar or (x_next, u, theta) -> scalar")
        nx, nu = step.size1_in(0), step.size1_in(1)
        if step.size1_out(0) != nx or cost.size1_in(0) != nx or cost.size1_in(1) != nu or cost.numel_out(0) != 1:
            raise ValueError(f"cost: signature does not match step's (nx={nx}, nu={nu})")
        if cost.n_in() == 3 and (cost.size2_in(2) != 1 or cost.size1_in(2) < 1):
            raise ValueError("cost: its third input theta must be a column vector")
        #: Length of the cost's parameter vector ``theta`` (0: the cost has none).
        self.n_theta = cost.size1_in(2) if cost.n_in() == 3 else 0
        self.nx, self.nu, self.N, self.gamma = nx, nu, int(horizon_steps), gamma
        self.u_min = np.full(nu, -np.inf) if u_min is None else _bound(u_min, "u_min", nu)
        self.u_max = np.full(nu, np.inf) if u_max is None else _bound(u_max, "u_max", nu)
        if np.any(self.u_min > self.u_max):
            raise ValueError("u_min: must not exceed u_max")
        self._step = step
        N = self.N
        Xs = ca.MX.sym("X", nx, N + 1)
        Us = ca.MX.sym("U", nu, N)
        x0 = ca.MX.sym("x0", nx)
        # defects d_k = f(x_k, u_k) - x_{k+1}   (multiple shooting)
        defects = step.map(N)(Xs[:, :N], Us) - Xs[:, 1:]
        weights = ca.DM(gamma ** np.arange(N))
        if self.n_theta == 0:
            # J = sum_k gamma^k l(x_{k+1}, u_k)
            objective = ca.mtimes(cost.map(N)(Xs[:, 1:], Us), weights)
            params = x0
        else:
            # J = sum_k gamma^k l(x_{k+1}, u_k; theta), theta the same at every stage of one solve
            theta = ca.MX.sym("theta", self.n_theta)
            objective = ca.mtimes(cost.map(N)(Xs[:, 1:], Us, ca.repmat(theta, 1, N)), weights)
            params = ca.vertcat(x0, theta)
        nlp = {"x": ca.vertcat(ca.vec(Xs), ca.vec(Us)), "p": params, "f": objective,
               "g": ca.vertcat(Xs[:, 0] - x0, ca.vec(defects))}
        self._nlp = nlp
        self._options = {**IPOPT_OPTIONS, **(ipopt_options or {})}
        self._solver = self._make_solver(False)
        self._warm_solver: Any = self._make_solver(True) if warm_start else None
        nxv = nx * (N + 1)
        self._lbx = np.concatenate([np.full(nxv, -np.inf), np.tile(self.u_min, N)])
        self._ubx = np.concatenate([np.full(nxv, np.inf), np.tile(self.u_max, N)])
        self._ng = nx * (N + 1)
        self._warm: dict[str, np.ndarray] | None = None
        self._warm_step = 0

    def _make_solver(self, warm: bool) -> Any:
        ca = _casadi()
        opts = {**self._options, **IPOPT_WARM_OPTIONS} if warm else self._options
        return ca.nlpsol("ocp_warm" if warm else "ocp", "ipopt", self._nlp,
                         {"expand": True, "print_time": False, "ipopt": opts})

    def reset(self) -> None:
        """Forget the warm start (the next :meth:`solve` starts from its ``guess``)."""
        self._warm = None

    def _shifted(self, shift: int, x_hat: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        nx, nu, N = self.nx, self.nu, self.N
        w, lam_x, lam_g = self._warm["x"], self._warm["lam_x"], self._warm["lam_g"]
        X = w[: nx * (N + 1)].reshape(N + 1, nx)
        U = w[nx * (N + 1):].reshape(N, nu)
        shift = min(shift, N)
        U_new = np.concatenate([U[shift:], np.repeat(U[-1:], shift, axis=0)])
        X_new = np.concatenate([X[shift:], np.zeros((shift, nx))])
        for k in range(N + 1 - shift, N + 1):
            X_new[k] = np.asarray(self._step(X_new[k - 1], U_new[k - 1])).ravel()
        X_new[0] = x_hat
        lu = lam_x[nx * (N + 1):].reshape(N, nu)
        lu = np.concatenate([lu[shift:], np.repeat(lu[-1:], shift, axis=0)])
        lg = lam_g.reshape(N + 1, nx)
        lg = np.concatenate([lg[:1], lg[1 + shift:], np.repeat(lg[-1:], shift, axis=0)])
        w0 = np.concatenate([X_new.ravel(), U_new.ravel()])
        return w0, np.concatenate([np.zeros(nx * (N + 1)), lu.ravel()]), lg.ravel()

    def solve(self, x_hat: Any, *, step: int = 0, guess: tuple[np.ndarray, np.ndarray] | None = None,
              theta: Any = None) -> ShootingSolution:
        """Solve the problem from the measured state ``x_hat``.

        Parameters
        ----------
        x_hat : array_like, shape (nx,)
            Current state.
        step : int, optional
            Control step of this solve (for the warm-start shift and error messages).
        guess : tuple of arrays, shapes (N + 1, nx) and (N, nu), optional
            Initial guess when there is no warm start (default: ``x_hat`` repeated, inputs clipped 0).
        theta : array_like, shape (n_theta,), optional
            The cost's parameters for this solve; required if and only if the cost has a third input.

        Returns
        -------
        ShootingSolution

        Raises
        ------
        ValueError
            ``x_hat`` of the wrong shape or not finite; a ``guess`` of the wrong shapes; ``theta`` missing,
            not expected, of the wrong shape or not finite.
        NMPCSolveError
            IPOPT did not solve the problem (names ``step`` and the status).
        """
        nx, nu, N = self.nx, self.nu, self.N
        x_hat = np.asarray(x_hat, dtype=np.float64)
        if x_hat.shape != (nx,) or not np.all(np.isfinite(x_hat)):
            raise ValueError(f"x_hat: expected a finite vector of shape ({nx},), got {x_hat!r}")
        p = x_hat
        if self.n_theta == 0:
            if theta is not None:
                raise ValueError("theta: this problem's cost has no parameters")
        else:
            th = None if theta is None else np.asarray(theta, dtype=np.float64)
            if th is None or th.shape != (self.n_theta,) or not np.all(np.isfinite(th)):
                raise ValueError(f"theta: expected a finite vector of shape ({self.n_theta},), got {theta!r}")
            p = np.concatenate([x_hat, th])
        args: dict[str, Any] = {"p": p, "lbx": self._lbx, "ubx": self._ubx, "lbg": 0.0, "ubg": 0.0}
        if self._warm is not None:
            args["x0"], args["lam_x0"], args["lam_g0"] = self._shifted(step - self._warm_step, x_hat)
            if self._warm_solver is None:
                self._warm_solver = self._make_solver(True)
            solver = self._warm_solver
        else:
            solver = self._solver
            if guess is None:
                X0 = np.tile(x_hat, (N + 1, 1))
                U0 = np.tile(np.clip(0.0, self.u_min, self.u_max), (N, 1))
            else:
                X0, U0 = (np.asarray(g, dtype=np.float64) for g in guess)
                if X0.shape != (N + 1, nx) or U0.shape != (N, nu):
                    raise ValueError(f"guess: expected shapes ({N + 1}, {nx}) and ({N}, {nu}), "
                                     f"got {X0.shape} and {U0.shape}")
            args["x0"] = np.concatenate([X0.ravel(), U0.ravel()])
        t0 = time.perf_counter()
        sol = solver(**args)
        solve_ms = 1e3 * (time.perf_counter() - t0)
        stats = solver.stats()
        status = str(stats.get("return_status", "unknown"))
        if status not in ("Solve_Succeeded", "Solved_To_Acceptable_Level"):
            raise NMPCSolveError(step, status)
        w = np.asarray(sol["x"]).ravel()
        self._warm = {"x": w, "lam_x": np.asarray(sol["lam_x"]).ravel(), "lam_g": np.asarray(sol["lam_g"]).ravel()}
        self._warm_step = step
        return ShootingSolution(u=w[nx * (N + 1):].reshape(N, nu), x=w[: nx * (N + 1)].reshape(N + 1, nx),
                                objective=float(sol["f"]), status=status,
                                iterations=int(stats.get("iter_count", -1)), solve_ms=solve_ms)


# ----------------------------------------------------------------------------------------------------
# The vehicle instances
# ----------------------------------------------------------------------------------------------------
def _check_gamma(gamma: Any) -> float:
    if isinstance(gamma, bool) or not isinstance(gamma, (int, float, np.floating)) or not 0.0 < float(gamma) <= 1.0:
        raise ValueError(f"gamma: expected a number in (0, 1], got {gamma!r}")
    return float(gamma)


def _check_preview(preview: Any) -> bool:
    if not isinstance(preview, (bool, np.bool_)):
        raise TypeError(f"preview: expected a bool, got {type(preview).__name__} {preview!r}")
    return bool(preview)


def _bound(value: Any, name: str, n: int) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    if arr.shape != (n,) or np.any(np.isnan(arr)):
        raise ValueError(f"{name}: expected {n} numbers, got {value!r}")
    return arr


def force_mean(disturbance_mean: str | float, config: DoubleLaneChangeConfig | None = None) -> float:
    """The disturbance mean force [N] a controller predicts with.

    Parameters
    ----------
    disturbance_mean : {"true", "prior", "zero"} or float
        ``"true"``: the environment's mean (``config.disturbance.mean``, 261 N); ``"prior"``: the
        designer's prior of eq. (55) (``DoubleLaneChangeTask``'s, 150 N); ``"zero"``: 0; a number: that
        force in newtons.
    config : DoubleLaneChangeConfig, optional
        The task (default: the paper's).

    Returns
    -------
    float

    Raises
    ------
    ValueError
        Unknown name, or a non-finite number (the message names ``disturbance_mean``).
    """
    cfg = DoubleLaneChangeModel(config).config
    if isinstance(disturbance_mean, str):
        if disturbance_mean == "true":
            return float(cfg.disturbance.mean)
        if disturbance_mean == "prior":
            task = DoubleLaneChangeTask()
            vx = task.model.noise_index
            return float(task.prior_mean[vx] * cfg.params.m / cfg.dt)
        if disturbance_mean == "zero":
            return 0.0
        raise ValueError(f"disturbance_mean: expected 'true', 'prior', 'zero' or a force in N, got {disturbance_mean!r}")
    if isinstance(disturbance_mean, bool) or not isinstance(disturbance_mean, (int, float, np.floating, np.integer)) \
            or not math.isfinite(float(disturbance_mean)):
        raise ValueError(f"disturbance_mean: expected 'true', 'prior', 'zero' or a finite force in N, "
                         f"got {disturbance_mean!r}")
    return float(disturbance_mean)


def _predict_step(ca: Any, model: CasadiTrackingModel, force: float) -> Any:
    """``(s, u) -> f(s, u) + (F T / m) e_vx``: the prediction model with a known mean force."""
    cfg = model.config
    s = ca.SX.sym("s", 6)
    u = ca.SX.sym("u", 2)
    xi = np.zeros(6)
    xi[DoubleLaneChangeModel.NOISE_INDEX] = force * cfg.dt / cfg.params.m
    return ca.Function("f_mean", [s, u], [model.step(s, u) + ca.DM(xi)], ["s", "u"], ["s_next"])


def _tangent_cost(ca: Any, model: CasadiTrackingModel) -> Any:
    """``(s', u, theta) -> l(s', u)`` of eq. (54) with the path replaced by the line ``theta = [X_c, Y_c, m_c]``.

    ``Y_line(X) = Y_c + m_c (X - X_c)``; the lateral error is ``Y' - Y_line(X')``, measured in ``Y`` as the
    environment measures ``e_y`` (not perpendicular to the line).
    """
    cfg = model.config
    s = ca.SX.sym("s", 6)
    u = ca.SX.sym("u", 2)
    theta = ca.SX.sym("theta", 3)
    # e_y = Y - (Y_c + m_c (X - X_c)) ; l = T (45 (v_x - 12)^2 + 60 e_y^2 + 800 delta^2 + a_x^2)
    e_y = s[4] - (theta[1] + theta[2] * (s[5] - theta[0]))
    dv = s[2] - cfg.v_des
    cost_expr = cfg.dt * (cfg.q_speed * dv * dv + cfg.q_lateral * e_y * e_y
                          + cfg.r_steer * u[0] * u[0] + cfg.r_accel * u[1] * u[1])
    return ca.Function("l_tangent", [s, u, theta], [cost_expr], ["s_next", "u", "theta"], ["l"])


def _tangent_line(cfg: DoubleLaneChangeConfig, X: float) -> np.ndarray:
    """``[X, Y_ref(X), dY_ref/dX (X)]``: the reference's tangent line at ``X`` (what ``e_y``, ``e_phi`` refer to)."""
    ref = cfg.reference
    return np.array([X, float(ref.lateral(X)), float(ref.slope(X))])


def _line_guess(s0: np.ndarray, line: np.ndarray, cfg: DoubleLaneChangeConfig, n: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """A guess on the tangent line at ``v_des`` from ``s0``'s ``X`` (no look at the path ahead): (n + 1, 6), (n, 2)."""
    X = s0[5] + cfg.v_des * cfg.dt * np.arange(n + 1)
    Y = line[1] + line[2] * (X - line[0])
    states = np.stack([np.zeros(n + 1), np.zeros(n + 1), np.full(n + 1, cfg.v_des),
                       np.full(n + 1, math.atan(line[2])), Y, X], axis=1)
    states[0] = s0
    return states, np.zeros((n, 2))


def _reference_guess(cfg: DoubleLaneChangeConfig, s0: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """A guess on the reference at ``v_des`` from ``s0``'s ``X``: shapes (n + 1, 6), (n, 2)."""
    X = s0[5] + cfg.v_des * cfg.dt * np.arange(n + 1)
    y_ref, psi_ref = cfg.reference.lateral_and_heading(X)
    states = np.stack([np.zeros(n + 1), np.zeros(n + 1), np.full(n + 1, cfg.v_des), psi_ref, y_ref, X], axis=1)
    states[0] = s0
    return states, np.zeros((n, 2))


class VehicleNMPC:
    """NMPC of the double lane change (see the module docstring): a state-feedback controller ``s -> u``.

    With ``preview=True`` (default) the prediction charges eq. (54) against the true reference path
    ``Y_ref(X)`` over the whole horizon. With ``preview=False`` the controller does not know the path
    ahead: at each solve it takes the reference's position and heading at the car's current ``X_c = X``,

    .. math::

        Y_{line}(X) = Y_{ref}(X_c) + \\tan\\psi_{ref}(X_c)\\,(X - X_c),

    and predicts as if the path continued as this straight line (the tangent), charging
    ``60 (Y_{k+1} - Y_{line}(X_{k+1}))^2`` instead of ``60 (Y_{k+1} - Y_{ref}(X_{k+1}))^2``; everything
    else (model, mean force, discount, horizon, bounds) is unchanged. The plant still drives the real
    course, and the costs reported by :func:`drive` are the real course's.

    What the no-preview controller knows: the full state ``s`` and the tangent line at ``X_c``, i.e.
    ``e_y = Y - Y_ref(X_c)`` and ``e_phi = phi - psi_ref(X_c)`` (the policies' observation) plus the
    *absolute* heading ``psi_ref(X_c)`` of that tangent. Because the dynamics are invariant to shifts
    and rotations of the road frame, the optimal plan on a straight line depends on ``s`` only through
    ``[v_y, r, v_x - 12, e_phi, e_y]`` and ``psi_ref(X_c)``; the heading enters only because eq. (54)
    measures the lateral error in ``Y`` (vertically), not perpendicular to the line: the perpendicular
    offset is ``e_y cos psi_ref(X_c)`` and the lateral weight is, in effect, ``60 / cos^2 psi_ref(X_c)``
    (at most 1.10 times 60 on the paper's course, ``|psi_ref| <= 0.30 rad``). Nothing about the path
    beyond ``X_c`` (its curvature, the lane changes ahead) enters the prediction or the initial guess.

    Parameters
    ----------
    config : DoubleLaneChangeConfig or dict, optional
        The task (default: the paper's).
    horizon : float, optional
        Prediction horizon [s]; ``N = round(horizon / T)`` steps. Default 2.
    gamma : float, optional
        Discount of the stage costs in (0, 1]. Default 0.99.
    force : float or str, optional
        Disturbance mean force in the prediction [N], or a name of :func:`force_mean`. Default 261 (the
        true mean).
    period : int, optional
        Re-solve every ``period`` control steps; in between, the stored plan's inputs are applied.
    ipopt_options : dict, optional
        Overrides of :data:`IPOPT_OPTIONS`.
    preview : bool, optional
        Predict on the true path ahead (True, default) or on the tangent line at the current ``X``
        (False; see above).

    Raises
    ------
    ValueError
        Invalid arguments (the message names the argument).
    TypeError
        ``preview`` is not a bool.

    Attributes
    ----------
    preview : bool
    solve_ms : list of float
        Wall time of each solve [ms].
    solution : ShootingSolution or None
        The last solve's solution (its ``objective`` is the *predicted* cost, on the tangent line without
        preview).
    line : numpy.ndarray, shape (3,), or None
        Without preview, the tangent line ``[X_c, Y_ref(X_c), tan psi_ref(X_c)]`` of the last solve.
    """

    def __init__(self, config: DoubleLaneChangeConfig | dict[str, Any] | None = None, *, horizon: float = 2.0,
                 gamma: float = 0.99, force: float | str = 261.0, period: int = 1,
                 ipopt_options: dict[str, Any] | None = None, preview: bool = True) -> None:
        self.preview = _check_preview(preview)
        ca = _casadi()
        self.model = casadi_tracking_model(config)
        cfg = self.config = self.model.config
        self.horizon_steps = _horizon_steps(horizon, cfg.dt)
        self.period = _period(period)
        self.force = force_mean(force, cfg)
        bound = np.array([cfg.delta_max, cfg.ax_max])
        cost = self.model.cost if self.preview else _tangent_cost(ca, self.model)
        self.core = RecedingHorizon(_predict_step(ca, self.model, self.force), cost,
                                    horizon_steps=self.horizon_steps, gamma=gamma, u_min=-bound, u_max=bound,
                                    ipopt_options=ipopt_options)
        self.solution: ShootingSolution | None = None
        self.line: np.ndarray | None = None
        self.solve_ms: list[float] = []
        self._k = 0
        self._plan: np.ndarray | None = None
        self._plan_step = 0

    def reset(self) -> None:
        """Start a new episode (no warm start, no timings)."""
        self.core.reset()
        self.solve_ms = []
        self._k = 0
        self._plan = None
        self.solution = None
        self.line = None

    def __call__(self, s: np.ndarray) -> np.ndarray:
        """The input for tracking state ``s`` (shape (6,)): the first input of the current plan, shape (2,).

        Raises
        ------
        NMPCSolveError
            IPOPT failed at this step.
        """
        k = self._k
        if self._plan is None or k - self._plan_step >= self.period:
            s = np.asarray(s, dtype=np.float64)
            if self.preview:
                guess = None if self._plan is not None else _reference_guess(self.config, s, self.horizon_steps)
                sol = self.core.solve(s, step=k, guess=guess)
            else:
                # only the tangent at the current X: e_y, e_phi and the tangent's heading, nothing ahead
                self.line = _tangent_line(self.config, float(s[5]))
                guess = None if self._plan is not None else _line_guess(s, self.line, self.config,
                                                                         self.horizon_steps)
                sol = self.core.solve(s, step=k, guess=guess, theta=self.line)
            self.solution = sol
            self.solve_ms.append(sol.solve_ms)
            self._plan, self._plan_step = sol.u, k
        self._k += 1
        return self._plan[k - self._plan_step].copy()


class CourseOptimum:
    """The whole-course optimum: every input of the course optimised at once, applied open loop.

    Implements the problem of :class:`RecedingHorizon` with ``N`` = the course's steps, ``gamma = 1`` and
    the given mean force, solved once from the start state: with the true mean, the least expected course
    cost any controller can reach on this course (up to the noise, ``std(F_dis) = 5.7 N``).

    Parameters
    ----------
    config : DoubleLaneChangeConfig or dict, optional
    force : float, optional
        Mean force in the prediction [N]. Default 261 (true).
    ipopt_options : dict, optional

    Attributes
    ----------
    solution : ShootingSolution or None
        The plan, after the first call.
    solve_ms : list of float
        The one solve's wall time [ms] (offline: not an online cost).
    """

    def __init__(self, config: DoubleLaneChangeConfig | dict[str, Any] | None = None, *, force: float = 261.0,
                 ipopt_options: dict[str, Any] | None = None) -> None:
        ca = _casadi()
        self.model = casadi_tracking_model(config)
        cfg = self.config = self.model.config
        self.force = force_mean(force, cfg)
        bound = np.array([cfg.delta_max, cfg.ax_max])
        self.core = RecedingHorizon(_predict_step(ca, self.model, self.force), self.model.cost,
                                    horizon_steps=cfg.max_steps, gamma=1.0, u_min=-bound, u_max=bound,
                                    ipopt_options=ipopt_options, warm_start=False)
        self.solution: ShootingSolution | None = None
        self._start: np.ndarray | None = None
        self.solve_ms: list[float] = []
        self._k = 0

    def reset(self) -> None:
        """Start a new episode (the plan is kept: it depends on the start state only)."""
        self._k = 0

    def plan(self, s0: np.ndarray) -> ShootingSolution:
        """Solve the whole-course problem from ``s0`` (shape (6,)) unless already solved from it (offline).

        Raises
        ------
        NMPCSolveError
            IPOPT failed.
        """
        s0 = np.asarray(s0, dtype=np.float64)
        if self.solution is None or not np.array_equal(s0, self._start):
            self.core.reset()
            self.solution = self.core.solve(s0, step=0, guess=_reference_guess(self.config, s0, self.core.N))
            self._start = s0.copy()
        self.solve_ms = [self.solution.solve_ms]
        return self.solution

    def __call__(self, s: np.ndarray) -> np.ndarray:
        """Input ``k`` of the plan (solved at the first call from ``s`` if :meth:`plan` was not called), shape (2,)."""
        if self._k == 0:
            self.plan(s)
        if self._k >= self.core.N:
            raise RuntimeError(f"step {self._k}: beyond the course's {self.core.N} planned inputs")
        u = self.solution.u[self._k].copy()
        self._k += 1
        return u


# ----------------------------------------------------------------------------------------------------
# LQR of the linearisation on the straight
# ----------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class AffineLQR:
    """``u = -L x - l0`` on the paper's relative state ``x = [v_y, r, v_x - 12, e_phi, e_y]``.

    Attributes
    ----------
    gain : numpy.ndarray, shape (2, 5)
    offset : numpy.ndarray, shape (2,)
    S : numpy.ndarray, shape (5, 5)
        DARE solution ``S = Q + gamma P``.
    gamma : float
    force : float
        Mean force the offset compensates [N].
    """

    gain: np.ndarray
    offset: np.ndarray
    S: np.ndarray
    gamma: float
    force: float
    solve_ms: list[float] = field(default_factory=list)

    def reset(self) -> None:
        """Nothing to reset (stateless); kept for the controller protocol."""

    def __call__(self, s: np.ndarray) -> np.ndarray:
        raise TypeError("AffineLQR acts on observations: use act(obs)")

    def act(self, obs: np.ndarray) -> np.ndarray:
        """``u = -L x - l0`` for the observation ``x`` (shape (5,)); shape (2,)."""
        return -self.gain @ np.asarray(obs[:5], dtype=np.float64) - self.offset


def discounted_lqr(A: Any, B: Any, Q: Any, R: Any, gamma: float, mu: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The discounted LQ optimum as ``(L, l0, S)``: :func:`mixedrl.lq.discounted_lq_optimum` for ``gamma`` in (0, 1].

    For ``x' = A x + B u + xi``, ``E xi = mu``, ``l = x'^T Q x' + u^T R u``, policy ``u = -L x - l0``
    (EQUATIONS.md, last section).

    Parameters
    ----------
    A : array_like, shape (n, n)
    B : array_like, shape (n, m)
    Q : array_like, shape (n, n)
        Symmetric PSD.
    R : array_like, shape (m, m)
        Symmetric positive definite.
    gamma : float
        Discount in (0, 1] (1 allowed: ``L`` and ``l0`` stay finite when ``A_c`` is stable).
    mu : array_like, shape (n,)
        Noise mean.

    Returns
    -------
    L : numpy.ndarray, shape (m, n)
    l0 : numpy.ndarray, shape (m,)
    S : numpy.ndarray, shape (n, n)

    Raises
    ------
    ValueError
        Bad ``gamma``, or the DARE has no stabilising solution (names ``Q``).

    """
    sol = discounted_lq_optimum(A, B, Q, R, _check_gamma(gamma), mu)
    return sol.gain, sol.offset, sol.S


def linearise_straight(config: DoubleLaneChangeConfig | dict[str, Any] | None = None
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Jacobians of the shared ``f`` (eq. 53 discretised) at ``v_x = v_des`` on the straight, ``u = 0``.

    Implements ``A = df/dx``, ``B = df/du`` at ``x = [0, 0, v_des, 0, 0]`` on the five-component state of
    eq. (53) (torch autograd on :class:`~mixedrl.envs.VehicleDynamics`, float64). On the straight the
    paper's relative state equals this state minus the equilibrium.

    Returns
    -------
    A : numpy.ndarray, shape (5, 5)
    B : numpy.ndarray, shape (5, 2)
    """
    model = DoubleLaneChangeModel(config)
    x0 = torch.tensor([0.0, 0.0, model.config.v_des, 0.0, 0.0], dtype=torch.float64)
    u0 = torch.zeros(2, dtype=torch.float64)
    A, B = torch.autograd.functional.jacobian(lambda x, u: model.dynamics(x, u), (x0, u0))
    return A.numpy(), B.numpy()


def straight_lqr(config: DoubleLaneChangeConfig | dict[str, Any] | None = None, *, gamma: float = 0.99,
                 force: float | str = "true") -> AffineLQR:
    """The LQR reference: :func:`discounted_lqr` on :func:`linearise_straight` with eq. (54)'s weights.

    ``Q = T diag(0, 0, 45, 0, 60)``, ``R = T diag(800, 1)`` (the cost of eq. 54 on the relative state),
    ``mu = [0, 0, F T / m, 0, 0]`` with ``F`` from :func:`force_mean`.

    Raises
    ------
    ValueError
        Bad ``gamma`` or ``force``.
    """
    cfg = DoubleLaneChangeModel(config).config
    F = force_mean(force, cfg)
    A, B = linearise_straight(cfg)
    Q = cfg.dt * np.diag([0.0, 0.0, cfg.q_speed, 0.0, cfg.q_lateral])
    R = cfg.dt * np.diag([cfg.r_steer, cfg.r_accel])
    mu = np.zeros(5)
    mu[DoubleLaneChangeModel.NOISE_INDEX] = F * cfg.dt / cfg.params.m
    L, l0, S = discounted_lqr(A, B, Q, R, gamma, mu)
    return AffineLQR(gain=L, offset=l0, S=S, gamma=_check_gamma(gamma), force=F)


# ----------------------------------------------------------------------------------------------------
# Driving the reproduction's course
# ----------------------------------------------------------------------------------------------------
def _start_state(cfg: DoubleLaneChangeConfig) -> np.ndarray:
    """The evaluation's deterministic start (on the reference at ``X = 0``, ``v_des``), as in evaluate_tracking."""
    ref = cfg.reference
    return np.array([0.0, 0.0, cfg.v_des, ref.heading(0.0), ref.lateral(0.0), 0.0])


class _StateFeedbackPolicy:
    """An observation policy for :func:`evaluate_tracking` around a state-feedback controller.

    The true next state is ``f(s, u) + xi e_vx``: every component but ``v_x`` is the deterministic
    ``f`` of the applied input, and ``v_x = v_des + obs[2]`` is observed. So the controller's state is
    reconstructed exactly from the start state, its own (clipped) inputs and the observations; each
    observation is checked against the reconstruction (``1e-9``), so a desynchronisation raises.
    """

    def __init__(self, controller: Any, cfg: DoubleLaneChangeConfig, start: np.ndarray,
                 on_step: Callable[[float], None]) -> None:
        self.controller = controller
        self.model = DoubleLaneChangeModel(cfg)
        self.cfg = cfg
        self.bound = self.model.action_bound
        self.start = start
        self.on_step = on_step
        self._s: np.ndarray | None = None
        self._u: np.ndarray | None = None

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, dtype=np.float64)
        if self._s is None:
            s = self.start.copy()
        else:
            s = np.array(self.model.dynamics.step_scalar(tuple(self._s), tuple(self._u)))
            s[DoubleLaneChangeModel.NOISE_INDEX] = obs[2] + self.cfg.v_des
        if not np.allclose(self.model.observe(s), obs, rtol=0.0, atol=1e-9):
            raise RuntimeError("obs: the observation does not match the reconstructed state")
        t0 = time.perf_counter()
        u = self.controller.act(obs) if isinstance(self.controller, AffineLQR) else self.controller(s)
        self.on_step(1e3 * (time.perf_counter() - t0))
        u = np.clip(np.asarray(u, dtype=np.float64), -self.bound, self.bound)
        self._s, self._u = s, u
        return u


def drive(controller: Any, config: DoubleLaneChangeConfig | dict[str, Any] | None = None, *, seed: int = 0,
          progress: Any = None) -> tuple[TrackingResult, dict[str, float]]:
    """Drive one course of the reproduction (:func:`mixedrl.envs.evaluate_tracking`) with a reference.

    Parameters
    ----------
    controller : VehicleNMPC, CourseOptimum or AffineLQR
        A state-feedback controller ``s -> u`` with ``reset()`` (or the LQR, on observations).
    config : DoubleLaneChangeConfig or dict, optional
    seed : int, optional
        Noise seed of the course (as in ``DoubleLaneChangeTask.evaluate``).
    progress : tqdm, optional
        Updated once per control step.

    Returns
    -------
    result : TrackingResult
        The Table I metrics and the trajectory, from ``evaluate_tracking``.
    timing : dict
        ``solve_ms_mean``, ``solve_ms_max`` (per optimisation; per control step for the LQR),
        ``step_ms_mean``, ``step_ms_max`` (online time per control step), ``solves``.
    """
    cfg = DoubleLaneChangeModel(config).config
    start = _start_state(cfg)
    controller.reset()
    if isinstance(controller, CourseOptimum):
        controller.plan(start)  # offline: the plan is made before the course, not inside a control step
    steps: list[float] = []

    def on_step(ms: float) -> None:
        steps.append(ms)
        if progress is not None:
            progress.update(1)

    policy = _StateFeedbackPolicy(controller, cfg, start, on_step)
    result = evaluate_tracking(policy, cfg, seed=int(seed), start_state=start)
    solves = list(getattr(controller, "solve_ms", [])) or steps
    timing = {"solve_ms_mean": float(np.mean(solves)), "solve_ms_max": float(np.max(solves)),
              "step_ms_mean": float(np.mean(steps)), "step_ms_max": float(np.max(steps)),
              "solves": len(solves)}
    return result, timing


def _horizon_steps(horizon: Any, dt: float) -> int:
    if isinstance(horizon, bool) or not isinstance(horizon, (int, float, np.floating, np.integer)) \
            or not math.isfinite(float(horizon)) or round(float(horizon) / dt) < 1:
        raise ValueError(f"horizon: expected a finite time in seconds of at least one step ({dt} s), got {horizon!r}")
    return int(round(float(horizon) / dt))


def _period(period: Any) -> int:
    return check_positive_int(period, "period")


def _seeds(seeds: Any) -> tuple[int, ...]:
    try:
        out = tuple(seeds)
    except TypeError:
        raise ValueError(f"seeds: expected a non-empty sequence of non-negative ints, got {seeds!r}") from None
    if not out:
        raise ValueError(f"seeds: expected a non-empty sequence of non-negative ints, got {seeds!r}")
    return tuple(check_nonnegative_int(s, "seeds") for s in out)


def run_reference(controller: str, *, gamma: float = 0.99, horizon: float = 2.0,
                  disturbance_mean: str | float = "true", seeds: Sequence[int] = (0,), period: int = 1,
                  progress: bool = False, keep_trajectory: bool = False,
                  config: DoubleLaneChangeConfig | dict[str, Any] | None = None, preview: bool = True
                  ) -> dict[str, Any]:
    """Drive the reproduction's double lane change with a reference controller; Table I metrics.

    Parameters
    ----------
    controller : {"nmpc", "lqr", "optimum"}
        :class:`VehicleNMPC`, :func:`straight_lqr` or :class:`CourseOptimum`.
    gamma : float, optional
        Discount in (0, 1] of the NMPC and the LQR (the optimum always minimises the undiscounted course
        cost, ``gamma = 1``). Default 0.99.
    horizon : float, optional
        NMPC horizon [s] (ignored by the LQR and the optimum). Default 2.
    disturbance_mean : {"true", "prior", "zero"} or float, optional
        Mean force the controller predicts with (:func:`force_mean`). Default ``"true"`` (261 N).
    seeds : sequence of int, optional
        Noise seeds, one course each (as ``DoubleLaneChangeTask.evaluate``). Default ``(0,)``.
    period : int, optional
        NMPC re-solve period [control steps]. Default 1 (every step).
    progress : bool, optional
        Show a tqdm bar over control steps.
    keep_trajectory : bool, optional
        Also return ``"trajectories"`` (the :class:`~mixedrl.envs.TrackingResult` of each seed).
    config : DoubleLaneChangeConfig or dict, optional
        The task (default: the paper's).
    preview : bool, optional
        NMPC only: predict on the true path ahead (True, default) or on the reference's tangent line at
        the car's current ``X`` (False: the NMPC knows what ``e_y`` and ``e_phi`` tell, nothing ahead;
        see :class:`VehicleNMPC`). The LQR never previews, the optimum always does: for them only the
        default is accepted.

    Returns
    -------
    dict
        Means over seeds: ``lateral_mae`` [m], ``speed_mae`` [m/s], ``lateral_max``, ``speed_max``,
        ``cost`` (undiscounted eq. 54 course cost), ``terminated``, ``solve_ms_mean``, ``solve_ms_max``
        (per optimisation: per NMPC solve, the optimum's one offline solve, the LQR's per-step
        evaluation), ``step_ms_mean``, ``step_ms_max`` (online time per control step); the settings
        (``controller``, ``gamma``, ``horizon``, ``period``, ``disturbance_mean``, ``force_N``,
        ``seeds``; and ``preview`` for the NMPC when it is False) and ``per_seed`` (the same figures per
        seed).

    Raises
    ------
    ValueError
        A bad argument (the message names it).
    TypeError
        ``preview`` is not a bool.
    ImportError
        ``"nmpc"``/``"optimum"`` without CasADi installed.
    NMPCSolveError
        IPOPT failed (names the control step and the status).
    """
    if controller not in CONTROLLERS:
        raise ValueError(f"controller: expected one of {CONTROLLERS}, got {controller!r}")
    preview = _check_preview(preview)
    if not preview and controller != "nmpc":
        raise ValueError(f"preview: only the NMPC has a no-preview variant (the LQR never previews, the "
                         f"optimum plans the whole course); got preview=False with controller {controller!r}")
    gamma = _check_gamma(gamma)
    cfg = DoubleLaneChangeModel(config).config
    horizon_steps = _horizon_steps(horizon, cfg.dt)
    period = _period(period)
    force = force_mean(disturbance_mean, cfg)
    seeds = _seeds(seeds)
    if controller == "nmpc":
        ctrl: Any = VehicleNMPC(cfg, horizon=horizon_steps * cfg.dt, gamma=gamma, force=force, period=period,
                                preview=preview)
    elif controller == "lqr":
        ctrl = straight_lqr(cfg, gamma=gamma, force=force)
    else:
        ctrl = CourseOptimum(cfg, force=force)
    per_seed, runs = [], []
    desc = f"{controller} gamma={1.0 if controller == 'optimum' else gamma:g}" + ("" if preview else " no preview")
    bar = tqdm(total=cfg.max_steps * len(seeds), desc=desc, unit="step",
               disable=not progress, leave=False)
    try:
        for seed in seeds:
            res, timing = drive(ctrl, cfg, seed=seed, progress=bar)
            runs.append(res)
            per_seed.append({"seed": seed, "lateral_mae": res.mean_abs_lateral_error,
                             "speed_mae": res.mean_abs_speed_error, "lateral_max": res.max_abs_lateral_error,
                             "speed_max": res.max_abs_speed_error, "cost": res.total_cost,
                             "terminated": res.terminated, **timing})
    finally:
        bar.close()
    keys = ("lateral_mae", "speed_mae", "lateral_max", "speed_max", "cost", "terminated",
            "solve_ms_mean", "solve_ms_max", "step_ms_mean", "step_ms_max")
    out: dict[str, Any] = {
        "controller": controller,
        "gamma": 1.0 if controller == "optimum" else gamma,
        "horizon": {"nmpc": horizon_steps * cfg.dt, "lqr": math.inf, "optimum": cfg.max_steps * cfg.dt}[controller],
        "period": period if controller == "nmpc" else None,
        "disturbance_mean": disturbance_mean, "force_N": force, "seeds": list(seeds),
        **({} if preview else {"preview": False}),
        **{k: float(np.mean([row[k] for row in per_seed])) for k in keys},
        "per_seed": per_seed,
    }
    if keep_trajectory:
        out["trajectories"] = runs
    return out


#: The rows of the "references, not learned" block: (label, run_reference keyword arguments).
REFERENCE_SETTINGS: tuple[tuple[str, dict[str, Any]], ...] = (
    ("whole-course optimum", {"controller": "optimum"}),
    ("NMPC 2 s, gamma=1, true mean", {"controller": "nmpc", "gamma": 1.0, "disturbance_mean": "true"}),
    ("NMPC 2 s, gamma=1, prior mean", {"controller": "nmpc", "gamma": 1.0, "disturbance_mean": "prior"}),
    ("NMPC 2 s, gamma=0.99, true mean", {"controller": "nmpc", "gamma": 0.99, "disturbance_mean": "true"}),
    ("NMPC 2 s, gamma=0.99, prior mean", {"controller": "nmpc", "gamma": 0.99, "disturbance_mean": "prior"}),
    ("LQR, gamma=1, true mean", {"controller": "lqr", "gamma": 1.0}),
    ("LQR, gamma=0.99, true mean", {"controller": "lqr", "gamma": 0.99}),
    # the NMPC without preview: it predicts on the reference's tangent at the car's X (VehicleNMPC)
    ("NMPC 2 s, gamma=1, true mean, no preview",
     {"controller": "nmpc", "gamma": 1.0, "disturbance_mean": "true", "preview": False}),
    ("NMPC 2 s, gamma=1, prior mean, no preview",
     {"controller": "nmpc", "gamma": 1.0, "disturbance_mean": "prior", "preview": False}),
    ("NMPC 2 s, gamma=0.99, true mean, no preview",
     {"controller": "nmpc", "gamma": 0.99, "disturbance_mean": "true", "preview": False}),
    ("NMPC 2 s, gamma=0.99, prior mean, no preview",
     {"controller": "nmpc", "gamma": 0.99, "disturbance_mean": "prior", "preview": False}),
    # the LQR (no preview either) with the prior's mean, beside the no-preview NMPC
    ("LQR, gamma=1, prior mean", {"controller": "lqr", "gamma": 1.0, "disturbance_mean": "prior"}),
    ("LQR, gamma=0.99, prior mean", {"controller": "lqr", "gamma": 0.99, "disturbance_mean": "prior"}),
)


def reference_row(label: str, *, seeds: Sequence[int] = (0, 1, 2), period: int = 1, horizon: float = 2.0,
                  progress: bool = False, keep_trajectory: bool = False) -> dict[str, Any]:
    """One row of :data:`REFERENCE_SETTINGS` (by its label): its :func:`run_reference` result plus ``"method"``.

    Raises
    ------
    ValueError
        Unknown ``label``, or a bad argument of :func:`run_reference`.
    """
    settings = dict(REFERENCE_SETTINGS)
    if label not in settings:
        raise ValueError(f"label: expected one of {list(settings)}, got {label!r}")
    kwargs = dict(settings[label])
    if kwargs["controller"] == "nmpc":
        kwargs.update(period=period, horizon=horizon)
    logger.info("reference row: %s", label)
    return {"method": label, **run_reference(seeds=seeds, progress=progress, keep_trajectory=keep_trajectory,
                                             **kwargs)}


def reference_rows(seeds: Sequence[int] = (0, 1, 2), *, period: int = 1, horizon: float = 2.0,
                   progress: bool = False, keep_trajectory: bool = False) -> list[dict[str, Any]]:
    """The reference rows for the reproduction's table ("references, not learned").

    Runs every entry of :data:`REFERENCE_SETTINGS` through :func:`run_reference` (:func:`reference_row`)
    and returns one dict per row: its result with a ``"method"`` label added.

    Parameters
    ----------
    seeds : sequence of int, optional
        Noise seeds (default ``(0, 1, 2)``).
    period : int, optional
        NMPC re-solve period [control steps].
    horizon : float, optional
        NMPC horizon [s].
    progress, keep_trajectory : bool, optional
        As :func:`run_reference`.

    Returns
    -------
    list of dict
    """
    return [reference_row(label, seeds=seeds, period=period, horizon=horizon, progress=progress,
                          keep_trajectory=keep_trajectory) for label, _ in REFERENCE_SETTINGS]


def jsonable(row: dict[str, Any]) -> dict[str, Any]:
    """A row of :func:`run_reference` without its trajectories, ready for :func:`json.dumps`."""
    out = {k: v for k, v in row.items() if k != "trajectories"}
    if isinstance(out.get("horizon"), float) and math.isinf(out["horizon"]):
        out["horizon"] = "infinite"
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m validation.nmpc``: run references and write ``references.json`` atomically.

    Without ``--controller`` it runs every row of :func:`reference_rows`; with it, one
    :func:`run_reference` per ``(controller, gamma, mean)`` combination given (``--no-preview``: the
    NMPC without preview).
    """
    parser = argparse.ArgumentParser(prog="python -m validation.nmpc", description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, help="output directory (references.json)")
    parser.add_argument("--controller", nargs="+", choices=CONTROLLERS, help="default: every reference row")
    parser.add_argument("--gamma", nargs="+", type=float, default=[0.99, 1.0])
    parser.add_argument("--mean", nargs="+", default=["true"], help="'true', 'prior', 'zero' or a force in N")
    parser.add_argument("--horizon", type=float, default=2.0, help="NMPC horizon [s]")
    parser.add_argument("--period", type=int, default=1, help="NMPC re-solve period [steps]")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--no-preview", action="store_true",
                        help="NMPC on the tangent line at the car's X (no path ahead); with --controller nmpc")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.controller is None:
        rows = reference_rows(args.seeds, period=args.period, horizon=args.horizon, progress=True)
    else:
        means = [m if m in MEAN_NAMES else float(m) for m in args.mean]
        if args.no_preview and set(args.controller) != {"nmpc"}:
            parser.error("--no-preview: only with --controller nmpc")
        rows = []
        for name in args.controller:
            for gamma in ([1.0] if name == "optimum" else args.gamma):
                for mean in means:
                    res = run_reference(name, gamma=gamma, horizon=args.horizon, disturbance_mean=mean,
                                        seeds=args.seeds, period=args.period, progress=True,
                                        preview=not args.no_preview)
                    tail = ", no preview" if args.no_preview else ""
                    rows.append({"method": f"{name}, gamma={gamma:g}, mean={mean}{tail}", **res})
    atomic_write_text(out / "references.json", json.dumps([jsonable(r) for r in rows], indent=2) + "\n")
    logger.info("wrote %s", out / "references.json")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
