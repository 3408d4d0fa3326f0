"""Double-lane-change tracking: the shared model ``f`` (eqs. 53-54), cost, noise and a torch vector env.

How the reference enters (EQUATIONS.md, point 11)
-------------------------------------------------
Eq. (53) is kept literally as the body dynamics, in a road-fixed frame: ``phi`` is the yaw angle and
``y = Y`` the lateral position of the centre of gravity, so ``dY/dt = v_x sin(phi) + v_y cos(phi)`` is
eq. (53)'s last row. The longitudinal position ``X`` is added, ``dX/dt = v_x cos(phi) - v_y sin(phi)``,
and the deterministic *tracking state* is

.. math:: s = [v_y,\\ r,\\ v_x,\\ \\phi,\\ Y,\\ X] \\quad (6 \\text{ components; the first five obey eq. 53}).

The reference (:class:`~mixedrl.envs.reference.DoubleLaneChangeReference`) never enters the dynamics;
it enters only through the relative quantities that the paper calls ``y`` and ``phi``,

.. math:: e_y = Y - Y_{ref}(X), \\qquad e_\\phi = \\phi - \\psi_{ref}(X),

which appear in the policy's observation and in the cost (eq. 54). The environment that makes data
and the model that plans call the same :class:`~mixedrl.envs.vehicle.VehicleDynamics`; the only
difference is the additive noise ``xi = F_dis T / m`` on ``v_x`` (index :data:`NOISE_INDEX`).

One true step
-------------
The true environment, ``s' = f(s, u) + E xi`` (eq. 1 for this task), is written once:
:meth:`DoubleLaneChangeModel.true_step`. Training (:meth:`mixedrl.tasks.DoubleLaneChangeTask.true_step`),
:class:`DoubleLaneChangeVectorEnv`, the Gymnasium env (:mod:`mixedrl.envs.dlc_env`) and the Table I
evaluation (:func:`~mixedrl.envs.evaluate_tracking`, which drives the Gymnasium env) all call it; each
keeps its own random stream (see the method's Notes).

The column functions :func:`tracking_errors`, :func:`observation_columns`,
:func:`observation_from_errors` and :func:`stage_cost` compute the errors, the observation and the
cost of eq. (54) on Python floats, numpy arrays or torch tensors; the model and the Gymnasium env share
them.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from mixedrl.checks import check_number, check_positive_int, check_unknown_keys
from mixedrl.config import DISTURBANCE_LAWS
from mixedrl.envs.reference import DoubleLaneChangeReference
from mixedrl.envs.vehicle import VX_INDEX, VehicleDynamics, VehicleParams

__all__ = [
    "Disturbance",
    "DoubleLaneChangeConfig",
    "DoubleLaneChangeModel",
    "DoubleLaneChangeVectorEnv",
    "NOISE_INDEX",
    "STATE_DIM",
    "ACTION_DIM",
    "make_config",
    "observation_columns",
    "observation_from_errors",
    "stage_cost",
    "tracking_errors",
]

#: Index of the state component that the disturbance acts on (``v_x``; EQUATIONS.md, point 6).
NOISE_INDEX = VX_INDEX
#: Dimension of the tracking state ``s = [v_y, r, v_x, phi, Y, X]``.
STATE_DIM = 6
#: Dimension of the input ``u = [delta, a_x]``.
ACTION_DIM = 2


@dataclass(frozen=True)
class Disturbance:
    """Random longitudinal disturbance force ``F_dis`` (eq. 53) and its noise ``xi = F_dis T / m`` (eq. 54).

    Attributes
    ----------
    law : str
        Distribution of ``F_dis`` around its mean, one of :data:`mixedrl.config.DISTURBANCE_LAWS`; every
        law has the mean and the variance below (see Notes). Default ``"gaussian"`` (the paper's).
    mean : float
        Mean force on a level road [N]. Paper: 261.
    variance : float
        Variance of ``F_dis`` [N^2]. Paper: 32 (``N(mean, covariance)``; EQUATIONS.md, point 7).
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
    State-dependent mean (for the Case-3 estimator, eq. 19): with a road grade
    ``theta(X) = grade_amplitude * sin(2 pi X / grade_wavelength + grade_phase)`` the mean force is
    ``mean - m g sin(theta(X))`` (an uphill grade slows the car), evaluated at the state *before* the
    step. ``F_dis`` has that mean and variance ``variance``, independent across steps:

    .. math:: F_{dis} = \\bar F(X) + \\sigma z, \\qquad E z = 0, \\quad \\mathrm{Var}\\, z = 1,

    with the standardised draw ``z`` of the law (:meth:`standard_noise`):

    * ``"gaussian"``: ``z ~ N(0, 1)`` (the paper's ``N(261, 32)``); excess kurtosis 0;
    * ``"student_t"``: ``z = t sqrt((nu - 2) / nu)``, ``t`` Student-t with ``nu = dof`` degrees of
      freedom (variance ``nu / (nu - 2)``, hence the rescale), i.e. ``F_dis`` is Student-t with scale
      ``sqrt(variance (nu - 2) / nu)``; heavy tails: excess kurtosis ``6 / (nu - 4)`` for ``nu > 4``,
      infinite for ``2 < nu <= 4``;
    * ``"bumps"``: ``z = -1`` or ``+1`` with probability 1/2 each, i.e. ``F_dis = mean -+ sqrt(variance)``
      (a symmetric two-point law); excess kurtosis -2, the smallest of any law.

    The planners (IBE, prior, oracle) model the noise as a Gaussian; only the true environment draws
    from the law.
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
        for f in dataclasses.fields(self):
            if f.name != "law":
                object.__setattr__(self, f.name, check_number(
                    getattr(self, f.name), f.name, positive=f.name == "grade_wavelength",
                    nonneg=f.name == "variance"))
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

        .. math:: F_{dis} = \\bar F(X) + \\sigma z

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
        The Gaussian law draws exactly what the package drew before the other laws existed
        (``torch.randn`` / ``Generator.standard_normal``, one normal per state, in order), so every
        published number is unchanged. The Student-t draw uses ``Generator.standard_t`` on numpy and
        Bailey's polar method on torch (uniform pairs ``(U, V)`` in the unit disc, ``W = U^2 + V^2``,
        ``t = U sqrt(nu (W^(-2/nu) - 1) / W)``, exact for any ``nu > 0``; R. W. Bailey, Math. Comp. 62
        (1994) 779-781), since torch has no Student-t sampler that takes a generator. The two-point law
        draws one uniform per state: ``z = -1`` if it is below 1/2, else ``+1``.
        """
        if generator is None or isinstance(generator, torch.Generator):
            if shape is None:
                raise ValueError("shape: a torch draw needs a shape")
            return _standard_noise_torch(self, tuple(shape), generator, dtype, device)
        if not isinstance(generator, np.random.Generator):
            raise ValueError(f"generator: expected a torch.Generator or a numpy.random.Generator, got "
                             f"{type(generator).__name__}")
        if self.law == "gaussian":
            return generator.standard_normal(shape)
        if self.law == "student_t":
            # z = t sqrt((nu - 2) / nu), t ~ Student-t(nu): variance 1
            return generator.standard_t(self.dof, shape) * math.sqrt((self.dof - 2.0) / self.dof)
        u = generator.random(shape)
        if shape is None:
            return -1.0 if u < 0.5 else 1.0
        return np.where(u < 0.5, -1.0, 1.0)

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


@dataclass(frozen=True)
class DoubleLaneChangeConfig:
    """Everything that defines the double-lane-change task (one typed, documented object).

    Attributes
    ----------
    params : VehicleParams
        Vehicle parameters (paper values by default).
    dt : float
        Sampling time ``T`` [s]. Paper: 1/200.
    scheme : str
        Discretisation of ``f``, ``"euler"`` (default; see :meth:`VehicleDynamics.__call__`) or ``"rk4"``.
    reference : DoubleLaneChangeReference
        The reference path.
    disturbance : Disturbance
        The true disturbance (used by the environments only; planners bring their own noise model).
    v_des : float
        Desired speed [m/s]. Paper: 12.
    course_length : float
        Length of the course along ``X`` [m]; the episode lasts ``round(course_length / (v_des T))``
        steps (default 120 m: 2000 steps, 10 s).
    preview_distances : tuple of float
        Look-ahead distances ``d_i`` [m] of the optional reference preview in the observation (default
        none: the observation is the paper's 5-dim relative state).
    delta_max : float
        Bound on ``|delta|`` [rad]. Default 0.4.
    ax_max : float
        Bound on ``|a_x|`` [m/s^2]. Default 4.
    max_lateral_error : float
        The car has left the road when ``|e_y| > max_lateral_error`` [m]. Default 3.
    min_speed : float
        Episodes terminate when ``v_x < min_speed`` [m/s] (the bicycle model is a forward-driving model).
        Default 1.
    q_speed, q_lateral, r_steer, r_accel : float
        Weights of eq. (54): 45, 60, 800, 1.
    reset_half_widths : tuple of 5 floats
        Half-widths of the uniform start perturbation of ``[v_y, r, v_x - v_des, e_phi, e_y]`` at
        ``X = 0`` for ``reset`` (default ``(0, 0, 0.1, 0.02, 0.1)``).
    train_half_widths : tuple of 5 floats
        Same for :meth:`DoubleLaneChangeModel.reset_states` (training states, ``X ~ U(0, course_length)``);
        default ``(0.3, 0.2, 1.0, 0.1, 1.0)``.

    Raises
    ------
    ValueError
        If any field is invalid (the message starts with its name).
    """

    params: VehicleParams = field(default_factory=VehicleParams)
    dt: float = 1.0 / 200.0
    scheme: str = "euler"
    reference: DoubleLaneChangeReference = field(default_factory=DoubleLaneChangeReference)
    disturbance: Disturbance = field(default_factory=Disturbance)
    v_des: float = 12.0
    course_length: float = 120.0
    preview_distances: tuple[float, ...] = ()
    delta_max: float = 0.4
    ax_max: float = 4.0
    max_lateral_error: float = 3.0
    min_speed: float = 1.0
    q_speed: float = 45.0
    q_lateral: float = 60.0
    r_steer: float = 800.0
    r_accel: float = 1.0
    reset_half_widths: tuple[float, ...] = (0.0, 0.0, 0.1, 0.02, 0.1)
    train_half_widths: tuple[float, ...] = (0.3, 0.2, 1.0, 0.1, 1.0)

    def __post_init__(self) -> None:
        if not isinstance(self.params, VehicleParams):
            raise ValueError(f"params: expected VehicleParams, got {type(self.params).__name__}")
        if not isinstance(self.reference, DoubleLaneChangeReference):
            raise ValueError(f"reference: expected DoubleLaneChangeReference, got {type(self.reference).__name__}")
        if not isinstance(self.disturbance, Disturbance):
            raise ValueError(f"disturbance: expected Disturbance, got {type(self.disturbance).__name__}")
        if self.scheme not in ("euler", "rk4"):
            raise ValueError(f"scheme: expected 'euler' or 'rk4', got {self.scheme!r}")
        for name in ("dt", "v_des", "course_length", "delta_max", "ax_max", "max_lateral_error"):
            object.__setattr__(self, name, check_number(getattr(self, name), name, positive=True))
        for name in ("min_speed", "q_speed", "q_lateral", "r_steer", "r_accel"):
            object.__setattr__(self, name, check_number(getattr(self, name), name, nonneg=True))
        preview = tuple(check_number(d, "preview_distances", positive=True) for d in self.preview_distances)
        object.__setattr__(self, "preview_distances", preview)
        for name in ("reset_half_widths", "train_half_widths"):
            widths = tuple(check_number(w, name, nonneg=True) for w in getattr(self, name))
            if len(widths) != 5:
                raise ValueError(f"{name}: expected 5 half-widths [v_y, r, v_x, e_phi, e_y], got {len(widths)}")
            object.__setattr__(self, name, widths)

    @property
    def max_steps(self) -> int:
        """Episode length ``round(course_length / (v_des T))`` [steps]."""
        return max(1, round(self.course_length / (self.v_des * self.dt)))

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> "DoubleLaneChangeConfig":
        """Build a config from a (JSON-like) dict; nested ``params``/``reference``/``disturbance`` may be dicts.

        Raises
        ------
        ValueError
            On an unknown key at any level.
        """
        return make_config(None, **values)

    def to_dict(self) -> dict[str, Any]:
        """A JSON-serialisable dict that :meth:`from_dict` turns back into this config."""
        out = dataclasses.asdict(self)
        for key in ("preview_distances", "reset_half_widths", "train_half_widths"):
            out[key] = list(out[key])
        return out


_NESTED = {"params": VehicleParams, "reference": DoubleLaneChangeReference, "disturbance": Disturbance}


def make_config(config: DoubleLaneChangeConfig | dict[str, Any] | None = None, **overrides: Any
                ) -> DoubleLaneChangeConfig:
    """Return ``config`` (default: the paper's task) with ``overrides`` applied.

    Parameters
    ----------
    config : DoubleLaneChangeConfig or dict, optional
        Base configuration.
    **overrides
        Field values; nested ``params``, ``reference`` and ``disturbance`` may be given as dicts of
        their own fields (merged into the base values).

    Returns
    -------
    DoubleLaneChangeConfig

    Raises
    ------
    ValueError
        Unknown keys (at any level) or invalid values.
    """
    if isinstance(config, dict):
        overrides = {**config, **overrides}
        config = None
    if config is None:
        config = DoubleLaneChangeConfig()
    if not isinstance(config, DoubleLaneChangeConfig):
        raise ValueError(f"config: expected DoubleLaneChangeConfig or dict, got {type(config).__name__}")
    allowed = {f.name for f in dataclasses.fields(DoubleLaneChangeConfig)}
    check_unknown_keys(overrides, allowed, "config")
    for key, cls in _NESTED.items():
        if isinstance(overrides.get(key), dict):
            sub = overrides[key]
            check_unknown_keys(sub, {f.name for f in dataclasses.fields(cls)}, key)
            overrides[key] = dataclasses.replace(getattr(config, key), **sub)
    return dataclasses.replace(config, **overrides)


# ----------------------------------------------------------------------------------------------------
# Column functions: the relative quantities, observation and cost of eq. (54) on one backend's columns.
# Each works on Python floats (the Gymnasium environment's fast single step), numpy arrays and torch
# tensors alike; :class:`DoubleLaneChangeModel` calls them on the columns of a batched state.
# ----------------------------------------------------------------------------------------------------
def tracking_errors(cfg: DoubleLaneChangeConfig, phi: Any, Y: Any, X: Any) -> tuple[Any, Any]:
    """Lateral and heading errors of a tracking state against the reference (module docstring).

    .. math:: e_y = Y - Y_{ref}(X), \\qquad e_\\phi = \\phi - \\psi_{ref}(X)

    Parameters
    ----------
    cfg : DoubleLaneChangeConfig
        The task (its ``reference``).
    phi, Y, X : float, numpy.ndarray or torch.Tensor, shape (...)
        Yaw angle [rad], lateral and longitudinal position [m] (same backend).

    Returns
    -------
    tuple
        ``(e_y, e_phi)``, each of the type and shape of ``X``.
    """
    y_ref, psi_ref = cfg.reference.lateral_and_heading(X)
    # e_y = Y - Y_ref(X) ;  e_phi = phi - psi_ref(X)
    return Y - y_ref, phi - psi_ref


def observation_from_errors(cfg: DoubleLaneChangeConfig, vy: Any, r: Any, vx: Any, e_phi: Any, e_y: Any,
                            X: Any, y_ref: Any) -> list[Any]:
    """The observation's columns from already computed errors (see :meth:`DoubleLaneChangeModel.observe`).

    .. math:: o = [v_y,\\ r,\\ v_x - v_{des},\\ e_\\phi,\\ e_y,\\
                   Y_{ref}(X + d_1) - Y_{ref}(X), \\dots]

    Parameters
    ----------
    cfg : DoubleLaneChangeConfig
        The task (``v_des``, ``preview_distances``, ``reference``).
    vy, r, vx, e_phi, e_y, X : float, numpy.ndarray or torch.Tensor, shape (...)
        Components of the state and its errors (:func:`tracking_errors`).
    y_ref : float, numpy.ndarray or torch.Tensor, shape (...)
        ``Y_ref(X)`` (reused for the preview differences).

    Returns
    -------
    list
        ``5 + len(preview_distances)`` columns, each of shape (...).
    """
    feats = [vy, r, vx - cfg.v_des, e_phi, e_y]
    for d in cfg.preview_distances:
        feats.append(cfg.reference.lateral(X + d) - y_ref)
    return feats


def observation_columns(cfg: DoubleLaneChangeConfig, vy: Any, r: Any, vx: Any, phi: Any, Y: Any, X: Any
                        ) -> list[Any]:
    """The observation's columns of the tracking state ``[v_y, r, v_x, phi, Y, X]`` (one column each).

    Parameters
    ----------
    cfg : DoubleLaneChangeConfig
        The task.
    vy, r, vx, phi, Y, X : float, numpy.ndarray or torch.Tensor, shape (...)
        The six components of the tracking state.

    Returns
    -------
    list
        As :func:`observation_from_errors`.
    """
    y_ref, psi_ref = cfg.reference.lateral_and_heading(X)
    return observation_from_errors(cfg, vy, r, vx, phi - psi_ref, Y - y_ref, X, y_ref)


def stage_cost(cfg: DoubleLaneChangeConfig, dv: Any, e_y: Any, delta: Any, ax: Any) -> Any:
    """Implements eq. (54)'s utility on columns (charged on the next state, eq. 2).

    .. math:: l = T\\,\\big(q_v\\, \\Delta v^2 + q_y\\, e_y^2 + r_\\delta\\, \\delta^2 + r_a\\, a_x^2\\big)

    with the paper's weights ``(45, 60, 800, 1)`` by default.

    Parameters
    ----------
    cfg : DoubleLaneChangeConfig
        The task (``dt`` and the weights).
    dv, e_y : float, numpy.ndarray or torch.Tensor, shape (...)
        Speed error ``v_x' - v_des`` [m/s] and lateral error ``e_y'`` [m] of the next state.
    delta, ax : float, numpy.ndarray or torch.Tensor, shape (...)
        The applied input.

    Returns
    -------
    float, numpy.ndarray or torch.Tensor, shape (...)
        The cost (>= 0).
    """
    # l(x', u) = T (45 (v_x - 12)^2 + 60 y^2 + u^T diag(800, 1) u)   (eq. 54, charged on the next state)
    return cfg.dt * (cfg.q_speed * dv * dv + cfg.q_lateral * e_y * e_y
                     + cfg.r_steer * delta * delta + cfg.r_accel * ax * ax)


def _cost_cols(cfg: DoubleLaneChangeConfig, vx: Any, Y: Any, X: Any, delta: Any, ax: Any) -> Any:
    return stage_cost(cfg, vx - cfg.v_des, Y - cfg.reference.lateral(X), delta, ax)


def _is_torch(x: Any) -> bool:
    return isinstance(x, torch.Tensor)


def _stack(cols: list[Any], like: Any) -> Any:
    if _is_torch(like):
        return torch.stack(torch.broadcast_tensors(*cols), dim=-1)
    return np.stack(np.broadcast_arrays(*cols), axis=-1)


def _check_state(s: Any, name: str = "s") -> Any:
    if not _is_torch(s):
        s = np.asarray(s, dtype=np.float64)
    if s.ndim < 1 or s.shape[-1] != STATE_DIM:
        raise ValueError(f"{name}: expected shape (..., {STATE_DIM}), got {tuple(s.shape)}")
    return s


def _check_action(u: Any, like: Any, name: str = "u") -> Any:
    if _is_torch(like) != _is_torch(u):
        raise ValueError(f"{name}: must be of the same backend (torch or numpy) as the state")
    if not _is_torch(u):
        u = np.asarray(u, dtype=np.float64)
    if u.ndim < 1 or u.shape[-1] != ACTION_DIM:
        raise ValueError(f"{name}: expected shape (..., {ACTION_DIM}), got {tuple(u.shape)}")
    return u


def _student_t_torch(dof: float, n: int, generator: torch.Generator | None, device: str | torch.device
                     ) -> torch.Tensor:
    """``n`` Student-t draws with ``dof`` degrees of freedom (float64), Bailey's polar method."""
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


def _standard_noise_torch(dist: Disturbance, shape: tuple[int, ...], generator: torch.Generator | None,
                          dtype: torch.dtype, device: str | torch.device) -> torch.Tensor:
    if dist.law == "gaussian":
        return torch.randn(shape, generator=generator, dtype=dtype, device=device)
    n = math.prod(shape)
    if dist.law == "student_t":
        # z = t sqrt((nu - 2) / nu): variance 1
        z = _student_t_torch(dist.dof, n, generator, device) * math.sqrt((dist.dof - 2.0) / dist.dof)
    else:  # "bumps": z = -1 or +1 with probability 1/2 each
        u = torch.rand(n, generator=generator, dtype=torch.float64, device=device)
        z = torch.where(u < 0.5, -1.0, 1.0).to(torch.float64)
    return z.reshape(shape).to(dtype)


def _check_numpy_generator(generator: Any) -> None:
    if not isinstance(generator, np.random.Generator):
        raise ValueError(f"generator: expected a numpy.random.Generator for a numpy state, got "
                         f"{type(generator).__name__}")


class DoubleLaneChangeModel:
    """The deterministic model of the double-lane-change task, for planning (torch) and checking (numpy).

    This is the object the Algorithm-2 code plans with. Every method is batched over leading dimensions
    and works on torch tensors (differentiable, float32/float64) and numpy arrays.

    Parameters
    ----------
    config : DoubleLaneChangeConfig or dict, optional
        The task (default: the paper's).
    compile : bool, optional
        Fuse the torch step with :func:`torch.compile` (see :class:`VehicleDynamics`). Default False.

    Raises
    ------
    ValueError
        Invalid config.

    Attributes
    ----------
    config : DoubleLaneChangeConfig
    dynamics : VehicleDynamics
        The shared ``f`` (eq. 53 discretised).
    reference : DoubleLaneChangeReference
    state_dim, obs_dim, action_dim : int
        6, ``5 + len(preview_distances)``, 2.
    noise_index : int
        :data:`NOISE_INDEX` (= 2, ``v_x``).
    action_bound : numpy.ndarray, shape (2,)
        ``[delta_max, ax_max]``; the environments clip actions to ``[-bound, bound]``.

    Examples
    --------
    >>> import torch
    >>> from mixedrl.envs import DoubleLaneChangeModel
    >>> model = DoubleLaneChangeModel()
    >>> s = model.reset_states(4, torch.Generator().manual_seed(0), dtype=torch.float64)
    >>> u = torch.zeros(4, 2, dtype=torch.float64)
    >>> s_next = model.step(s, u)             # deterministic f on the tracking state
    >>> tuple(model.observe(s_next).shape), tuple(model.cost(s_next, u).shape)
    ((4, 5), (4,))
    """

    STATE_DIM = STATE_DIM
    ACTION_DIM = ACTION_DIM
    NOISE_INDEX = NOISE_INDEX

    def __init__(self, config: DoubleLaneChangeConfig | dict[str, Any] | None = None, *, compile: bool = False
                 ) -> None:
        self.config = make_config(config)
        cfg = self.config
        self.dynamics = VehicleDynamics(cfg.params, cfg.dt, cfg.scheme, compile=compile)
        self.reference = cfg.reference
        self.state_dim = STATE_DIM
        self.action_dim = ACTION_DIM
        self.obs_dim = 5 + len(cfg.preview_distances)
        self.noise_index = NOISE_INDEX
        self.action_bound = np.array([cfg.delta_max, cfg.ax_max])

    def __repr__(self) -> str:
        return f"DoubleLaneChangeModel(config={self.config!r})"

    # --- dynamics ---------------------------------------------------------------------------------
    def step(self, s: Any, u: Any) -> Any:
        """Deterministic ``f`` on the tracking state: implements eq. (54)'s ``f`` (eq. 53 discretised).

        .. math:: s_{t+1} = f(s_t, u_t) + \\xi_t e_{v_x}, \\qquad (\\text{this method returns } f(s_t, u_t))

        Parameters
        ----------
        s : torch.Tensor or numpy.ndarray, shape (..., 6)
            Tracking state ``[v_y, r, v_x, phi, Y, X]``.
        u : torch.Tensor or numpy.ndarray, shape (..., 2)
            Input ``[delta, a_x]``, *not* clipped (use :meth:`squash_action` or :meth:`clip_action`).

        Returns
        -------
        torch.Tensor or numpy.ndarray, shape (..., 6)
            ``f(s, u)``.

        Raises
        ------
        ValueError
            Wrong shapes, mixed backends/dtypes (and NaN/inf on the numpy path).
        """
        s = _check_state(s)
        u = _check_action(u, s)
        return self.dynamics(s, u)

    # --- relative quantities, observation, cost --------------------------------------------------
    def errors(self, s: Any) -> tuple[Any, Any]:
        """Lateral and heading errors ``(e_y, e_phi) = (Y - Y_ref(X), phi - psi_ref(X))``, each shape (...)."""
        s = _check_state(s)
        return tracking_errors(self.config, s[..., 3], s[..., 4], s[..., 5])

    def paper_state(self, s: Any) -> Any:
        """The paper's ``x = [v_y, r, v_x, phi, y]`` with ``phi``, ``y`` relative to the reference.

        Returns ``[v_y, r, v_x, e_phi, e_y]``, shape (..., 5).
        """
        s = _check_state(s)
        e_y, e_phi = tracking_errors(self.config, s[..., 3], s[..., 4], s[..., 5])
        return _stack([s[..., 0], s[..., 1], s[..., 2], e_phi, e_y], s)

    def observe(self, s: Any) -> Any:
        """The policy's observation of a tracking state.

        .. math:: o = [v_y,\\ r,\\ v_x - v_{des},\\ e_\\phi,\\ e_y,\\
                       Y_{ref}(X + d_1) - Y_{ref}(X), \\dots]

        Parameters
        ----------
        s : torch.Tensor or numpy.ndarray, shape (..., 6)

        Returns
        -------
        torch.Tensor or numpy.ndarray, shape (..., obs_dim)
            ``obs_dim = 5 + len(preview_distances)``.

        Raises
        ------
        ValueError
            Wrong shape.
        """
        s = _check_state(s)
        cols = observation_columns(self.config, *(s[..., i] for i in range(STATE_DIM)))
        return _stack(cols, s)

    def cost(self, s_next: Any, u: Any) -> Any:
        """Stage cost charged on the next state: implements eq. (54) (with eq. 2's convention).

        .. math:: l(s', u) = T\\,\\big(45 (v_x' - 12)^2 + 60\\, e_y'^2 + 800\\, \\delta^2 + a_x^2\\big)

        Parameters
        ----------
        s_next : torch.Tensor or numpy.ndarray, shape (..., 6)
            Next tracking state.
        u : torch.Tensor or numpy.ndarray, shape (..., 2)
            The input applied.

        Returns
        -------
        torch.Tensor or numpy.ndarray, shape (...)
            Cost (>= 0).

        Raises
        ------
        ValueError
            Wrong shapes or mixed backends.
        """
        s_next = _check_state(s_next, "s_next")
        u = _check_action(u, s_next)
        return _cost_cols(self.config, s_next[..., 2], s_next[..., 4], s_next[..., 5], u[..., 0], u[..., 1])

    def is_terminated(self, s: Any) -> Any:
        """True where the car has left the road (``|e_y| > max_lateral_error``), ``v_x < min_speed``, or
        a component is not finite. Shape (...), bool."""
        s = _check_state(s)
        cfg = self.config
        e_y, _ = tracking_errors(cfg, s[..., 3], s[..., 4], s[..., 5])
        if _is_torch(s):
            finite = torch.isfinite(s).all(dim=-1)
            return ~finite | ~(e_y.abs() <= cfg.max_lateral_error) | ~(s[..., 2] >= cfg.min_speed)
        finite = np.isfinite(s).all(axis=-1)
        with np.errstate(invalid="ignore"):
            return ~finite | ~(np.abs(e_y) <= cfg.max_lateral_error) | ~(s[..., 2] >= cfg.min_speed)

    # --- actions ----------------------------------------------------------------------------------
    def clip_action(self, u: Any) -> Any:
        """Clip ``u`` to ``[-action_bound, action_bound]`` (what the environments do). Shape (..., 2)."""
        if _is_torch(u):
            bound = torch.as_tensor(self.action_bound, dtype=u.dtype, device=u.device)
            return torch.maximum(torch.minimum(u, bound), -bound)
        return np.clip(np.asarray(u, dtype=np.float64), -self.action_bound, self.action_bound)

    def squash_action(self, raw: torch.Tensor) -> torch.Tensor:
        """Map an unbounded tensor into the action box: ``u = action_bound * tanh(raw)`` (differentiable)."""
        bound = torch.as_tensor(self.action_bound, dtype=raw.dtype, device=raw.device)
        return bound * torch.tanh(raw)

    # --- noise --------------------------------------------------------------------------------------
    def xi_mean(self, s: Any) -> Any:
        """Mean of the true noise ``xi = F_dis T / m`` on ``v_x`` at state ``s`` [m/s], shape (...)."""
        s = _check_state(s)
        cfg = self.config
        return cfg.disturbance.mean_force(s[..., 5], cfg.params.m, cfg.params.g) * (cfg.dt / cfg.params.m)

    @property
    def xi_std(self) -> float:
        """Standard deviation of the true noise ``xi`` [m/s] (``std(F_dis) T / m``)."""
        cfg = self.config
        return cfg.disturbance.std * cfg.dt / cfg.params.m

    def sample_force(self, s: Any, generator: torch.Generator | np.random.Generator | None) -> Any:
        """Draw the true disturbance force ``F_dis`` [N] at each state (eq. 53; road grade honoured).

        .. math:: F_{dis} = \\bar F(X) + \\sigma\\, z, \\qquad E z = 0,\\ \\mathrm{Var}\\, z = 1, \\qquad
                  \\bar F(X) = \\text{mean} - m g \\sin\\theta(X)

        (:meth:`Disturbance.mean_force`; ``sigma`` = :attr:`Disturbance.std`), one standardised draw
        ``z`` of the configured law per state (:meth:`Disturbance.standard_noise`: a standard normal for
        the default ``"gaussian"``), drawn from ``generator``.

        Parameters
        ----------
        s : torch.Tensor, numpy.ndarray or tuple of 6 floats
            Tracking state(s), shape (..., 6); a tuple is one unbatched state (the Gymnasium env's path).
        generator : torch.Generator, numpy.random.Generator or None
            A :class:`torch.Generator` (or None: torch's global generator) for a torch state, a
            :class:`numpy.random.Generator` for a numpy or tuple state.

        Returns
        -------
        torch.Tensor, numpy.ndarray or float
            ``F_dis``, shape (...) (a float for a tuple state).

        Raises
        ------
        ValueError
            Wrong shape, or a generator of the other backend.
        """
        cfg = self.config
        if isinstance(s, tuple):
            _check_numpy_generator(generator)
            if len(s) != STATE_DIM:
                raise ValueError(f"s: expected {STATE_DIM} floats, got {len(s)}")
            z = float(cfg.disturbance.standard_noise(generator))
            return cfg.disturbance.mean_force(s[5], cfg.params.m, cfg.params.g) + cfg.disturbance.std * z
        s = _check_state(s)
        mean = cfg.disturbance.mean_force(s[..., 5], cfg.params.m, cfg.params.g)
        if _is_torch(s):
            if generator is not None and not isinstance(generator, torch.Generator):
                raise ValueError(f"generator: expected a torch.Generator for a torch state, got "
                                 f"{type(generator).__name__}")
            noise = cfg.disturbance.standard_noise(generator, tuple(s.shape[:-1]), dtype=s.dtype, device=s.device)
        else:
            _check_numpy_generator(generator)
            noise = cfg.disturbance.standard_noise(generator, tuple(s.shape[:-1]))
        return mean + cfg.disturbance.std * noise

    def true_step(self, s: Any, u: Any, generator: torch.Generator | np.random.Generator | None = None, *,
                  force: Any = None) -> Any:
        """One step of the *true* environment: implements eq. (1) for the vehicle (eqs. 53-54).

        .. math::

            s_{t+1} = f(s_t, u_t) + E\\, \\xi_t, \\qquad \\xi_t = F_{dis,t}\\, T / m, \\qquad
            F_{dis,t} = \\bar F(X_t) + \\sigma z_t

        (``z_t`` the configured law's standardised draw, a standard normal by default: ``F_dis ~
        N(mean, variance)``), where ``f`` is :meth:`step`, ``E`` the unit vector of ``v_x``
        (:meth:`noise_vector`) and the force is drawn at the state *before* the step
        (:meth:`sample_force`, so a road grade and the law are honoured).
        This is the one true-environment step of the package: :meth:`mixedrl.tasks.DoubleLaneChangeTask.true_step`
        (training), :class:`DoubleLaneChangeVectorEnv`, the Gymnasium env
        :class:`~mixedrl.envs.dlc_env.DoubleLaneChangeEnv` and hence :func:`~mixedrl.envs.evaluate_tracking`
        all call it.

        Parameters
        ----------
        s : torch.Tensor, numpy.ndarray or tuple of 6 floats
            Tracking state(s) ``[v_y, r, v_x, phi, Y, X]``, shape (..., 6); a tuple is one unbatched
            state on Python floats (the Gymnasium env's fast path; ``u`` is then a pair of floats).
        u : torch.Tensor, numpy.ndarray or tuple of 2 floats
            Input ``[delta, a_x]``, shape (..., 2), same backend (and dtype) as ``s``; not clipped here.
        generator : torch.Generator or numpy.random.Generator, optional
            Source of the force when ``force`` is not given (see :meth:`sample_force`).
        force : torch.Tensor, numpy.ndarray or float, shape (...), optional
            An already drawn ``F_dis`` [N]; then ``generator`` is not used (and must be None).

        Returns
        -------
        torch.Tensor, numpy.ndarray or tuple of 6 floats
            The next state, of the type (and dtype) of ``s``.

        Raises
        ------
        ValueError
            Wrong shapes, mixed backends, both ``generator`` and ``force`` given.

        Notes
        -----
        Why the draw can be passed in: each caller keeps its own random stream (training and the vector
        env a :class:`torch.Generator`; the Gymnasium env Gymnasium's ``np_random``, which seeds the
        evaluation episodes of Table I). A caller that reports the force (the environments' ``info``)
        draws it with :meth:`sample_force` and passes ``force=``; the others pass the generator. Either
        way the draws are made in the same order from the same generator as before this function
        existed, so the published numbers are unchanged. The tuple path adds ``xi`` to ``v_x`` alone
        (the other components of ``E xi`` are zero) and returns Python floats: it is the same formula,
        evaluated with :mod:`math` (:meth:`VehicleDynamics.step_scalar`), for speed.
        """
        if force is None:
            force = self.sample_force(s, generator)
        elif generator is not None:
            raise ValueError("generator: pass either a generator or an already drawn force, not both")
        xi = self.xi_from_force(force)
        if isinstance(s, tuple):
            # s' = f(s, u) + xi e_vx   (eq. 54), on Python floats
            nxt = list(self.dynamics.step_scalar(s, u))
            nxt[NOISE_INDEX] += xi
            return tuple(nxt)
        # s' = f(s, u) + E xi,  E xi = xi e_vx   (eqs. 1, 54)
        return self.step(s, u) + self.noise_vector(xi)

    def xi_from_force(self, force: Any) -> Any:
        """``xi = F_dis T / m`` (eq. 54) [m/s]."""
        return force * (self.config.dt / self.config.params.m)

    def noise_vector(self, xi: Any) -> Any:
        """Embed scalar noise ``xi`` (shape (...)) into the state space: shape (..., 6), zero except ``v_x``."""
        if _is_torch(xi):
            out = torch.zeros(*xi.shape, STATE_DIM, dtype=xi.dtype, device=xi.device)
        else:
            xi = np.asarray(xi, dtype=np.float64)
            out = np.zeros(xi.shape + (STATE_DIM,))
        out[..., NOISE_INDEX] = xi
        return out

    # --- state distributions ------------------------------------------------------------------------
    def _states_from_errors(self, X: torch.Tensor, dev: torch.Tensor) -> torch.Tensor:
        cfg = self.config
        ref = cfg.reference
        vy, r, dvx, e_phi, e_y = dev.unbind(-1)
        return torch.stack([vy, r, cfg.v_des + dvx, ref.heading(X) + e_phi, ref.lateral(X) + e_y, X], dim=-1)

    def reset_states(self, n: int, generator: torch.Generator | None = None, *, dtype: torch.dtype = torch.float32,
                     device: str | torch.device = "cpu") -> torch.Tensor:
        """Training start states: ``X ~ U(0, course_length)``, relative state uniform in ``train_half_widths``.

        Parameters
        ----------
        n : int
            Number of states.
        generator : torch.Generator, optional
            Source of randomness (pass a seeded one for reproducibility).
        dtype, device
            Of the returned tensor.

        Returns
        -------
        torch.Tensor, shape (n, 6)
            ``[v_y, r, v_des + dv_x, psi_ref(X) + e_phi, Y_ref(X) + e_y, X]``.

        Raises
        ------
        ValueError
            If ``n`` is not a positive int.
        """
        n = check_positive_int(n, "n")
        cfg = self.config
        X = cfg.course_length * torch.rand(n, generator=generator, dtype=dtype, device=device)
        w = torch.tensor(cfg.train_half_widths, dtype=dtype, device=device)
        dev = w * (2.0 * torch.rand(n, 5, generator=generator, dtype=dtype, device=device) - 1.0)
        return self._states_from_errors(X, dev)

    def initial_states(self, n: int, generator: torch.Generator | None = None, *,
                       dtype: torch.dtype = torch.float32, device: str | torch.device = "cpu",
                       along: bool = False) -> torch.Tensor:
        """Episode start states (``X = 0``, perturbation uniform in ``reset_half_widths``), shape (n, 6).

        With ``along=True`` each start is at ``X ~ U(0, course_length)`` instead (on the reference there,
        the same small perturbation): starts spread along the whole course.
        """
        n = check_positive_int(n, "n")
        cfg = self.config
        if along:
            X = cfg.course_length * torch.rand(n, generator=generator, dtype=dtype, device=device)
        else:
            X = torch.zeros(n, dtype=dtype, device=device)
        w = torch.tensor(cfg.reset_half_widths, dtype=dtype, device=device)
        dev = w * (2.0 * torch.rand(n, 5, generator=generator, dtype=dtype, device=device) - 1.0)
        return self._states_from_errors(X, dev)


class DoubleLaneChangeVectorEnv:
    """Batched torch version of the environment: ``num_envs`` cars, same ``f``, true noise, autoreset.

    Parameters
    ----------
    num_envs : int
        Batch size.
    config : DoubleLaneChangeConfig or dict, optional
        The task.
    dtype : torch.dtype, optional
        float32 (default) or float64.
    device : str or torch.device, optional
        Default ``"cpu"``.
    seed : int, optional
        Seed of the internal :class:`torch.Generator` (start states and noise).
    compile : bool, optional
        Fuse ``f`` with :func:`torch.compile`.

    Raises
    ------
    ValueError
        Invalid arguments.

    Notes
    -----
    ``step(u)`` clips ``u`` to the action box, applies ``s' = f(s, u) + xi e_vx`` with
    ``xi = F_dis T / m`` drawn at the current state (:meth:`DoubleLaneChangeModel.true_step`), returns the reward ``-l(s', u)`` (eq. 54),
    ``terminated`` (:meth:`DoubleLaneChangeModel.is_terminated`) and ``truncated`` (time limit), and
    resets finished cars *in the same call* (their returned observation is the new start's; the
    pre-reset next state and observation are in ``info["next_state"]`` and ``info["final_obs"]``).
    ``info["state"]`` is the state the action was applied in, so
    ``(info["state"], info["action"], info["next_state"])`` are the data triples of eq. (9).
    """

    def __init__(self, num_envs: int, config: DoubleLaneChangeConfig | dict[str, Any] | None = None, *,
                 dtype: torch.dtype = torch.float32, device: str | torch.device = "cpu", seed: int | None = None,
                 compile: bool = False) -> None:
        self.num_envs = check_positive_int(num_envs, "num_envs")
        if dtype not in (torch.float32, torch.float64):
            raise ValueError(f"dtype: expected torch.float32 or torch.float64, got {dtype}")
        self.model = DoubleLaneChangeModel(config, compile=compile)
        self.config = self.model.config
        self.dtype = dtype
        self.device = torch.device(device)
        self.generator = torch.Generator(device=self.device)
        if seed is not None:
            self.generator.manual_seed(int(seed))
        self.state = torch.zeros(self.num_envs, STATE_DIM, dtype=dtype, device=self.device)
        self.elapsed = torch.zeros(self.num_envs, dtype=torch.long, device=self.device)
        self._bound = torch.as_tensor(self.model.action_bound, dtype=dtype, device=self.device)

    def reset(self, seed: int | None = None) -> torch.Tensor:
        """Reset every car; returns observations, shape (num_envs, obs_dim)."""
        if seed is not None:
            self.generator.manual_seed(int(seed))
        self.state = self.model.initial_states(self.num_envs, self.generator, dtype=self.dtype, device=self.device)
        self.elapsed.zero_()
        return self.model.observe(self.state)

    def step(self, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, dict[str, Any]]:
        """Advance every car one step (see class Notes).

        Parameters
        ----------
        u : torch.Tensor, shape (num_envs, 2)

        Returns
        -------
        obs : torch.Tensor, shape (num_envs, obs_dim)
        reward : torch.Tensor, shape (num_envs,)
        terminated, truncated : torch.Tensor of bool, shape (num_envs,)
        info : dict of tensors, each shape (num_envs, ...)

        Raises
        ------
        ValueError
            Wrong shape or dtype, or NaN/inf in ``u``; the state is then left unchanged.
        """
        if not isinstance(u, torch.Tensor) or tuple(u.shape) != (self.num_envs, ACTION_DIM):
            shape = tuple(u.shape) if isinstance(u, torch.Tensor) else type(u).__name__
            raise ValueError(f"u: expected a tensor of shape ({self.num_envs}, {ACTION_DIM}), got {shape}")
        if u.dtype != self.dtype:
            raise ValueError(f"u: expected dtype {self.dtype}, got {u.dtype}")
        if not bool(torch.isfinite(u).all()):
            raise ValueError("u: contains NaN or inf")
        model = self.model
        s = self.state
        u = torch.maximum(torch.minimum(u, self._bound), -self._bound)
        force = model.sample_force(s, self.generator)
        xi = model.xi_from_force(force)
        # s' = f(s, u) + xi e_vx   (eq. 54): the one true step
        s_next = model.true_step(s, u, force=force)
        reward = -model.cost(s_next, u)
        self.elapsed += 1
        terminated = model.is_terminated(s_next)
        truncated = (self.elapsed >= self.config.max_steps) & ~terminated
        e_y, _ = model.errors(s_next)
        final_obs = model.observe(s_next)
        info = {
            "state": s, "action": u, "next_state": s_next, "final_obs": final_obs,
            "xi": xi, "disturbance": force, "lateral_error": e_y,
            "speed_error": s_next[:, 2] - self.config.v_des,
        }
        done = terminated | truncated
        new_state = s_next
        if bool(done.any()):
            fresh = model.initial_states(self.num_envs, self.generator, dtype=self.dtype, device=self.device)
            new_state = torch.where(done[:, None], fresh, s_next)
            self.elapsed = torch.where(done, torch.zeros_like(self.elapsed), self.elapsed)
        self.state = new_state
        obs = final_obs if new_state is s_next else model.observe(new_state)
        return obs, reward, terminated, truncated, info
