"""Tests of the run configuration (mixedrl.config): the nested task configuration, dotted overrides,
the refusal of the old flat form, and errors naming the dotted key."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

from mixedrl.envs import DoubleLaneChangeConfig
from mixedrl.config import (
    DISTURBANCE_LAWS,
    FLAT_FORM_RELEASE,
    DoubleLaneChangeTaskConfig,
    LinearTaskConfig,
    TrainConfig,
    apply_overrides,
    task_config,
)

#: A config.json written by the code before the task configuration existed (commit 231ea19), verbatim.
OLD_CONFIG = {
    "activation": "elu", "actor_lr": 0.0003, "batch_size": 512, "checkpoint_every": 500, "critic_lr": 0.003,
    "ddpg_buffer_size": 200000, "ddpg_envs": 16, "ddpg_noise_std": 0.2, "ddpg_tau": 0.005, "ddpg_warmup": 2000,
    "eval_every": 100, "eval_seeds": 2, "expectation": "sigma", "grad_clip": 10.0, "hidden_sizes": [64, 64],
    "horizon": 60, "ibe_recursion": "exact", "iterations": 1500, "j_max": 5, "lr_decay_to": 0.01,
    "method": "mixed", "mvc_check": "mean", "noise_samples": 4, "num_threads": 1, "seed": 3,
    "stop_epsilon": 0.0, "stop_patience": 100, "task": "dlc", "train_half_widths": [0.3, 0.2, 1.0, 0.1, 1.0],
    "value_output": "square"}


def test_defaults_are_the_papers_experiment() -> None:
    """Section VI's numbers: prior 150 N / 4 N, truth N(261, 32), gamma 0.99, eq. 54's weights."""
    task = TrainConfig().task
    assert isinstance(task, DoubleLaneChangeTaskConfig)
    assert (task.name, task.gamma, task.prior_force_mean, task.prior_force_std) == ("dlc", 0.99, 150.0, 4.0)
    d = task.disturbance
    assert (d.law, d.mean, d.variance, d.grade_amplitude) == ("gaussian", 261.0, 32.0, 0.0)
    c = task.cost
    assert (c.q_speed, c.q_lateral, c.r_steer, c.r_accel) == (45.0, 60.0, 800.0, 1.0)
    assert task.preview_distances == () and task.train_half_widths == (0.3, 0.2, 1.0, 0.1, 1.0)
    assert "gaussian" in DISTURBANCE_LAWS


def test_config_json_holds_the_whole_task_and_round_trips(tmp_path: Path) -> None:
    cfg = TrainConfig(task={"prior_force_mean": 300, "disturbance": {"variance": 64}, "preview_distances": [5.0]})
    path = tmp_path / "config.json"
    cfg.save(path)
    saved = json.loads(path.read_text())
    task = saved["task"]
    assert {k: task[k] for k in ("name", "gamma", "prior_force_mean", "prior_force_std", "disturbance", "cost",
                                 "preview_distances", "train_half_widths")} == {
        "name": "dlc", "gamma": 0.99, "prior_force_mean": 300.0, "prior_force_std": 4.0,
        "disturbance": {"law": "gaussian", "mean": 261.0, "variance": 64.0, "dof": 3.0, "grade_amplitude": 0.0,
                        "grade_wavelength": 40.0, "grade_phase": 0.0},
        "cost": {"q_speed": 45.0, "q_lateral": 60.0, "r_steer": 800.0, "r_accel": 1.0},
        "preview_distances": [5.0], "train_half_widths": [0.3, 0.2, 1.0, 0.1, 1.0]}
    # the task section is the environment's whole configuration (one schema): vehicle, reference, bounds
    env_fields = {f.name for f in dataclasses.fields(DoubleLaneChangeConfig)}
    assert env_fields <= set(task) and set(task) - env_fields == {"name", "gamma", "prior_force_mean",
                                                                     "prior_force_std"}
    assert (task["params"]["m"], task["dt"], task["v_des"], task["reference"]["dy1"]) == (1500.0, 0.005, 12.0, 4.05)
    assert "train_half_widths" not in saved  # only under task now
    assert TrainConfig.load(path) == cfg
    lin = TrainConfig(task={"name": "linear", "prior_mean": [0, -1]})
    assert TrainConfig.from_dict(json.loads(json.dumps(lin.to_dict()))) == lin
    assert lin.to_dict()["task"]["disturbance"] == {"law": "gaussian", "mean": [0.0, 0.5],
                                                    "cov": [[0.0, 0.0], [0.0, 0.01]]}


_RELEASE = r"read by mixedrl 0\.1\.0 at git commit b510485; this release reads the sections"


def test_an_old_config_json_names_the_release_that_reads_it(tmp_path: Path) -> None:
    assert FLAT_FORM_RELEASE == "mixedrl 0.1.0 at git commit b510485"
    (tmp_path / "config.json").write_text(json.dumps(OLD_CONFIG))
    with pytest.raises(ValueError, match=r"^config: \['activation', 'actor_lr', .*'value_output'\] at the top level is "
                                         r"the flat form, " + _RELEASE):
        TrainConfig.load(tmp_path / "config.json")
    for part in ({"train_half_widths": [1, 1, 1, 1, 1]}, {"model_course_starts": "loop"}, {"ddpg_tau": 0.1},
                 {"state_source": "true"}, {"true_envs": 2}):
        with pytest.raises(ValueError, match=rf"^config: \['{next(iter(part))}'\] at the top level is the flat form, "
                                             + _RELEASE):
            TrainConfig.from_dict({"method": "mixed", **part})
    assert TrainConfig(task="linear").task == LinearTaskConfig()  # a task's name stays a config's task


@pytest.mark.parametrize("data,key", [
    ({"task": {"prior_mena": 1}}, "task.prior_mena"),
    ({"task": {"disturbance": {"meen": 1}}}, "task.disturbance.meen"),
    ({"task": {"cost": {"q_sped": 1}}}, "task.cost.q_sped"),
    ({"task": {"name": "linear", "prior_force_mean": 1}}, "task.prior_force_mean"),  # a dlc field on linear
    ({"task": {"name": "linear", "disturbance": {"variance": 1}}}, "task.disturbance.variance"),
    ({"batchsize": 3}, "batchsize"),
])
def test_unknown_keys_at_any_level_name_the_dotted_key(data: dict, key: str) -> None:
    with pytest.raises(ValueError, match=rf"^config: unknown key\(s\) \['{key}'\]"):
        TrainConfig.from_dict(data)


@pytest.mark.parametrize("task,field", [
    ({"gamma": 1.0}, "task.gamma"), ({"gamma": 0}, "task.gamma"),
    ({"prior_force_std": 0}, "task.prior_force_std"), ({"prior_force_mean": math.nan}, "task.prior_force_mean"),
    ({"prior_force_mean": "150"}, "task.prior_force_mean"),
    ({"disturbance": {"variance": -1}}, "task.disturbance.variance"),
    ({"disturbance": {"law": "cauchy"}}, "task.disturbance.law"),
    ({"disturbance": {"law": "student_t", "dof": 2.0}}, "task.disturbance.dof"),
    ({"disturbance": {"dof": math.inf}}, "task.disturbance.dof"),
    ({"name": "linear", "disturbance": {"law": "cauchy"}}, "task.disturbance.law"),
    ({"disturbance": 3}, "task.disturbance"),
    ({"cost": {"q_speed": math.inf}}, "task.cost.q_speed"), ({"cost": {"r_steer": -1}}, "task.cost.r_steer"),
    ({"preview_distances": [-1.0]}, "task.preview_distances"), ({"preview_distances": 5}, "task.preview_distances"),
    ({"train_half_widths": [1, 2]}, "task.train_half_widths"), ({"name": "cartpole"}, "task.name"),
    ({"name": "linear", "prior_cov": [[1, 2], [2, 1]]}, "task.prior_cov"),  # indefinite
    ({"name": "linear", "prior_mean": [0, 0, 0]}, "task.prior_mean"),
    ({"name": "linear", "A": [[1, 0]]}, "task.A"),
    ({"name": "linear", "disturbance": {"mean": [0.5]}}, "task.disturbance.mean"),
    ({"name": "linear", "disturbance": {"cov": [[0, 0], [1, 0]]}}, "task.disturbance.cov"),  # not symmetric
    ({"name": "linear", "R": [[-1]]}, "task.R"),
])
def test_bad_task_values_name_the_field(task: dict, field: str) -> None:
    with pytest.raises(ValueError, match=f"^{field.replace('.', '[.]')}"):
        TrainConfig(task=task)


def test_apply_overrides_dotted_keys() -> None:
    data = {"seed": 1, "task": "dlc"}
    out = apply_overrides(data, {"task.prior_force_mean": 300, "task.disturbance.mean": 100, "seed": 2})
    assert out == {"seed": 2, "task": {"name": "dlc", "prior_force_mean": 300, "disturbance": {"mean": 100}}}
    assert data == {"seed": 1, "task": "dlc"}  # the input is not modified
    full = TrainConfig().to_dict()
    cfg = TrainConfig.from_dict(apply_overrides(full, {"task.cost.q_lateral": 7, "task.gamma": 0.95}))
    assert (cfg.task.cost.q_lateral, cfg.task.gamma, cfg.task.cost.q_speed) == (7.0, 0.95, 45.0)
    assert full["task"]["cost"]["q_lateral"] == 60.0
    with pytest.raises(ValueError, match="^seed.x"):
        apply_overrides(full, {"seed.x": 1})
    with pytest.raises(ValueError, match="^task..gamma"):
        apply_overrides(full, {"task..gamma": 1})
    with pytest.raises(ValueError, match=r"^config: unknown key\(s\) \['task.disturbance.meen'\]"):
        TrainConfig.from_dict(apply_overrides(full, {"task.disturbance.meen": 1}))


def test_old_flat_keys_are_refused_wherever_they_are_given() -> None:
    # an override, a keyword argument, replace: the flat key reaches the top level and names the release
    with pytest.raises(ValueError, match=r"^config: \['batch_size'\] at the top level is the flat form, " + _RELEASE):
        TrainConfig.from_dict(apply_overrides({}, {"batch_size": 32, "algorithm.batch_size": 16}))
    with pytest.raises(ValueError, match=r"^config: \['iterations'\] at the top level is the flat form, " + _RELEASE):
        TrainConfig(iterations=7)
    with pytest.raises(ValueError, match=r"^config: \['checkpoint_every'\] at the top level is the flat form"):
        TrainConfig().replace(checkpoint_every=3)
    with pytest.raises(ValueError, match=r"^config: unknown key\(s\) \['iteratons'\]; allowed: \['algorithm', "):
        TrainConfig(iteratons=7)


def test_replace_accepts_dotted_keys_and_task_objects() -> None:
    cfg = TrainConfig().replace(**{"task.prior_force_mean": 200.0}, seed=4)
    assert (cfg.task.prior_force_mean, cfg.seed, cfg.task.prior_force_std) == (200.0, 4, 4.0)
    lin = cfg.replace(task=task_config("linear"))
    assert lin.task == LinearTaskConfig()
    assert cfg.replace(task="linear") == lin


# ---------------------------------------------------------------------------------------- sections (issue 19)
def test_train_config_has_at_most_eight_sections() -> None:
    import dataclasses

    names = [f.name for f in dataclasses.fields(TrainConfig)]
    assert names == ["method", "seed", "task", "algorithm", "sampler", "ddpg", "run"]
    assert set(TrainConfig().to_dict()) == set(names)


def test_dotted_section_keys_and_unknown_keys_name_the_dotted_key() -> None:
    cfg = TrainConfig.from_dict(apply_overrides({}, {"algorithm.iterations": 300, "sampler.name": "true_copies"}))
    assert cfg.algorithm.iterations == 300 and cfg.sampler.name == "true_copies"
    with pytest.raises(ValueError, match=r"algorithm\.iteratons"):
        TrainConfig.from_dict({"algorithm": {"iteratons": 3}})
    with pytest.raises(ValueError, match=r"sampler\.kick_prob"):
        TrainConfig.from_dict({"sampler": {"name": "true_copies", "kick_prob": 0.1}})
    with pytest.raises(ValueError, match="^sampler.name"):
        TrainConfig(sampler="replay")


def test_the_dlc_task_supplies_its_experiment_configuration() -> None:
    cfg = TrainConfig(task="dlc")  # the double lane change's preset: the reproduction's settings
    assert cfg == TrainConfig.for_task("dlc") == TrainConfig.from_dict({})
    assert cfg.sampler.name == "dlc_course" and cfg.sampler.course_starts == "along"
    assert cfg.algorithm.lr_decay_iterations == 1500 and cfg.algorithm.batch_weighting == "relative"
    # a partial section keeps the preset for what it does not name
    part = TrainConfig(task="dlc", algorithm={"iterations": 30})
    assert part.algorithm.lr_decay_iterations == 1500 and part.algorithm.iterations == 30


def test_a_task_without_a_preset_gets_generic_defaults() -> None:
    cfg = TrainConfig(task="linear")
    # the measured generic defaults (experiments/studies/custom_defaults.toml): rollouts restarted outside 3 x obs_scale,
    # the relative batch weighting
    assert cfg.sampler.name == "model_rollouts" and cfg.sampler.box == 3.0
    assert cfg.algorithm.lr_decay_iterations == 0  # the decay is tied to the budget
    assert cfg.algorithm.batch_weighting == "relative"
    assert not hasattr(cfg.sampler, "kick_prob")


def test_a_course_sampler_on_a_task_without_a_course_names_option_and_task() -> None:
    with pytest.raises(ValueError, match=r"^sampler\.name: 'dlc_course'.*task 'linear'"):
        TrainConfig(task="linear", sampler="dlc_course")
    with pytest.raises(ValueError, match=r"^config: unknown key\(s\) \['sampler\.course_starts'\]"):
        TrainConfig(task="linear", sampler={"course_starts": "loop"})


def test_a_bare_config_gives_a_users_own_task_object_the_library_defaults() -> None:
    """Issue 40: ``TrainConfig()`` names no task, so a user's task object trains with the generic defaults
    (model rollouts, the budget's decay), not the double lane change's course sampler and preset."""
    from mixedrl.algorithms.agpi import AGPI
    from mixedrl.samplers import ModelStateSampler
    from mixedrl.tasks import LinearTask

    class Mine(LinearTask):  # a user's own task class (no built-in name, no course)
        pass

    cfg = TrainConfig(algorithm={"batch_size": 8})
    generic = TrainConfig(task="linear", algorithm={"batch_size": 8})
    assert (cfg.algorithm, cfg.sampler, cfg.ddpg, cfg.run) == (generic.algorithm, generic.sampler, generic.ddpg,
                                                               generic.run)
    assert cfg.sampler.name == "model_rollouts" and cfg.algorithm.lr_decay_iterations == 0
    assert cfg.task == TrainConfig(task="dlc").task  # what the CLI and make_trainer build without a task object
    assert TrainConfig.from_dict(cfg.to_dict()) == cfg  # the sections are written: a round trip keeps them
    agent = AGPI(Mine(), cfg)
    assert type(agent.sampler) is ModelStateSampler


def test_a_course_sampler_on_a_custom_task_without_a_course_is_refused_by_the_trainer() -> None:
    from mixedrl.algorithms.agpi import AGPI
    from mixedrl.tasks import LinearTask

    with pytest.raises(ValueError, match=r"^sampler\.name: 'dlc_course'.*LinearTask"):
        AGPI(LinearTask(), TrainConfig(sampler="dlc_course", algorithm={"batch_size": 8}))


def test_every_shipped_flat_run_config_is_refused_naming_the_release() -> None:
    """The configs embedded in shipped per-run results in the flat form are records of runs of
    :data:`FLAT_FORM_RELEASE`: each is refused with an error naming it; the sectioned ones load and round-trip, but
    for those of a retired ``algorithm.feedforward`` (learner_tuning's ``default_lq``) or of a deleted setting away
    from today's behaviour (``experiments/results/actor_average``), refused naming the commit that runs them."""
    root = Path(__file__).resolve().parents[1] / "experiments" / "results"
    from mixedrl.config import DELETED_AT, DELETED_SETTINGS, RETIRED_FEEDFORWARDS

    flat = sectioned = retired = deleted = 0
    for path in sorted(root.rglob("*.json")):
        data = json.loads(path.read_text())
        if not (isinstance(data, dict) and isinstance(data.get("config"), dict) and "method" in data["config"]):
            continue
        if "study" in data["config"]:  # a study's own run record (gym_benchmark), not a TrainConfig
            continue
        config = data["config"]
        value = config.get("algorithm", {}).get("feedforward")
        if value in RETIRED_FEEDFORWARDS:  # a run of a value retired since: refused naming the commit that runs it
            with pytest.raises(ValueError, match=rf"^algorithm\.feedforward: '{value}' was retired .*; git commit "
                                                 rf"{RETIRED_FEEDFORWARDS[value]} can still run it$"):
                TrainConfig.from_dict(config)
            retired += 1
            continue
        gone = [(sec, name) for (sec, name), today in DELETED_SETTINGS.items()
                if name in config.get(sec, {}) and config[sec][name] != today]
        if gone:  # a run of a setting deleted since: refused naming the commit that runs it
            sec, name = gone[0]
            with pytest.raises(ValueError, match=rf"^{sec}\.{name}: this setting was deleted .*; git commit "
                                                 rf"{DELETED_AT[(sec, name)]} can still run it$"):
                TrainConfig.from_dict(config)
            deleted += 1
            continue
        if "algorithm" in config:
            cfg = TrainConfig.from_dict(config)
            assert TrainConfig.from_dict(cfg.to_dict()) == cfg, path
            sectioned += 1
            continue
        with pytest.raises(ValueError, match=r"^config: \[.*\] at the top level is the flat form, " + _RELEASE):
            TrainConfig.from_dict(config)
        flat += 1
    assert flat >= 300 and retired == 12 and deleted == 120


def test_dlc_obs_scale_override() -> None:
    """``task.obs_scale`` (default ``None``: the task's scales, left out of ``to_dict`` so config.json and
    config hashes are as before) sets the DLC task's observation scale; its length is checked."""
    import torch

    from mixedrl.sweep import config_hash
    from mixedrl.tasks import task_from_config

    default = TrainConfig()
    assert default.task.obs_scale is None and "obs_scale" not in default.to_dict()["task"]
    assert TrainConfig.from_dict(default.to_dict()) == default
    scales = [0.3, 0.2, 0.5, 0.1, 0.5, 0.7]
    cfg = TrainConfig(task={"preview_distances": [2.0], "obs_scale": scales})
    assert cfg.to_dict()["task"]["obs_scale"] == scales and TrainConfig.from_dict(cfg.to_dict()) == cfg
    assert config_hash(cfg) != config_hash(cfg.replace(**{"task.obs_scale": None}))
    assert torch.equal(task_from_config(cfg.task).obs_scale, torch.tensor(scales, dtype=torch.float32))
    assert task_from_config(cfg.replace(**{"task.obs_scale": None}).task).obs_scale.tolist()[5] == 2.0
    with pytest.raises(ValueError, match=r"task\.obs_scale: expected 5 \+ len\(preview_distances\) = 6 numbers, got 5"):
        TrainConfig(task={"preview_distances": [2.0], "obs_scale": scales[:5]})
    with pytest.raises(ValueError, match=r"task\.obs_scale"):
        TrainConfig(task={"obs_scale": [0.3, 0.2, 0.5, 0.1, -0.5]})


def test_linear_task_config_holds_every_field_of_the_lq_problem():
    """The LQ problem has one representation (mixedrl.lq.LQProblem); its JSON face names each of its fields
    (or maps it to task.disturbance), and a value set on the face reaches the problem unchanged."""
    from mixedrl.config_tasks import _PROBLEM_KEYS
    from mixedrl.lq import LQProblem

    face = {f.name for f in dataclasses.fields(LinearTaskConfig)}
    for f in dataclasses.fields(LQProblem):
        assert f.name in face or f.name in _PROBLEM_KEYS, f"LinearTaskConfig lacks LQProblem.{f.name}"
    cfg = LinearTaskConfig(gamma=0.8, prior_mean=(0.1, -0.2), R=((0.3,),),
                           disturbance={"mean": (0.0, 0.4), "cov": ((0.0, 0.0), (0.0, 0.02))})
    problem = cfg.problem()
    np.testing.assert_array_equal(problem.prior_mean, [0.1, -0.2])
    np.testing.assert_array_equal(problem.R, [[0.3]])
    np.testing.assert_array_equal(problem.noise_mean, [0.0, 0.4])
    assert problem.gamma == 0.8
    assert cfg.prior_mean == (0.1, -0.2) and cfg.R == ((0.3,),)  # JSON face: tuples
    with pytest.raises(ValueError, match=r"task\.disturbance\.cov"):
        LinearTaskConfig(disturbance={"mean": (0.0, 0.4), "cov": ((0.0, 1.0), (0.0, 0.02))})


@pytest.mark.parametrize("seed", [2**64, -1])
def test_a_seed_beyond_64_bits_is_refused_naming_it(seed: int) -> None:
    with pytest.raises(ValueError, match=r"^seed: "):
        TrainConfig(seed=seed)
    assert TrainConfig(seed=2**64 - 1).seed == 2**64 - 1


@pytest.mark.parametrize("section, name, other", [("algorithm", "rollout_critic_steps", 4),
                                                   ("algorithm", "rollout_updates", 2),
                                                   ("algorithm", "actor_average", 0.995),
                                                   ("algorithm", "bellman_steps", 10),
                                                   ("algorithm", "feedforward_handover", True),
                                                   ("sampler", "course_ramp", 500)])
def test_a_deleted_setting_is_read_at_todays_behaviour_and_refused_otherwise(section: str, name: str,
                                                                            other: object) -> None:
    """A saved config holding a deleted setting at the value that is today's behaviour loads as the config
    without it; another value is refused, naming the key."""
    from mixedrl.config import DELETED_AT, DELETED_SETTINGS

    data = TrainConfig(task="linear", algorithm={"rollout_horizon": 4}).to_dict()
    kept = json.loads(json.dumps(data))
    data[section][name] = DELETED_SETTINGS[(section, name)]
    assert TrainConfig.from_dict(data) == TrainConfig.from_dict(kept)
    assert name in data[section]  # the caller's dict is left as it was
    data[section][name] = other
    with pytest.raises(ValueError, match=rf"^{section}\.{name}: this setting was deleted") as err:
        TrainConfig.from_dict(data)
    if (section, name) == ("sampler", "course_ramp"):  # retired with the trained feed-forward family
        assert str(err.value).endswith("; git commit ee954d7 can still run it")
    if (section, name) == ("algorithm", "feedforward_handover"):
        assert str(err.value).endswith(f"; git commit {DELETED_AT[(section, name)]} can still run it")
