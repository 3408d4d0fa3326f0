"""A batched torch double lane change: :class:`DoubleLaneChangeVectorEnv` (``num_envs`` cars, autoreset)."""

from __future__ import annotations

from typing import Any

import torch

from mixedrl.checks import check_finite, check_positive_int
from mixedrl.envs.dlc_config import DoubleLaneChangeConfig
from mixedrl.envs.model import ACTION_DIM, STATE_DIM, DoubleLaneChangeModel

__all__ = ["DoubleLaneChangeVectorEnv"]


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
    ``step(u)`` clips ``u`` to the action box, applies :meth:`DoubleLaneChangeModel.true_step` with the
    env's own generator, returns the reward ``-l(s', u)`` (eq. 54), ``terminated`` and ``truncated``
    (time limit), and resets finished cars in the same call (the pre-reset next state and observation
    are in ``info["next_state"]`` and ``info["final_obs"]``).
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
        check_finite(u, "u")
        model = self.model
        s = self.state
        u = model.clip_action(u)
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
        self.state, obs = s_next, final_obs
        if bool(done.any()):
            fresh = model.initial_states(self.num_envs, self.generator, dtype=self.dtype, device=self.device)
            self.state = torch.where(done[:, None], fresh, s_next)
            self.elapsed = torch.where(done, torch.zeros_like(self.elapsed), self.elapsed)
            obs = model.observe(self.state)
        return obs, reward, terminated, truncated, info
