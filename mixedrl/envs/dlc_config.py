"""The configuration of the double lane change, defined once for the environment and a run's task.

:class:`DoubleLaneChangeConfig` is what the environment needs; :class:`DoubleLaneChangeTaskConfig` adds
the discount of eq. (2) and the prior of eq. (55) and is a run's ``task`` section (dotted keys
``task.<field>``, ``task.cost.<field>``, ...; docs/vehicle.rst). The classes are frozen dataclasses;
:func:`make_config` and :meth:`DoubleLaneChangeConfig.from_dict` build them from (JSON-like) dicts.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from typing import Any, TypeVar

from mixedrl.checks import check_fields, check_number, check_unknown_keys
from mixedrl.envs.disturbance import Disturbance
from mixedrl.envs.reference import DoubleLaneChangeReference
from mixedrl.envs.vehicle import VehicleParams

__all__ = ["CostWeights", "DoubleLaneChangeConfig", "DoubleLaneChangeTaskConfig", "make_config"]

_C = TypeVar("_C")


#: The largest prior force moment (N) a task accepts: the IBE squares it (float64 overflows near 1e308).
MAX_PRIOR_FORCE = 1e100


@dataclass(frozen=True)
class CostWeights:
    """Weights of the utility of eq. (54), charged on the next state (eq. 2).

    .. math:: l = T\\,\\big(q_v (v_x - v_{des})^2 + q_y\\, e_y^2 + r_\\delta\\, \\delta^2 + r_a\\, a_x^2\\big)

    A run sets them with ``task.cost.<field>``.

    Attributes
    ----------
    q_speed : float
        Weight of the squared speed error ``(v_x - 12)^2``. Paper: 45.
    q_lateral : float
        Weight of the squared lateral error ``e_y^2``. Paper: 60.
    r_steer : float
        Weight of the squared steering angle ``delta^2``. Paper: 800.
    r_accel : float
        Weight of the squared acceleration ``a_x^2``. Paper: 1.

    Raises
    ------
    ValueError
        A weight is not a finite number >= 0 (the message starts with its name).
    """

    q_speed: float = 45.0
    q_lateral: float = 60.0
    r_steer: float = 800.0
    r_accel: float = 1.0

    def __post_init__(self) -> None:
        check_fields(self, nonneg=True)


def _numbers(value: Any, name: str, **kind: bool) -> tuple[float, ...]:
    """``value`` (a list or tuple of numbers) as a tuple of floats, each checked by ``check_number``."""
    if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple)):
        raise ValueError(f"{name}: expected a list of numbers, got {value!r}")
    return tuple(check_number(v, name, **kind) for v in value)


@dataclass(frozen=True)
class DoubleLaneChangeConfig:
    """Everything that defines the double-lane-change environment.

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
    cost : CostWeights
        Weights of eq. (54): 45, 60, 800, 1 (also readable, and accepted by :func:`make_config`, as the
        flat ``q_speed``, ``q_lateral``, ``r_steer``, ``r_accel``).
    v_des : float
        Desired speed [m/s]. Paper: 12.
    course_length : float
        Length of the course along ``X`` [m]; the episode lasts ``round(course_length / (v_des T))``
        steps (default 120 m: 2000 steps, 10 s).
    preview_distances : tuple of float
        Look-ahead distances ``d_i`` [m] of the optional reference preview in the observation (default
        none: the observation is the paper's 5-dim relative state ``[v_y, r, v_x - 12, e_phi, e_y]``).
    delta_max : float
        Bound on ``|delta|`` [rad]. Default 0.4.
    ax_max : float
        Bound on ``|a_x|`` [m/s^2]. Default 4.
    max_lateral_error : float
        The car has left the road when ``|e_y| > max_lateral_error`` [m]. Default 3.
    min_speed : float
        Episodes terminate when ``v_x < min_speed`` [m/s] (the bicycle model is a forward-driving model).
        Default 1.
    reset_half_widths : tuple of 5 floats
        Half-widths of the uniform start perturbation of ``[v_y, r, v_x - v_des, e_phi, e_y]`` at
        ``X = 0`` for ``reset`` (default ``(0, 0, 0.1, 0.02, 0.1)``).
    train_half_widths : tuple of 5 floats
        Same for :meth:`~mixedrl.envs.model.DoubleLaneChangeModel.reset_states` (training states
        anywhere on the course, ``X ~ U(0, course_length)``); default ``(0.3, 0.2, 1.0, 0.1, 1.0)``.

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
    cost: CostWeights = field(default_factory=CostWeights)
    v_des: float = 12.0
    course_length: float = 120.0
    preview_distances: tuple[float, ...] = ()
    delta_max: float = 0.4
    ax_max: float = 4.0
    max_lateral_error: float = 3.0
    min_speed: float = 1.0
    reset_half_widths: tuple[float, ...] = (0.0, 0.0, 0.1, 0.02, 0.1)
    train_half_widths: tuple[float, ...] = (0.3, 0.2, 1.0, 0.1, 1.0)

    def __post_init__(self) -> None:
        for name, cls in _nested(type(self)).items():
            if not isinstance(getattr(self, name), cls):
                raise ValueError(f"{name}: expected {cls.__name__}, got {type(getattr(self, name)).__name__}")
        if self.scheme not in ("euler", "rk4"):
            raise ValueError(f"scheme: expected 'euler' or 'rk4', got {self.scheme!r}")
        check_fields(self, ("dt", "v_des", "course_length", "delta_max", "ax_max", "max_lateral_error"), positive=True)
        check_fields(self, ("min_speed",), nonneg=True)
        object.__setattr__(self, "preview_distances",
                           _numbers(self.preview_distances, "preview_distances", positive=True))
        for name in ("reset_half_widths", "train_half_widths"):
            widths = _numbers(getattr(self, name), name, nonneg=True)
            if len(widths) != 5:
                raise ValueError(f"{name}: expected 5 half-widths [v_y, r, v_x, e_phi, e_y], got {len(widths)}")
            object.__setattr__(self, name, widths)

    # the weights of eq. (54), also readable flat
    q_speed = property(lambda self: self.cost.q_speed, doc="``cost.q_speed``.")
    q_lateral = property(lambda self: self.cost.q_lateral, doc="``cost.q_lateral``.")
    r_steer = property(lambda self: self.cost.r_steer, doc="``cost.r_steer``.")
    r_accel = property(lambda self: self.cost.r_accel, doc="``cost.r_accel``.")

    @property
    def max_steps(self) -> int:
        """Episode length ``round(course_length / (v_des T))`` [steps]."""
        return max(1, round(self.course_length / (self.v_des * self.dt)))

    @classmethod
    def from_dict(cls: type[_C], values: dict[str, Any], where: str = "") -> _C:
        """Build a config from a (JSON-like) dict; the nested fields (``params``, ``reference``,
        ``disturbance``, ``cost``) may be dicts of their own fields. Missing fields take the defaults.

        Parameters
        ----------
        values : dict
            Field values.
        where : str, optional
            The dotted place of ``values`` in a larger configuration (``"task"`` in a run's
            :class:`~mixedrl.config.TrainConfig`); errors then name the full dotted key.

        Raises
        ------
        ValueError
            On an unknown key at any level, or an invalid value (naming the field).
        """
        if not isinstance(values, dict):
            raise ValueError(f"{where or 'values'}: expected a dict (a JSON object), got {values!r}")
        if not where:
            return make_config(cls(), **values)
        return _merge(cls(), values, where, dotted=True)

    def to_dict(self) -> dict[str, Any]:
        """A JSON-serialisable dict that :meth:`from_dict` turns back into this config (tuples as lists)."""
        return json.loads(json.dumps(dataclasses.asdict(self)))  # nested dicts, tuples as lists


@dataclass(frozen=True)
class DoubleLaneChangeTaskConfig(DoubleLaneChangeConfig):
    """The experiment of Section VI: the double lane change with a random longitudinal force.

    :class:`DoubleLaneChangeConfig` plus the learning problem: a run's ``task`` section. The prior of
    eq. (55) is given in force units and acts on ``v_x``: ``mu_M = prior_force_mean T / m``,
    ``K_M = (prior_force_std T / m)^2``, ``1e-20`` on the other four components of ``xi``.

    Attributes
    ----------
    name : str
        Always ``"dlc"`` for this class (selects it when a run's configuration is loaded).
    gamma : float
        Discount factor of eq. (2), in (0, 1). Default 0.99.
    prior_force_mean : float
        The designer's prior mean of ``F_dis`` [N] (eq. 55; paper: 150).
    prior_force_std : float
        The designer's prior standard deviation ``sqrt(K_M)`` in force units [N] (paper: 4).
    obs_scale : tuple of float or None
        The observation's typical magnitudes (the networks' input scaling, the sampler's box and kicks),
        ``5 + len(preview_distances)`` positive numbers. ``None`` (default): ``(0.3, 0.2, 0.5, 0.1, 0.5)``
        and 2 m for every preview column.

    Raises
    ------
    ValueError
        If any field is invalid (the message starts with its name).
    """

    name: str = "dlc"
    gamma: float = 0.99
    prior_force_mean: float = 150.0
    prior_force_std: float = 4.0
    obs_scale: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.obs_scale is not None:
            scale = _numbers(self.obs_scale, "obs_scale", positive=True)
            expected = 5 + len(self.preview_distances)
            if len(scale) != expected:
                raise ValueError(f"obs_scale: expected 5 + len(preview_distances) = {expected} numbers, "
                                 f"got {len(scale)}")
            object.__setattr__(self, "obs_scale", scale)
        if self.name != "dlc":
            raise ValueError(f"name: expected 'dlc' for DoubleLaneChangeTaskConfig, got {self.name!r}")
        check_fields(self, ("gamma", "prior_force_mean", "prior_force_std"), positive=("prior_force_std",))
        if not 0.0 < self.gamma < 1.0:
            raise ValueError(f"gamma: expected a number in (0, 1), got {self.gamma!r}")
        for name in ("prior_force_mean", "prior_force_std"):
            if abs(getattr(self, name)) > MAX_PRIOR_FORCE:
                raise ValueError(f"{name}: |{getattr(self, name)!r}| N exceeds {MAX_PRIOR_FORCE:g} N: the IBE forms "
                                 f"second moments of the force, which would overflow float64")


#: The flat keys of the cost weights that :func:`make_config` accepts (moved into ``cost``).
_FLAT_COST = tuple(f.name for f in dataclasses.fields(CostWeights))


def _nested(cls: type) -> dict[str, type]:
    """Field name -> dataclass type, for the fields of ``cls`` that are configurations themselves."""
    return {f.name: f.default_factory for f in dataclasses.fields(cls)
            if f.default_factory is not dataclasses.MISSING and dataclasses.is_dataclass(f.default_factory)}


def _merge(base: _C, values: dict[str, Any], where: str, dotted: bool) -> _C:
    """``base`` with ``values`` applied, dicts merged into nested fields. ``where`` is the dotted place of
    ``values`` (``""`` at the top); ``dotted`` reports unknown keys by their full dotted name."""
    prefix = f"{where}." if where else ""
    allowed = {f.name for f in dataclasses.fields(base) if f.init}
    if dotted or not where:
        check_unknown_keys({prefix + k: v for k, v in values.items()}, {prefix + k for k in allowed}, "config")
    else:
        check_unknown_keys(values, allowed, where)
    if not values:
        return base  # nothing to change: the configuration itself, not a copy
    values = dict(values)
    for name, cls in _nested(type(base)).items():
        if name in values and not isinstance(values[name], cls):
            if not isinstance(values[name], dict):
                raise ValueError(f"{prefix}{name}: expected a dict (a JSON object) or a {cls.__name__}, "
                                 f"got {values[name]!r}")
            values[name] = _merge(getattr(base, name), values[name], prefix + name, dotted)
    try:
        return dataclasses.replace(base, **values)
    except ValueError as exc:
        if not where:
            raise
        raise ValueError(f"{prefix}{exc}") from None


def make_config(config: DoubleLaneChangeConfig | dict[str, Any] | None = None, **overrides: Any
                ) -> DoubleLaneChangeConfig:
    """Return ``config`` (default: the paper's task) with ``overrides`` applied.

    Parameters
    ----------
    config : DoubleLaneChangeConfig or dict, optional
        Base configuration (a :class:`DoubleLaneChangeTaskConfig` stays one).
    **overrides
        Field values; the nested ``params``, ``reference``, ``disturbance`` and ``cost`` may be given as
        dicts of their own fields (merged into the base values). The flat weights ``q_speed``,
        ``q_lateral``, ``r_steer``, ``r_accel`` are moved into ``cost``.

    Returns
    -------
    DoubleLaneChangeConfig

    Raises
    ------
    ValueError
        Unknown keys (at any level) or invalid values; the message starts with the (dotted) field name.
    """
    if isinstance(config, dict):
        config, overrides = None, {**config, **overrides}
    config = DoubleLaneChangeConfig() if config is None else config
    if not isinstance(config, DoubleLaneChangeConfig):
        raise ValueError(f"config: expected DoubleLaneChangeConfig or dict, got {type(config).__name__}")
    flat = {k: overrides.pop(k) for k in _FLAT_COST if k in overrides}
    if flat:
        cost = overrides.get("cost", {})
        if isinstance(cost, CostWeights):
            cost = dataclasses.asdict(cost)
        if not isinstance(cost, dict):
            raise ValueError(f"cost: expected a dict (a JSON object) or a CostWeights, got {cost!r}")
        overrides["cost"] = {**cost, **flat}
    return _merge(config, overrides, "", dotted=False)
