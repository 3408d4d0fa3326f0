"""Table I metrics: drive the double lane change with a policy and measure the tracking errors."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import torch

from mixedrl.checks import as_vector, check_positive_int
from mixedrl.envs.dlc_env import DoubleLaneChangeEnv
from mixedrl.envs.dlc_config import DoubleLaneChangeConfig

__all__ = ["TrackingResult", "evaluate_tracking"]


@dataclass(frozen=True)
class TrackingResult:
    """Outcome of one drive through the course (see :func:`evaluate_tracking`).

    Attributes
    ----------
    mean_abs_lateral_error : float
        ``mean_t |e_y(s_t)|`` over the visited next states [m] (Table I, "position error").
    mean_abs_speed_error : float
        ``mean_t |v_x(s_t) - 12|`` [m/s] (Table I, "speed error").
    max_abs_lateral_error, max_abs_speed_error : float
        The maxima of the same sequences.
    total_cost : float
        Undiscounted sum of the eq. (54) costs.
    terminated : bool
        True if the episode ended early (left the road, too slow, non-finite).
    n_steps : int
        Number of steps driven.
    time : numpy.ndarray, shape (n_steps + 1,)
        ``t_k = k T`` [s].
    states : numpy.ndarray, shape (n_steps + 1, 6)
        Tracking states ``[v_y, r, v_x, phi, Y, X]`` including the start.
    observations : numpy.ndarray, shape (n_steps + 1, obs_dim)
    actions : numpy.ndarray, shape (n_steps, 2)
        Applied (clipped) actions.
    lateral_error, speed_error : numpy.ndarray, shape (n_steps + 1,)
        ``e_y`` [m] and ``v_x - 12`` [m/s] along the run (index 0 is the start).
    disturbance : numpy.ndarray, shape (n_steps,)
        True ``F_dis`` [N] at each step.
    costs : numpy.ndarray, shape (n_steps,)
        Stage costs ``l(s_{k+1}, u_k)``.
    """

    mean_abs_lateral_error: float
    mean_abs_speed_error: float
    max_abs_lateral_error: float
    max_abs_speed_error: float
    total_cost: float
    terminated: bool
    n_steps: int
    time: np.ndarray
    states: np.ndarray
    observations: np.ndarray
    actions: np.ndarray
    lateral_error: np.ndarray
    speed_error: np.ndarray
    disturbance: np.ndarray
    costs: np.ndarray

    def table_row(self) -> dict[str, float]:
        """The two Table I figures, namespaced: ``{"eval/lateral_error_m": ..., "eval/speed_error_mps": ...}``."""
        return {"eval/lateral_error_m": self.mean_abs_lateral_error,
                "eval/speed_error_mps": self.mean_abs_speed_error}


def _as_numpy_policy(policy: Any) -> Callable[[np.ndarray], np.ndarray]:
    if isinstance(policy, torch.nn.Module):
        params = list(policy.parameters())
        dtype = params[0].dtype if params else torch.float32
        device = params[0].device if params else torch.device("cpu")

        def call(obs: np.ndarray) -> np.ndarray:
            with torch.no_grad():
                out = policy(torch.as_tensor(obs, dtype=dtype, device=device))
            return out.detach().cpu().numpy()
        return call

    def call_plain(obs: np.ndarray) -> np.ndarray:
        out = policy(obs)
        if isinstance(out, torch.Tensor):
            out = out.detach().cpu().numpy()
        return out
    return call_plain


def evaluate_tracking(policy: Callable[[np.ndarray], Any] | torch.nn.Module,
                      config: DoubleLaneChangeConfig | dict[str, Any] | None = None, *,
                      seed: int = 0, start_state: np.ndarray | None = None,
                      max_steps: int | None = None, normalized_actions: bool = False) -> TrackingResult:
    """Drive one double lane change with ``policy`` and return the Table I metrics and the trajectory.

    Implements the evaluation behind Table I: mean absolute lateral error and mean absolute speed error
    over one run of the course under the true disturbance,

    .. math::

        \\bar e_y = \\frac1N \\sum_{k=1}^{N} |Y_k - Y_{ref}(X_k)|, \\qquad
        \\bar e_v = \\frac1N \\sum_{k=1}^{N} |v_{x,k} - 12|.

    Parameters
    ----------
    policy : callable or torch.nn.Module
        Maps an observation (numpy array of shape (obs_dim,); a tensor of the module's dtype for an
        ``nn.Module``) to an action of shape (2,). Actions are clipped to the action box.
    config : DoubleLaneChangeConfig or dict, optional
        The task (default: the paper's).
    seed : int, optional
        Seed of the disturbance sequence (and of the start perturbation if ``start_state`` is None).
    start_state : numpy.ndarray, shape (6,), optional
        Start tracking state. Default: exactly on the reference at ``X = 0``, 12 m/s, zero ``v_y``,
        ``r`` (deterministic start, so methods are compared on the same footing).
    max_steps : int, optional
        Stop after this many steps (default: the full course, ``config.max_steps``).
    normalized_actions : bool, optional
        False (default): the policy returns the physical input ``u = [delta, a_x]`` [rad, m/s^2], as the
        paper's ``pi(x)`` and :class:`~mixedrl.envs.DoubleLaneChangeModel` do. True: it returns the
        Gymnasium env's normalised action in ``[-1, 1]^2`` (e.g. a policy trained on the Gymnasium env).

    Returns
    -------
    TrackingResult
        Metrics averaged over the ``N`` next states ``s_1 .. s_N`` (the cost's convention), maxima and
        the full trajectory.

    Raises
    ------
    ValueError
        Bad ``start_state``, or the policy returns an action of the wrong shape or with NaN.

    Notes
    -----
    The paper does not say over which time span Table I averages; here it is the whole course (or until
    termination, which ``TrackingResult.terminated`` reports).

    Each step is the package's one true step, :meth:`~mixedrl.envs.DoubleLaneChangeModel.true_step`
    (called by the Gymnasium env this function drives), with ``F_dis`` drawn from the env's
    ``np_random`` seeded with ``seed``: the same transition as in training, on Python floats.
    """
    env = DoubleLaneChangeEnv(config)
    cfg = env.config
    if start_state is None:
        ref = cfg.reference
        start_state = np.array([0.0, 0.0, cfg.v_des, ref.heading(0.0), ref.lateral(0.0), 0.0])
    start_state = as_vector(start_state, "start_state", 6)
    n_max = cfg.max_steps if max_steps is None else check_positive_int(max_steps, "max_steps")
    call = _as_numpy_policy(policy)
    obs, info = env.reset(seed=seed, options={"state": start_state})
    states, observations, actions, forces, costs = [info["state"]], [obs], [], [], []
    lat, spd = [info["lateral_error"]], [info["speed_error"]]
    terminated = False
    for _ in range(n_max):
        action = np.asarray(call(obs), dtype=np.float64)
        if normalized_actions:
            obs, reward, terminated, truncated, info = env.step(action)
        else:
            obs, reward, terminated, truncated, info = env.step_physical(action)
        states.append(info["state"])
        observations.append(obs)
        actions.append(info["action"])
        forces.append(info["disturbance"])
        costs.append(-reward)
        lat.append(info["lateral_error"])
        spd.append(info["speed_error"])
        if terminated or truncated:
            break
    lat_a, spd_a = np.asarray(lat), np.asarray(spd)
    n = len(actions)
    return TrackingResult(
        mean_abs_lateral_error=float(np.mean(np.abs(lat_a[1:]))),
        mean_abs_speed_error=float(np.mean(np.abs(spd_a[1:]))),
        max_abs_lateral_error=float(np.max(np.abs(lat_a[1:]))),
        max_abs_speed_error=float(np.max(np.abs(spd_a[1:]))),
        total_cost=float(np.sum(costs)), terminated=bool(terminated), n_steps=n,
        time=np.arange(n + 1) * cfg.dt, states=np.asarray(states), observations=np.asarray(observations),
        actions=np.asarray(actions).reshape(n, 2), lateral_error=lat_a, speed_error=spd_a,
        disturbance=np.asarray(forces), costs=np.asarray(costs),
    )
