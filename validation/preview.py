"""The preview study's references and tools (docs/references.rst, "Mixed RL with path preview"):
the NMPC that knows the path only ``reach`` metres ahead (:class:`LimitedPreviewNMPC`), a plain-NumPy copy
of a run's actor (:class:`NumpyActor`, :func:`actor_weights`) and the per-distance scale of the preview
columns (:func:`preview_scale`). Used by ``experiments/analysis/preview_study.py`` and its tests.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

__all__ = ["LimitedPreviewNMPC", "NumpyActor", "actor_weights", "preview_scale"]


class LimitedPreviewNMPC:
    """The 2 s NMPC of :class:`validation.nmpc.VehicleNMPC` that knows the path only ``reach`` metres ahead.

    At each solve, with the car at ``X_c`` and ``X_e = X_c + reach``, it charges eq. (54) against

    .. math:: Y_{lim}(X) = Y_{ref}(\\min(X, X_e)) + \\tan\\psi_{ref}(X_e)\\,\\max(X - X_e, 0),

    the true path up to ``X_e`` continued by its tangent there (``reach = 0``: the no-preview NMPC's
    tangent at the car). Everything else (model, mean, discount, horizon, warm start) is the NMPC's.

    Parameters
    ----------
    reach : float
        Preview distance ``D`` >= 0 [m].
    **kwargs
        Passed to :class:`validation.nmpc.VehicleNMPC` (``horizon``, ``gamma``, ``force``).

    Raises
    ------
    ValueError
        ``reach`` negative or not finite.
    """

    def __init__(self, reach: float, **kwargs: Any) -> None:
        import casadi as ca

        from validation import nmpc

        if not (isinstance(reach, (int, float)) and np.isfinite(reach) and reach >= 0):
            raise ValueError(f"reach: expected a finite distance >= 0 [m], got {reach!r}")
        self.reach = float(reach)
        self.inner = nmpc.VehicleNMPC(preview=False, **kwargs)
        model = self.inner.model
        cfg = model.config
        s, u, theta = ca.SX.sym("s", 6), ca.SX.sym("u", 2), ca.SX.sym("theta", 3)
        # theta = [X_e, Y_ref(X_e), slope(X_e)];  Y_lim(X) = Y_ref(min(X, X_e)) + slope_e max(X - X_e, 0)
        y_lim = model.lateral(ca.fmin(s[5], theta[0])) + theta[2] * ca.fmax(s[5] - theta[0], 0)
        e_y, dv = s[4] - y_lim, s[2] - cfg.v_des
        cost = ca.Function("l_limited", [s, u, theta],
                           [cfg.dt * (cfg.q_speed * dv * dv + cfg.q_lateral * e_y * e_y
                                      + cfg.r_steer * u[0] * u[0] + cfg.r_accel * u[1] * u[1])])
        bound = np.array([cfg.delta_max, cfg.ax_max])
        self.inner.core = nmpc.RecedingHorizon(nmpc._predict_step(ca, model, self.inner.force), cost,
                                               horizon_steps=self.inner.horizon_steps,
                                               gamma=self.inner.core.gamma, u_min=-bound, u_max=bound)
        self.config = cfg
        self.solve_ms = self.inner.solve_ms

    def reset(self) -> None:
        """Start a new episode."""
        self.inner.reset()
        self.solve_ms = self.inner.solve_ms

    def __call__(self, s: np.ndarray) -> np.ndarray:
        """The first input of the plan for tracking state ``s`` (shape (6,))."""
        from validation import nmpc

        inner, k = self.inner, self.inner._k
        s = np.asarray(s, dtype=np.float64)
        X_e = float(s[5]) + self.reach
        line = nmpc._tangent_line(self.config, X_e)
        guess = None
        if inner._plan is None:
            guess = nmpc._reference_guess(self.config, s, inner.horizon_steps)
        sol = inner.core.solve(s, step=k, guess=guess, theta=line)
        inner.solve_ms.append(sol.solve_ms)
        inner._plan, inner._plan_step = sol.u, k
        inner._k += 1
        return sol.u[0].copy()


class NumpyActor:
    """The forward pass of a :class:`mixedrl.networks.Actor` in plain NumPy (float64), for deployment.

    ``u = bound * tanh(W_L(... elu(W_1 (o / scale) + b_1) ...) + b_L)``: the same weights, no torch call.

    Parameters
    ----------
    state_dict : dict
        ``actor.state_dict()`` of an :class:`~mixedrl.networks.Actor` with ELU hidden layers (tensors or
        nested lists, as :func:`actor_weights` writes them).

    Raises
    ------
    ValueError
        ``state_dict`` lacks the actor's buffers or a layer's shapes do not chain.
    """

    def __init__(self, state_dict: dict[str, Any]) -> None:
        arrays = {k: np.asarray(v.detach().numpy() if isinstance(v, torch.Tensor) else v, dtype=np.float64)
                  for k, v in state_dict.items()}
        for key in ("action_bound", "net.input_scale"):
            if key not in arrays:
                raise ValueError(f"state_dict: expected the actor's {key!r}, got keys {sorted(arrays)}")
        self.bound, self.inv_scale = arrays["action_bound"], 1.0 / arrays["net.input_scale"]
        idx = sorted({int(k.split(".")[2]) for k in arrays if k.startswith("net.body.")})
        self.layers = [(arrays[f"net.body.{i}.weight"], arrays[f"net.body.{i}.bias"]) for i in idx]
        width = self.inv_scale.shape[0]
        for W, b in self.layers:
            if W.shape[1] != width or b.shape != (W.shape[0],):
                raise ValueError(f"state_dict: layer of shape {W.shape} does not follow a width of {width}")
            width = W.shape[0]
        self.obs_dim = self.inv_scale.shape[0]

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """The action for one observation (shape (obs_dim,)): shape (2,)."""
        z = obs * self.inv_scale
        for W, b in self.layers[:-1]:
            z = W @ z + b
            z = np.where(z > 0.0, z, np.expm1(np.minimum(z, 0.0)))  # ELU
        W, b = self.layers[-1]
        return self.bound * np.tanh(W @ z + b)


def actor_weights(actor: torch.nn.Module) -> dict[str, list[Any]]:
    """``actor.state_dict()`` as nested lists (exact float32 values), for the per-run JSON."""
    return {k: v.detach().double().tolist() for k, v in actor.state_dict().items()}


def preview_scale(task: Any) -> torch.Tensor:
    """``max_X |Y_ref(X + d_i) - Y_ref(X)|`` over the course (``X`` in [0, course_length], 1 cm grid) for
    each preview distance of the task: each preview column then lies in [-1, 1] on the path."""
    cfg = task.model.config
    X = np.linspace(0.0, cfg.course_length, int(round(cfg.course_length * 100)) + 1)
    return torch.tensor([float(np.abs(cfg.reference.lateral(X + d) - cfg.reference.lateral(X)).max())
                         for d in cfg.preview_distances], dtype=torch.float32)
