"""Data-driven peers from Stable-Baselines3: TD3 and SAC on the double lane change (issue 10).

:func:`train_peer` trains SB3's ``TD3`` or ``SAC`` **with the hyperparameters a user gets**
(``TD3("MlpPolicy", env, seed=seed)``; nothing tuned) through the Gymnasium environment
``mixedrl/DoubleLaneChange-v0`` (:class:`~mixedrl.envs.DoubleLaneChangeEnv`, its own episode length and
termination) and, every ``eval_every`` true transitions, evaluates the deterministic policy on the full
course exactly as a mixedrl run is evaluated:

* the same function: :meth:`mixedrl.envs.dlc_task.DoubleLaneChangeTask.evaluate` (what
  ``trainer.evaluate(eval_seeds(config))`` calls, :func:`mixedrl.envs.evaluate_tracking` once per seed),
  on the task of ``TrainConfig(seed=seed, run={"eval_seeds": eval_seeds})``, with that run's evaluation seeds
  :func:`mixedrl.runs.eval_seeds`;
* the same observation: the environment's observation of a state is the task's ``observe`` of that state
  (:func:`observation_mismatch` measures it; ``tests/test_peers.py`` asserts it is zero);
* the same action mapping: the policy's normalised action ``a`` becomes the physical input
  ``u = clip(a, -1, 1) * [delta_max, ax_max]`` (:class:`PhysicalPolicy`), the arithmetic of
  :meth:`~mixedrl.envs.DoubleLaneChangeEnv.step`.

True transitions are counted by a wrapper around the environment (:class:`TransitionCounter`: one per
``env.step``), not estimated; the run checks the count against SB3's ``num_timesteps``. Wall time is the
training time without the evaluations (as ``time/elapsed_s`` of a mixedrl run).

Command line::

    python -m validation.peers --algo sac --seed 0 --transitions 100000 --out runs/peers/sac_s0.json

SB3 is an optional dependency: ``pip install -c constraints.txt -e ".[peers]"`` (pinned in
``constraints.txt``); without it :func:`train_peer` raises an ``ImportError`` that says so, and the rest
of this module (the wrapper, the policy mapping, the observation check) works.
"""

from __future__ import annotations

import argparse
import inspect
import json
import logging
import math
import time
from importlib import metadata
from pathlib import Path
from types import ModuleType
from typing import Any, Callable, Sequence

import gymnasium as gym
import numpy as np
import torch

from mixedrl.checks import check_nonnegative_int, check_positive_int
from mixedrl.config import TrainConfig
from mixedrl.envs import ENV_ID, DoubleLaneChangeEnv
from mixedrl.runs import atomic_write_text, eval_seeds as run_eval_seeds
from mixedrl.tasks import DoubleLaneChangeTask, task_from_config

__all__ = [
    "ALGOS",
    "INSTALL_HINT",
    "RESERVED_KWARGS",
    "PhysicalPolicy",
    "TransitionCounter",
    "without_log_folder",
    "import_sb3",
    "make_peer_env",
    "observation_mismatch",
    "peer_task",
    "train_peer",
    "main",
]

logger = logging.getLogger(__name__)

#: The peers: Stable-Baselines3's TD3 and SAC.
ALGOS = ("td3", "sac")
#: What to do when Stable-Baselines3 is missing.
INSTALL_HINT = ("stable-baselines3 is not installed: the peers (validation.peers) need the optional extra "
                "'peers'; install it with: pip install -c constraints.txt -e '.[peers]'")
#: Constructor arguments that ``kwargs`` may not set (they are set from the other arguments).
RESERVED_KWARGS = frozenset({"policy", "env", "seed", "verbose", "device", "tensorboard_log", "_init_setup_model"})


def import_sb3() -> ModuleType:
    """Import Stable-Baselines3, with an error that names the extra to install.

    Returns
    -------
    module
        ``stable_baselines3``.

    Raises
    ------
    ImportError
        Stable-Baselines3 is not installed (the message is :data:`INSTALL_HINT`).
    """
    try:
        import stable_baselines3
    except ImportError as exc:
        raise ImportError(INSTALL_HINT) from exc
    return stable_baselines3


def without_log_folder(model: Any) -> Any:
    """Give an SB3 model a logger that writes nothing, and return it.

    Stable-Baselines3's default logger (``stable_baselines3.common.logger.configure``) creates a folder
    ``$TMPDIR/SB3-<date>`` on every ``learn`` even with ``verbose=0``; a model with its own logger does not.
    """
    from stable_baselines3.common.logger import Logger

    model.set_logger(Logger(folder=None, output_formats=[]))
    return model


class TransitionCounter(gym.Wrapper):
    """Counts the true-environment transitions: one per call of ``step`` that returns (a reset is none).

    Parameters
    ----------
    env : gymnasium.Env
        The true environment.

    Attributes
    ----------
    count : int
        Transitions so far.
    """

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.count = 0

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        """Step the wrapped environment and count the transition (not counted if the step raises)."""
        out = self.env.step(action)
        self.count += 1
        return out


class PhysicalPolicy:
    """A normalised-action policy as a physical-input policy: ``u = clip(a, -1, 1) * [delta_max, ax_max]``.

    The product is the one :meth:`mixedrl.envs.DoubleLaneChangeEnv.step` computes from a normalised
    action, so driving the course with ``PhysicalPolicy(act, cfg)`` through the physical interface of
    :func:`mixedrl.envs.evaluate_tracking` (as every mixedrl run is evaluated) applies exactly the inputs
    the environment applies to ``act``'s actions.

    Parameters
    ----------
    act : callable
        Observation (numpy, shape (obs_dim,)) -> normalised action, shape (2,).
    config : DoubleLaneChangeConfig
        The task (``delta_max``, ``ax_max``).
    """

    def __init__(self, act: Callable[[np.ndarray], Any], config: Any) -> None:
        self.act = act
        self.bound = np.array([float(config.delta_max), float(config.ax_max)])

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """The physical input [rad, m/s^2], shape (2,)."""
        a = np.asarray(self.act(obs), dtype=np.float64).reshape(2)
        return np.clip(a, -1.0, 1.0) * self.bound


def peer_task(seed: int = 0, eval_seeds: int = 2) -> tuple[DoubleLaneChangeTask, list[int]]:
    """The task and evaluation seeds of a mixedrl run with ``TrainConfig(seed=seed, run={"eval_seeds": eval_seeds})``.

    Returns
    -------
    task : DoubleLaneChangeTask
        Built by :func:`mixedrl.tasks.task_from_config` from the run's default task configuration.
    seeds : list of int
        :func:`mixedrl.runs.eval_seeds` of that run.

    Raises
    ------
    ValueError
        ``seed`` negative or ``eval_seeds`` not a positive integer (from :class:`TrainConfig`).
    """
    config = TrainConfig(seed=seed, run=dict(eval_seeds=eval_seeds))
    task = task_from_config(config.task)
    if not isinstance(task, DoubleLaneChangeTask):  # pragma: no cover - the default task is the vehicle
        raise TypeError(f"task: expected the double lane change, got {type(task).__name__}")
    return task, run_eval_seeds(config)


def make_peer_env(task: DoubleLaneChangeTask) -> TransitionCounter:
    """The training environment of a peer: ``DoubleLaneChangeEnv`` on ``task``'s configuration, counted.

    The environment is the one :func:`mixedrl.envs.evaluate_tracking` drives (same class, same
    configuration), with its own episode length (the course) and termination.
    """
    return TransitionCounter(DoubleLaneChangeEnv(task.model.config))


def observation_mismatch(env: gym.Env, task: DoubleLaneChangeTask, actions: np.ndarray, seed: int = 0) -> float:
    """Largest ``|obs - task.observe(state)|`` along an episode of ``env`` driven by ``actions``.

    Checks that the environment's observation is the task's observation of the state that
    :func:`mixedrl.envs.evaluate_tracking` and the trainers use (``info["state"]``), at the reset and
    after every step.

    Parameters
    ----------
    env : gymnasium.Env
        A (possibly wrapped) :class:`~mixedrl.envs.DoubleLaneChangeEnv`.
    task : DoubleLaneChangeTask
        The task whose ``observe`` the trainers and the evaluation use.
    actions : numpy.ndarray, shape (n, 2)
        Normalised actions; the episode stops early if it ends.
    seed : int
        Seed of the reset.

    Returns
    -------
    float
        The largest absolute difference over every component and step.
    """
    obs, info = env.reset(seed=seed)
    worst = 0.0
    for a in [None, *np.asarray(actions, dtype=np.float64)]:
        if a is not None:
            obs, _, terminated, truncated, info = env.step(a)
        ref = task.observe(torch.as_tensor(info["state"], dtype=torch.float64)[None])[0].numpy()
        worst = max(worst, float(np.max(np.abs(np.asarray(obs) - ref))))
        if a is not None and (terminated or truncated):
            break
    return worst


def _jsonable(value: Any) -> Any:
    """A JSON-compatible form of an SB3 hyperparameter value (classes by name, else ``repr``)."""
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else str(value)
    if isinstance(value, (np.integer, np.floating)):
        return _jsonable(value.item())
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, tuple) and hasattr(value, "_fields"):  # e.g. SB3's TrainFreq(frequency, unit)
        return {f: _jsonable(getattr(value, f)) for f in value._fields}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if hasattr(value, "value") and isinstance(getattr(value, "value"), (str, int)):  # an Enum
        return value.value
    if isinstance(value, type):
        return f"{value.__module__}.{value.__qualname__}"
    return repr(value)


def _hyperparameters(model: Any) -> dict[str, Any]:
    """Every constructor argument of ``model``'s class as the built model holds it, and the network."""
    skip = RESERVED_KWARGS | {"self", "stats_window_size"}
    out: dict[str, Any] = {"policy": "MlpPolicy"}
    for name in inspect.signature(type(model).__init__).parameters:
        if name not in skip and hasattr(model, name):
            out[name] = _jsonable(getattr(model, name))
    out["net_arch"] = _jsonable(getattr(model.policy, "net_arch", None))
    out["activation_fn"] = _jsonable(getattr(model.policy, "activation_fn", None))
    out["device"] = str(model.device)
    return out


def _check_kwargs(kwargs: Any) -> dict[str, Any]:
    if kwargs is None:
        return {}
    if not isinstance(kwargs, dict) or not all(isinstance(k, str) for k in kwargs):
        raise TypeError(f"kwargs: expected a dict with string keys or None, got {type(kwargs).__name__}")
    reserved = sorted(set(kwargs) & RESERVED_KWARGS)
    if reserved:
        raise ValueError(f"kwargs: {reserved} cannot be overridden (set by train_peer's own arguments)")
    try:
        json.dumps(kwargs, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"kwargs: must be JSON data (they are recorded in the result), got {kwargs!r}: {exc}") from None
    return dict(kwargs)


def train_peer(algo: str, *, seed: int = 0, transitions: int = 100_000, eval_every: int = 10_000,
               eval_seeds: int = 2, out: str | Path | None = None, progress: bool = False,
               kwargs: dict[str, Any] | None = None) -> dict[str, Any]:
    """Train SB3's TD3 or SAC on the double lane change; evaluate it on the course as mixedrl runs are.

    The model is ``TD3("MlpPolicy", env, seed=seed, **kwargs)`` (or ``SAC``): SB3's defaults unless
    ``kwargs`` overrides some (tests only; recorded). ``env`` is ``Monitor(TransitionCounter(
    DoubleLaneChangeEnv(cfg)))`` with ``cfg`` the task of ``TrainConfig(seed=seed)``; SB3 seeds Python,
    numpy, torch, the action space and the environment's first reset from ``seed``.

    After every ``eval_every`` true transitions (and at the end) the deterministic policy
    (``model.predict(obs, deterministic=True)``) drives the full course once per evaluation seed of
    ``TrainConfig(seed=seed, run={"eval_seeds": eval_seeds})``, through
    :meth:`mixedrl.envs.dlc_task.DoubleLaneChangeTask.evaluate` with :class:`PhysicalPolicy`. An evaluation takes
    place where SB3 starts a new rollout, i.e. after the gradient steps on the data so far, so the policy
    evaluated at ``n`` transitions has learnt from exactly those ``n``.

    Parameters
    ----------
    algo : {"td3", "sac"}
        The peer.
    seed : int
        Seed of everything (SB3's ``seed``: torch, numpy, Python, action space, environment).
    transitions : int
        Budget of true-environment transitions (SB3's ``total_timesteps``, one environment). With the
        default ``train_freq=1`` the run uses exactly this many; a ``train_freq`` of ``n`` steps that does
        not divide it finishes its last rollout (up to ``n - 1`` more), and the count reports that.
    eval_every : int
        Evaluate every this many true transitions.
    eval_seeds : int
        Number of evaluation seeds (``RunConfig.eval_seeds``).
    out : str or pathlib.Path, optional
        Write the result as JSON there (atomically; parent directories created).
    progress : bool
        Show a tqdm progress bar over the transitions.
    kwargs : dict, optional
        Extra constructor arguments of the SB3 class (e.g. ``{"learning_starts": 50}`` for a short test);
        they must be JSON data and are recorded under ``config.kwargs``.

    Returns
    -------
    dict
        ``method`` (= ``algo``), ``seed``, ``config`` (``algo``, ``seed``, ``transitions``, ``eval_every``,
        ``eval_seeds`` (the list), ``env``, ``task``, ``sb3_version``, ``torch_version``, ``kwargs``,
        ``hyperparameters``: every constructor argument as the built model holds it, network included),
        ``rows``: one per evaluation, ``{true_transitions, wall_seconds, lateral_mae, speed_mae, cost}``,
        ``true_transitions`` (total), ``train_seconds``, ``episodes`` (completed training episodes).

    Raises
    ------
    ValueError
        ``algo`` unknown; ``seed`` negative; ``transitions``, ``eval_every`` or ``eval_seeds`` not a
        positive integer; ``kwargs`` sets a reserved argument or is not JSON data.
    TypeError
        ``kwargs`` not a dict with string keys.
    ImportError
        Stable-Baselines3 is not installed (install the extra ``peers``).

    Notes
    -----
    Side effects of SB3's seeding and of the study's thread rule: the process's global Python, numpy and
    torch random states are seeded from ``seed`` (SB3's ``set_random_seed``) and torch runs one thread
    (``torch.set_num_threads(1)``, as every mixedrl run of the study).
    """
    if algo not in ALGOS:
        raise ValueError(f"algo: expected one of {ALGOS}, got {algo!r}")
    check_nonnegative_int(seed, "seed")
    transitions = check_positive_int(transitions, "transitions")
    eval_every = check_positive_int(eval_every, "eval_every")
    eval_seeds = check_positive_int(eval_seeds, "eval_seeds")
    extra = _check_kwargs(kwargs)
    sb3 = import_sb3()
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.monitor import Monitor

    seed = int(seed)
    task, seeds = peer_task(seed, eval_seeds)
    counter = make_peer_env(task)
    env = Monitor(counter)
    cls = {"td3": sb3.TD3, "sac": sb3.SAC}[algo]
    try:
        model = without_log_folder(cls("MlpPolicy", env, seed=seed, verbose=0, device="cpu", **extra))
    except TypeError as exc:
        raise ValueError(f"kwargs: not accepted by {cls.__name__}: {exc}") from None
    config = {
        "algo": algo, "seed": seed, "transitions": transitions, "eval_every": eval_every, "eval_seeds": seeds,
        "env": ENV_ID, "task": TrainConfig(seed=seed, run=dict(eval_seeds=eval_seeds)).to_dict()["task"],
        "sb3_version": sb3.__version__, "torch_version": torch.__version__,
        "gymnasium_version": metadata.version("gymnasium"), "kwargs": extra,
        "hyperparameters": _hyperparameters(model),
    }
    policy = PhysicalPolicy(lambda obs: model.predict(obs, deterministic=True)[0], task.model.config)
    rows: list[dict[str, Any]] = []
    clock = {"start": 0.0, "in_eval": 0.0}

    def wall() -> float:
        return time.perf_counter() - clock["start"] - clock["in_eval"]

    def evaluate(spent: float | None = None) -> None:
        n, spent = counter.count, wall() if spent is None else spent
        t0 = time.perf_counter()
        ev = task.evaluate(policy, seeds)
        clock["in_eval"] += time.perf_counter() - t0
        rows.append({"true_transitions": int(n), "wall_seconds": float(spent), "lateral_mae": ev["lateral_mae"],
                     "speed_mae": ev["speed_mae"], "cost": ev["cost"]})
        logger.info("%s seed %d: %d transitions, lateral %.4f m, speed %.4f m/s, cost %.2f", algo, seed, n,
                    ev["lateral_mae"], ev["speed_mae"], ev["cost"])

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=transitions, desc=f"{algo} seed {seed}", unit="tr", leave=False)

    class Evaluations(BaseCallback):
        """Evaluate at the start of a rollout once ``eval_every`` more transitions have been learnt from."""

        def __init__(self) -> None:
            super().__init__()
            self.next_eval = eval_every

        def _on_training_start(self) -> None:
            clock["start"] = time.perf_counter()

        def _on_rollout_start(self) -> None:
            if counter.count >= self.next_eval:
                evaluate()
                self.next_eval = (counter.count // eval_every + 1) * eval_every

        def _on_step(self) -> bool:
            if bar is not None:
                bar.update(1)
                if rows:
                    bar.set_postfix(cost=f"{rows[-1]['cost']:.4g}")
            return True

    torch.set_num_threads(1)
    try:
        model.learn(total_timesteps=transitions, callback=Evaluations())
    finally:
        if bar is not None:
            bar.close()
    train_seconds = wall()
    if counter.count != model.num_timesteps:  # one environment: SB3's step count must be the true count
        raise RuntimeError(f"true transitions: counted {counter.count}, SB3 reports {model.num_timesteps}")
    if not rows or rows[-1]["true_transitions"] != counter.count:
        evaluate(train_seconds)
    result = {"method": algo, "seed": seed, "config": config, "rows": rows,
              "true_transitions": int(counter.count), "train_seconds": float(train_seconds),
              "episodes": len(env.get_episode_rewards())}
    if out is not None:
        path = Path(out)
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(path, json.dumps(result, indent=1, allow_nan=True) + "\n")
    return result


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m validation.peers``: train one peer and write its JSON (see :func:`train_peer`)."""
    parser = argparse.ArgumentParser(prog="python -m validation.peers", description=__doc__.splitlines()[0])
    parser.add_argument("--algo", required=True, choices=ALGOS)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--transitions", type=int, default=100_000)
    parser.add_argument("--eval-every", type=int, default=10_000)
    parser.add_argument("--eval-seeds", type=int, default=2)
    parser.add_argument("--out", required=True, help="output JSON file")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        result = train_peer(args.algo, seed=args.seed, transitions=args.transitions, eval_every=args.eval_every,
                            eval_seeds=args.eval_seeds, out=args.out, progress=not args.no_progress)
    except ValueError as exc:
        parser.error(str(exc))
    last = result["rows"][-1]
    logger.info("wrote %s: %d true transitions, %.0f s; lateral %.4f m, speed %.4f m/s, cost %.2f", args.out,
                result["true_transitions"], result["train_seconds"], last["lateral_mae"], last["speed_mae"],
                last["cost"])
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
