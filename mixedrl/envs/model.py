"""The double-lane-change model Algorithm 2 plans with: :class:`DoubleLaneChangeModel`.

The deterministic ``f`` (eq. 53 discretised), the observation and cost of eq. (54), the true step
``f + E xi`` and the start distributions, batched, on torch tensors and numpy arrays.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from mixedrl.checks import check_positive_int
from mixedrl.envs.columns import observation_columns, stage_cost, tracking_errors
from mixedrl.envs.dlc_config import DoubleLaneChangeConfig, make_config
from mixedrl.envs.libm import ops_for
from mixedrl.envs.vehicle import VX_INDEX, VehicleDynamics

__all__ = ["ACTION_DIM", "NOISE_INDEX", "STATE_DIM", "DoubleLaneChangeModel"]

#: Index of the state component that the disturbance acts on (``v_x``).
NOISE_INDEX = VX_INDEX
#: Dimension of the tracking state ``s = [v_y, r, v_x, phi, Y, X]``.
STATE_DIM = 6
#: Dimension of the input ``u = [delta, a_x]``.
ACTION_DIM = 2


def _is_torch(x: Any) -> bool:
    return isinstance(x, torch.Tensor)


def _check(x: Any, dim: int, name: str, like: Any = None) -> Any:
    """``x`` (a tensor, or as a float64 array) of shape (..., dim), of the backend of ``like`` if given."""
    if like is not None and _is_torch(like) != _is_torch(x):
        raise ValueError(f"{name}: must be of the same backend (torch or numpy) as the state")
    if not _is_torch(x):
        x = np.asarray(x, dtype=np.float64)
    if x.ndim < 1 or x.shape[-1] != dim:
        raise ValueError(f"{name}: expected shape (..., {dim}), got {tuple(x.shape)}")
    return x


class DoubleLaneChangeModel:
    """The deterministic model of the double-lane-change task, for planning (torch) and checking (numpy).

    Every method is batched over leading dimensions; torch tensors are differentiable. Methods raise
    ``ValueError`` on a wrong last dimension or mixed backends (and NaN/inf in a numpy :meth:`step`).

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

    STATE_DIM = state_dim = STATE_DIM
    ACTION_DIM = action_dim = ACTION_DIM
    NOISE_INDEX = noise_index = NOISE_INDEX

    def __init__(self, config: DoubleLaneChangeConfig | dict[str, Any] | None = None, *, compile: bool = False
                 ) -> None:
        self.config = cfg = make_config(config)
        self.dynamics = VehicleDynamics(cfg.params, cfg.dt, cfg.scheme, compile=compile)
        self.reference = cfg.reference
        self.obs_dim = 5 + len(cfg.preview_distances)
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
        """
        s = _check(s, STATE_DIM, "s")
        u = _check(u, ACTION_DIM, "u", s)
        return self.dynamics(s, u)

    # --- relative quantities, observation, cost --------------------------------------------------
    def errors(self, s: Any) -> tuple[Any, Any]:
        """Lateral and heading errors ``(e_y, e_phi) = (Y - Y_ref(X), phi - psi_ref(X))``, each shape (...)."""
        s = _check(s, STATE_DIM, "s")
        return tracking_errors(self.config, s[..., 3], s[..., 4], s[..., 5])

    def paper_state(self, s: Any) -> Any:
        """The paper's ``x = [v_y, r, v_x, phi, y]`` with ``phi``, ``y`` relative to the reference.

        Returns ``[v_y, r, v_x, e_phi, e_y]``, shape (..., 5).
        """
        s = _check(s, STATE_DIM, "s")
        e_y, e_phi = tracking_errors(self.config, s[..., 3], s[..., 4], s[..., 5])
        return ops_for(s).stack([s[..., 0], s[..., 1], s[..., 2], e_phi, e_y])

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
        """
        s = _check(s, STATE_DIM, "s")
        return ops_for(s).stack(observation_columns(self.config, *(s[..., i] for i in range(STATE_DIM))))

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
        """
        s_next = _check(s_next, STATE_DIM, "s_next")
        u = _check(u, ACTION_DIM, "u", s_next)
        cfg, (vx, Y, X, delta, ax) = self.config, (s_next[..., 2], s_next[..., 4], s_next[..., 5], u[..., 0], u[..., 1])
        return stage_cost(cfg, vx - cfg.v_des, Y - cfg.reference.lateral(X), delta, ax)

    def is_terminated(self, s: Any) -> Any:
        """True where the car has left the road (``|e_y| > max_lateral_error``), ``v_x < min_speed``, or
        a component is not finite. Shape (...), bool."""
        s = _check(s, STATE_DIM, "s")
        cfg = self.config
        e_y, _ = tracking_errors(cfg, s[..., 3], s[..., 4], s[..., 5])
        finite = torch.isfinite(s).all(dim=-1) if _is_torch(s) else np.isfinite(s).all(axis=-1)
        with np.errstate(invalid="ignore"):
            return ~finite | ~(abs(e_y) <= cfg.max_lateral_error) | ~(s[..., 2] >= cfg.min_speed)

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
        s = _check(s, STATE_DIM, "s")
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

        with one draw ``z`` of the configured law per state
        (:meth:`~mixedrl.envs.disturbance.Disturbance.standard_noise`).

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
            A generator of the other backend.
        """
        cfg, dist = self.config, self.config.disturbance
        if isinstance(s, tuple):
            if len(s) != STATE_DIM:
                raise ValueError(f"s: expected {STATE_DIM} floats, got {len(s)}")
            X, shape = s[5], None
        else:
            s = _check(s, STATE_DIM, "s")
            X, shape = s[..., 5], tuple(s.shape[:-1])
        mean = dist.mean_force(X, cfg.params.m, cfg.params.g)
        if _is_torch(s):
            if generator is not None and not isinstance(generator, torch.Generator):
                raise ValueError(f"generator: expected a torch.Generator for a torch state, got "
                                 f"{type(generator).__name__}")
            noise = dist.standard_noise(generator, shape, dtype=s.dtype, device=s.device)
        elif not isinstance(generator, np.random.Generator):
            raise ValueError(f"generator: expected a numpy.random.Generator for a numpy state, got "
                             f"{type(generator).__name__}")
        else:
            noise = dist.standard_noise(generator, shape)
        return mean + dist.std * noise

    def true_step(self, s: Any, u: Any, generator: torch.Generator | np.random.Generator | None = None, *,
                  force: Any = None) -> Any:
        """One step of the *true* environment: implements eq. (1) for the vehicle (eqs. 53-54).

        .. math::

            s_{t+1} = f(s_t, u_t) + E\\, \\xi_t, \\qquad \\xi_t = F_{dis,t}\\, T / m, \\qquad
            F_{dis,t} = \\bar F(X_t) + \\sigma z_t

        where ``f`` is :meth:`step`, ``E`` the unit vector of ``v_x`` and the force is drawn at the state
        before the step (:meth:`sample_force`); every true-environment path calls it (docs/vehicle.rst).

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
            Both ``generator`` and ``force`` given.

        Notes
        -----
        A caller that reports the force draws it with :meth:`sample_force` and passes ``force=``.
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
    def _starts(self, n: int, generator: torch.Generator | None, widths: tuple[float, ...], along: bool,
                dtype: torch.dtype, device: str | torch.device) -> torch.Tensor:
        """``n`` states ``X`` (0, or ``U(0, course_length)`` when ``along``) on the reference, perturbed uniformly
        in ``+-widths``: ``[v_y, r, v_des + dv_x, psi_ref(X) + e_phi, Y_ref(X) + e_y, X]``."""
        n = check_positive_int(n, "n")
        cfg = self.config
        if along:
            X = cfg.course_length * torch.rand(n, generator=generator, dtype=dtype, device=device)
        else:
            X = torch.zeros(n, dtype=dtype, device=device)
        w = torch.tensor(widths, dtype=dtype, device=device)
        vy, r, dvx, e_phi, e_y = (w * (2.0 * torch.rand(n, 5, generator=generator, dtype=dtype, device=device)
                                       - 1.0)).unbind(-1)
        ref = cfg.reference
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
        return self._starts(n, generator, self.config.train_half_widths, True, dtype, device)

    def initial_states(self, n: int, generator: torch.Generator | None = None, *,
                       dtype: torch.dtype = torch.float32, device: str | torch.device = "cpu",
                       along: bool = False) -> torch.Tensor:
        """Episode start states (``X = 0``, perturbation uniform in ``reset_half_widths``), shape (n, 6).

        With ``along=True`` each start is at ``X ~ U(0, course_length)`` instead (on the reference there,
        the same small perturbation): starts spread along the whole course.
        """
        return self._starts(n, generator, self.config.reset_half_widths, along, dtype, device)
