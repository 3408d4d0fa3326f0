"""Head-to-head benchmark on Gymnasium's Pendulum-v1 and MountainCarContinuous-v0 (issue 41, item 4).

One command runs (or resumes) every run of the study spec ``experiments/studies/gym_benchmark.toml`` and
writes the table and the figure::

    PYTHONPATH=. python experiments/analysis/gym_benchmark.py [--spec ...] [--out runs/gym_benchmark]
        [--results experiments/results/gym_benchmark] [--shard K/N] [--analysis-only] [--reduced]

* **Runs.** One JSON per run in ``--out`` (``<env>__<disturbance>__<method>__s<seed>.json``), written
  atomically with the run's full configuration (``config``); a run whose JSON exists with the same
  configuration is skipped (a different configuration is an error naming the file). ``--shard K/N`` runs
  every N-th run from the K-th (N processes share the study). Each run seeds every random draw from its
  seed: SB3's ``seed`` (torch, numpy, Python, the action space, the env's first reset, hence the
  disturbance's draws of the training env), mixedrl's ``TrainConfig.seed`` (the generator, the plant's
  episode seeds :func:`mixedrl.plant.episode_seed`).
* **Methods.** Stable-Baselines3 SAC, TD3 and DDPG with rl-zoo's hyperparameters and budgets (written in the
  spec, copied from the rl_zoo3 2.9.2 wheel's ``hyperparams/*.yml``) on the disturbed env
  (:class:`mixedrl.plant.DisturbedEnv`, true transitions counted by a wrapper, checked against SB3's
  ``num_timesteps``); Algorithm 2 (``mixed``, ``model``, ``oracle``) with ``TrainConfig``'s defaults
  through the plant interface (:func:`mixedrl.plant.attach_plant` on a
  :class:`mixedrl.plant.GymnasiumPlant` of the same disturbed env; the nominal physics in torch is the
  designer's ``f``: :class:`mixedrl.envs.gym_models.PendulumV1Task`,
  :class:`mixedrl.envs.gym_models.MountainCarTask`).
  Model-driven RL (the prior, no true transition) and the oracle (the true disturbance law) are the
  prior-model and true-model reference policies.
* **Evaluation.** Every policy, at every point of every curve, through one function,
  :func:`evaluate_policy`: the disturbed env, one episode per fixed episode seed of the spec, the
  deterministic action, the env's own undiscounted return, until the env ends the episode.
* **Statistics.** Over each run's final evaluation, per (env, disturbance): the IQM with a stratified
  bootstrap 95% percentile interval and the probability of improvement of mixed RL over each method, by
  rliable (Agarwal et al. 2021, *Deep RL at the edge of the statistical precipice*) when it is installed
  (extra ``benchmark``), else by :func:`iqm`, :func:`stratified_bootstrap_interval` and
  :func:`probability_of_improvement` here, which implement the same definitions.
* **Outputs.** ``table.md`` / ``table.json`` (return IQM [95% CI], true transitions per method, P(mixed >
  method), the zoo's published number beside) and ``returns.png`` (return against true transitions,
  every seed's curve) in ``--results``; ``timing.json`` (seconds per 1k steps or iterations, one core).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import time
import tomllib
import warnings
from copy import deepcopy
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import gymnasium as gym
import numpy as np
import scipy.stats
import torch

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:  # run as a script: the repository's mixedrl and validation
    sys.path.insert(0, str(ROOT))

from mixedrl.checkpoint import atomic_write_text
from mixedrl.envs.gym_models import MountainCarTask, PendulumV1Task
from mixedrl.plant import DisturbedEnv, GymnasiumPlant, attach_plant, unwrapped_state
from mixedrl.task_base import Task

SPEC = ROOT / "experiments" / "studies" / "gym_benchmark.toml"
RESULTS = ROOT / "experiments" / "results" / "gym_benchmark"
#: Colours of the methods in the figure.
COLOURS = {"sac": "tab:blue", "td3": "tab:orange", "ddpg": "tab:green", "mixed": "tab:red",
           "model": "tab:gray", "oracle": "black"}


# ================================================================================================ statistics
def iqm(scores: np.ndarray) -> float:
    """Interquartile mean: the 25% trimmed mean of all entries (rliable's ``aggregate_iqm``)."""
    return float(scipy.stats.trim_mean(np.asarray(scores, dtype=float), proportiontocut=0.25, axis=None))


def probability_of_improvement(x: np.ndarray, y: np.ndarray) -> float:
    """``P(X > Y) + P(X = Y) / 2`` per task, averaged over tasks (rliable's ``probability_of_improvement``).

    ``x`` (runs_x, tasks), ``y`` (runs_y, tasks); per task the Mann-Whitney ``U`` of ``x`` against ``y``
    divided by ``runs_x * runs_y`` (0.5 where the two columns are identical, as rliable).
    """
    x, y = np.atleast_2d(np.asarray(x, float).T).T, np.atleast_2d(np.asarray(y, float).T).T
    out = []
    for m in range(x.shape[1]):
        a, b = x[:, m], y[:, m]
        if np.array_equal(a, b):
            out.append(0.5)
            continue
        greater = (a[:, None] > b[None, :]).sum() + 0.5 * (a[:, None] == b[None, :]).sum()
        out.append(greater / (a.size * b.size))
    return float(np.mean(out))


def stratified_bootstrap_interval(func: Callable[..., float], *scores: np.ndarray, reps: int = 50_000,
                                  confidence: float = 0.95, seed: int = 0) -> tuple[float, float]:
    """Percentile interval of ``func(*scores)`` under the stratified bootstrap (rliable's default).

    Each score matrix (runs, tasks) is resampled with replacement *within each task* (the runs of a task
    are one stratum; ``task_bootstrap=False``), independently per matrix; the interval is the
    ``(1 - confidence) / 2`` and ``(1 + confidence) / 2`` percentiles of the ``reps`` statistics.
    """
    rng = np.random.default_rng(seed)
    mats = [np.atleast_2d(np.asarray(s, float).T).T for s in scores]
    stats = np.empty(reps)
    for r in range(reps):
        sample = []
        for s in mats:
            idx = rng.integers(0, s.shape[0], size=s.shape)
            sample.append(np.take_along_axis(s, idx, axis=0))
        stats[r] = func(*sample)
    lo, hi = np.percentile(stats, [50 * (1 - confidence), 50 * (1 + confidence)])
    return float(lo), float(hi)


def have_rliable() -> bool:
    """rliable (extra ``benchmark``) importable (its ``arch`` needs pandas < 3)."""
    try:
        from rliable import library, metrics  # noqa: F401
    except Exception:  # noqa: BLE001 - missing, or broken by an incompatible dependency
        return False
    return True


@contextlib.contextmanager
def _global_numpy_seed(seed: int) -> Iterator[None]:
    """NumPy's global generator seeded with ``seed`` inside the block, restored after it: rliable's stratified
    bootstraps (``StratifiedBootstrap.update_indices``, rliable 1.2) draw their indices from ``np.random``, not
    from the ``random_state`` they are given, so without this the intervals change from one call to the next."""
    state = np.random.get_state()
    np.random.seed(seed)
    try:
        yield
    finally:
        np.random.set_state(state)


def interval_estimates(scores: dict[str, np.ndarray], reps: int = 50_000, confidence: float = 0.95,
                       seed: int = 0, backend: str = "auto") -> dict[str, dict[str, float]]:
    """IQM and its stratified bootstrap interval of each method's scores (runs, tasks).

    ``backend``: ``"rliable"``, ``"numpy"`` (this module) or ``"auto"`` (rliable if installed).
    Returns ``{method: {"iqm", "lo", "hi", "backend"}}``.
    """
    use = have_rliable() if backend == "auto" else backend == "rliable"
    out: dict[str, dict[str, float]] = {}
    for name, s in scores.items():
        s = np.atleast_2d(np.asarray(s, float).T).T
        if use:
            from rliable import library as rly, metrics

            with warnings.catch_warnings(), _global_numpy_seed(seed):  # arch: "random_state is deprecated"
                warnings.simplefilter("ignore", FutureWarning)
                point, ci = rly.get_interval_estimates({name: s}, lambda x: np.array([metrics.aggregate_iqm(x)]),
                                                       reps=reps, confidence_interval_size=confidence,
                                                       random_state=np.random.RandomState(seed))
            out[name] = {"iqm": float(point[name][0]), "lo": float(ci[name][0, 0]), "hi": float(ci[name][1, 0]),
                         "backend": "rliable"}
        else:
            lo, hi = stratified_bootstrap_interval(iqm, s, reps=reps, confidence=confidence, seed=seed)
            out[name] = {"iqm": iqm(s), "lo": lo, "hi": hi, "backend": "numpy"}
    return out


def improvement_estimates(pairs: dict[str, tuple[np.ndarray, np.ndarray]], reps: int = 50_000,
                          confidence: float = 0.95, seed: int = 0, backend: str = "auto"
                          ) -> dict[str, dict[str, float]]:
    """Probability of improvement ``P(X > Y)`` of each pair ``(x, y)`` with its stratified bootstrap interval."""
    use = have_rliable() if backend == "auto" else backend == "rliable"
    out: dict[str, dict[str, float]] = {}
    for name, (x, y) in pairs.items():
        x, y = np.atleast_2d(np.asarray(x, float).T).T, np.atleast_2d(np.asarray(y, float).T).T
        if use:
            from rliable import library as rly, metrics

            with warnings.catch_warnings(), _global_numpy_seed(seed):
                warnings.simplefilter("ignore", FutureWarning)
                point, ci = rly.get_interval_estimates({name: (x, y)}, metrics.probability_of_improvement,
                                                       reps=reps, confidence_interval_size=confidence,
                                                       random_state=np.random.RandomState(seed))
            out[name] = {"p": float(np.squeeze(point[name])), "lo": float(np.ravel(ci[name])[0]),
                         "hi": float(np.ravel(ci[name])[1]), "backend": "rliable"}
        else:
            lo, hi = stratified_bootstrap_interval(probability_of_improvement, x, y, reps=reps,
                                                   confidence=confidence, seed=seed)
            out[name] = {"p": probability_of_improvement(x, y), "lo": lo, "hi": hi, "backend": "numpy"}
    return out


# ================================================================================================ tasks
def make_task(env_spec: dict[str, Any], disturbance: dict[str, Any]) -> Task:
    """The designer's task of an env of the spec: nominal physics, true law (the oracle's) and prior."""
    prior = env_spec.get("prior", {})
    args = dict(prior_mean=float(prior.get("mean", 0.0)), prior_std=float(prior.get("std", 1.0)))
    if env_spec["task"] == "pendulum":
        return PendulumV1Task(torque_mean=float(disturbance["mean"]), torque_std=float(disturbance["std"]), **args)
    if env_spec["task"] == "mountain_car":
        return MountainCarTask(force_mean=float(disturbance["mean"]), force_std=float(disturbance["std"]), **args)
    raise ValueError(f"envs.*.task: expected 'pendulum' or 'mountain_car', got {env_spec['task']!r}")


def make_env(env_id: str, disturbance: dict[str, Any]) -> DisturbedEnv:
    """The true system: ``gym.make(env_id)`` (its own time limit) with the disturbance after the clip."""
    return DisturbedEnv(gym.make(env_id), mean=float(disturbance["mean"]), std=float(disturbance["std"]))


# ================================================================================================ evaluation
def evaluate_policy(act: Callable[[np.ndarray, gym.Env], Any], env_id: str, disturbance: dict[str, Any],
                    episode_seeds: Sequence[int]) -> dict[str, Any]:
    """THE evaluation of every method: one episode of the disturbed env per seed, the deterministic action.

    ``act(obs, env)`` returns the action (SB3: ``model.predict(obs, deterministic=True)``; Algorithm 2:
    the actor of the env's state); episode ``i`` starts with ``env.reset(seed=episode_seeds[i])`` (which
    also seeds the disturbance's draws) and runs until the env terminates or truncates it (its own time
    limit). Returns the episodes' undiscounted env returns, their mean (``return``), lengths and the
    evaluation transitions (``transitions``).
    """
    env = make_env(env_id, disturbance)
    returns, lengths = [], []
    shape, dtype = env.action_space.shape, env.action_space.dtype
    for seed in episode_seeds:
        obs, _ = env.reset(seed=int(seed))
        ret, n, done = 0.0, 0, False
        while not done:
            action = np.asarray(act(obs, env), dtype=dtype).reshape(shape)
            obs, reward, terminated, truncated, _ = env.step(action)
            ret, n, done = ret + float(reward), n + 1, bool(terminated or truncated)
        returns.append(ret)
        lengths.append(n)
    env.close()
    return {"return": float(np.mean(returns)), "returns": returns, "lengths": lengths,
            "transitions": int(sum(lengths))}


def task_actor(task: Task, policy: torch.nn.Module) -> Callable[[np.ndarray, gym.Env], np.ndarray]:
    """An Algorithm 2 actor as ``act(obs, env)``: ``policy(task.observe(state))`` on the env's state (float32
    observations, as in training and in :func:`mixedrl.plant.evaluate_on_plant`)."""

    def act(obs: np.ndarray, env: gym.Env) -> np.ndarray:
        x = torch.as_tensor(unwrapped_state(env))[None]
        with torch.no_grad():
            return policy(task.observe(x.float())).double()[0].numpy()

    return act


# ================================================================================================ runs
def load_spec(path: str | Path = SPEC) -> dict[str, Any]:
    with open(path, "rb") as fh:
        return tomllib.load(fh)


def run_id(run: dict[str, Any]) -> str:
    return f"{run['env']}__{run['disturbance']['name']}__{run['method']}__s{run['seed']}"


def expand_runs(spec: dict[str, Any], reduced: bool = False) -> list[dict[str, Any]]:
    """Every run of the spec (each with its full configuration), sorted by env, disturbance, method, seed."""
    red = spec.get("reduced", {}) if reduced else None
    ev = spec["evaluation"]
    runs = []
    for env_id, env_spec in spec["envs"].items():
        for dist in env_spec["disturbances"]:
            for name, method in spec["methods"].items():
                per_env = method.get("envs", {}).get(env_id, {})
                if method["kind"] == "sb3" and not per_env:
                    continue
                seeds = per_env.get("seeds", method.get("seeds", spec["seeds"]))
                if red is not None:
                    seeds = [s for s in red["seeds"] if s in seeds] or list(red["seeds"])
                for seed in seeds:
                    run: dict[str, Any] = {
                        "study": spec["name"], "env": env_id, "env_spec": deepcopy(env_spec),
                        "disturbance": dict(dist), "method": name, "kind": method["kind"], "seed": int(seed),
                        "evaluation": {"episode_seeds": list(red["episode_seeds"] if red else ev["episode_seeds"]),
                                       "points": int(red["points"] if red else ev["points"])},
                        "reduced": None}
                    if method["kind"] == "sb3":
                        hp = deepcopy(per_env["hyperparams"])
                        run.update(algo=method["algo"], hyperparams=hp, zoo=per_env.get("zoo"))
                        if red is not None:
                            run["reduced"] = {"n_timesteps": int(red["sb3_timesteps"]),
                                              "learning_starts": min(int(hp.get("learning_starts", 100)),
                                                                     int(red["learning_starts"])),
                                              "buffer_size": int(red["buffer_size"])}
                    elif method["kind"] == "mixedrl":
                        run.update(mixedrl_method=method["method"], config=deepcopy(method.get("config", {})),
                                   reference=method.get("reference"))
                        if red is not None:
                            run["reduced"] = {"iterations": int(red["mixedrl_iterations"])}
                    else:
                        raise ValueError(f"methods.{name}.kind: expected 'sb3' or 'mixedrl', got {method['kind']!r}")
                    run["id"] = run_id(run)
                    runs.append(run)
    return runs


def _versions() -> dict[str, str]:
    from importlib import metadata

    out = {}
    for pkg in ("mixedrl", "torch", "gymnasium", "numpy", "stable-baselines3"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def run_sb3(run: dict[str, Any], progress: bool = False) -> dict[str, Any]:
    """Train one SB3 peer on the disturbed env with the spec's (zoo's) hyperparameters; evaluate along it."""
    import stable_baselines3 as sb3
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.noise import NormalActionNoise, OrnsteinUhlenbeckActionNoise

    from validation.peers import TransitionCounter, _hyperparameters, without_log_folder

    hp = deepcopy(run["hyperparams"])
    total = int(hp.pop("n_timesteps"))
    if run["reduced"]:
        total = run["reduced"]["n_timesteps"]
        hp["learning_starts"] = run["reduced"]["learning_starts"]
        hp["buffer_size"] = run["reduced"]["buffer_size"]
    counter = TransitionCounter(make_env(run["env"], run["disturbance"]))
    env = Monitor(counter)
    zeros = np.zeros(env.action_space.shape[0])
    noise_type, noise_std = hp.pop("noise_type", None), hp.pop("noise_std", None)
    if noise_type == "normal":  # as rl_zoo3's ExperimentManager builds it
        hp["action_noise"] = NormalActionNoise(mean=zeros, sigma=noise_std * np.ones_like(zeros))
    elif noise_type == "ornstein-uhlenbeck":
        hp["action_noise"] = OrnsteinUhlenbeckActionNoise(mean=zeros, sigma=noise_std * np.ones_like(zeros))
    elif noise_type is not None:
        raise ValueError(f"hyperparams.noise_type: unknown {noise_type!r}")
    if "train_freq" in hp and isinstance(hp["train_freq"], list):
        hp["train_freq"] = tuple(hp["train_freq"])
    cls = getattr(sb3, run["algo"])
    model = without_log_folder(cls("MlpPolicy", env, seed=run["seed"], verbose=0, device="cpu", **hp))
    ev = run["evaluation"]
    every = max(1, total // ev["points"])
    rows: list[dict[str, Any]] = []
    clock = {"start": 0.0, "eval": 0.0}

    def act(obs: np.ndarray, _env: gym.Env) -> np.ndarray:
        return model.predict(obs, deterministic=True)[0]

    def evaluate() -> None:
        t0 = time.perf_counter()
        res = evaluate_policy(act, run["env"], run["disturbance"], ev["episode_seeds"])
        spent = t0 - clock["start"] - clock["eval"]
        clock["eval"] += time.perf_counter() - t0
        rows.append({"true_transitions": int(counter.count), "wall_seconds": float(spent), **res})

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=total, desc=run["id"], unit="tr", leave=False)

    class Evaluations(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.next_eval = every

        def _on_training_start(self) -> None:
            clock["start"] = time.perf_counter()
            evaluate()  # the initial policy, 0 true transitions

        def _on_rollout_start(self) -> None:
            if counter.count >= self.next_eval:
                evaluate()
                self.next_eval = (counter.count // every + 1) * every

        def _on_step(self) -> bool:
            if bar is not None:
                bar.update(1)
            return True

    try:
        model.learn(total_timesteps=total, callback=Evaluations())
    finally:
        if bar is not None:
            bar.close()
    train_seconds = time.perf_counter() - clock["start"] - clock["eval"]
    if counter.count != model.num_timesteps:
        raise RuntimeError(f"true transitions: counted {counter.count}, SB3 reports {model.num_timesteps}")
    if rows[-1]["true_transitions"] != counter.count:
        evaluate()
    return {"rows": rows, "true_transitions": int(counter.count), "train_seconds": float(train_seconds),
            "steps": int(counter.count), "episodes": len(env.get_episode_rewards()),
            "hyperparameters": _hyperparameters(model)}  # every constructor argument as the built model holds it


def run_mixedrl(run: dict[str, Any], progress: bool = False) -> dict[str, Any]:
    """Algorithm 2 (mixed, model or oracle) with TrainConfig's defaults on the plant; evaluate along it."""
    from mixedrl.algorithms.agpi import AGPI
    from mixedrl.config import TrainConfig
    from mixedrl.runs import train

    task = make_task(run["env_spec"], run["disturbance"])
    plant_env = make_env(run["env"], run["disturbance"])
    attach_plant(task, GymnasiumPlant(plant_env), evaluation="plant")
    cfg = deepcopy(run["config"])
    algorithm = dict(cfg.pop("algorithm", {}))
    if run["reduced"]:
        algorithm["iterations"] = run["reduced"]["iterations"]
    sampler = {"name": "model_rollouts", **cfg.pop("sampler", {})}
    probe = TrainConfig(method=run["mixedrl_method"], task="linear", seed=run["seed"], algorithm=algorithm)
    iterations = probe.algorithm.iterations  # a global task's budget and eval_every are region_budget x these
    points = run["evaluation"]["points"]
    config = TrainConfig(method=run["mixedrl_method"], task="linear", seed=run["seed"], algorithm=algorithm,
                         sampler=sampler, run={"eval_every": max(1, iterations // points), "eval_seeds": 1,
                                               "num_threads": 1, **cfg.pop("run", {})}, **cfg)
    trainer = AGPI(task, config)
    rows: list[dict[str, Any]] = []
    clock = {"eval": 0.0}

    def evaluate(policy: torch.nn.Module, seeds: list[int], horizon: int | None = None) -> dict[str, Any]:
        t0 = time.perf_counter()
        res = evaluate_policy(task_actor(task, policy), run["env"], run["disturbance"],
                              run["evaluation"]["episode_seeds"])
        clock["eval"] += time.perf_counter() - t0
        rows.append({"true_transitions": int(trainer.true_transitions), "iteration": int(trainer.k), **res})
        return {"plant_return": res["return"]}

    evaluate(trainer.policy, [])  # the initial policy
    clock["eval"] = 0.0
    task.plant_evaluate = evaluate  # train()'s evaluations: the same function as every method's
    t0 = time.perf_counter()
    results = train(trainer, progress=progress)
    train_seconds = time.perf_counter() - t0 - clock["eval"]
    if rows[-1]["iteration"] != trainer.k:
        evaluate(trainer.policy, [])
    return {"rows": rows, "true_transitions": int(results["plant_transitions"]["training"]),
            "train_seconds": float(train_seconds), "steps": int(results["iterations"]),
            "trainconfig": trainer.config.to_dict(), "region_budget": trainer.region_budget,
            "final_ibe_mean": results.get("final_ibe_mean"),
            "plant_transitions": results["plant_transitions"]}


def run_one(run: dict[str, Any], out_dir: Path, progress: bool = False) -> tuple[dict[str, Any], bool]:
    """Run ``run`` into ``out_dir/<id>.json`` unless that JSON exists with the same config; (result, ran)."""
    path = out_dir / f"{run['id']}.json"
    config = json.loads(json.dumps(run))
    if path.exists():
        old = json.loads(path.read_text())
        if old.get("config") != config:
            raise ValueError(f"{path}: exists with a different configuration (delete it to rerun)")
        return old, False
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    body = (run_sb3 if run["kind"] == "sb3" else run_mixedrl)(run, progress=progress)
    result = {"id": run["id"], "config": config, "versions": _versions(), "wall_seconds": time.perf_counter() - t0,
              "final_return": body["rows"][-1]["return"], **body}
    out_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(result, indent=1, allow_nan=True) + "\n")
    return result, True


def run_all(runs: list[dict[str, Any]], out_dir: Path, shard: tuple[int, int] = (0, 1),
            progress: bool = True) -> list[dict[str, Any]]:
    """Run (or resume) this shard's runs, sequentially; tqdm over the runs (and inside each run)."""
    from tqdm.auto import tqdm

    mine = [r for i, r in enumerate(runs) if i % shard[1] == shard[0]]
    out = []
    bar = tqdm(mine, desc="gym_benchmark", unit="run", disable=not progress)
    for run in bar:
        bar.set_postfix_str(run["id"])
        out.append(run_one(run, out_dir, progress=progress)[0])
    return out


# ================================================================================================ analysis
def load_results(out_dir: Path, runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The JSONs of ``runs`` present in ``out_dir`` (a missing run is left out and reported)."""
    found, missing = [], []
    for run in runs:
        path = out_dir / f"{run['id']}.json"
        (found.append(json.loads(path.read_text())) if path.exists() else missing.append(run["id"]))
    if missing:
        print(f"gym_benchmark: {len(missing)} run(s) missing from {out_dir} (left out): {missing[:5]}...",
              file=sys.stderr)
    return found


def _fmt(x: float) -> str:
    return f"{x:.1f}" if abs(x) < 1e4 else f"{x:.3g}"


def analyse(spec: dict[str, Any], results: list[dict[str, Any]], results_dir: Path, reduced: bool = False,
            backend: str = "auto") -> dict[str, Any]:
    """Write ``table.md``, ``table.json``, ``timing.json`` and ``returns.png`` into ``results_dir``."""
    stats_spec = spec.get("statistics", {})
    reps = int(spec["reduced"]["bootstrap_reps"]) if reduced else int(stats_spec.get("reps", 50_000))
    conf, bseed = float(stats_spec.get("confidence", 0.95)), int(stats_spec.get("bootstrap_seed", 0))
    ref = stats_spec.get("improvement_reference", "mixed")
    cells: dict[tuple[str, str], dict[str, list[dict[str, Any]]]] = {  # the spec's order of envs and methods
        (env_id, d["name"]): {m: [] for m in spec["methods"]}
        for env_id, env_spec in spec["envs"].items() for d in env_spec["disturbances"]}
    for r in results:
        c = r["config"]
        cells.setdefault((c["env"], c["disturbance"]["name"]), {}).setdefault(c["method"], []).append(r)
    cells = {k: {m: rs for m, rs in v.items() if rs} for k, v in cells.items()}
    cells = {k: v for k, v in cells.items() if v}
    table: dict[str, Any] = {"study": spec["name"], "reduced": reduced, "confidence": conf, "reps": reps,
                             "cells": []}
    lines = [f"# {spec['name']}{' (reduced: CI budgets, not results)' if reduced else ''}", "",
             "Final return against the true (disturbed) env: deterministic policy, "
             f"{len(results[0]['config']['evaluation']['episode_seeds']) if results else 0} fixed episode seeds, "
             f"the env's own return. IQM over seeds [{conf:.0%} stratified bootstrap percentile interval, "
             f"{reps} reps]; P({ref} > method) with its interval. Zoo: rl-baselines3-zoo benchmark.md on the "
             "UNdisturbed env (mean +- std), for scale.", ""]
    for (env_id, dname), methods in cells.items():
        scores = {m: np.array([[r["final_return"]] for r in sorted(rs, key=lambda r: r["config"]["seed"])])
                  for m, rs in methods.items()}
        est = interval_estimates(scores, reps=reps, confidence=conf, seed=bseed, backend=backend)
        pairs = {m: (scores[ref], scores[m]) for m in scores if m != ref and ref in scores}
        poi = improvement_estimates(pairs, reps=reps, confidence=conf, seed=bseed, backend=backend)
        lines += [f"## {env_id}, disturbance {dname}", "",
                  f"| method | seeds | true transitions (training, per run) | return IQM [{conf:.0%} CI] | "
                  f"P({ref} > method) | zoo (undisturbed) |", "|---|---|---|---|---|---|"]
        cell = {"env": env_id, "disturbance": dname, "methods": {}}
        for m in spec["methods"]:
            if m not in methods:
                continue
            rs = methods[m]
            tt = sorted({r["true_transitions"] for r in rs})
            zoo = rs[0]["config"].get("zoo")
            zoo_s = "" if not zoo else (f"{zoo['mean']} +- {zoo['std']}" if "std" in zoo else f"{zoo['mean']}") + \
                (f" at {zoo['timesteps']}" if zoo else "")
            ref_note = rs[0]["config"].get("reference")
            label = m + (f" ({ref_note})" if ref_note else "")
            e = est[m]
            p = poi.get(m)
            p_s = "" if p is None else f"{p['p']:.2f} [{p['lo']:.2f}, {p['hi']:.2f}]"
            tt_s = str(tt[0]) if len(tt) == 1 else f"{tt[0]}-{tt[-1]}"
            lines.append(f"| {label} | {len(rs)} | {tt_s} | {_fmt(e['iqm'])} [{_fmt(e['lo'])}, {_fmt(e['hi'])}] | "
                         f"{p_s} | {zoo_s} |")
            cell["methods"][m] = {"seeds": [r["config"]["seed"] for r in rs], "true_transitions": tt,
                                  "final_returns": [float(s[0]) for s in scores[m]], **e,
                                  "improvement": p, "zoo": zoo}
        if "model" in est and "oracle" in est:
            gap = est["oracle"]["iqm"] - est["model"]["iqm"]
            lines += ["", f"What the disturbance costs the prior-model policy: oracle IQM - model IQM = {_fmt(gap)}."]
            cell["disturbance_cost"] = gap
        extra = {f"{a} > {b}": (scores[a], scores[b]) for a, b in stats_spec.get("pairs", [])
                 if a in scores and b in scores}
        if extra:  # the spec's further pairs (paired by seed): P(a > b), and on how many seeds a is higher
            cell["pairs"] = improvement_estimates(extra, reps=reps, confidence=conf, seed=bseed, backend=backend)
            for name, (x, y) in extra.items():
                p, wins = cell["pairs"][name], int(np.sum(x[:, 0] > y[:, 0]))
                cell["pairs"][name]["higher_on"] = wins
                lines += ["", f"P({name}) = {p['p']:.2f} [{p['lo']:.2f}, {p['hi']:.2f}]; higher on {wins} of "
                          f"{len(x)} seeds."]
        lines.append("")
        table["cells"].append(cell)
    timing = timing_table(results)
    lines += ["## Training time (one core, evaluations excluded)", "",
              "| env | method | unit | seconds per 1k units (median over runs) | runs |", "|---|---|---|---|---|"]
    for t in timing:
        lines.append(f"| {t['env']} | {t['method']} | {t['unit']} | {t['seconds_per_1k']:.2f} | {t['runs']} |")
    backend_used = {v["backend"] for c in table["cells"] for v in c["methods"].values()}
    lines += ["", f"Statistics: {', '.join(sorted(backend_used))}."]
    results_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(results_dir / "table.md", "\n".join(lines) + "\n")
    atomic_write_text(results_dir / "table.json", json.dumps(table, indent=1) + "\n")
    atomic_write_text(results_dir / "timing.json", json.dumps(timing, indent=1) + "\n")
    figure(cells, results_dir / "returns.png")
    return table


def timing_table(results: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Seconds of training per 1k env steps (SB3) or 1k iterations (Algorithm 2), median over runs."""
    groups: dict[tuple[str, str], list[float]] = {}
    for r in results:
        if r["steps"] > 0:
            key = (r["config"]["env"], r["config"]["method"])
            groups.setdefault(key, []).append(1000 * r["train_seconds"] / r["steps"])
    kinds = {(r["config"]["env"], r["config"]["method"]): r["config"]["kind"] for r in results}
    return [{"env": e, "method": m, "unit": "iterations" if kinds[(e, m)] == "mixedrl" else "env steps",
             "seconds_per_1k": float(np.median(v)), "runs": len(v)} for (e, m), v in groups.items()]


def figure(cells: dict[tuple[str, str], dict[str, list[dict[str, Any]]]], path: Path) -> None:
    """Return against true transitions, one thin line per seed (references: one dashed line per seed; the
    zoo's published mean +- std on the undisturbed env as a star at its budget)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(cells), figsize=(6.5 * len(cells), 4.5), squeeze=False)
    for ax, ((env_id, dname), methods) in zip(axes[0], cells.items()):
        right = 1.0
        for k, (m, rs) in enumerate(methods.items()):
            colour = COLOURS.get(m, None)
            for i, r in enumerate(sorted(rs, key=lambda r: r["config"]["seed"])):
                label = m if i == 0 else None
                if r["true_transitions"] == 0:  # a reference policy: no true transition, its final return
                    ax.axhline(r["final_return"], color=colour, lw=0.8, ls="--", alpha=0.6,
                               label=(f"{m} ({r['config'].get('reference')}), 0 true transitions"
                                      if i == 0 else None))
                    continue
                x = [row["true_transitions"] for row in r["rows"]]
                y = [row["return"] for row in r["rows"]]
                ax.plot(x, y, color=colour, lw=0.8, alpha=0.6, marker=".", ms=3, label=label)
            zoo = rs[0]["config"].get("zoo")
            if zoo:  # the zoo's published number, on the undisturbed env
                x_zoo = zoo["timesteps"] * (1 + 0.08 * k)  # side by side where the budgets coincide
                ax.errorbar(x_zoo, zoo["mean"], yerr=zoo.get("std", 0.0), color=colour, marker="*",
                            ms=9, capsize=3, ls="none", label=f"{m}: zoo, undisturbed env")
                right = max(right, x_zoo)
            right = max([right] + [row["true_transitions"] for r in rs for row in r["rows"]])
        ax.set_xscale("symlog", linthresh=100)
        ax.set_xlim(0, 1.5 * right)
        ax.set_xlabel("true transitions (training)")
        ax.set_ylabel("return (env's own, mean over the episode seeds)")
        ax.set_title(f"{env_id}, disturbance {dname}")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# ================================================================================================ main
def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--spec", default=str(SPEC))
    parser.add_argument("--out", default=None, help="run JSONs (default runs/gym_benchmark[_reduced])")
    parser.add_argument("--results", default=None,
                        help=f"table and figure (default {RESULTS.relative_to(ROOT)}; reduced: <out>/results)")
    parser.add_argument("--reduced", action="store_true", help="CI: tiny budgets, 2 seeds")
    parser.add_argument("--shard", default="0/1", help="K/N: run every N-th run from the K-th")
    parser.add_argument("--analysis-only", action="store_true", help="only the table and figure")
    parser.add_argument("--only", default=None, help="only runs whose id contains this")
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument("--stats", default="auto", choices=("auto", "rliable", "numpy"))
    args = parser.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    torch.set_num_threads(1)
    spec = load_spec(args.spec)
    runs = expand_runs(spec, reduced=args.reduced)
    if args.only:
        runs = [r for r in runs if args.only in r["id"]]
    out = Path(args.out or ROOT / "runs" / (spec["name"] + ("_reduced" if args.reduced else "")))
    results_dir = Path(args.results) if args.results else (out / "results" if args.reduced else RESULTS)
    k, n = (int(v) for v in args.shard.split("/"))
    if not args.analysis_only:
        run_all(runs, out, shard=(k, n), progress=not args.no_progress)
    if n == 1 or args.analysis_only:
        results = load_results(out, runs)
        if results:
            analyse(spec, results, results_dir, reduced=args.reduced, backend=args.stats)
            print(f"gym_benchmark: {len(results)} runs -> {results_dir}/table.md, returns.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
