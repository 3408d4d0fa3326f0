"""Column functions of the double lane change: the tracking errors, the observation and the cost of
eq. (54), on Python floats, numpy arrays or torch tensors alike.
"""

from __future__ import annotations

from typing import Any

from mixedrl.envs.dlc_config import DoubleLaneChangeConfig

__all__ = ["observation_columns", "observation_from_errors", "stage_cost", "tracking_errors"]


def tracking_errors(cfg: DoubleLaneChangeConfig, phi: Any, Y: Any, X: Any) -> tuple[Any, Any]:
    """Lateral and heading errors of a tracking state against the reference.

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
    return Y - y_ref, phi - psi_ref


def observation_from_errors(cfg: DoubleLaneChangeConfig, vy: Any, r: Any, vx: Any, e_phi: Any, e_y: Any,
                            X: Any, y_ref: Any) -> list[Any]:
    """The observation's columns from already computed errors
    (see :meth:`~mixedrl.envs.model.DoubleLaneChangeModel.observe`).

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
    return [vy, r, vx - cfg.v_des, e_phi, e_y] + [cfg.reference.lateral(X + d) - y_ref for d in cfg.preview_distances]


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
    w = cfg.cost
    return cfg.dt * (w.q_speed * dv * dv + w.q_lateral * e_y * e_y
                     + w.r_steer * delta * delta + w.r_accel * ax * ax)
