"""The batched course evaluation (mixedrl.envs.evaluation.evaluate_courses) against the sequential one.

What is checked:

* the numpy rows of the vehicle and the reference are bit-identical to the Python-float step the
  Gymnasium environment takes (``VehicleDynamics.step_rows``, ``LibmReference``), where numpy's own
  ``tanh``/``arctan`` are not;
* ``evaluate_courses(..., exact=True)`` gives every course exactly what ``evaluate_tracking`` gives it, with
  either stepper, for policies whose courses end at different steps (the finished ones are masked);
* ``exact=False`` (one policy call per step on a batch of rows, or stacked policies) agrees to float32
  rounding (1e-6 relative), and exactly for a policy that works row by row in float64;
* a batch of runs evaluated at once (``runs.evaluate_together``, ``Task.evaluate_many``) gives each run its
  own numbers; the final evaluation of a run (``trainer.evaluate``) is unchanged bit for bit;
* bad input names the argument.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mixedrl.config import TrainConfig
from mixedrl.envs import DoubleLaneChangeModel, evaluate_courses, evaluate_tracking, make_config
from mixedrl.envs.evaluation import NUMPY_MIN_ROWS, _stacked_call
from mixedrl.envs.libm import elementwise
from mixedrl.networks import Actor, stacked_actors
from mixedrl.runs import eval_seeds, evaluate_together, make_trainer, train_batch
from mixedrl.tasks import DoubleLaneChangeTask, make_task

SCALARS = ("mean_abs_lateral_error", "mean_abs_speed_error", "max_abs_lateral_error", "max_abs_speed_error",
           "total_cost", "terminated", "n_steps")
ARRAYS = ("time", "states", "observations", "actions", "lateral_error", "speed_error", "disturbance", "costs")


def feedback(k_y: float, k_phi: float):
    """A float64 state feedback on the observation (row by row, so batching cannot change its bits)."""

    def policy(obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs)
        delta = -(k_y * obs[..., 4] + k_phi * obs[..., 3] + 0.05 * obs[..., 1])
        return np.stack([delta, -obs[..., 2]], axis=-1)

    return policy


def constant(delta: float):
    """Steer at a constant angle: the car leaves the road after some hundred steps."""
    return lambda obs: np.broadcast_to(np.array([delta, 0.0]), np.shape(obs)[:-1] + (2,))


def shake(net: torch.nn.Module, seed: int) -> torch.nn.Module:
    """Move the weights far from the initial ones (so the car does something), in place."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.3 * torch.randn(p.shape, generator=gen))
    return net


def actor(seed: int) -> Actor:
    """A small float32 actor with shaken weights."""
    gen = torch.Generator().manual_seed(seed)
    net = Actor(5, 2, (32, 32), "elu", gen, torch.tensor([0.4, 4.0]), torch.tensor([0.3, 0.2, 0.5, 0.1, 0.5]))
    return shake(net, seed)


def assert_same(a, b) -> None:
    for name in SCALARS:
        assert getattr(a, name) == getattr(b, name), name
    for name in ARRAYS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


# --------------------------------------------------------------------------------- elementwise dynamics
def test_numpy_rows_of_the_vehicle_are_the_python_float_step_bit_for_bit(rng) -> None:
    model = DoubleLaneChangeModel()
    n = 500
    s = np.column_stack([rng.normal(0, 0.5, n), rng.normal(0, 0.3, n), 12 + rng.normal(0, 1, n),
                         rng.normal(0, 0.3, n), rng.normal(0, 2, n), rng.uniform(0, 120, n)])
    u = np.column_stack([rng.uniform(-0.4, 0.4, n), rng.uniform(-4, 4, n)])
    rows = np.column_stack(model.dynamics.step_rows(s, u))
    scalar = np.array([model.dynamics.step_scalar(tuple(x), tuple(a)) for x, a in zip(s, u)])
    np.testing.assert_array_equal(rows, scalar)
    ref, rows_ref = model.config.reference, model.config.reference.rows()
    y, psi = rows_ref.lateral_and_heading(s[:, 5])
    np.testing.assert_array_equal(y, [ref.lateral(float(x)) for x in s[:, 5]])
    np.testing.assert_array_equal(psi, [ref.heading(float(x)) for x in s[:, 5]])
    np.testing.assert_array_equal(rows_ref.lateral(s[:, 5]), y)


def test_numpy_vectorised_transcendentals_are_why_libm_is_used(rng) -> None:
    # numpy's SIMD tanh differs from the C library's in the last bit for some arguments (on x86-64); the
    # element-by-element version does not. (If numpy ever agrees everywhere, the first check is moot.)
    x = rng.normal(0, 3, 20_000)
    exact = np.array([math.tanh(v) for v in x])
    np.testing.assert_array_equal(elementwise(math.tanh)(x), exact)
    np.testing.assert_array_equal(elementwise(math.atan2)(x, x[::-1]), [math.atan2(a, b) for a, b in zip(x, x[::-1])])
    assert np.max(np.abs(np.tanh(x) - exact)) <= 2 * np.finfo(float).eps


# ----------------------------------------------------------------------------------- lock step = sequential
@pytest.mark.parametrize("stepper", ["env", "numpy"])
def test_courses_in_lock_step_equal_the_sequential_drives_bit_for_bit(stepper: str) -> None:
    # three policies ending at different steps: two leave the road early (at different steps), one drives on
    policies = [feedback(0.1, 1.0), constant(0.1), constant(0.05)]
    seeds = [[3, 4], [5, 6], [7, 8]]
    out = evaluate_courses(policies, seeds=seeds, max_steps=400, stepper=stepper)
    steps = set()
    for p, policy in enumerate(policies):
        assert len(out[p]) == 2
        for j, seed in enumerate(seeds[p]):
            alone = evaluate_tracking(policy, seed=seed, max_steps=400)
            assert_same(out[p][j], alone)
            steps.add(alone.n_steps)
    assert len(steps) >= 3 and 400 in steps  # the masks were exercised: courses ended at different steps
    assert any(r.terminated for r in out[1]) and not any(r.terminated for r in out[0])


@pytest.mark.parametrize("overrides", [
    {"preview_distances": (5.0, 12.0)},
    {"disturbance": {"law": "student_t", "dof": 4.0}},
    {"disturbance": {"law": "bumps"}},
    {"disturbance": {"grade_amplitude": 0.05, "grade_wavelength": 30.0}},
], ids=["preview", "student_t", "bumps", "grade"])
def test_every_configured_course_is_reproduced_bit_for_bit(overrides: dict) -> None:
    cfg = make_config(None, **overrides)
    policies = [feedback(0.1, 1.0), constant(0.1)]
    out = evaluate_courses(policies, cfg, seeds=[[1, 2], [3]], max_steps=300, stepper="numpy")
    for p, seeds in enumerate([[1, 2], [3]]):
        for j, seed in enumerate(seeds):
            assert_same(out[p][j], evaluate_tracking(policies[p], cfg, seed=seed, max_steps=300))


def test_a_full_course_of_a_float32_actor_is_bit_identical_with_exact_policy_calls() -> None:
    policies = [actor(0), actor(1)]
    out = evaluate_courses(policies, seeds=[[11], [12]], stepper="numpy")
    for p, policy in enumerate(policies):
        assert_same(out[p][0], evaluate_tracking(policy, seed=11 + p))


def test_normalised_actions_and_a_start_state_are_honoured_exactly() -> None:
    start = np.array([0.1, 0.0, 11.5, 0.02, 0.1, 0.0])
    policy = feedback(1.0, 5.0)  # in [-1, 1] units: clipped by the environment
    for stepper in ("env", "numpy"):
        out = evaluate_courses([policy], seeds=[0, 1], start_state=start, max_steps=150, normalized_actions=True,
                               stepper=stepper)
        for j in range(2):
            assert_same(out[0][j], evaluate_tracking(policy, seed=j, start_state=start, max_steps=150,
                                                     normalized_actions=True))


def test_batched_policy_calls_agree_to_float32_rounding() -> None:
    policies = [actor(0), actor(1), actor(2)]
    seeds = [[21, 22], [23, 24], [25, 26]]
    assert _stacked_call(policies) is not None  # the stacked path is the one taken
    out = evaluate_courses(policies, seeds=seeds, max_steps=600, exact=False)
    # unequal numbers of seeds: no stacking, one call per policy
    per_policy = evaluate_courses(policies, seeds=[[21, 22], [23, 24], [25]], max_steps=600, exact=False)
    for p, policy in enumerate(policies):
        for j, seed in enumerate(seeds[p]):
            alone = evaluate_tracking(policy, seed=seed, max_steps=600)
            got = [out[p][j]] + ([per_policy[p][j]] if j < len(per_policy[p]) else [])
            for r in got:
                assert r.n_steps == alone.n_steps and r.terminated == alone.terminated
                for name in SCALARS[:5]:
                    assert getattr(r, name) == pytest.approx(getattr(alone, name), rel=1e-6), name
    # a policy that works row by row in float64 has the same bits batched or not
    ok = evaluate_courses([feedback(0.1, 1.0)], seeds=[1, 2], max_steps=300, exact=False)[0]
    for j in range(2):
        assert_same(ok[j], evaluate_tracking(feedback(0.1, 1.0), seed=j + 1, max_steps=300))


def test_a_finished_course_is_masked_in_batched_calls_too() -> None:
    # off the road the policy returns NaN: only a finished course sees such an observation, and its action
    # is computed (fixed batch shapes) but neither checked nor used
    def leaves_then_nan(obs: np.ndarray) -> np.ndarray:
        out = np.broadcast_to(np.array([0.1, 0.0]), np.shape(obs)[:-1] + (2,)).copy()
        out[np.abs(obs[..., 4]) > 3.0] = np.nan
        return out

    for stepper in ("env", "numpy"):
        out = evaluate_courses([leaves_then_nan, feedback(0.1, 1.0)], seeds=[[1, 2], [3, 4]], max_steps=400,
                               exact=False, stepper=stepper)
        for j, seed in enumerate((1, 2)):
            alone = evaluate_tracking(leaves_then_nan, seed=seed, max_steps=400)
            assert alone.terminated and alone.n_steps < 400
            assert_same(out[0][j], alone)
        with pytest.raises(ValueError, match=r"^policies: entry 1 \(seed 3\) returned NaN"):
            evaluate_courses([feedback(0.1, 1.0), lambda obs: np.full(np.shape(obs)[:-1] + (2,), np.nan)],
                             seeds=[[1, 2], [3, 4]], exact=False, max_steps=5, stepper=stepper)


def test_stacked_actors_and_the_vmap_of_other_modules_agree_with_each_module() -> None:
    obs = torch.randn(3, 4, 5, generator=torch.Generator().manual_seed(0))
    actors = [actor(0), actor(1), actor(2)]
    fast = stacked_actors(actors)
    assert fast is not None
    expected = torch.stack([a(obs[p]) for p, a in enumerate(actors)]).detach()
    torch.testing.assert_close(fast(obs), expected, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(_stacked_call(actors)(obs.numpy()), expected.numpy(), rtol=1e-6, atol=1e-6)
    torch.manual_seed(0)
    nets = [torch.nn.Sequential(torch.nn.Linear(5, 8), torch.nn.ELU(), torch.nn.Linear(8, 2)) for _ in range(3)]
    assert stacked_actors(nets) is None  # not actors: the vmap path
    expected = torch.stack([n(obs[p]) for p, n in enumerate(nets)]).detach().numpy()
    np.testing.assert_allclose(_stacked_call(nets)(obs.numpy()), expected, rtol=1e-6, atol=1e-6)
    out = evaluate_courses(nets, seeds=[1, 2], max_steps=200, exact=False)
    for p, net in enumerate(nets):
        for j, seed in enumerate((1, 2)):
            alone = evaluate_tracking(net, seed=seed, max_steps=200)
            assert out[p][j].n_steps == alone.n_steps
            assert out[p][j].total_cost == pytest.approx(alone.total_cost, rel=1e-6)
    other = Actor(5, 2, (16,), "elu", torch.Generator().manual_seed(0), torch.tensor([0.4, 4.0]))
    assert stacked_actors([actor(0), other]) is None and stacked_actors([]) is None


def test_stacking_is_refused_for_modules_it_cannot_represent() -> None:
    assert _stacked_call([torch.nn.Linear(5, 2)]) is None  # one module that is not an actor: its own call
    assert _stacked_call([actor(0), torch.nn.Linear(5, 2)]) is None
    other = Actor(5, 2, (16,), "elu", torch.Generator().manual_seed(0), torch.tensor([0.4, 4.0]))
    assert _stacked_call([actor(0), other]) is None
    a, b = (torch.nn.Sequential(torch.nn.Linear(5, 2)) for _ in range(2))
    assert _stacked_call([a, b]) is not None
    a.extra, b.extra = torch.zeros(2), torch.ones(2)  # a plain tensor attribute each: not in the stacked state
    assert _stacked_call([a, b]) is None


# ------------------------------------------------------------------------------------- runs of a batch
def test_a_batch_of_runs_evaluated_at_once_gives_each_run_its_own_numbers(tmp_path) -> None:
    # the trained actors as deployed ("learned"): the batched calls' float32 last bits against the per-course ones
    # (the default's shifted policies are checked bit for bit below)
    configs = [TrainConfig(method=m, seed=s).replace(**{"algorithm.iterations": 2, "run.eval_every": 1,
                                                        "task.course_length": 18.0,
                                                        "algorithm.feedforward": "learned"})
               for m, s in (("mixed", 0), ("model", 1), ("oracle", 2))]
    shifted = [make_trainer(c.replace(**{"algorithm.feedforward": "auto"})) for c in configs]
    for t, seed in zip(shifted, (5, 6, 7)):
        shake(t.learned_policy, seed)
    alone = [t.evaluate(eval_seeds(c)) for t, c in zip(shifted, configs)]
    assert all(t.feedforward == "lq_handover" for t in shifted)
    assert evaluate_together(shifted, [eval_seeds(c) for c in configs], exact=True) == alone
    trainers = [make_trainer(c) for c in configs]
    for t, seed in zip(trainers, (5, 6, 7)):  # distinct policies that do something
        shake(t.policy, seed)
    seeds = [eval_seeds(c) for c in configs]
    alone = [t.evaluate(s) for t, s in zip(trainers, seeds)]
    together = evaluate_together(trainers, seeds)
    exact = evaluate_together(trainers, seeds, exact=True)
    for a, b, e in zip(alone, together, exact):
        assert e == a  # exact: bit for bit
        assert b.keys() == a.keys()
        for key in a:
            assert b[key] == pytest.approx(a[key], rel=1e-6), key
    assert len({a["cost"] for a in alone}) == 3  # three different policies: a swap would be seen

    # in training: the final evaluation (results.json, and the last metrics row) is each trainer's own,
    # exact; the periodic one before it is batched
    results = train_batch(trainers, progress=False)
    for t, s, r in zip(trainers, seeds, results):
        final = t.evaluate(s)
        assert r["final"] == {k: v for k, v in final.items()}
        assert r["cost"] == final["cost"] and r["lateral_mae"] == final["lateral_mae"]
        first, last = r["metrics"]
        assert last["eval/cost"] == final["cost"] and last["eval/speed_mae"] == final["speed_mae"]
        assert "eval/cost" in first


def test_the_last_evaluation_of_a_run_is_exact_and_is_its_final_one(monkeypatch) -> None:
    # the final evaluation of a finished run is taken at its last iteration (exact) and reused by summarize
    import mixedrl.runs as runs

    calls = []
    original = runs.evaluate_together

    def spy(trainers, seeds, *, exact=False):
        calls.append((len(trainers), exact))
        return original(trainers, seeds, exact=exact)

    monkeypatch.setattr(runs, "evaluate_together", spy)
    config = TrainConfig(method="mixed", seed=0).replace(**{"algorithm.iterations": 3, "run.eval_every": 2,
                                                            "task.course_length": 6.0})
    trainer = make_trainer(config)
    result = runs.train(trainer, progress=False)
    assert calls == [(1, False), (1, True)]  # iteration 2 (periodic), iteration 3 (the last: exact)
    assert result["final"] == trainer.evaluate(eval_seeds(config))


def test_the_generic_task_evaluates_many_policies_one_by_one() -> None:
    task = make_task("pendulum")
    policies = [actor_for(task, 0), actor_for(task, 1)]
    many = task.evaluate_many(policies, [[1, 2], [3]], exact=False)
    assert many == [task.evaluate(policies[0], [1, 2]), task.evaluate(policies[1], [3])]


def actor_for(task, seed: int) -> Actor:
    return Actor(task.obs_dim, task.action_dim, (16,), "elu", torch.Generator().manual_seed(seed), task.action_bound)


# ------------------------------------------------------------------------------------------- bad input
def test_bad_input_names_the_argument() -> None:
    good = feedback(0.1, 1.0)
    with pytest.raises(ValueError, match="^policies:"):
        evaluate_courses([], seeds=[0])
    with pytest.raises(ValueError, match="^policies:"):
        evaluate_courses(actor(0), seeds=[0])
    with pytest.raises(ValueError, match="^policies: entry 1"):
        evaluate_courses([good, 3], seeds=[0])
    with pytest.raises(ValueError, match="^seeds:"):
        evaluate_courses([good], seeds=[])
    with pytest.raises(ValueError, match=r"^seeds: expected one list of seeds per policy \(2\)"):
        evaluate_courses([good, good], seeds=[[0], [1], [2]])
    with pytest.raises(ValueError, match="^seeds: entry 1"):
        evaluate_courses([good, good], seeds=[[0], []])
    with pytest.raises(ValueError, match="^seeds: entry 0"):
        evaluate_courses([good, good], seeds=[[0.5], [1]])
    with pytest.raises(ValueError, match="^stepper:"):
        evaluate_courses([good], seeds=[0], stepper="gpu")
    with pytest.raises(ValueError, match="^max_steps:"):
        evaluate_courses([good], seeds=[0], max_steps=0)
    with pytest.raises(ValueError, match="^start_state:"):
        evaluate_courses([good], seeds=[0], start_state=np.zeros(5))
    bad_shape = lambda obs: np.zeros(3)  # noqa: E731
    for exact in (True, False):
        for stepper in ("env", "numpy"):
            with pytest.raises(ValueError, match=r"^policies: entry 1.*shape"):
                evaluate_courses([good, bad_shape], seeds=[0], exact=exact, max_steps=5, stepper=stepper)
    for stepper in ("env", "numpy"):
        with pytest.raises(ValueError, match=r"^policies: entry 0 \(seed 7\) returned .*NaN"):
            evaluate_courses([lambda obs: np.array([np.nan, 0.0])], seeds=[7], max_steps=5, stepper=stepper)
    model = DoubleLaneChangeModel()
    with pytest.raises(ValueError, match="^x:"):
        model.dynamics.step_rows(np.zeros((3, 4)), np.zeros((3, 2)))
    with pytest.raises(ValueError, match="^u:"):
        model.dynamics.step_rows(np.zeros((3, 6)), np.zeros((2, 2)))
    task = DoubleLaneChangeTask()
    with pytest.raises(ValueError, match="^seeds:"):
        task.evaluate_many([actor(0), actor(1)], [[0]])
    with pytest.raises(ValueError, match="^policies:"):
        task.evaluate_many(actor(0), [[0]])
    with pytest.raises(ValueError, match="^seeds:"):
        evaluate_together([make_trainer(TrainConfig(method="mixed", seed=0))], [])


def test_the_auto_stepper_switches_to_numpy_rows_at_the_threshold() -> None:
    # the same numbers either way (checked above); here only that both sides of the threshold run
    policy = feedback(0.1, 1.0)
    small = evaluate_courses([policy], seeds=list(range(NUMPY_MIN_ROWS - 1)), max_steps=20)
    large = evaluate_courses([policy], seeds=list(range(NUMPY_MIN_ROWS)), max_steps=20)
    for j in range(NUMPY_MIN_ROWS - 1):
        assert_same(small[0][j], large[0][j])
