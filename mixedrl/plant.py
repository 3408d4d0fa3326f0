"""The true system as a *plant*: something that can be reset and stepped, never set.

By default the true system ``x' = f(x, u) + E xi`` (eq. 1) is simulated (:meth:`mixedrl.tasks.Task.true_step`,
the *simulated plant*). A real system, or a simulator the model only approximates, is given to a task with
:func:`attach_plant` as a :class:`Plant` (``reset(seed) -> x``, ``step(u) -> x'``):
:class:`GymnasiumPlant` wraps a Gymnasium env, :class:`SimulatedPlant` the simulated plant, and
:class:`DisturbedEnv` adds an unmodelled disturbance to Pendulum-v1 or MountainCarContinuous-v0.

Training then drives the plant where it drove the simulated true copies (:class:`PlantCopies`); every call
is checked (:class:`CheckedPlant`), and a failure stops the run with a :class:`PlantError` (``--resume``
continues from the last checkpoint). Evaluation runs one plant episode per seed (:func:`evaluate_on_plant`).
docs/tutorial.rst, section 4, describes the workflow: episode seeds, counting, saturation.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from typing import Any, Protocol, runtime_checkable

import gymnasium as gym
import numpy as np
import torch

from mixedrl.task_base import Task

__all__ = ["CheckedPlant", "DisturbedEnv", "GymnasiumPlant", "PLANT_EVALUATIONS", "Plant", "PlantCopies", "PlantError",
           "SimulatedPlant", "attach_plant", "check_plant_sampler", "credit_evaluations", "evaluate_on_plant",
           "episode_seed", "plant_copies", "plant_transitions", "unwrapped_state"]

#: ``Task.plant_evaluation``: ``"simulated"`` (the default: :meth:`Task.evaluate`, the model plus simulated
#: noise), ``"plant"`` (:func:`evaluate_on_plant`) or ``"none"``.
PLANT_EVALUATIONS = ("simulated", "plant", "none")


class PlantError(RuntimeError):
    """A plant raised, or returned a non-finite state or one of the wrong shape.

    Attributes
    ----------
    plant : object
        The plant (the user's object, not its :class:`CheckedPlant`).
    step : int
        The plant's transition index at the failure (0 for the first step; ``reset`` reports the index of
        the next step).
    problem : str
        What went wrong.
    """

    def __init__(self, plant: Any, step: int, call: str, problem: str) -> None:
        self.plant, self.step, self.problem = plant, int(step), problem
        super().__init__(f"plant {type(plant).__name__} ({plant!r}) at step {step} ({call}): {problem}")


@runtime_checkable
class Plant(Protocol):
    """One true system, stepped sequentially.

    ``reset(seed)`` starts an episode (``seed``: an int, so that an episode can be repeated) and returns
    its state, ``step(u)`` applies the action ``u`` (shape ``(action_dim,)``, float64) and returns the next
    state; states are ``(state_dim,)`` arrays in the coordinates of the task's model ``f``. A plant may
    expose ``last_reward`` (float), ``last_terminated`` and ``last_truncated`` (bool) after each step.
    """

    def reset(self, seed: int | None = None) -> np.ndarray: ...

    def step(self, u: np.ndarray) -> np.ndarray: ...


class CheckedPlant:
    """A :class:`Plant` whose every call is checked and counted.

    Parameters
    ----------
    plant : Plant
        The system.
    state_dim : int
        The length of the states it must return.

    Attributes
    ----------
    transitions : int
        Steps taken so far.
    owner : object
        Who started the current episode (a :class:`PlantCopies` or ``"evaluation"``); another user resets
        the plant before stepping it.
    """

    def __init__(self, plant: Any, state_dim: int) -> None:
        if isinstance(plant, CheckedPlant):
            plant = plant.plant
        if not callable(getattr(plant, "reset", None)) or not callable(getattr(plant, "step", None)):
            raise ValueError(f"plant: expected an object with reset(seed) and step(u) (mixedrl.plant.Plant), got "
                             f"{type(plant).__name__}")
        self.plant, self.state_dim = plant, int(state_dim)
        self.transitions = 0
        self.owner: Any = None

    def __repr__(self) -> str:
        return f"CheckedPlant({self.plant!r})"

    def _call(self, call: str, *args: Any) -> np.ndarray:
        """``plant.<call>(*args)``: its state, checked (any failure of the user's plant is a PlantError)."""
        try:
            value = getattr(self.plant, call)(*args)
        except Exception as exc:  # noqa: BLE001
            raise PlantError(self.plant, self.transitions, call, f"raised {type(exc).__name__}: {exc}") from exc
        try:
            x = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise PlantError(self.plant, self.transitions, call, f"returned {type(value).__name__}, not an array "
                             f"of numbers ({exc})") from None
        if x.shape != (self.state_dim,):
            raise PlantError(self.plant, self.transitions, call, f"returned a state of shape {x.shape}, expected "
                             f"({self.state_dim},)")
        if not np.isfinite(x).all():
            raise PlantError(self.plant, self.transitions, call, f"returned a non-finite state {x.tolist()}")
        return x

    def reset(self, seed: int, owner: Any = None) -> np.ndarray:
        """``plant.reset(seed)``, checked; ``owner`` starts the episode."""
        x = self._call("reset", int(seed))
        self.owner = owner
        return x

    def step(self, u: np.ndarray) -> np.ndarray:
        """``plant.step(u)``, checked and counted."""
        x = self._call("step", np.asarray(u, dtype=np.float64))
        self.transitions += 1
        return x

    @property
    def episode_over(self) -> bool:
        """The plant's own episode end (``last_terminated`` or ``last_truncated``; False without them)."""
        return bool(getattr(self.plant, "last_terminated", False) or getattr(self.plant, "last_truncated", False))


def episode_seed(seed: int, stream: int, episode: int) -> int:
    """The reset seed of ``episode`` of a stream (0: training copies, 1: evaluation) of run ``seed``."""
    return int(np.random.SeedSequence([int(seed), int(stream), int(episode)]).generate_state(1)[0])


def attach_plant(task: Task, plant: Any, evaluation: str = "plant") -> Task:
    """Make ``plant`` (a :class:`Plant`, or a list of them: one per true copy) the true system of ``task``.

    Parameters
    ----------
    task : Task
        The model (``f``, cost, prior); its ``true_mean``/``true_cov`` then serve only the simulated
        evaluation and the oracle.
    plant : Plant or sequence of Plant
        The true system(s). Training drives ``sampler.true_envs`` copies: one plant, or that many.
    evaluation : {"plant", "simulated", "none"}, optional
        How a run evaluates (:data:`PLANT_EVALUATIONS`).

    Returns
    -------
    Task
        ``task`` itself.

    Raises
    ------
    ValueError
        ``plant`` lacks ``reset``/``step`` or ``evaluation`` is unknown (naming the argument), or
        ``evaluation`` is not ``"simulated"`` for a task whose own ``evaluate`` cannot run on a plant
        (``Task.evaluates_on_plant`` False).
    """
    if evaluation not in PLANT_EVALUATIONS:
        raise ValueError(f"evaluation: expected one of {PLANT_EVALUATIONS}, got {evaluation!r}")
    if evaluation != "simulated" and not getattr(task, "evaluates_on_plant", True):
        name = type(task).__name__
        raise ValueError(f"evaluation: {name}.evaluate is the task's own and cannot evaluate on a plant (it does "
                         f"not call task.plant_evaluate); attach with evaluation='simulated', or make "
                         f"{name}.evaluate return self.plant_evaluate(policy, seeds, horizon) when that is set "
                         f"and declare {name}.evaluates_on_plant = True")
    plants = list(plant) if isinstance(plant, (list, tuple)) else [plant]
    if not plants:
        raise ValueError("plant: expected a plant or a non-empty list of plants, got an empty list")
    task.plant = [CheckedPlant(p, task.state_dim) for p in plants]
    task.plant_evaluation = evaluation
    task.plant_evaluate = {"simulated": None, "none": lambda policy, seeds, horizon=None: {},
                           "plant": functools.partial(evaluate_on_plant, task)}[evaluation]
    return task


class PlantCopies:
    """The training side of a task's plant(s): the ``n`` true copies of a sampler, stepped in lock step.

    Parameters
    ----------
    plants : sequence of CheckedPlant
        One plant per copy (or one plant for ``n = 1``).
    n : int
        Number of true copies the sampler drives (``sampler.true_envs``).
    seed : int
        The run's seed; episode ``e`` starts with :func:`episode_seed` ``(seed, 0, e)``.

    Raises
    ------
    ValueError
        ``len(plants) != n``, naming ``sampler.true_envs``.
    """

    def __init__(self, plants: Sequence[CheckedPlant], n: int, seed: int) -> None:
        if len(plants) != n:
            raise ValueError(f"sampler.true_envs: the task has {len(plants)} plant(s), the sampler drives {n} "
                             f"true copies (set sampler.true_envs={len(plants)})")
        self.plants, self.seed, self.episodes = list(plants), int(seed), 0
        #: Which copies' plant episode ended at the last :meth:`step` (bool, shape (n,)).
        self.done = torch.zeros(n, dtype=torch.bool)

    def reset(self, rows: torch.Tensor | None = None) -> torch.Tensor:
        """Start new plant episodes for ``rows`` (bool mask; all by default); their states, (k, state_dim)."""
        idx = range(len(self.plants)) if rows is None else torch.nonzero(rows).flatten().tolist()
        out = [self.plants[i].reset(episode_seed(self.seed, 0, self.episodes + k), owner=self)
               for k, i in enumerate(idx)]
        self.episodes += len(out)
        return torch.as_tensor(np.stack(out)) if out else torch.zeros(0, self.plants[0].state_dim, dtype=torch.float64)

    def current(self, states: torch.Tensor) -> torch.Tensor:
        """``states`` if every plant is in an episode this driver started, else fresh episodes of all."""
        if all(p.owner is self for p in self.plants):
            return states
        return self.reset()

    def step(self, u: torch.Tensor) -> torch.Tensor:
        """Step every copy with its row of ``u`` (n, action_dim); next states (n, state_dim) float64."""
        out = [p.step(u[i].detach().double().numpy()) for i, p in enumerate(self.plants)]
        self.done = torch.tensor([p.episode_over for p in self.plants], dtype=torch.bool)
        return torch.as_tensor(np.stack(out))

    @property
    def transitions(self) -> int:
        """Plant steps taken by all copies."""
        return sum(p.transitions for p in self.plants)


def plant_copies(task: Task, config: Any) -> PlantCopies | None:
    """The :class:`PlantCopies` of ``task``'s plant for a model-rollout sampler, or ``None`` (simulated plant)."""
    plants = getattr(task, "plant", None)
    if plants is None:
        return None
    if not isinstance(plants, list) or not all(isinstance(p, CheckedPlant) for p in plants):
        raise ValueError(f"task.plant: expected the list attach_plant makes, got {type(plants).__name__} (give "
                         f"{type(task).__name__} its plant with mixedrl.plant.attach_plant(task, plant))")
    return PlantCopies(plants, config.sampler.true_envs, config.seed)


def check_plant_sampler(task: Task, config: Any) -> None:
    """Raise ``ValueError`` if ``task`` has a plant and ``config.method`` is ``"ddpg"`` or
    ``config.sampler.name`` is ``"true_copies"`` (both need batches of true copies)."""
    if getattr(task, "plant", None) is None:
        return
    if config.method == "ddpg":
        raise ValueError("config: method 'ddpg' steps batches of simulated true copies; a task with a plant "
                         "trains with Algorithm 2 (methods 'mixed', 'model', 'oracle')")
    if config.sampler.name == "true_copies":
        raise ValueError("sampler.name: a task with a plant needs a model-rollout sampler ('model_rollouts', or "
                         "'dlc_course'); 'true_copies' uses batch_size true copies as PEV's batch")


def evaluate_on_plant(task: Task, policy: torch.nn.Module, seeds: list[int], horizon: int | None = None
                      ) -> dict[str, Any]:
    """Evaluate ``policy`` on the task's (first) plant: one episode per seed, one after the other.

    Episode ``i`` starts with ``reset(episode_seed(seeds[i], 1, 0))``, acts with ``policy(observe(x))``
    (float32 observations) and runs ``horizon`` steps (default ``task.eval_horizon``) or until the plant
    ends it or the state is terminal for the task. Each step adds one to ``task.evaluation_transitions``.

    Returns
    -------
    dict
        Means over the episodes: ``cost`` (the task's discounted ``sum gamma^t l(x_{t+1}, u_t)``),
        ``plant_return`` (the plant's undiscounted ``sum last_reward``; ``None`` without rewards),
        ``plant_terminated_fraction``, ``terminated_fraction`` (by the plant or the task; a truncation
        is not a termination) and ``episode_length`` (steps).

    Raises
    ------
    ValueError
        The task has no plant, or ``seeds`` is empty.
    PlantError
        The plant failed.
    """
    plants = getattr(task, "plant", None)
    if not plants:
        raise ValueError(f"task: {type(task).__name__} has no plant (mixedrl.plant.attach_plant)")
    if len(seeds) == 0:
        raise ValueError("seeds: expected at least one evaluation seed, got none")
    plant = plants[0]
    rewarded = hasattr(plant.plant, "last_reward")
    horizon = int(task.eval_horizon if horizon is None else horizon)
    episodes = []  # (cost, return, plant terminated, terminated, length) of each episode
    with torch.no_grad():
        for seed in seeds:
            x = torch.as_tensor(plant.reset(episode_seed(seed, 1, 0), owner="evaluation"))[None]
            cost, ret, t, task_end = 0.0, 0.0, 0, False
            for t in range(horizon):
                u = policy(task.observe(x.float())).double()
                x = torch.as_tensor(plant.step(u[0].numpy()))[None]
                task.evaluation_transitions = getattr(task, "evaluation_transitions", 0) + 1
                cost += task.gamma**t * float(task.cost(x, u)[0])
                if rewarded:
                    ret += float(plant.plant.last_reward)
                task_end = bool(task.is_terminal(x)[0])
                if plant.episode_over or task_end:
                    break
            plant_end = bool(getattr(plant.plant, "last_terminated", False))
            episodes.append((cost, ret, plant_end, plant_end or task_end, t + 1))
    costs, returns, plant_ends, ends, lengths = zip(*episodes)
    return {"cost": float(np.mean(costs)), "plant_return": float(np.mean(returns)) if rewarded else None,
            "plant_terminated_fraction": float(np.mean(plant_ends)), "terminated_fraction": float(np.mean(ends)),
            "episode_length": float(np.mean(lengths))}


# ---- plants ----
class SimulatedPlant:
    """The simulated plant behind the :class:`Plant` interface: ``reset(seed)`` draws the start from
    ``task.sample_initial`` and each step is ``task.true_step`` (eq. 1), from a generator seeded by ``seed``.
    """

    def __init__(self, task: Task) -> None:
        self.task = task
        self.generator = torch.Generator().manual_seed(0)
        self.state: torch.Tensor | None = None

    def __repr__(self) -> str:
        return f"SimulatedPlant({type(self.task).__name__})"

    def reset(self, seed: int | None = None) -> np.ndarray:
        self.generator.manual_seed(0 if seed is None else int(seed))
        self.state = self.task.sample_initial(1, self.generator).to(torch.float64)
        return self.state[0].numpy().copy()

    def step(self, u: np.ndarray) -> np.ndarray:
        if self.state is None:
            raise RuntimeError("step before reset")
        u_t = torch.as_tensor(np.asarray(u, dtype=np.float64)).reshape(1, -1)
        with torch.no_grad():
            self.state = self.task.true_step(self.state, u_t, self.generator)
        return self.state[0].numpy().copy()


def unwrapped_state(env: Any) -> np.ndarray:
    """``env.unwrapped.state`` as float64: the model's state for Pendulum-v1 (``[theta, theta_dot]``, the
    angle not wrapped), MountainCarContinuous-v0 (``[position, velocity]``) and
    :class:`~mixedrl.envs.DoubleLaneChangeEnv` (its simulator state)."""
    return np.array(env.unwrapped.state, dtype=np.float64)


class GymnasiumPlant:
    """A :class:`Plant` made of a :class:`gymnasium.Env` with Box action and observation spaces.

    Parameters
    ----------
    env : gymnasium.Env
        The system (its own action clipping, reward, termination and time limit apply).
    state_fn : callable, optional
        ``env -> state`` (``(state_dim,)``, the coordinates of the task's model ``f``); the observation
        is not enough for a model that needs the full state. Default :func:`unwrapped_state`.
    action_fn : callable, optional
        The task's action ``u`` (float64, ``(action_dim,)``) -> the env's action; the identity by default.
        The double lane change's env takes normalised actions:
        ``action_fn=lambda u: u / task.action_bound.numpy()``.

    Attributes
    ----------
    last_reward : float
    last_terminated, last_truncated : bool
        Of the last step.

    Raises
    ------
    ValueError
        A space of ``env`` is not a ``gymnasium.spaces.Box`` (the message names it).

    Examples
    --------
    The three environments it is documented for (``state_fn`` :func:`unwrapped_state`, the default; run by
    ``tests/test_plant.py``):

    .. code-block:: python

       from mixedrl.envs.gym_models import MountainCarTask, PendulumV1Task
       from mixedrl.tasks import task_from_config

       pendulum = attach_plant(PendulumV1Task(), GymnasiumPlant(gym.make("Pendulum-v1")))
       car = attach_plant(MountainCarTask(), GymnasiumPlant(gym.make("MountainCarContinuous-v0")))
       # the package's double lane change: the env's actions are normalised
       import mixedrl.envs  # registers mixedrl/DoubleLaneChange-v0
       dlc = task_from_config("dlc")
       bound = dlc.action_bound.double().numpy()
       dlc = attach_plant(dlc, GymnasiumPlant(gym.make("mixedrl/DoubleLaneChange-v0"),
                                              action_fn=lambda u: u / bound))
    """

    def __init__(self, env: Any, state_fn: Callable[[Any], np.ndarray] = unwrapped_state,
                 action_fn: Callable[[np.ndarray], np.ndarray] | None = None) -> None:
        for space in ("action_space", "observation_space"):
            if not isinstance(getattr(env, space, None), gym.spaces.Box):
                raise ValueError(f"env: {space} must be a gymnasium.spaces.Box, got "
                                 f"{type(getattr(env, space, None)).__name__}")
        self.env, self.state_fn, self.action_fn = env, state_fn, action_fn
        self.last_reward, self.last_terminated, self.last_truncated = math.nan, False, False

    def __repr__(self) -> str:
        spec = getattr(self.env, "spec", None)
        return f"GymnasiumPlant({getattr(spec, 'id', None) or type(self.env.unwrapped).__name__})"

    def reset(self, seed: int | None = None) -> np.ndarray:
        self.env.reset(seed=seed)
        self.last_reward, self.last_terminated, self.last_truncated = math.nan, False, False
        return self.state_fn(self.env)

    def step(self, u: np.ndarray) -> np.ndarray:
        space = self.env.action_space
        u = u if self.action_fn is None else self.action_fn(u)
        action = np.asarray(u, dtype=space.dtype).reshape(space.shape)
        _, reward, terminated, truncated, _ = self.env.step(action)
        self.last_reward, self.last_terminated, self.last_truncated = float(reward), bool(terminated), bool(truncated)
        return self.state_fn(self.env)


class DisturbedEnv(gym.Wrapper):
    """Pendulum-v1 or MountainCarContinuous-v0 with an unmodelled force ``xi ~ N(mean, std^2)`` (action
    units: a torque for the pendulum, a force for the car) added after the env's action clip.

    After the wrapped step the state moves by ``E xi``, ``E`` the force's effect over one step of the env's
    semi-implicit Euler scheme (:func:`mixedrl.envs.gym_models.pendulum_noise_matrix`,
    :func:`~mixedrl.envs.gym_models.mountain_car_noise_matrix`), so the true system is exactly
    ``x' = f(x, u) + E xi`` with ``f`` the env's own step (applied after the env's speed and position clips).
    The observation is recomputed from the moved state; reward and termination are the env's.

    With ``before_clip=True`` the force is an actuator bias added to the action before the env's clip, so
    the additive model does not hold near the limit (declare ``action_limit`` and ``saturation_margin`` on
    the task, :meth:`mixedrl.tasks.Task.saturated`).

    Parameters
    ----------
    env : gymnasium.Env
        ``gymnasium.make("Pendulum-v1")`` or ``gymnasium.make("MountainCarContinuous-v0")``.
    mean, std : float
        The disturbance's mean and standard deviation (``std = 0``: a constant force).
    before_clip : bool, optional
        Add the force to the action before the env's clip (an actuator bias) rather than after it.

    Notes
    -----
    The draws come from a generator seeded by ``reset(seed=...)`` (a fresh episode without a seed
    continues the stream).
    """

    def __init__(self, env: Any, mean: float = 0.0, std: float = 0.0, before_clip: bool = False) -> None:
        super().__init__(env)
        if not (math.isfinite(mean) and math.isfinite(std) and std >= 0):
            raise ValueError(f"std: expected finite mean and std >= 0, got mean={mean!r}, std={std!r}")
        from mixedrl.envs.gym_models import mountain_car_noise_matrix, pendulum_noise_matrix

        inner, name = env.unwrapped, type(env.unwrapped).__name__
        if name not in ("PendulumEnv", "Continuous_MountainCarEnv"):
            raise ValueError(f"env: DisturbedEnv supports Pendulum-v1 and MountainCarContinuous-v0, got {name}")
        #: ``E`` (state_dim, 1) of the force added after the action clip.
        self.E = (pendulum_noise_matrix(inner.dt, inner.m, inner.l) if name == "PendulumEnv"
                  else mountain_car_noise_matrix(inner.power)).numpy()
        self.mean, self.std, self.before_clip = float(mean), float(std), bool(before_clip)
        self.rng = np.random.default_rng(0)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict]:
        if seed is not None:
            self.rng = np.random.default_rng(seed)
        return self.env.reset(seed=seed, options=options)

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        xi = self.mean + self.std * self.rng.standard_normal()
        if self.before_clip:
            return self.env.step(np.asarray(action, dtype=self.action_space.dtype) + np.float32(xi))
        _, reward, terminated, truncated, info = self.env.step(action)
        inner = self.env.unwrapped
        state = np.asarray(inner.state, dtype=np.float64) + self.E[:, 0] * xi
        inner.state = state.astype(np.asarray(inner.state).dtype)
        obs = inner._get_obs() if hasattr(inner, "_get_obs") else np.array(inner.state, dtype=np.float32)
        return obs, reward, terminated, truncated, info


def credit_evaluations(trainers: Sequence[Any], task: Task, results: list[dict[str, Any]]
                       ) -> list[dict[str, Any]]:
    """``results`` of ``task.evaluate_many`` on the ``trainers``' policies, after moving each policy's
    evaluation transitions (``task.last_evaluation_counts``) from ``task`` to its trainer's own task."""
    counts = getattr(task, "last_evaluation_counts", None)
    if counts is not None and len(counts) == len(trainers):
        task.evaluation_transitions -= sum(counts)
        for trainer, count in zip(trainers, counts):
            trainer.task.evaluation_transitions += count
        task.last_evaluation_counts = None
    return results


def plant_transitions(trainer: Any) -> dict[str, Any]:
    """The plant transitions of a run (``results.json``: ``plant_transitions``).

    Returns
    -------
    dict
        ``training`` (``trainer.true_transitions``), ``evaluation`` (``task.evaluation_transitions``, the
        plant's or the simulated plant's; ``None`` where ``Task.counts_evaluation_transitions`` is False
        and the evaluation is simulated) and ``plant`` (``"simulated"`` or the plant's repr).
    """
    task = trainer.task
    training = getattr(trainer, "true_transitions", None)
    counted = getattr(task, "counts_evaluation_transitions", True) or task.plant_evaluation != "simulated"
    plants = getattr(task, "plant", None)
    return {"training": None if training is None else int(training),
            "evaluation": int(task.evaluation_transitions) if counted else None,
            "plant": "simulated" if not plants else repr(plants[0].plant)}
