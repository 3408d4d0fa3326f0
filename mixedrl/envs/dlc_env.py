"""Gymnasium face of the double lane change: ``mixedrl/DoubleLaneChange-v0`` (docs/vehicle.rst)."""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from mixedrl.checks import as_vector, check_unknown_keys
from mixedrl.envs.columns import observation_from_errors, stage_cost
from mixedrl.envs.libm import MathOps
from mixedrl.envs.dlc_config import DoubleLaneChangeConfig, make_config
from mixedrl.envs.model import STATE_DIM, DoubleLaneChangeModel

__all__ = ["DoubleLaneChangeEnv"]


def _pair(value: Any, name: str, space: str) -> tuple[float, float]:
    """Validate a length-2 finite action as two floats: ``TypeError`` (naming the type and ``space``) if
    it is not real numbers, ``ValueError`` for a wrong shape or a NaN/inf component."""
    kind = ""
    try:
        a = np.asarray(value)
        kind = a.dtype.kind
        # refuse what would convert silently: strings, bytes, a lone object, complex numbers
        if kind in "USVc" or (kind == "O" and a.ndim == 0):
            raise TypeError
        a = a.astype(np.float64, copy=False)
    except (TypeError, ValueError) as exc:
        what = f"real numbers (got {a.dtype})" if kind == "c" else "a numeric array"
        raise TypeError(f"{name}: expected {what} in {space}, got {type(value).__name__} {value!r:.80}") from exc
    if a.shape != (2,):
        raise ValueError(f"{name}: expected shape (2,), got {a.shape}")
    a0, a1 = float(a[0]), float(a[1])
    if not (math.isfinite(a0) and math.isfinite(a1)):
        raise ValueError(f"{name}: contains NaN or inf ({a0!r}, {a1!r})")
    return a0, a1


class DoubleLaneChangeEnv(gym.Env):
    """Double lane change at 12 m/s with a random longitudinal disturbance (the paper's Section VI task).

    Description, action and observation spaces, rewards, starting state, episode end and arguments:
    docs/vehicle.rst ("Gymnasium environment"). One step is :meth:`DoubleLaneChangeModel.true_step` with
    ``F_dis`` drawn from ``self.np_random``; :meth:`step` takes the normalised action in ``[-1, 1]^2``,
    :meth:`step_physical` the physical ``u = [delta, a_x]``.

    ``info`` (reset and step): ``lateral_error`` ``e_y`` [m], ``speed_error`` ``v_x - 12`` [m/s],
    ``state`` (the tracking state, shape (6,)); step only: ``disturbance`` (true ``F_dis`` [N]),
    ``xi`` (``F_dis T / m`` [m/s]), ``action`` (the applied, clipped action), ``action_clipped``.
    """

    metadata = {"render_modes": [], "render_fps": 200}

    def __init__(self, config: DoubleLaneChangeConfig | dict[str, Any] | None = None,
                 render_mode: str | None = None, **overrides: Any) -> None:
        if render_mode is not None:
            raise ValueError(f"render_mode: this environment does not render, got {render_mode!r}")
        self.render_mode = None
        self.config = make_config(config, **overrides)
        self.model = DoubleLaneChangeModel(self.config)
        self.action_space = spaces.Box(low=-1.0, high=1.0, shape=(2,), dtype=np.float64)
        big = np.finfo(np.float64).max  # "any finite value" (Gymnasium's checker rejects infinite bounds)
        self.observation_space = spaces.Box(-big, big, shape=(self.model.obs_dim,), dtype=np.float64)
        self._state: tuple[float, ...] | None = None
        self._elapsed, self._done = 0, False

    @property
    def state(self) -> np.ndarray:
        """Current tracking state ``[v_y, r, v_x, phi, Y, X]``, shape (6,) (a copy)."""
        if self._state is None:
            raise RuntimeError("state: call reset() first")
        return np.array(self._state)

    def _observe(self, s: tuple[float, ...]) -> tuple[np.ndarray, dict[str, Any]]:
        """The observation of ``s`` and the ``info`` entries of every state."""
        cfg = self.config
        vy, r, vx, phi, Y, X = s
        y_ref, psi_ref = cfg.reference.lateral_and_heading(X)
        e_y = Y - y_ref
        obs = np.array(observation_from_errors(cfg, vy, r, vx, phi - psi_ref, e_y, X, y_ref), dtype=np.float64)
        return obs, {"lateral_error": e_y, "speed_error": vx - cfg.v_des, "state": np.array(s)}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start a new episode (see the class docstring, *Starting State*).

        Raises
        ------
        ValueError
            Unknown option, or ``options["state"]`` not a finite vector of shape (6,).
        """
        super().reset(seed=seed)
        options = {} if options is None else options
        check_unknown_keys(options, {"state"}, "options")
        cfg = self.config
        if "state" in options:
            s = tuple(as_vector(options["state"], "options['state']", STATE_DIM).tolist())
        else:
            dev = (self.np_random.uniform(-1.0, 1.0, size=5) * np.asarray(cfg.reset_half_widths)).tolist()
            y_ref, psi_ref = cfg.reference.lateral_and_heading(0.0)
            s = (dev[0], dev[1], cfg.v_des + dev[2], psi_ref + dev[3], y_ref + dev[4], 0.0)
        self._state, self._elapsed, self._done = s, 0, False
        return self._observe(s)

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """One step of ``T`` seconds with the normalised action ``a``: ``u = clip(a, -1, 1) * bound``.

        Raises
        ------
        TypeError
            ``action`` not numeric (a string, an object, ...); the message names its type and the space.
        ValueError
            ``action`` not of shape (2,) or not finite (the state is left unchanged).
        RuntimeError
            If called before :meth:`reset`, or after the episode ended (terminated or truncated) without
            a new :meth:`reset`.
        """
        a0, a1 = _pair(action, "action", str(self.action_space))
        c0, c1 = MathOps.clip(a0, -1.0, 1.0), MathOps.clip(a1, -1.0, 1.0)
        return self._step_physical(c0 * self.config.delta_max, c1 * self.config.ax_max, c0 != a0 or c1 != a1)

    def step_physical(self, u: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Same as :meth:`step`, with the physical input ``u = [delta, a_x]`` [rad, m/s^2].

        ``u`` is clipped to ``[-delta_max, delta_max] x [-ax_max, ax_max]``; errors as :meth:`step`.
        """
        d_max, a_max = self.config.delta_max, self.config.ax_max
        delta, ax = _pair(u, "u", f"[-{d_max}, {d_max}] x [-{a_max}, {a_max}]")
        delta_c, ax_c = MathOps.clip(delta, -d_max, d_max), MathOps.clip(ax, -a_max, a_max)
        return self._step_physical(delta_c, ax_c, delta_c != delta or ax_c != ax)

    def _step_physical(self, delta_c: float, ax_c: float, clipped: bool
                       ) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self._state is None:
            raise RuntimeError("step: call reset() before step()")
        if self._done:
            raise RuntimeError("step: the episode has ended (terminated or truncated); call reset() before "
                               "stepping again")
        cfg, model, s = self.config, self.model, self._state
        # F_dis = mean(X) + std z at the current state, from np_random; xi = F_dis T / m
        force = model.sample_force(s, self.np_random)
        xi = model.xi_from_force(force)
        # s' = f(s, u) + xi e_vx   (eq. 54): the one true step, on Python floats
        s_next = model.true_step(s, (delta_c, ax_c), force=force)
        self._state = s_next
        self._elapsed += 1
        obs, info = self._observe(s_next)
        e_y, vx = info["lateral_error"], s_next[2]
        reward = -stage_cost(cfg, vx - cfg.v_des, e_y, delta_c, ax_c)
        terminated = (not all(map(math.isfinite, s_next)) or not (abs(e_y) <= cfg.max_lateral_error)
                      or not (vx >= cfg.min_speed))
        truncated = (not terminated) and self._elapsed >= cfg.max_steps
        self._done = terminated or truncated
        info.update(disturbance=force, xi=xi, action=np.array((delta_c, ax_c)), action_clipped=clipped)
        return obs, float(reward), bool(terminated), bool(truncated), info
