"""The precision yardstick (mixedrl.precision): the policy at the equilibrium against the discounted LQ optimum.

The references are derived here, independently of the code under test: the LQ optimum from scipy's DARE
and the closed form of docs/lq.rst, the double lane change's longitudinal loop as a scalar problem solved
by the quadratic formula, and steady states from the physics (the action that balances the mean force).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg
import torch

from mixedrl.algorithms.agpi import AGPI
from mixedrl.config import TrainConfig
from mixedrl.envs.pendulum import PendulumTask
from mixedrl.networks import AffineActor
from mixedrl.precision import gap_summary, lq_reference, policy_gap, run_policy_gap
from mixedrl.runs import RunDirectory, train
from mixedrl.tasks import DoubleLaneChangeTask, Equilibrium, LinearTask, Task

# float32 actors: the action at the equilibrium carries float32 round-off of a few units in 1e-7
ACTION_ATOL = 1e-6


def scipy_optimum(A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray, gamma: float, mu: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """``(L, l0)`` of the discounted LQ optimum: scipy's DARE and the closed form of docs/lq.rst."""
    g = gamma
    S = scipy.linalg.solve_discrete_are(math.sqrt(g) * A, math.sqrt(g) * B, Q, g * R)
    M = R + B.T @ S @ B
    L = np.linalg.solve(M, B.T @ S @ A)
    Ac = A - B @ L
    p = np.linalg.solve(np.eye(A.shape[0]) - g * Ac.T, Ac.T @ S @ mu)
    return L, np.linalg.solve(M, B.T @ (S @ mu + g * p))


def affine_actor(L: np.ndarray, l0: np.ndarray) -> AffineActor:
    actor = AffineActor(L.shape[1], L.shape[0], torch.Generator().manual_seed(0))
    with torch.no_grad():
        actor.L.copy_(torch.as_tensor(L))
        actor.l0.copy_(torch.as_tensor(l0))
    return actor


# ------------------------------------------------------------------------------------------ LinearTask
def test_linear_task_linearisation_is_the_task() -> None:
    task = LinearTask()
    lin = task.linearisation()
    assert np.allclose(lin.A, task.A, atol=1e-12) and np.allclose(lin.B, task.B, atol=1e-12)
    assert np.allclose(lin.Q, task.Q, atol=1e-12) and np.allclose(lin.R, task.R, atol=1e-12)
    assert np.array_equal(lin.E, np.eye(2)) and lin.gamma == task.gamma


def test_exact_lq_policy_has_no_gap() -> None:
    task = LinearTask()
    L, l0 = scipy_optimum(task.A, task.B, task.Q, task.R, task.gamma, task.true_mean)
    gap = policy_gap(task, affine_actor(L, l0), task.true_mean, task.true_cov)
    assert np.allclose(gap["optimum_action"], -l0, rtol=1e-10)
    assert np.abs(gap["action_error"]).max() < ACTION_ATOL
    assert np.abs(gap["action_error_true_mean"]).max() < ACTION_ATOL
    assert abs(gap["value_regret"]) < 1e-6 * gap["optimum_value"]
    json.dumps(gap)  # JSON-ready


@pytest.mark.parametrize("offset", [0.3, -1.25])
def test_a_deliberate_offset_is_the_gap(offset: float) -> None:
    """``u = -L x - (l0 + delta)``: the action error at the equilibrium is ``-delta``; the regret is positive."""
    task = LinearTask()
    L, l0 = scipy_optimum(task.A, task.B, task.Q, task.R, task.gamma, task.true_mean)
    gap = policy_gap(task, affine_actor(L, l0 + offset), task.true_mean, task.true_cov)
    assert gap["action_error"] == pytest.approx([-offset], abs=ACTION_ATOL)
    assert gap["max_abs_action_error"] == pytest.approx(abs(offset), abs=ACTION_ATOL)
    assert gap["value_regret"] > 0.0


def test_own_mean_and_true_mean_differ_by_the_prior_offset() -> None:
    """The exact policy for the prior's mean: zero gap against the own mean, ``l0(mu) - l0(mu_M)`` against the truth."""
    task = LinearTask()
    L, l0_prior = scipy_optimum(task.A, task.B, task.Q, task.R, task.gamma, task.prior_mean)
    _, l0_true = scipy_optimum(task.A, task.B, task.Q, task.R, task.gamma, task.true_mean)
    gap = policy_gap(task, affine_actor(L, l0_prior), task.prior_mean, task.prior_cov)
    assert np.abs(gap["action_error"]).max() < ACTION_ATOL
    assert gap["action_error_true_mean"] == pytest.approx(l0_true - l0_prior, abs=ACTION_ATOL)
    assert abs(float(l0_true[0] - l0_prior[0])) > 0.1  # the test can fail


# ------------------------------------------------------------------------------------------ pendulum
def test_pendulum_default_linearisation_matches_the_hand_derived_one() -> None:
    task = PendulumTask()
    by_hand, by_autograd = task.linearisation(), Task.linearisation(task)
    for key in ("A", "B", "Q", "R", "E"):
        assert np.allclose(by_hand[key], by_autograd[key], atol=1e-12), key


def test_pendulum_feed_forward_against_the_known_bias() -> None:
    """The optimum's action at the upright (scipy reference) and its steady state: no rate, and the torque
    balances gravity and the bias, ``u_ss = -(tau + m g l theta_ss)`` (linearised)."""
    task = PendulumTask()
    lin = task.linearisation()
    E = lin.E
    for torque in (0.5, 0.0, -0.3):
        mean = np.array([task.xi_per_torque * torque])
        ref = lq_reference(lin, mean)
        _, l0 = scipy_optimum(lin.A, lin.B, lin.Q, lin.R, task.gamma, E @ mean)
        assert ref.action == pytest.approx(-l0, rel=1e-9, abs=1e-12)
        theta, omega = ref.steady_state
        assert omega == pytest.approx(0.0, abs=1e-12)
        assert ref.steady_action[0] == pytest.approx(-(torque + task.mass * task.gravity * task.length * theta),
                                                     rel=1e-9, abs=1e-12)
    # the feed-forward is linear in the bias, zero without one, and pushes against it
    zero, true = lq_reference(lin, [0.0]), lq_reference(lin, task.true_mean)
    assert zero.action == pytest.approx([0.0], abs=1e-12) and true.action[0] < -0.5


def test_pendulum_policy_gap_of_the_lqr_with_the_prior() -> None:
    """The LQR designed for the prior (zero bias) misses exactly the true mean's feed-forward."""
    task = PendulumTask()
    lin = task.linearisation()
    L, l0 = scipy_optimum(lin.A, lin.B, lin.Q, lin.R, task.gamma, lin.E @ task.prior_mean)
    _, l0_true = scipy_optimum(lin.A, lin.B, lin.Q, lin.R, task.gamma, lin.E @ task.true_mean)
    gap = policy_gap(task, affine_actor(L, l0), task.prior_mean, task.prior_cov)
    assert np.abs(gap["action_error"]).max() < ACTION_ATOL
    assert gap["action_error_true_mean"] == pytest.approx(l0_true - l0, abs=ACTION_ATOL)


# ------------------------------------------------------------------------------------------ double lane change
def scalar_offset(b: float, q: float, r: float, gamma: float, mu: float) -> float:
    """``l0`` of the scalar discounted LQ problem ``e' = e + b a + mu``, ``l = q e'^2 + r a^2``.

    ``S = q + gamma S r / (r + b^2 S)`` (the scalar DARE with ``A = 1``) is the positive root of
    ``b^2 S^2 + (r - q b^2 - gamma r) S - q r = 0``; then ``L = b S / (r + b^2 S)``, ``A_c = 1 - b L``,
    ``p = A_c S mu / (1 - gamma A_c)`` and ``l0 = b (S mu + gamma p) / (r + b^2 S)``.
    """
    lin_coef = r - q * b * b - gamma * r
    S = (-lin_coef + math.sqrt(lin_coef**2 + 4.0 * b * b * q * r)) / (2.0 * b * b)
    L = b * S / (r + b * b * S)
    Ac = 1.0 - b * L
    p = Ac * S * mu / (1.0 - gamma * Ac)
    return b * (S * mu + gamma * p) / (r + b * b * S)


def test_dlc_feed_forward_difference_between_261_and_150_newtons() -> None:
    """At the origin the longitudinal loop decouples (at ``v_y = r = phi = 0`` nothing couples ``v_x`` to the
    lateral states): the action difference is the scalar problem's; at the optimum's steady state the
    acceleration cancels the mean force exactly, so the difference there is ``-(261 - 150) / 1500``."""
    task = DoubleLaneChangeTask()
    cfg = task.model.config
    lin = task.linearisation()
    T, m, vx = cfg.dt, cfg.params.m, task.noise_index
    refs = {}
    for force in (261.0, 150.0):
        mean = np.zeros(5)
        mean[vx] = force * T / m
        refs[force] = lq_reference(lin, mean)
    steady = refs[261.0].steady_action - refs[150.0].steady_action
    assert steady[1] == pytest.approx(-(261.0 - 150.0) / m, rel=1e-9)  # -0.074 m/s^2
    assert abs(steady[0]) < 1e-12  # no steering
    origin = refs[261.0].action - refs[150.0].action
    expected = -(scalar_offset(T, T * cfg.q_speed, T * cfg.r_accel, task.gamma, 261.0 * T / m)
                 - scalar_offset(T, T * cfg.q_speed, T * cfg.r_accel, task.gamma, 150.0 * T / m))
    assert origin[1] == pytest.approx(expected, rel=1e-8)
    assert abs(origin[0]) < 1e-12
    # the speed error the optimum holds with the true mean: (mu / T - l0) / L of the scalar loop
    assert refs[261.0].steady_state[2] > 0.0 and abs(refs[261.0].steady_state[[0, 1, 3, 4]]).max() < 1e-12


def test_dlc_linearisation_is_the_lqr_references() -> None:
    """The core's linearisation gives the LQR reference's controller (validation.nmpc.straight_lqr)."""
    from validation.nmpc import straight_lqr

    task = DoubleLaneChangeTask()
    lin = task.linearisation()
    for force in (261.0, 150.0):
        lqr = straight_lqr(force=force, gamma=task.gamma)
        mean = np.zeros(5)
        mean[task.noise_index] = task.force_to_xi(force)
        ref = lq_reference(lin, mean)
        assert np.allclose(ref.solution.gain, lqr.gain, rtol=1e-9, atol=1e-12)
        assert ref.action == pytest.approx(-lqr.offset, rel=1e-9, abs=1e-12)


def test_dlc_observation_at_the_equilibrium_is_the_origin() -> None:
    task = DoubleLaneChangeTask()
    lin = task.linearisation()
    s = lin.to_state(torch.zeros(1, 5, dtype=torch.float64))
    assert torch.allclose(task.observe(s), torch.zeros(1, 5, dtype=torch.float64), atol=1e-12)
    assert float(task.cost(s, torch.zeros(1, 2, dtype=torch.float64))) == pytest.approx(0.0, abs=1e-15)


# ------------------------------------------------------------------------------------------ errors, trainers
class _NoEquilibrium(LinearTask):
    def equilibrium(self) -> None:
        return None


class _NotARestPoint(LinearTask):
    def equilibrium(self) -> Equilibrium:
        return Equilibrium(state=np.array([0.0, 1.0]), action=np.zeros(1))  # moving: x' = x + 0.1 v


class _CostNotAtMinimum(LinearTask):
    def cost(self, s_next: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return super().cost(s_next, u) + s_next[:, 0]


def test_bad_equilibria_are_clear_errors() -> None:
    assert _NoEquilibrium().linearisation() is None
    with pytest.raises(ValueError, match="^equilibrium: _NotARestPoint.f"):
        _NotARestPoint().linearisation()
    with pytest.raises(ValueError, match="^cost: _CostNotAtMinimum.cost has a nonzero gradient"):
        _CostNotAtMinimum().linearisation()
    with pytest.raises(ValueError, match="^noise_mean"):
        lq_reference(LinearTask().linearisation(), [0.0])


def _config(method: str, **run: object) -> TrainConfig:
    return TrainConfig(method=method, task="linear", seed=0, algorithm={"batch_size": 16, "hidden_sizes": (8,)},
                       ddpg={"batch_size": 16}, run=run)


@pytest.mark.parametrize("method, mean", [("model", "prior_mean"), ("oracle", "true_mean"), ("mixed", "prior_mean")])
def test_run_policy_gap_uses_the_methods_own_mean(method: str, mean: str) -> None:
    """Before any data the IBE's mean is the prior's; model-driven RL plans with the prior, the oracle the truth."""
    task = LinearTask()
    trainer = AGPI(task, _config(method))
    gap, reason = run_policy_gap(trainer)
    assert reason is None
    assert gap["noise_mean"] == pytest.approx(getattr(task, mean).tolist(), abs=1e-15)
    assert gap["true_mean"] == pytest.approx(task.true_mean.tolist())
    with torch.no_grad():
        critic = float(trainer.critic(torch.zeros(1, 2)))
        action = trainer.policy(torch.zeros(1, 2))[0].tolist()
    assert gap["value"] == pytest.approx(critic) and gap["action"] == pytest.approx(action)


def test_no_equilibrium_gives_null_with_a_reason() -> None:
    gap, reason = run_policy_gap(AGPI(_NoEquilibrium(), _config("model")))
    assert gap is None and "defines no equilibrium" in reason
    assert gap_summary(gap) is None


def test_policy_gap_in_results_json_of_a_tiny_run(tmp_path: Path) -> None:
    out = tmp_path / "run"
    trainer = AGPI(LinearTask(), _config("mixed", eval_every=2, checkpoint_every=2, eval_seeds=1).replace(**{"algorithm.iterations": 2}))
    train(trainer, RunDirectory(out), progress=False)
    results = json.loads((out / "results.json").read_text())
    gap = results["policy_gap"]
    assert len(gap["action_error"]) == 1 and len(gap["optimum_action"]) == 1
    assert gap["noise_mean"] == pytest.approx(results["final_ibe_mean"])
    assert gap["action"][0] - gap["optimum_action"][0] == pytest.approx(gap["action_error"][0], abs=1e-12)
    assert "policy_gap_reason" not in results


def test_table_one_aggregates_and_lists_the_policy_gap(tmp_path: Path) -> None:
    """validation.reproduce: per method the mean and std of |action error| per component, and one line each."""
    from validation.reproduce import aggregate, format_table

    def run(seed: int, error: list[float]) -> dict:
        return {"label": "ddpg", "seed": seed, "lateral_mae": 0.2, "speed_mae": 0.05, "iterations_to_converge": 10,
                "train_seconds": 1.0, "cost": 80.0, "convergence_criterion": "c",
                "policy_gap": {"action_error": error}}

    results = aggregate(tmp_path, [run(0, [0.1, -0.2]), run(1, [-0.3, 0.4])], wall=1.0, quick=True)
    assert results["ddpg"]["policy_gap_abs_mean"] == pytest.approx([0.2, 0.3])
    assert results["ddpg"]["policy_gap_abs_std"] == pytest.approx([math.sqrt(0.02), math.sqrt(0.02)])
    assert [r["policy_gap_action_error"] for r in results["ddpg"]["runs"]] == [[0.1, -0.2], [-0.3, 0.4]]
    assert "policy_gap (ddpg): |action - LQ optimum| at the origin, own mean: 0.2000 ± 0.1414, 0.3000 ± 0.1414" \
        in format_table(results)


def test_ddpg_is_compared_with_the_true_mean_and_its_q_critic() -> None:
    from mixedrl.algorithms.ddpg import DDPG

    task = LinearTask()
    trainer = DDPG(task, _config("ddpg"))
    gap, reason = run_policy_gap(trainer)
    assert reason is None and gap["noise_mean"] == pytest.approx(task.true_mean.tolist())
    assert gap["action_error"] == pytest.approx(gap["action_error_true_mean"])
    obs = torch.zeros(1, 2)
    with torch.no_grad():
        assert gap["value"] == pytest.approx(float(trainer.critic(obs, trainer.policy(obs))))


def test_a_failing_linearisation_is_a_reason_not_a_crash() -> None:
    gap, reason = run_policy_gap(AGPI(_NotARestPoint(), _config("model")))
    assert gap is None and reason.startswith("no linearisation at the equilibrium: ValueError: equilibrium:")


def test_train_and_evaluate_print_the_policy_gap(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from mixedrl.cli import main

    out = tmp_path / "run"
    assert main(["train", "--method", "model", "--out", str(out), "--iterations", "2", "--no-progress", "--set",
                 "task.name=linear", "algorithm.batch_size=16", "algorithm.hidden_sizes=[8]", "run.eval_seeds=1"]) == 0
    captured = capsys.readouterr()
    printed, saved = json.loads(captured.out), json.loads((out / "results.json").read_text())["policy_gap"]
    assert printed["policy_gap"]["action_error"] == saved["action_error"]
    assert captured.err.startswith("policy_gap: action - LQ optimum at the equilibrium [")
    assert main(["evaluate", str(out)]) == 0
    assert json.loads(capsys.readouterr().out)["policy_gap"]["action_error"] == pytest.approx(saved["action_error"])


# ------------------------------------------------ algorithm.feedforward = "lq_ss" (a departure), a constant shift
def _ff(method: str) -> TrainConfig:
    """``"lq_ss"`` as :func:`~mixedrl.departures.anchor.steady_anchor` gives it: a constant shift, not calibrated."""
    return TrainConfig(method=method, task="linear", seed=0, algorithm={
        "batch_size": 16, "hidden_sizes": (8,), "feedforward": "lq_ss", "feedforward_width": 0.0,
        "feedforward_calibration": 0})


def _steady(lin: object, mu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """scipy's DARE: the discounted LQ optimum's steady state ``x_ss = (I - A + B L)^-1 (E mu - B l0)`` for the
    noise mean ``mu`` and its action there ``-L x_ss - l0``."""
    L, l0 = scipy_optimum(lin.A, lin.B, lin.Q, lin.R, lin.gamma, lin.E @ mu)
    x_ss = np.linalg.solve(np.eye(lin.A.shape[0]) - lin.A + lin.B @ L, lin.E @ mu - lin.B @ l0)
    return x_ss, -L @ x_ss - l0


def test_feedforward_policy_takes_the_action_at_the_equilibrium_and_shifts_by_a_constant() -> None:
    from mixedrl.precision import FeedForwardPolicy

    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(3, 5), torch.nn.Tanh(), torch.nn.Linear(5, 2))
    o_star, u_ff = torch.tensor([0.2, -0.1, 0.4]), torch.tensor([0.3, -0.7])
    pol = FeedForwardPolicy(net, o_star, u_ff)
    with torch.no_grad():
        assert pol(o_star[None])[0].tolist() == pytest.approx(u_ff.tolist(), abs=ACTION_ATOL)
        obs = torch.randn(7, 3)
        shift = pol(obs) - net(obs)
        assert torch.allclose(shift, (u_ff - net(o_star[None])[0]).expand(7, 2), atol=1e-6)
        clipped = FeedForwardPolicy(net, o_star, torch.tensor([5.0, -5.0]), bound=torch.tensor([1.0, 2.0]))
        assert clipped(obs).abs().max(dim=0).values.tolist() <= [1.0, 2.0]
        assert clipped(o_star[None])[0].tolist() == [1.0, -2.0]


@pytest.mark.parametrize("method, mean", [("model", "prior_mean"), ("oracle", "true_mean")])
def test_feedforward_lq_ss_anchors_at_the_optimum_for_the_methods_own_mean(method: str, mean: str) -> None:
    """The action at the LQ optimum's steady state is the optimum's there for the method's own mean (not the other
    mean's), derived here from scipy's DARE; away from it the policy is the actor shifted by that constant."""
    task = LinearTask()
    trainer = AGPI(task, _ff(method))
    lin = task.linearisation()
    x_ss, u_ss = _steady(lin, getattr(task, mean))
    _, u_other = _steady(lin, getattr(task, "true_mean" if mean == "prior_mean" else "prior_mean"))
    o_ss = torch.as_tensor(x_ss, dtype=torch.float32)[None]
    with torch.no_grad():
        u = trainer.policy(o_ss)[0].numpy()
        learned_ss = trainer.learned_policy(o_ss)[0].numpy()
        x = torch.tensor([[0.5, -1.0]])
        shifted = (trainer.policy(x) - trainer.learned_policy(x))[0].numpy()
    assert u == pytest.approx(u_ss, abs=1e-5)
    assert abs(float(u_ss[0] - u_other[0])) > 0.1  # the two means give different feed-forwards here
    assert shifted == pytest.approx(u_ss - learned_ss, abs=1e-5)


def test_feedforward_lq_ss_follows_the_ibe_and_leaves_training_unchanged() -> None:
    """Mixed RL's feed-forward is the IBE posterior's; the option changes no weight of training."""
    a = AGPI(LinearTask(), TrainConfig(method="mixed", task="linear", seed=0,
                                       algorithm={"batch_size": 16, "hidden_sizes": (8,)}))
    b = AGPI(LinearTask(), _ff("mixed"))  # the calibration (not read in training either) off: the shift's anchor
    for _ in range(5):
        a.iteration()
        _ = a.policy  # the default deploys a calibrated shift: its draws must leave training's stream alone
        b.iteration()
    for pa, pb in zip(list(a.actor.parameters()) + list(a.critic.parameters()),
                      list(b.actor.parameters()) + list(b.critic.parameters())):
        assert torch.equal(pa, pb)
    task, lin = b.task, b.task.linearisation()
    mean, cov = b.noise_moments()
    assert abs(float(mean[1] - task.prior_mean[1])) > 0.1  # the IBE has moved away from the prior
    ref = lq_reference(lin, mean, cov)
    with torch.no_grad():
        u_ss = b.policy(torch.as_tensor(ref.steady_state, dtype=torch.float32)[None])[0].numpy()
    assert u_ss == pytest.approx(ref.steady_action, abs=1e-5)


def test_feedforward_lq_ss_errors_name_the_option(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"algorithm.feedforward: 'lq_ss' .* method 'ddpg' has none"):
        TrainConfig(method="ddpg", task="linear", algorithm={"feedforward": "lq_ss"})
    with pytest.raises(ValueError, match=r"algorithm.feedforward: expected one of"):
        TrainConfig(task="linear", algorithm={"feedforward": "affine"})
    with pytest.raises(ValueError, match=r"algorithm.feedforward: 'lq_ss' needs a task with an equilibrium"):
        AGPI(_NoEquilibrium(), _ff("model"))


#: The retired values (key, value, commit that still runs it) and the values allowed in their place.
RETIRED = [("feedforward", v, "ee954d7") for v in ("lq_train", "lq_affine", "lq_affine_ss")] + [
    ("feedforward", "lq", "c44231f"), ("actor_output", "clip", "c44231f")]
ALLOWED = {"feedforward": r"\('auto', 'learned', 'lq_ss', 'lq_handover'\)",
           "actor_output": r"\('tanh', 'clip_inward'\)"}


def _retired_message(key: str, value: str, commit: str) -> str:
    return (rf"^algorithm\.{key}: '{value}' was retired \(.*results page.*\); expected one of {ALLOWED[key]}; "
            rf"git commit {commit} can still run it$")


@pytest.mark.parametrize("key, value, commit", RETIRED)
def test_a_retired_value_is_refused_naming_the_commit_that_runs_it(key: str, value: str, commit: str,
                                                                  tmp_path: Path) -> None:
    """The trained anchored actors, the equilibrium shift and the two-sided clip were retired: a config, a spec or a
    saved run naming one is refused with the key, the value, the allowed values and the commit that still runs
    it, before anything is built."""
    from mixedrl.run_results import evaluate_run
    from mixedrl.runs import make_trainer
    from mixedrl.sweep import expand, parse_spec

    message = _retired_message(key, value, commit)
    with pytest.raises(ValueError, match=message):
        TrainConfig(task="linear", algorithm={key: value})
    with pytest.raises(ValueError, match=message):
        TrainConfig.from_dict({"method": "mixed", "task": "linear", "algorithm": {key: value}})
    with pytest.raises(ValueError, match=message):
        TrainConfig(task="linear").replace(**{f"algorithm.{key}": value})
    with pytest.raises(ValueError, match=rf"algorithm\.{key}: '{value}' was retired"):
        expand(parse_spec(f'methods = ["mixed"]\nseeds = [0]\n[base]\n"task.name" = "linear"\n'
                          f'"algorithm.{key}" = "{value}"\n', "retired"))
    # a run saved by a commit that trained it: its config.json (digest and all) is refused as it is read
    cfg = TrainConfig(method="mixed", task="linear", seed=0,
                      algorithm={"batch_size": 16, "hidden_sizes": (8,), "iterations": 2})
    run = RunDirectory(tmp_path / "run")
    train(make_trainer(cfg), run, progress=False)
    record = run.read_record()
    if key == "feedforward":  # evaluated again with it (mixedrl evaluate RUN --feedforward VALUE)
        with pytest.raises(ValueError, match=message):
            evaluate_run(run.path, feedforward=value)
    record["algorithm"][key] = value
    from mixedrl.checkpoint import write_with_digest
    write_with_digest(run.config_path, (json.dumps(record, indent=2, sort_keys=True) + "\n").encode())
    with pytest.raises(ValueError, match=message):
        run.read_config()
    with pytest.raises(ValueError, match=message):
        evaluate_run(run.path)
    with pytest.raises(ValueError, match=message):
        train(make_trainer(cfg.replace(**{"algorithm.iterations": 4})), run, progress=False, resume=True)


def test_gain_in_observation_coordinates_maps_back_to_minus_l() -> None:
    """The pendulum observes (theta, theta_dot) scaled; G J_o = -L (the LQR's gain, LQRPolicy)."""
    from mixedrl.precision import equilibrium_gain

    task = PendulumTask()
    lin = task.linearisation()
    G = equilibrium_gain(task, lin).numpy()
    J_o = torch.func.jacrev(lambda x: task.observe(lin.to_state(x[None]))[0])(
        torch.zeros(lin.A.shape[0], dtype=torch.float64)).numpy()
    L = lq_reference(lin, np.zeros(lin.E.shape[1])).solution.gain
    assert np.allclose(G @ J_o, -L, rtol=1e-10, atol=1e-10)


class _Blind(LinearTask):
    """Observes only the first coordinate: the observation does not determine the state."""

    def observe(self, s: torch.Tensor) -> torch.Tensor:
        return s[..., :1]


def test_an_observation_that_misses_a_coordinate_has_no_gain() -> None:
    from mixedrl.precision import equilibrium_gain

    task = _Blind()
    with pytest.raises(ValueError, match=r"task: the LQ gain in observation coordinates needs observations .* rank 1"):
        equilibrium_gain(task, task.linearisation())


# ------------------------------------------- algorithm.feedforward = "lq_ss" and "auto" (the library default)
def test_auto_is_lq_handover_where_the_task_declares_an_equilibrium_else_learned(
        caplog: pytest.LogCaptureFixture) -> None:
    from mixedrl.departures.anchor import resolve

    assert TrainConfig().algorithm.feedforward == "auto"
    assert TrainConfig.preset("paper").algorithm.feedforward == "learned"
    assert AGPI(LinearTask(), _config("mixed")).feedforward == "lq_handover"
    assert AGPI(_NoEquilibrium(), _config("mixed")).feedforward == "learned"
    assert resolve(TrainConfig(method="ddpg", task="linear"), LinearTask()) == "learned"
    with caplog.at_level("WARNING", logger="mixedrl.departures.anchor"):  # no gain in observations: no hand-over
        assert resolve(_config("model"), _Blind()) == "lq_ss"
    assert "no hand-over to the LQ optimum" in caplog.text
    for value in ("learned", "lq_ss", "lq_handover"):
        assert resolve(TrainConfig(task="linear", algorithm={"feedforward": value}), _NoEquilibrium()) == value
    with caplog.at_level("WARNING", logger="mixedrl.algorithms.agpi"):
        assert AGPI(_NotARestPoint(), _config("model")).feedforward == "learned"  # an equilibrium that fails
    assert "algorithm.feedforward 'auto': no LQ problem" in caplog.text
    with pytest.raises(ValueError, match=r"algorithm.feedforward: 'lq_ss' needs a task with an equilibrium"):
        AGPI(_NoEquilibrium(), TrainConfig(method="model", task="linear", algorithm={"feedforward": "lq_ss"}))
    with pytest.raises(ValueError, match=r"algorithm.feedforward_width: "):
        TrainConfig(algorithm={"feedforward_width": -0.5})


def test_results_record_the_resolved_feed_forward(tmp_path: Path) -> None:
    """``results.json`` names the deployed feed-forward ("auto" resolved); DDPG's, deployed as trained, none."""
    from mixedrl.cli import main

    for method in ("mixed", "ddpg"):
        out = tmp_path / method
        assert main(["train", "--method", method, "--out", str(out), "--iterations", "2", "--no-progress", "--set",
                     "task.name=linear", "algorithm.batch_size=16", "algorithm.hidden_sizes=[8]", "ddpg.batch_size=16",
                     "run.eval_seeds=1"]) == 0
        saved = json.loads((out / "results.json").read_text())
        assert saved.get("feedforward") == {"mixed": "lq_handover", "ddpg": None}[method]


@pytest.mark.parametrize("width", [0.0, 0.5])
def test_lq_ss_takes_the_optimums_steady_action_at_its_steady_state(width: float) -> None:
    """With ``"lq_ss"`` the deployed policy takes, at the LQ optimum's steady state for the oracle's mean (derived
    here from scipy's DARE: ``x_ss = (I - A + B L)^-1 (E mu - B l0)``), the optimum's action there ``-L x_ss -
    l0``; away from it the shift is the same constant (``width`` 0) or fades (``width`` > 0)."""
    task = LinearTask()
    trainer = AGPI(task, TrainConfig(method="oracle", task="linear", seed=0, algorithm={
        "batch_size": 16, "hidden_sizes": (8,), "feedforward": "lq_ss", "feedforward_width": width,
        "feedforward_calibration": 0}))
    lin = task.linearisation()
    L, l0 = scipy_optimum(lin.A, lin.B, lin.Q, lin.R, lin.gamma, lin.E @ task.true_mean)
    x_ss = np.linalg.solve(np.eye(2) - lin.A + lin.B @ L, lin.E @ task.true_mean - lin.B @ l0)
    assert np.abs(x_ss).max() > 0.05  # the steady state is not the equilibrium here
    with torch.no_grad():
        u_ss = trainer.policy(torch.as_tensor(x_ss, dtype=torch.float32)[None])[0].numpy()
        far = torch.as_tensor(x_ss, dtype=torch.float32)[None] + 20.0 * task.obs_scale
        far_shift = (trainer.policy(far) - trainer.learned_policy(far))[0].numpy()
        u_eq = trainer.policy(torch.zeros(1, 2))[0].numpy()
    assert u_ss == pytest.approx(-L @ x_ss - l0, abs=1e-5)
    assert abs(float(u_eq[0] + l0[0])) > 1e-3  # the shift is not the one at the equilibrium (the retired "lq")
    learned_ss = trainer.learned_policy(torch.as_tensor(x_ss, dtype=torch.float32)[None])[0].detach().numpy()
    if width == 0.0:
        assert far_shift == pytest.approx(-L @ x_ss - l0 - learned_ss, abs=1e-5)
    else:
        assert np.abs(far_shift).max() < 1e-6


# ------------------------------------------- algorithm.feedforward = "lq_handover": the box of trained observations
def test_the_handover_is_the_policy_inside_the_box_and_the_affine_law_outside() -> None:
    """Inside ``[low, high]`` the deployed action is the wrapped policy's bit for bit; far outside it is the
    affine law ``u_a + G (o - o_a)`` (clipped); at the box's edge the blend is continuous."""
    from mixedrl.departures.anchor import HandoverPolicy

    torch.manual_seed(2)
    net = torch.nn.Sequential(torch.nn.Linear(2, 6), torch.nn.Tanh(), torch.nn.Linear(6, 1))
    low, high = torch.tensor([-1.0, -0.5]), torch.tensor([1.0, 0.5])
    gain, o_a, u_a = torch.tensor([[-2.0, -0.7]]), torch.tensor([0.3, 0.0]), torch.tensor([-0.4])
    pol = HandoverPolicy(net, low, high, gain, o_a, u_a, width=torch.tensor([0.25, 0.25]), bound=torch.tensor([5.0]))
    inside = (torch.rand(64, 2) * 2 - 1) * high
    far = torch.tensor([[3.0, 0.2], [-2.5, -0.1], [0.1, 2.0]])
    with torch.no_grad():
        assert torch.equal(pol(inside), net(inside))
        assert torch.equal(pol(torch.cat([inside, far]))[:64], net(inside))  # mixed rows: the inside ones untouched
        affine = torch.clamp(u_a + (far - o_a) @ gain.T, -5.0, 5.0)
        assert torch.allclose(pol(far), affine, atol=1e-5)
        edge = torch.tensor([[1.0, 0.1], [1.0 + 1e-4, 0.1]])
        assert torch.allclose(pol(edge)[0], pol(edge)[1], atol=1e-3)
        hard = HandoverPolicy(net, low, high, gain, o_a, u_a)  # no width: the affine law right outside
        assert torch.allclose(hard(edge[1:]), u_a + (edge[1:] - o_a) @ gain.T, atol=1e-6)


class _Engine:
    """What :func:`mixedrl.departures.anchor.remember` reads of a batched engine: members, task, rows."""

    def __init__(self, runs: list[AGPI]) -> None:
        self.members, self.task, self.batch = runs, runs[0].task, 3

    def rows(self, r: int) -> slice:
        return slice(r * self.batch, (r + 1) * self.batch)


def test_the_trained_box_covers_the_second_half_of_the_budget() -> None:
    """The box is the range of the observations of the trained states, per run, whatever the run deploys; it starts
    afresh at iteration ``iterations // 2``; non-finite states are left out, and a task without an equilibrium
    records none."""
    from mixedrl.departures.anchor import remember

    cfg = TrainConfig(method="model", task="linear", seed=0,
                      algorithm={"batch_size": 16, "hidden_sizes": (8,), "iterations": 10})
    a, b = AGPI(LinearTask(), cfg), AGPI(LinearTask(), cfg.replace(**{"algorithm.feedforward": "learned"}))
    engine = _Engine([a, b])
    first = torch.tensor([[[-3.0, 0.0], [0.0, 4.0], [1.0, 1.0], [9.0, 9.0], [9.0, 9.0], [9.0, 9.0]]], dtype=torch.float64)
    remember(engine, first, [0, 1])
    assert torch.equal(a.trained_box, torch.tensor([[-3.0, 0.0], [1.0, 4.0]]))
    assert torch.equal(b.trained_box, torch.tensor([[9.0, 9.0], [9.0, 9.0]]))  # deployed as trained: a box too
    c = AGPI(_NoEquilibrium(), cfg)
    remember(_Engine([c]), first, [0])
    assert c.trained_box is None
    a.k = 4
    later = torch.tensor([[[0.5, -2.0], [float("nan"), 50.0], [0.0, 0.0]] + [[0.0, 0.0]] * 3], dtype=torch.float64)
    remember(engine, later, [0])
    assert torch.equal(a.trained_box, torch.tensor([[-3.0, -2.0], [1.0, 4.0]]))  # widened; the NaN row left out
    a.k = 5  # iterations // 2: afresh
    remember(engine, later, [0])
    assert torch.equal(a.trained_box, torch.tensor([[0.0, -2.0], [0.5, 0.0]]))


def test_model_driven_rl_hands_over_to_the_prior_optimum_where_the_true_system_rests() -> None:
    """After training, far outside the trained box the deployed policy is the prior optimum's affine law; the
    box is part of the checkpoint, and a run stopped and resumed ends with the same box and policy."""
    from mixedrl.departures.anchor import equilibrium_gain, lq_reference as reference

    task = LinearTask()
    cfg = TrainConfig(method="model", task="linear", seed=3,
                      algorithm={"batch_size": 16, "hidden_sizes": (8,), "iterations": 6, "rollout_horizon": 4})
    trainer = AGPI(task, cfg)
    train(trainer, progress=False)
    assert trainer.feedforward == "lq_handover" and trainer.trained_box is not None
    lin = task.linearisation()
    ref = reference(lin, task.prior_mean, task.prior_cov)
    gain = equilibrium_gain(task, lin).float()
    o_ss, u_ss = torch.as_tensor(ref.steady_state, dtype=torch.float32), torch.as_tensor(ref.steady_action).float()
    # far from the box along the gain's null direction, where the affine law stays inside the action bound
    far = o_ss + 30.0 * torch.stack([gain[0, 1], -gain[0, 0]]) / gain.norm()
    with torch.no_grad():
        assert torch.allclose(trainer.policy(far[None])[0], u_ss + (far - o_ss) @ gain.T, atol=1e-4)
        assert not torch.allclose(trainer.learned_policy(far[None])[0], u_ss, atol=1e-2)
    resumed = AGPI(task, cfg)
    resumed.load_state_dict(trainer.state_dict())
    assert torch.equal(resumed.trained_box, trainer.trained_box)
    with torch.no_grad():
        probe = torch.tensor([[0.1, 0.2], [5.0, -3.0]])
        assert torch.equal(resumed.policy(probe), trainer.policy(probe))


def test_a_local_shift_keeps_the_gain_at_its_centre() -> None:
    from mixedrl.precision import FeedForwardPolicy

    torch.manual_seed(1)
    net = torch.nn.Sequential(torch.nn.Linear(3, 5), torch.nn.Tanh(), torch.nn.Linear(5, 1))
    o_star = torch.tensor([0.2, -0.1, 0.4])
    pol = FeedForwardPolicy(net, o_star, torch.tensor([0.9]), width=torch.tensor([0.3, 0.3, 0.3]))
    jac = torch.autograd.functional.jacobian(lambda o: pol(o[None])[0], o_star)
    jac_net = torch.autograd.functional.jacobian(lambda o: net(o[None])[0], o_star)
    assert torch.allclose(jac, jac_net, atol=1e-6)
    assert pol(o_star[None])[0].item() == pytest.approx(0.9, abs=ACTION_ATOL)
    obs = torch.randn(4, 3)
    with torch.no_grad():  # one observation as a batched one; batched rows as each alone
        assert pol(obs[0]).shape == net(obs[0]).shape == (1,)
        assert torch.allclose(pol(obs), torch.stack([pol(o) for o in obs]), atol=1e-7)


def test_evaluate_with_feedforward_lq_ss_reports_both_gaps(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A run deployed shifted (``lq_ss``) reports the shifted policy's gap and the learned actor's; ``mixedrl
    evaluate --feedforward`` evaluates it again with another value, and refuses a retired one naming its commit."""
    from mixedrl.cli import main

    out = tmp_path / "run"
    assert main(["train", "--method", "model", "--out", str(out), "--iterations", "2", "--no-progress", "--set",
                 "task.name=linear", "algorithm.batch_size=16", "algorithm.hidden_sizes=[8]", "run.eval_seeds=1",
                 "algorithm.feedforward=lq_ss"]) == 0
    results = json.loads((out / "results.json").read_text())
    assert results["feedforward"] == "lq_ss"
    assert abs(results["policy_gap"]["action_error"][0] - results["policy_gap_learned"]["action_error"][0]) > 1e-3
    capsys.readouterr()
    assert main(["evaluate", str(out), "--feedforward", "lq"]) == 2
    assert capsys.readouterr().err.strip() == (
        "mixedrl evaluate: error: algorithm.feedforward: 'lq' was retired (its measured rows stay on the results "
        "page, docs/results.rst); expected one of ('auto', 'learned', 'lq_ss', 'lq_handover'); git commit c44231f "
        "can still run it")
    assert main(["evaluate", str(out), "--feedforward", "learned"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["feedforward"] == "learned"
    assert printed["policy_gap"]["action_error"] == pytest.approx(results["policy_gap_learned"]["action_error"])


# ------------------------------------------------------------------- the yardstick of a run: the LQR with the true mean
def test_lqr_policy_is_scipys_discounted_optimum_with_the_means_feed_forward() -> None:
    """``LQRPolicy(task, mu)`` on the linear task (observation = state) is ``u = -L x - l0(mu)`` of scipy's DARE,
    for the true mean and for the prior's (which it tells apart)."""
    from mixedrl.precision import LQRPolicy

    task = LinearTask()
    x = torch.tensor([[0.0, 0.0], [0.3, -0.2], [-0.5, 0.4]])
    for mean in (task.true_mean, task.prior_mean):
        L, l0 = scipy_optimum(task.A, task.B, task.Q, task.R, task.gamma, np.asarray(mean))
        expected = -x.double().numpy() @ L.T - l0
        assert np.abs(expected).max() < float(task.action_bound[0])  # unclipped: the affine law itself
        assert np.allclose(LQRPolicy(task, mean)(x).double().numpy(), expected, atol=1e-5)
    assert not np.allclose(LQRPolicy(task, task.true_mean)(x).numpy(), LQRPolicy(task, task.prior_mean)(x).numpy())


def test_a_runs_results_carry_the_lqr_yardstick_uncounted(tmp_path: Path) -> None:
    """``results.json`` holds ``references.lqr_true_mean``: the LQR with the true mean evaluated on the run's own
    evaluation seeds (a better cost than the LQR with the prior's), not counted among the run's evaluation
    transitions; the run directory holds the training curve."""
    from mixedrl.precision import LQRPolicy

    out = tmp_path / "run"
    trainer = AGPI(LinearTask(), _config("mixed", eval_every=2, checkpoint_every=2, eval_seeds=2)
                   .replace(**{"algorithm.iterations": 4}))
    train(trainer, RunDirectory(out), progress=False)
    results = json.loads((out / "results.json").read_text())
    assert "references_reason" not in results
    counted = trainer.task.evaluation_transitions
    assert results["plant_transitions"]["evaluation"] == counted
    seeds = sorted({s for s in _eval_seeds(trainer)})
    fresh = LinearTask()
    ref = fresh.evaluate(LQRPolicy(fresh, fresh.true_mean), seeds)["cost"]
    prior = fresh.evaluate(LQRPolicy(fresh, fresh.prior_mean), seeds)["cost"]
    assert results["references"]["lqr_true_mean"]["cost"] == pytest.approx(ref, rel=1e-12)
    assert ref < prior
    assert (out / "training_curve.png").stat().st_size > 1000


def _eval_seeds(trainer: AGPI) -> list[int]:
    from mixedrl.runs import eval_seeds

    return eval_seeds(trainer.config)


def test_no_yardstick_on_the_double_lane_change_or_without_an_equilibrium() -> None:
    from mixedrl.precision import run_references

    refs, reason = run_references(AGPI(_NoEquilibrium(), _config("model")), [0])
    assert refs is None and "defines no equilibrium" in reason
    dlc = AGPI(DoubleLaneChangeTask(), TrainConfig(method="model", task="dlc", seed=0))
    refs, reason = run_references(dlc, [0])
    assert refs is None and "Task.lqr_reference" in reason


def test_training_curve_needs_evaluations() -> None:
    from mixedrl.runs import training_curve

    assert training_curve([{"iteration": 1}], {"method": "mixed", "seed": 0, "task": "linear", "final": {}}) is None
    png = training_curve([{"iteration": 1, "eval/cost": 3.0}, {"iteration": 2, "eval/cost": 2.0}],
                         {"method": "mixed", "seed": 0, "task": "linear", "final": {"cost": 2.0},
                          "references": {"lqr_true_mean": {"cost": 1.5}}})
    assert png is not None and png[:8] == b"\x89PNG\r\n\x1a\n"


def test_evaluating_a_run_without_a_trained_box_as_lq_handover_says_so(tmp_path: Path,
                                                                         caplog: pytest.LogCaptureFixture) -> None:
    """A run records its box whatever it deploys, so a run trained with ``"lq_ss"`` evaluates as ``"lq_handover"``
    silently; a checkpoint without a box (written before the box existed) is deployed as ``"lq_ss"`` (the same
    numbers), with a warning naming the option."""
    from mixedrl.checkpoint import load_checkpoint, save_checkpoint
    from mixedrl.run_results import evaluate_run

    out = tmp_path / "run"
    cfg = _config("model").replace(**{"algorithm.iterations": 2, "algorithm.feedforward": "lq_ss", "run.eval_seeds": 1})
    train(AGPI(LinearTask(), cfg), RunDirectory(out), progress=False)
    plain = evaluate_run(out)
    with caplog.at_level("WARNING", logger="mixedrl.run_results"):
        evaluate_run(out, feedforward="lq_handover")
    assert "holds no box" not in caplog.text
    checkpoint = RunDirectory(out).checkpoint_path
    state = load_checkpoint(checkpoint)
    del state["trainer"]["trained_box"]
    save_checkpoint(checkpoint, state)
    with caplog.at_level("WARNING", logger="mixedrl.run_results"):
        handed = evaluate_run(out, feedforward="lq_handover")
    assert "holds no box of the trained observations" in caplog.text
    assert handed["metrics"] == plain["metrics"]


# ------------------------------- algorithm.feedforward_calibration: the shift corrected on the model's mean state
class _Curved(torch.nn.Module):
    """A policy with a known curvature: the LQ optimum's affine law plus ``c (x_0 - a)^2``. Its action at ``a`` is the
    optimum's, so the deterministic closed loop rests at the optimum's steady state; under noise the mean of the
    square is the variance, so the stochastic closed loop rests elsewhere."""

    def __init__(self, L: np.ndarray, l0: np.ndarray, a: float, c: float) -> None:
        super().__init__()
        self.L, self.l0 = torch.as_tensor(L, dtype=torch.float32), torch.as_tensor(l0, dtype=torch.float32)
        self.a, self.c = a, c
        self.action_bound = torch.tensor([10.0])

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return -obs @ self.L.T - self.l0 + self.c * (obs[..., :1] - self.a) ** 2


def _calibrated_trainer(seed: int = 0, steps: int = 1) -> tuple[AGPI, np.ndarray]:
    """An oracle run on the linear test bed deploying ``"lq_ss"`` (constant shift) of :class:`_Curved`; the optimum's
    steady state ``x_ss`` from scipy's DARE."""
    task = LinearTask()
    trainer = AGPI(task, TrainConfig(method="oracle", task="linear", seed=seed, algorithm={
        "batch_size": 16, "hidden_sizes": (8,), "feedforward": "lq_ss", "feedforward_width": 0.0,
        "feedforward_calibration": steps}))
    lin = task.linearisation()
    L, l0 = scipy_optimum(lin.A, lin.B, lin.Q, lin.R, lin.gamma, lin.E @ task.true_mean)
    x_ss = np.linalg.solve(np.eye(2) - lin.A + lin.B @ L, lin.E @ task.true_mean - lin.B @ l0)
    trainer.actor = _Curved(L, l0, float(x_ss[0]), c=1.0)
    return trainer, x_ss


def _stationary_mean(task: LinearTask, policy: torch.nn.Module, start: np.ndarray, seed: int) -> np.ndarray:
    """The closed loop's mean state on the (oracle's = true) system, by the test's own simulation: 4,096 copies from
    ``start``, 1,000 steps, the mean over the last 500 (a noise stream of its own)."""
    gen = torch.Generator().manual_seed(seed)
    s = torch.as_tensor(start, dtype=torch.float64).expand(4096, -1).clone()
    total = torch.zeros(2, dtype=torch.float64)
    with torch.no_grad():
        for t in range(1000):
            s = task.true_step(s, policy(s.float()).double(), gen)
            if t >= 500:
                total += s.mean(0)
    return (total / 500).numpy()


def test_the_calibrated_shift_rests_where_the_optimum_does_under_noise() -> None:
    """A curved actor shifted to the optimum's action at ``x_ss`` rests away from ``x_ss`` under the noise; one
    Newton step of the calibration brings its mean state back to ``x_ss`` (the test's own simulation, not the
    calibration's draws), where the optimum's linear closed loop rests."""
    trainer, x_ss = _calibrated_trainer()
    task = trainer.task
    trainer.config.algorithm.feedforward_calibration = 0
    shifted = trainer.policy
    trainer.config.algorithm.feedforward_calibration = 1
    calibrated = trainer.policy
    before = _stationary_mean(task, shifted, x_ss, seed=11)
    after = _stationary_mean(task, calibrated, x_ss, seed=11)
    # measured: the curvature's bias 0.0069 (the stationary variance of x_0 times c); after the step 0.0002 to
    # 0.0008 (over the calibration's and the test's draws), at the test's own Monte-Carlo error (about 4e-4)
    assert np.abs(before - x_ss).max() > 0.005
    assert np.abs(after - x_ss).max() < 0.002


def test_the_calibration_is_reproducible_and_leaves_training_streams_alone() -> None:
    """The same seed gives the same correction; the run's generator is not drawn from; the correction is kept while
    the actor is the same and recomputed when its weights change."""
    a, _ = _calibrated_trainer(seed=3)
    b, _ = _calibrated_trainer(seed=3)
    state = a.generator.get_state().clone()
    pa, pb = a.policy, b.policy
    assert torch.equal(a._calibration[1], b._calibration[1])
    assert torch.equal(a.generator.get_state(), state)
    first = a._calibration
    with torch.no_grad():
        assert torch.equal(a.policy(torch.ones(1, 2)), pa(torch.ones(1, 2)))
    assert a._calibration is first  # the cached correction
    a.actor = torch.nn.Sequential(torch.nn.Linear(2, 1))  # new weights: the key changes
    a.actor.action_bound = torch.tensor([10.0])
    _ = a.policy
    assert a._calibration is not first
    assert torch.equal(pb(torch.ones(1, 2)), b.policy(torch.ones(1, 2)))


def test_feedforward_calibration_must_be_a_nonnegative_integer() -> None:
    for bad in (-1, 1.5, "one"):
        with pytest.raises(ValueError, match="algorithm.feedforward_calibration"):
            TrainConfig(method="mixed", task="linear", algorithm={"feedforward_calibration": bad})


def test_the_calibration_starts_from_the_optimums_stationary_distribution() -> None:
    """The copies start from ``N(x_ss, S)``, ``S`` the stationary covariance of the optimum's closed loop (here by
    iterating ``S <- A_c S A_c^T + E K E^T`` to its fixed point, not scipy's Lyapunov solver)."""
    from mixedrl.departures.calibration import CALIBRATION_COPIES, _stationary_draws

    trainer, x_ss = _calibrated_trainer()
    lin, task = trainer.task.linearisation(), trainer.task
    ref = lq_reference(lin, task.true_mean, task.true_cov)
    L, _ = scipy_optimum(lin.A, lin.B, lin.Q, lin.R, lin.gamma, lin.E @ task.true_mean)
    a_c, S = lin.A - lin.B @ L, np.zeros((2, 2))
    for _ in range(2000):
        S = a_c @ S @ a_c.T + lin.E @ task.true_cov @ lin.E.T
    draws = _stationary_draws(trainer, lin, ref, np.asarray(task.true_cov))
    assert draws.shape == (CALIBRATION_COPIES, 2)
    # 256 draws: a sample variance within about 9% (one sd) of the truth, a mean within 0.06 sd
    assert draws.mean(0) == pytest.approx(x_ss, abs=4 * float(np.sqrt(np.diag(S)).max()) / 16)
    assert np.diag(np.cov(draws.T)) == pytest.approx(np.diag(S), rel=0.35)
