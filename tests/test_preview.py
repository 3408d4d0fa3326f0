"""Mixed RL with path preview (issue 11, item 4; experiments/analysis/preview_study.py, docs/references.rst).

The training path with ``task.preview_distances``: the observation has ``5 + len(preview)`` columns and
its preview columns are ``Y_ref(X + d) - Y_ref(X)``; networks, the model box test, checkpoints, resume and
the ``mixedrl train --set`` command all carry the wider observation; the study script's plain-NumPy actor
equals the torch actor. Marked ``nmpc``: the limited-preview NMPC of the study equals the NMPC with
preview when its reach covers the horizon, and the no-preview NMPC at reach 0.
"""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from mixedrl.algorithms.model_data import ModelStateSampler
from mixedrl.cli import main
from mixedrl.config import ONE_STEP_LEARNER, TrainConfig
from mixedrl.runs import RunDirectory, load_checkpoint, make_trainer, train
from mixedrl.sweep import expand, load_spec
from mixedrl.tasks import task_from_config
from validation.preview import LimitedPreviewNMPC, NumpyActor, actor_weights, preview_scale

ROOT = Path(__file__).resolve().parents[1]
PREVIEW = (3.0, 6.0, 12.0)
FAST = {"algorithm.iterations": 12, "algorithm.batch_size": 32, "run.eval_every": 6, "run.checkpoint_every": 4,
        "run.eval_seeds": 1, "sampler.course_horizon": 30, "sampler.true_horizon": 30, "sampler.course_start": 2,
        "sampler.true_envs": 1, "sampler.true_steps": 2, "sampler.true_every": 3}


ROOT_SPEC = ROOT / "experiments" / "studies" / "preview.toml"


def _tanh_path(X: np.ndarray) -> np.ndarray:
    """The double lane change written out (mixedrl/envs/reference.py's defaults)."""
    z1 = 2.4 / 25.0 * (X - 27.19) - 1.2
    z2 = 2.4 / 21.95 * (X - 56.46) - 1.2
    return 4.05 / 2 * (1 + np.tanh(z1)) - 5.7 / 2 * (1 + np.tanh(z2))


def _config(**extra: object) -> TrainConfig:
    """The preview study's config: the one-step learner it was run with (its specs pin it), FAST, the preview."""
    return TrainConfig(method="mixed", task="dlc", algorithm=ONE_STEP_LEARNER).replace(
        **{**FAST, **extra, "task.preview_distances": list(PREVIEW)})


def test_preview_observation_is_the_path_ahead() -> None:
    """Columns 5.. of the observation are ``Y_ref(X + d_i) - Y_ref(X)`` on the trainer's own task."""
    trainer = make_trainer(_config())
    task = trainer.task
    s = task.sample_initial(64, torch.Generator().manual_seed(3))
    obs = task.observe(s).numpy()
    X = s[:, 5].numpy()
    assert task.obs_dim == obs.shape[1] == 5 + len(PREVIEW)
    want = np.stack([_tanh_path(X + d) - _tanh_path(X) for d in PREVIEW], axis=1)
    np.testing.assert_allclose(obs[:, 5:], want, rtol=0, atol=1e-12)
    # the path ahead differs from the path here: a preview computed at X would be all zeros
    assert np.abs(want).max() > 1.0


def test_networks_and_box_carry_the_preview() -> None:
    """Actor and critic take ``5 + len(preview)`` inputs scaled by the task's ``obs_scale`` (2 m on each
    preview column), and the model box (``model_box`` x ``obs_scale``) never restarts a rollout because
    of the path's shape: states on the reference anywhere on the course are inside it."""
    trainer = make_trainer(_config())
    task = trainer.task
    n_obs = 5 + len(PREVIEW)
    assert trainer.actor.net.input_scale.shape == trainer.critic.net.input_scale.shape == (n_obs,)
    assert torch.equal(trainer.actor.net.input_scale[5:], torch.full((len(PREVIEW),), 2.0))
    assert trainer.actor.net.body[0].in_features == trainer.critic.net.body[0].in_features == n_obs
    sampler = ModelStateSampler(task, trainer.config, torch.Generator().manual_seed(0))
    X = torch.linspace(0.0, 130.0, 2601, dtype=torch.float64)
    ref = task.model.config.reference
    y, psi = ref.lateral_and_heading(X)
    on_path = torch.stack([torch.zeros_like(X), torch.zeros_like(X), torch.full_like(X, 12.0), psi, y, X], 1)
    assert not bool(sampler._outside(on_path).any())
    off = on_path.clone()
    off[:, 4] += 3.0 * 0.5 * 1.01  # e_y just beyond model_box (3) x obs_scale (0.5 m)
    assert bool(sampler._outside(off).all())


def test_preview_training_checkpoints_and_resumes(tmp_path: Path) -> None:
    """A run with preview trains, saves a checkpoint of the wider networks, and its resumed run ends with
    exactly the weights of the uninterrupted one."""
    cfg = _config()
    full = make_trainer(cfg)
    res = train(full, RunDirectory(tmp_path / "full"))
    assert math.isfinite(res["cost"]) and res["iterations"] == 12
    state = load_checkpoint(RunDirectory(tmp_path / "full").checkpoint_path)
    assert state["trainer"]["actor"]["net.body.0.weight"].shape[1] == 5 + len(PREVIEW)
    saved = RunDirectory(tmp_path / "full").read_config()
    assert saved.task.preview_distances == PREVIEW
    assert train(make_trainer(cfg), RunDirectory(tmp_path / "cut"), stop_after=7) == {"interrupted_at": 7}
    resumed = make_trainer(cfg)
    train(resumed, RunDirectory(tmp_path / "cut"), resume=True)
    for net in ("actor", "critic"):
        assert all(torch.equal(a, b) for a, b in zip(full.state_dict()[net].values(), resumed.state_dict()[net].values()))


def test_cli_train_with_preview(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``mixedrl train --set task.preview_distances=[...]`` runs and evaluates with the wider observation."""
    out = tmp_path / "run"
    sets = [f"{k}={json.dumps(v)}" for k, v in FAST.items() if k != "algorithm.iterations"]
    assert main(["train", "--method", "mixed", "--out", str(out), "--iterations", "3", "--no-progress",
                 "--set", "task.preview_distances=[3, 6, 12]", *sets]) == 0
    capsys.readouterr()
    assert TrainConfig.load(out / "config.json").task.preview_distances == PREVIEW
    assert main(["evaluate", str(out)]) == 0
    assert math.isfinite(json.loads(capsys.readouterr().out)["cost"])
    assert main(["train", "--method", "mixed", "--out", str(tmp_path / "bad"), "--no-progress",
                 "--set", "task.preview_distances=[-3]"]) == 2
    assert "task.preview_distances" in capsys.readouterr().err


def test_numpy_actor_equals_the_torch_actor() -> None:
    """The study's deployment path (plain NumPy forward of the same weights, float64) gives the torch
    actor's actions (the same weights in float64: 1e-12), from the tensors and from the per-run JSON."""
    trainer = make_trainer(_config())
    actor = trainer.actor
    with torch.no_grad():  # move the weights off their initialisation
        for p in actor.parameters():
            p.add_(0.3 * torch.randn(p.shape, generator=torch.Generator().manual_seed(p.numel())))
    obs = trainer.task.observe(trainer.task.sample_initial(50, torch.Generator().manual_seed(1))).float()
    with torch.no_grad():
        want = copy.deepcopy(actor).double()(obs.double()).numpy()  # the same weights, in float64
        want32 = actor(obs).double().numpy()
    for weights in (actor.state_dict(), json.loads(json.dumps(actor_weights(actor)))):
        fast = NumpyActor(weights)
        got = np.stack([fast(o) for o in obs.double().numpy()])
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
        np.testing.assert_allclose(got, want32, rtol=0, atol=1e-4)  # torch's float32 rounding
    with pytest.raises(ValueError, match="^state_dict"):
        NumpyActor({"net.input_scale": [1.0]})


def test_study_spec_is_the_default_but_preview() -> None:
    """The study (experiments/studies/preview.toml) changes no training setting of the one-step learner it
    pins (:data:`mixedrl.config.ONE_STEP_LEARNER`) but the preview (and the reporting/checkpoint periods), on
    its batch design: S is that learner's default, M the default when the study first ran."""
    def dotted(d: dict) -> dict:
        return {f"{k}.{kk}" if isinstance(v, dict) and k != "task" else k: vv
                for k, v in d.items() for kk, vv in (v.items() if isinstance(v, dict) and k != "task" else [(k, v)])}

    runs = expand(load_spec(ROOT_SPEC))
    assert {r.point["variant"].split("_")[0] for r in runs} == {"S", "M"}
    for run in (r for r in runs if "_n" not in r.point["variant"]):  # the default budget
        design = run.point["variant"].split("_")[0]
        cfg = run.config.to_dict()
        base = TrainConfig(task="dlc", algorithm=ONE_STEP_LEARNER).replace(seed=run.config.seed).to_dict()
        assert cfg["task"].pop("preview_distances") == list(run.config.task.preview_distances)
        base["task"].pop("preview_distances")
        if run.point["variant"] == "M_P12s":  # scales its preview terms (task.obs_scale; tests/test_studies.py)
            cfg["task"].pop("obs_scale")
        cfg_d, base_d = dotted(cfg), dotted(base)
        diff = {k for k in cfg_d if cfg_d[k] != base_d[k]}
        assert diff <= {"run.eval_every", "run.checkpoint_every", "run.num_threads"} | (
            {"sampler.course_starts"} if design == "M" else set())
        assert cfg["sampler"]["course_starts"] == {"S": "along", "M": "start"}[design]


@pytest.mark.nmpc
def test_limited_preview_nmpc_brackets() -> None:
    """Reach beyond the horizon's travel = the NMPC with preview; reach 0 = the no-preview NMPC (1e-9)."""
    pytest.importorskip("casadi")
    from validation import nmpc

    s = np.array([0.0, 0.0, 12.0, 0.0, 0.0, 35.0])  # in the first lane change
    full = nmpc.VehicleNMPC(horizon=0.3, gamma=0.99, force="true")
    far = LimitedPreviewNMPC(10.0, horizon=0.3, gamma=0.99, force="true")  # 0.3 s at 12 m/s: 3.6 m
    blind = nmpc.VehicleNMPC(horizon=0.3, gamma=0.99, force="true", preview=False)
    zero = LimitedPreviewNMPC(0.0, horizon=0.3, gamma=0.99, force="true")
    np.testing.assert_allclose(far(s), full(s), rtol=0, atol=1e-9)
    np.testing.assert_allclose(zero(s), blind(s), rtol=0, atol=1e-9)
    half = LimitedPreviewNMPC(1.5, horizon=0.3, gamma=0.99, force="true")
    assert np.abs(half(s) - full(s)).max() > 1e-6
    with pytest.raises(ValueError, match="^reach"):
        LimitedPreviewNMPC(-1.0)


def test_per_distance_scale_puts_the_preview_in_unit_range() -> None:
    """The study's variant P12s: each preview column's ``obs_scale`` is its largest value on the course
    (:func:`validation.preview.preview_scale`), so the columns lie in [-1, 1] there (and reach 1); networks
    and the model box take the task's scale."""
    cfg = _config().replace(**{"task.preview_distances": [2.0, 4.0, 6.0, 8.0, 10.0, 12.0]})
    task = task_from_config(cfg.task)
    plain = task.obs_scale.clone()
    task.obs_scale = torch.cat([task.obs_scale[:5], preview_scale(task)])
    trainer = make_trainer(cfg, task)
    assert torch.equal(trainer.actor.net.input_scale, task.obs_scale)
    assert torch.equal(trainer.critic.net.input_scale, task.obs_scale)
    X = torch.linspace(0.0, 120.0, 12001, dtype=torch.float64)
    ref = task.model.config.reference
    y, psi = ref.lateral_and_heading(X)
    on_path = torch.stack([torch.zeros_like(X), torch.zeros_like(X), torch.full_like(X, 12.0), psi, y, X], 1)
    ratio = (task.observe(on_path)[:, 5:].abs() / task.obs_scale[5:]).max(dim=0).values
    np.testing.assert_allclose(ratio.numpy(), 1.0, atol=1e-3)
    assert torch.equal(plain[5:], torch.full((6,), 2.0))
