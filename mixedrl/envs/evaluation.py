"""Table I metrics: drive the double lane change with a policy and measure the tracking errors.

:func:`evaluate_tracking` drives one course; :func:`evaluate_courses` drives many courses of many
policies in lock step, with the same numbers (bit for bit with ``exact=True``).
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np
import torch

from mixedrl.checks import as_vector, check_positive_int, check_seed_lists
from mixedrl.envs.columns import observation_from_errors, stage_cost
from mixedrl.envs.dlc_env import DoubleLaneChangeEnv
from mixedrl.envs.dlc_config import DoubleLaneChangeConfig, make_config
from mixedrl.envs.libm import elementwise
from mixedrl.envs.model import DoubleLaneChangeModel
from mixedrl.networks import stacked_actors

__all__ = ["TrackingResult", "evaluate_tracking", "evaluate_courses"]


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
        first = next(policy.parameters(), None)
        dtype, device = (torch.float32, torch.device("cpu")) if first is None else (first.dtype, first.device)

        def call(obs: np.ndarray) -> np.ndarray:
            with torch.no_grad():
                return policy(torch.as_tensor(obs, dtype=dtype, device=device)).detach().cpu().numpy()
        return call

    def call_plain(obs: np.ndarray) -> np.ndarray:
        out = policy(obs)
        return out.detach().cpu().numpy() if isinstance(out, torch.Tensor) else out
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
        Start tracking state. Default: on the reference at ``X = 0``, 12 m/s, ``v_y = r = 0``.
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
    termination). Each step is :meth:`~mixedrl.envs.DoubleLaneChangeModel.true_step`, through the
    Gymnasium env, with ``F_dis`` drawn from its ``np_random`` seeded with ``seed``.
    """
    cfg = make_config(config)
    rows = _EnvRows(cfg, [seed], _start_state(cfg, start_state), normalized_actions,
                    cfg.max_steps if max_steps is None else check_positive_int(max_steps, "max_steps"))
    call = _as_numpy_policy(policy)
    for _ in range(rows.n_max):
        if rows.step(np.zeros(1, dtype=int), [np.asarray(call(rows.obs[0]), dtype=np.float64)])[0]:
            break
    return rows.result(0, cfg.dt)


def _tracking_result(dt: float, states: Any, observations: Any, actions: Any, forces: Any, costs: Any, lat: Any,
                     spd: Any, terminated: bool) -> TrackingResult:
    """The :class:`TrackingResult` of one course from its per-step sequences (sequential and batched)."""
    lat, spd, actions = np.asarray(lat), np.asarray(spd), np.asarray(actions).reshape(-1, 2)
    n = actions.shape[0]
    return TrackingResult(
        mean_abs_lateral_error=float(np.mean(np.abs(lat[1:]))),
        mean_abs_speed_error=float(np.mean(np.abs(spd[1:]))),
        max_abs_lateral_error=float(np.max(np.abs(lat[1:]))),
        max_abs_speed_error=float(np.max(np.abs(spd[1:]))),
        total_cost=float(np.sum(costs)), terminated=bool(terminated), n_steps=n,
        time=np.arange(n + 1) * dt, states=np.asarray(states), observations=np.asarray(observations),
        actions=actions, lateral_error=lat, speed_error=spd, disturbance=np.asarray(forces), costs=np.asarray(costs),
    )


def _start_state(cfg: DoubleLaneChangeConfig, start_state: np.ndarray | None) -> np.ndarray:
    """``start_state`` checked, or the deterministic default: on the reference at ``X = 0``, ``v_des``."""
    if start_state is None:
        ref = cfg.reference
        start_state = np.array([0.0, 0.0, cfg.v_des, ref.heading(0.0), ref.lateral(0.0), 0.0])
    return as_vector(start_state, "start_state", 6)


def _stacked_call(policies: Sequence[Any]) -> Callable[[np.ndarray], np.ndarray] | None:
    """One call of ``P`` modules of one architecture on ``(P, S, obs_dim)`` rows
    (:func:`mixedrl.networks.stacked_actors`, else :func:`torch.func.vmap`), or ``None`` when they cannot
    be stacked (different types or shapes, or tensors outside parameters and buffers)."""
    if not all(isinstance(p, torch.nn.Module) for p in policies):
        return None
    # plain actors (even one): one batched product per layer
    actors = stacked_actors(policies)
    if actors is not None:
        def call_actors(obs: np.ndarray) -> np.ndarray:
            with torch.no_grad():
                return actors(torch.as_tensor(obs, dtype=torch.float32)).numpy()
        return call_actors
    if len(policies) < 2:
        return None
    first = policies[0]

    def signature(module: torch.nn.Module) -> list[tuple[str, tuple[int, ...], torch.dtype]]:
        return [(k, tuple(v.shape), v.dtype) for k, v in module.state_dict().items()]

    if any(type(p) is not type(first) or signature(p) != signature(first) for p in policies):
        return None
    for p in policies:
        for sub in p.modules():
            if any(isinstance(v, torch.Tensor) for v in vars(sub).values()):
                return None  # a plain tensor attribute: each module's own value would be lost
    params, buffers = torch.func.stack_module_state(list(policies))
    params = {k: v.detach() for k, v in params.items()}
    base = copy.deepcopy(first).to("meta")
    dtype = next(iter(params.values())).dtype if params else torch.float32

    def one(p: dict[str, torch.Tensor], b: dict[str, torch.Tensor], x: torch.Tensor) -> torch.Tensor:
        return torch.func.functional_call(base, (p, b), (x,))

    batched = torch.func.vmap(one)

    def call(obs: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return batched(params, buffers, torch.as_tensor(obs, dtype=dtype)).cpu().numpy()
    return call


def _checked_actions(actions: Any, rows: int, what: str) -> np.ndarray:
    """A policy's output as float64 ``(rows, 2)``, checked for shape."""
    a = np.asarray(actions, dtype=np.float64)
    if a.size != rows * 2:
        raise ValueError(f"{what} returned an action of shape {a.shape}, expected {(rows, 2) if rows > 1 else (2,)}")
    return a.reshape(rows, 2)


#: From this many courses on, :func:`evaluate_courses` steps the vehicles as numpy rows (``stepper="auto"``).
NUMPY_MIN_ROWS = 6


class _EnvRows:
    """Courses stepped by their own Gymnasium environments (Python floats): the sequential step itself."""

    def __init__(self, cfg: DoubleLaneChangeConfig, row_seeds: list[int], start_state: np.ndarray,
                 normalized_actions: bool, n_max: int) -> None:
        self.envs = [DoubleLaneChangeEnv(cfg) for _ in row_seeds]
        self.normalized, self.n_max = normalized_actions, n_max
        self.records: list[dict[str, list[Any]]] = []
        obs = []
        for env, seed in zip(self.envs, row_seeds):
            o, info = env.reset(seed=seed, options={"state": start_state})
            obs.append(o)
            self.records.append({"states": [info["state"]], "observations": [o], "actions": [], "forces": [],
                                 "costs": [], "lat": [info["lateral_error"]], "spd": [info["speed_error"]]})
        self.obs = np.array(obs)
        self.terminated = np.zeros(len(row_seeds), dtype=bool)

    def step(self, idx: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Step the courses ``idx`` with the actions ``u`` (len(idx), 2); True where a course ended."""
        ended = np.zeros(idx.size, dtype=bool)
        for j, i in enumerate(idx):
            env, rec = self.envs[i], self.records[i]
            step = env.step if self.normalized else env.step_physical
            obs, reward, terminated, truncated, info = step(u[j])
            self.obs[i] = obs
            for key, value in zip(rec, (info["state"], obs, info["action"], info["disturbance"], -reward,
                                        info["lateral_error"], info["speed_error"])):
                rec[key].append(value)
            self.terminated[i] = terminated
            ended[j] = terminated or truncated
        return ended

    def result(self, i: int, dt: float) -> TrackingResult:
        return _tracking_result(dt, *self.records[i].values(), bool(self.terminated[i]))


class _NumpyRows:
    """Courses stepped as float64 numpy rows, bit-identical to :class:`_EnvRows`."""

    def __init__(self, cfg: DoubleLaneChangeConfig, row_seeds: list[int], start_state: np.ndarray,
                 normalized_actions: bool, n_max: int) -> None:
        self.cfg, self.normalized = cfg, normalized_actions
        self.model = DoubleLaneChangeModel(cfg)
        env = DoubleLaneChangeEnv(cfg)
        n, obs_dim = len(row_seeds), self.model.obs_dim
        # each course's draws from the generator its environment seeds, all at once (the same numbers)
        self.z = np.empty((n_max, n))
        obs0, info0 = env.reset(seed=0, options={"state": start_state})
        for i, seed in enumerate(row_seeds):
            env.reset(seed=seed, options={"state": start_state})
            self.z[:, i] = cfg.disturbance.standard_noise(env.np_random, (n_max,))
        # the per-step records, in the order of _tracking_result's arguments: n_max rows, plus the start row
        self.starts = (1, 1, 0, 0, 0, 1, 1)  # 1: the record holds the start row too
        tails = ((6,), (obs_dim,), (2,), (), (), (), ())
        self.records = tuple(np.full((n_max + extra, n) + tail, np.nan) for extra, tail in zip(self.starts, tails))
        self.states, self.observations, self.actions, self.forces, self.costs, self.lat, self.spd = self.records
        self.states[0], self.observations[0] = info0["state"], obs0
        self.lat[0], self.spd[0] = info0["lateral_error"], info0["speed_error"]
        self.state = np.array(np.broadcast_to(start_state, (n, 6)))
        self.obs = np.array(np.broadcast_to(obs0, (n, obs_dim)))
        self.n_steps = np.zeros(n, dtype=int)
        self.terminated = np.zeros(n, dtype=bool)
        self.columns = dataclasses.replace(cfg, reference=cfg.reference.rows())  # the columns on libm
        dist, m, g = cfg.disturbance, cfg.params.m, cfg.params.g
        self.mean_force = elementwise(lambda X: dist.mean_force(X, m, g))
        self.bound = np.array([cfg.delta_max, cfg.ax_max])

    def step(self, idx: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Step the courses ``idx`` with the actions ``u`` (len(idx), 2); True where a course ended."""
        cfg, model, k = self.cfg, self.model, int(self.n_steps[idx[0]])
        rows = slice(None) if idx.size == self.state.shape[0] else idx
        # the environment's clip to the action box (normalised actions: to [-1, 1], then scaled)
        u = np.clip(u, -1.0, 1.0) * self.bound if self.normalized else np.clip(u, -self.bound, self.bound)
        s = self.state[rows]
        # F_dis = mean(X) + std z at the current state ;  xi = F_dis T / m
        force = self.mean_force(s[:, 5]) + cfg.disturbance.std * self.z[k, rows]
        # s' = f(s, u) + xi e_vx   (eq. 54): the one true step, on rows
        vy, r, vx, phi, Y, X = model.dynamics.step_rows(s, u)
        vx = vx + model.xi_from_force(force)
        y_ref, psi_ref = self.columns.reference.lateral_and_heading(X)
        e_y = Y - y_ref
        obs = np.stack(observation_from_errors(self.columns, vy, r, vx, phi - psi_ref, e_y, X, y_ref), axis=1)
        s_next = np.stack([vy, r, vx, phi, Y, X], axis=1)
        with np.errstate(invalid="ignore"):
            terminated = (~np.isfinite(s_next).all(axis=1) | ~(np.abs(e_y) <= cfg.max_lateral_error)
                          | ~(vx >= cfg.min_speed))
        self.state[rows], self.obs[rows] = s_next, obs
        self.states[k + 1, rows], self.observations[k + 1, rows], self.actions[k, rows] = s_next, obs, u
        self.forces[k, rows] = force
        self.costs[k, rows] = stage_cost(cfg, vx - cfg.v_des, e_y, u[:, 0], u[:, 1])
        self.lat[k + 1, rows], self.spd[k + 1, rows] = e_y, vx - cfg.v_des
        self.n_steps[rows] = k + 1
        self.terminated[rows] = terminated
        # ended: terminated, or truncated at the course's end (the environment's time limit)
        return terminated | (k + 1 >= cfg.max_steps)

    def result(self, i: int, dt: float) -> TrackingResult:
        n = int(self.n_steps[i])
        rows = (np.ascontiguousarray(a[:n + extra, i]) for a, extra in zip(self.records, self.starts))
        return _tracking_result(dt, *rows, bool(self.terminated[i]))


def evaluate_courses(policies: Sequence[Callable[[np.ndarray], Any] | torch.nn.Module],
                     config: DoubleLaneChangeConfig | dict[str, Any] | None = None, *,
                     seeds: Sequence[int] | Sequence[Sequence[int]], start_state: np.ndarray | None = None,
                     max_steps: int | None = None, normalized_actions: bool = False,
                     exact: bool = True, stepper: str = "auto") -> list[list[TrackingResult]]:
    """Drive the double lane change with several policies on several seeds at once, in lock step.

    The evaluation of :func:`evaluate_tracking` for ``N = sum_p S_p`` courses: the disturbance of course
    ``(p, j)`` comes from the generator the environment seeds with ``seeds[p][j]``, and a course that
    ends is masked from then on (its record ends where the sequential drive ends).

    Parameters
    ----------
    policies : sequence of callable or torch.nn.Module, length P
        Each as ``policy`` of :func:`evaluate_tracking`.
    seeds : sequence of int, or sequence of P sequences of int
        The evaluation seeds: one list shared by every policy, or one (non-empty) list per policy.
    config, start_state, max_steps, normalized_actions : optional
        As for :func:`evaluate_tracking` (the same start for every course).
    exact : bool, optional
        True (default): each policy is called on one course's observation at a time, so every number
        equals :func:`evaluate_tracking`'s bit for bit. False: one call per policy on all its courses
        ``(S_p, obs_dim)``, or one call of the stacked policies when they are modules of one
        architecture with equally many seeds; faster, but a float32 network may then differ in the last
        bits (docs/reproduction.rst).
    stepper : {"auto", "numpy", "env"}, optional
        How the vehicles are stepped, with the same numbers either way: ``"numpy"``, float64 rows
        (:meth:`~mixedrl.envs.VehicleDynamics.step_rows`); ``"env"``, each course's own Gymnasium
        environment; ``"auto"`` (default), numpy from :data:`NUMPY_MIN_ROWS` courses on.

    Returns
    -------
    list of list of TrackingResult
        ``out[p][j]``: policy ``p`` on its ``j``-th seed, as :func:`evaluate_tracking` returns it.

    Raises
    ------
    ValueError
        ``policies`` empty or not callable; ``seeds`` empty, not ints, or not one list per policy;
        unknown ``stepper``; bad ``start_state`` or ``max_steps``; a policy returns an action of the
        wrong shape or with NaN (the message names the policy, and with ``exact`` the seed).

    Notes
    -----
    The numpy rows are bit-identical to the environment's Python floats: the arithmetic is correctly
    rounded and the transcendental functions are :mod:`math`'s (:mod:`mixedrl.envs.libm`).
    """
    if isinstance(policies, (torch.nn.Module, str, bytes)) or not isinstance(policies, Sequence) \
            or len(policies) == 0:
        raise ValueError(f"policies: expected a non-empty list of policies, got {type(policies).__name__}")
    for p, policy in enumerate(policies):
        if not callable(policy):
            raise ValueError(f"policies: entry {p} is a {type(policy).__name__}, not callable")
    if stepper not in ("auto", "numpy", "env"):
        raise ValueError(f"stepper: expected 'auto', 'numpy' or 'env', got {stepper!r}")
    seed_lists = check_seed_lists(seeds, len(policies))
    cfg = make_config(config)
    start_state = _start_state(cfg, start_state)
    n_max = cfg.max_steps if max_steps is None else check_positive_int(max_steps, "max_steps")
    owner = np.array([p for p, s in enumerate(seed_lists) for _ in s])
    row_seeds = [seed for s in seed_lists for seed in s]
    n_rows = len(row_seeds)
    use_numpy = stepper == "numpy" or (stepper == "auto" and n_rows >= NUMPY_MIN_ROWS)
    if exact and not use_numpy:
        # the sequential drive itself
        results: list[list[TrackingResult]] = [[] for _ in policies]
        for p, (policy, s) in enumerate(zip(policies, seed_lists)):
            for seed in s:
                try:
                    results[p].append(evaluate_tracking(policy, cfg, seed=seed, start_state=start_state,
                                                        max_steps=max_steps, normalized_actions=normalized_actions))
                except (ValueError, TypeError) as exc:  # the policy's action, refused by the environment
                    raise ValueError(f"policies: entry {p} (seed {seed}) returned a bad action ({exc})") from exc
        return results
    rows = (_NumpyRows if use_numpy else _EnvRows)(cfg, row_seeds, start_state, normalized_actions, n_max)
    calls = [_as_numpy_policy(policy) for policy in policies]
    blocks = [np.flatnonzero(owner == p) for p in range(len(policies))]
    stacked = _stacked_call(policies) if not exact and len({len(s) for s in seed_lists}) == 1 else None
    alive = np.ones(n_rows, dtype=bool)
    for _ in range(n_max):
        idx = np.flatnonzero(alive)
        if idx.size == 0:
            break
        obs = rows.obs
        # u_k = pi_p(o_k): per course (exact), or per policy / stacked over the policies on all rows
        if exact:
            raw = [calls[owner[i]](obs[i]) for i in idx]
            try:
                u = np.asarray(raw, dtype=np.float64).reshape(idx.size, 2)
            except ValueError:  # ragged or wrong sizes: find the course, and let _checked_actions name it
                u = np.concatenate([_checked_actions(out, 1, f"policies: entry {owner[i]} (seed {row_seeds[i]})")
                                    for i, out in zip(idx, raw)])
        else:
            # a finished course's row is still computed but not checked or used
            full = np.empty((n_rows, 2))
            if stacked is not None:
                full[:] = _checked_actions(stacked(obs.reshape(len(policies), -1, obs.shape[1])), n_rows,
                                           "policies (stacked)")
            else:
                for p, block in enumerate(blocks):
                    full[block] = _checked_actions(calls[p](obs[block]), block.size, f"policies: entry {p}")
            u = full[idx]
        bad = np.flatnonzero(~np.isfinite(u).all(axis=1))
        if bad.size:
            i = idx[bad[0]]
            raise ValueError(f"policies: entry {owner[i]} (seed {row_seeds[i]}) returned NaN or inf")
        alive[idx[rows.step(idx, u)]] = False
    results = [[] for _ in policies]
    for i in range(n_rows):
        results[owner[i]].append(rows.result(i, cfg.dt))
    return results
