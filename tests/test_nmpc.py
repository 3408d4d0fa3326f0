"""Independent checks of the reference controllers (validation/nmpc.py); tox env 'integration' (needs CasADi).

* the CasADi model is the package's torch model (1e-12, float64, saturation branch included);
* on a linear system the NMPC with a long horizon takes the DARE optimum's first action (1e-6);
* on a straight road without disturbance the NMPC holds 12 m/s;
* a solver failure raises an error naming the step and IPOPT's status (no fallback);
* a reduced NMPC run on a short piece of the course beats the LQR there;
* the LQR's affine optimum is validation.lq's, and the course driver is evaluate_tracking itself;
* without preview the NMPC predicts on the reference's tangent at the car's X: identical to the NMPC
  with preview on a straight road, different in the lane change.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

pytestmark = pytest.mark.nmpc
casadi = pytest.importorskip("casadi", reason="the NMPC references need CasADi: pip install -e '.[nmpc]'")

from mixedrl.envs import DoubleLaneChangeModel, evaluate_tracking, make_config  # noqa: E402
from validation import lq, nmpc  # noqa: E402
from validation.lq import LQProblem, optimal_solution  # noqa: E402


def _random_states(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    s = np.column_stack([
        rng.normal(0.0, 1.5, n), rng.normal(0.0, 1.0, n), rng.uniform(2.0, 25.0, n),
        rng.normal(0.0, 0.5, n), rng.normal(0.0, 3.0, n), rng.uniform(-20.0, 160.0, n),
    ])
    u = np.column_stack([rng.uniform(-0.6, 0.6, n), rng.uniform(-6.0, 6.0, n)])
    return s, u


def test_casadi_model_is_the_torch_model(rng: np.random.Generator) -> None:
    """f (eq. 53, Euler), the cost (eq. 54 on the next state) and the reference agree to 1e-12."""
    model = DoubleLaneChangeModel()
    cm = nmpc.casadi_tracking_model()
    n = 500
    s, u = _random_states(rng, n)
    # the Fiala saturation branch is visited (front and rear slip beyond alpha_sl) and so is the linear part
    p = model.config.params
    alpha_f = np.arctan2(s[:, 0] + p.a * s[:, 1], s[:, 2]) - u[:, 0]
    alpha_sl_f = math.atan(3.0 * p.mu * p.F_zf / p.C_f)
    assert (np.abs(alpha_f) > alpha_sl_f).sum() > 50 and (np.abs(alpha_f) < alpha_sl_f).sum() > 50
    f_torch = model.step(torch.tensor(s), torch.tensor(u)).numpy()
    f_cas = np.asarray(cm.step.map(n)(s.T, u.T)).T
    np.testing.assert_allclose(f_cas, f_torch, rtol=1e-12, atol=1e-12)
    l_torch = model.cost(torch.tensor(f_torch), torch.tensor(u)).numpy()
    l_cas = np.asarray(cm.cost.map(n)(f_torch.T, u.T)).ravel()
    np.testing.assert_allclose(l_cas, l_torch, rtol=1e-12, atol=1e-12)
    X = s[:, 5]
    np.testing.assert_allclose(np.asarray(cm.lateral.map(n)(X[None])).ravel(),
                               model.reference.lateral(X), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(cm.heading.map(n)(X[None])).ravel(),
                               model.reference.heading(X), rtol=1e-12, atol=1e-12)


def test_casadi_model_rk4_is_the_torch_rk4(rng: np.random.Generator) -> None:
    model = DoubleLaneChangeModel({"scheme": "rk4"})
    cm = nmpc.casadi_tracking_model({"scheme": "rk4"})
    s, u = _random_states(rng, 100)
    f_torch = model.step(torch.tensor(s), torch.tensor(u)).numpy()
    np.testing.assert_allclose(np.asarray(cm.step.map(100)(s.T, u.T)).T, f_torch, rtol=1e-12, atol=1e-12)


def _linear_problem() -> LQProblem:
    # a sampled double integrator with a lightly damped second state and mean-shifted noise
    return LQProblem(A=[[1.0, 0.1], [-0.05, 0.98]], B=[[0.005], [0.1]], Q=[[1.0, 0.2], [0.2, 0.5]], R=[[0.3]],
                     gamma=0.9, noise_mean=[0.01, -0.2], noise_cov=[[1e-4, 0.0], [0.0, 1e-4]],
                     prior_mean=[0.0, 0.0], prior_cov=[[1e-4, 0.0], [0.0, 1e-4]])


def _linear_horizon(prob: LQProblem, N: int, **kwargs: object) -> nmpc.RecedingHorizon:
    x = casadi.SX.sym("x", prob.n)
    u = casadi.SX.sym("u", prob.m)
    # x' = A x + B u + mu (the mean of the noise in the prediction)
    step = casadi.Function("f", [x, u], [casadi.DM(prob.A) @ x + casadi.DM(prob.B) @ u + casadi.DM(prob.noise_mean)])
    # l(x', u) = x'^T Q x' + u^T R u
    cost = casadi.Function("l", [x, u], [x.T @ casadi.DM(prob.Q) @ x + u.T @ casadi.DM(prob.R) @ u])
    return nmpc.RecedingHorizon(step, cost, horizon_steps=N, gamma=prob.gamma, **kwargs)


def test_linear_nmpc_takes_the_dare_optimum_first_action() -> None:
    """Long horizon (gamma^N ~ 1e-23): the first input is -L x - l0 of the DARE (validation.lq) to 1e-6."""
    prob = _linear_problem()
    opt = optimal_solution(prob)
    mpc = _linear_horizon(prob, 500)
    for x in ([1.0, -0.5], [-2.0, 0.3], [0.0, 0.0]):
        sol = mpc.solve(np.array(x))
        mpc.reset()
        expected = -opt.gain @ np.array(x) - opt.offset
        np.testing.assert_allclose(sol.u[0], expected, rtol=0.0, atol=1e-6)


def test_warm_started_solve_gives_the_same_answer() -> None:
    prob = _linear_problem()
    mpc = _linear_horizon(prob, 200)
    mpc.solve(np.array([1.0, -0.5]), step=0)
    warm = mpc.solve(np.array([0.8, -0.4]), step=1)
    mpc.reset()
    cold = mpc.solve(np.array([0.8, -0.4]), step=1)
    np.testing.assert_allclose(warm.u, cold.u, atol=1e-7)


def test_discounted_lqr_is_validation_lq_optimum() -> None:
    """One implementation of the discounted LQ optimum: the LQR's numbers are validation.lq's, bit for bit."""
    prob = _linear_problem()
    opt = optimal_solution(prob)
    assert nmpc.discounted_lq_optimum is lq.discounted_lq_optimum
    L, l0, S = nmpc.discounted_lqr(prob.A, prob.B, prob.Q, prob.R, prob.gamma, prob.noise_mean)
    np.testing.assert_array_equal(L, opt.gain)
    np.testing.assert_array_equal(l0, opt.offset)
    np.testing.assert_array_equal(S, opt.S)


def test_straight_lqr_compensates_the_mean_force() -> None:
    """Undiscounted, on the straight at the equilibrium, the LQR's a_x cancels the mean force exactly: -F/m.

    (Discounted, it does not: gamma < 1 makes a lasting speed error cheaper than the input that removes it.)
    """
    for mean, force in (("true", 261.0), ("prior", 150.0), ("zero", 0.0), (42.0, 42.0)):
        lqr = nmpc.straight_lqr(gamma=1.0, force=mean)
        u = lqr.act(np.zeros(5))
        assert lqr.force == force
        np.testing.assert_allclose(u, [0.0, -force / 1500.0], atol=1e-9)


def test_nmpc_holds_12_mps_on_a_straight_road() -> None:
    """No disturbance, straight reference: the NMPC keeps 12 m/s and the lane (and steers nothing)."""
    cfg = make_config(None, reference={"dy1": 0.0, "dy2": 0.0}, disturbance={"mean": 0.0, "variance": 0.0},
                      course_length=3.6)
    ctrl = nmpc.VehicleNMPC(cfg, horizon=0.3, gamma=0.99, force="true")
    result, timing = nmpc.drive(ctrl, cfg, seed=0)
    assert result.n_steps == 60 and not result.terminated and timing["solves"] == 60
    assert np.max(np.abs(result.speed_error)) < 1e-8
    assert np.max(np.abs(result.lateral_error)) < 1e-8
    # and from 0.5 m/s below it comes back: the speed error shrinks monotonically
    mpc = ctrl.core
    mpc.reset()
    s = np.array([0.0, 0.0, 11.5, 0.0, 0.0, 0.0])
    speeds = [s[2]]
    for k in range(60):
        u = mpc.solve(s, step=k).u[0]
        s = np.array(ctrl.model.step(s, u)).ravel()
        speeds.append(s[2])
    errors = np.abs(np.array(speeds) - 12.0)
    assert np.all(np.diff(errors) <= 1e-12) and errors[-1] < 0.5 * errors[0]


def test_solver_failure_names_step_and_status() -> None:
    prob = _linear_problem()
    # bounds make it more than one Newton step (a bound-free QP is solved in one IPOPT iteration)
    mpc = _linear_horizon(prob, 50, u_min=[-0.01], u_max=[0.01], ipopt_options={"max_iter": 1})
    with pytest.raises(nmpc.NMPCSolveError, match=r"step 7: IPOPT failed with status 'Maximum_Iterations_Exceeded'"):
        mpc.solve(np.array([1.0, -0.5]), step=7)
    # on the vehicle, inside a course: the exception reaches the caller, no input is applied
    ctrl = nmpc.VehicleNMPC(horizon=0.1, ipopt_options={"max_iter": 1})
    with pytest.raises(nmpc.NMPCSolveError) as info:
        nmpc.drive(ctrl, seed=0)
    assert info.value.step == 0 and info.value.status == "Maximum_Iterations_Exceeded"


def test_reduced_nmpc_on_a_piece_of_the_course_beats_the_lqr() -> None:
    """The first 36 m (into the first lane change), 0.5 s horizon, re-solved every 10 steps."""
    cfg = make_config(None, course_length=36.0)
    ctrl = nmpc.VehicleNMPC(cfg, horizon=0.5, gamma=1.0, force="true", period=10)
    res_nmpc, timing = nmpc.drive(ctrl, cfg, seed=0)
    res_lqr, _ = nmpc.drive(nmpc.straight_lqr(cfg, gamma=1.0), cfg, seed=0)
    assert res_nmpc.n_steps == cfg.max_steps and not res_nmpc.terminated
    assert timing["solves"] == math.ceil(cfg.max_steps / 10)
    # preview pays: the NMPC leaves the lane less and costs less than the LQR on the same noise
    assert res_nmpc.mean_abs_lateral_error < 0.5 * res_lqr.mean_abs_lateral_error
    assert res_nmpc.total_cost < res_lqr.total_cost


def test_drive_is_evaluate_tracking() -> None:
    """The state-feedback wrapper changes nothing: the LQR through drive() and as a plain observation
    policy in evaluate_tracking give identical runs."""
    lqr = nmpc.straight_lqr(gamma=0.99)
    cfg = make_config(None, course_length=30.0)
    res, _ = nmpc.drive(lqr, cfg, seed=3)
    ref = evaluate_tracking(lambda obs: -lqr.gain @ obs - lqr.offset, cfg, seed=3)
    np.testing.assert_array_equal(res.states, ref.states)
    assert res.total_cost == ref.total_cost


@pytest.mark.parametrize("kwargs, name", [
    ({"controller": "mpc"}, "controller"),
    ({"controller": "lqr", "gamma": 0.0}, "gamma"),
    ({"controller": "lqr", "gamma": 1.5}, "gamma"),
    ({"controller": "lqr", "horizon": -1.0}, "horizon"),
    ({"controller": "lqr", "horizon": float("nan")}, "horizon"),
    ({"controller": "lqr", "disturbance_mean": "posterior"}, "disturbance_mean"),
    ({"controller": "lqr", "disturbance_mean": float("inf")}, "disturbance_mean"),
    ({"controller": "lqr", "seeds": ()}, "seeds"),
    ({"controller": "lqr", "seeds": (-1,)}, "seeds"),
    ({"controller": "nmpc", "period": 0}, "period"),
])
def test_bad_arguments_name_the_argument(kwargs: dict, name: str) -> None:
    with pytest.raises(ValueError, match=f"^{name}:"):
        nmpc.run_reference(**kwargs)


def test_run_reference_lqr_keys() -> None:
    out = nmpc.run_reference("lqr", gamma=1.0, disturbance_mean=0.0, seeds=(0, 1), config={"course_length": 24.0})
    for key in ("lateral_mae", "speed_mae", "cost", "solve_ms_mean", "solve_ms_max"):
        assert math.isfinite(out[key])
    assert out["force_N"] == 0.0 and len(out["per_seed"]) == 2
    assert out["cost"] == pytest.approx(np.mean([r["cost"] for r in out["per_seed"]]))


@pytest.mark.parametrize("preview", [True, False])
@pytest.mark.parametrize("mean, force", [("true", 261.0), ("prior", 150.0), (-80.0, -80.0)])
def test_prediction_carries_the_chosen_mean(mean: object, force: float, preview: bool) -> None:
    """The NMPC predicts with f(s, u) + (F T / m) e_vx for the chosen F, and nothing else (with and
    without preview)."""
    ctrl = nmpc.VehicleNMPC(horizon=0.05, gamma=0.99, force=mean, preview=preview)
    model = DoubleLaneChangeModel()
    s0 = np.array([0.1, 0.02, 11.8, 0.05, 0.2, 3.0])
    ctrl(s0)
    sol = ctrl.solution
    xi = np.zeros(6)
    xi[2] = force * model.config.dt / model.config.params.m
    for k in range(ctrl.horizon_steps):
        np.testing.assert_allclose(sol.x[k + 1] - model.step(sol.x[k], sol.u[k]), xi, atol=1e-9)


def test_entry_point_writes_json(tmp_path) -> None:
    import json

    assert nmpc.main(["--controller", "lqr", "--gamma", "1.0", "--mean", "true", "150", "--seeds", "0",
                      "--out", str(tmp_path)]) == 0
    rows = json.loads((tmp_path / "references.json").read_text())
    assert [r["force_N"] for r in rows] == [261.0, 150.0] and rows[0]["horizon"] == "infinite"
    assert rows[0]["cost"] < rows[1]["cost"]  # compensating the true mean beats the prior's, same noise


# ----------------------------------------------------------------------------------------------------
# The NMPC without preview (preview=False): it predicts on the reference's tangent at the car's X
# ----------------------------------------------------------------------------------------------------
def _on_reference(X: float, speed: float = 12.0) -> np.ndarray:
    ref = DoubleLaneChangeModel().reference
    return np.array([0.0, 0.0, speed, ref.heading(X), ref.lateral(X), X])


def test_no_preview_on_a_straight_road_is_the_nmpc_with_preview() -> None:
    """On a straight road the tangent line is the true path: preview=False takes the same inputs (1e-9)."""
    cfg = make_config(None, reference={"dy1": 0.0, "dy2": 0.0}, course_length=1.5)
    with_preview = nmpc.VehicleNMPC(cfg, horizon=0.3, gamma=0.99, force="true", preview=True)
    without = nmpc.VehicleNMPC(cfg, horizon=0.3, gamma=0.99, force="true", preview=False)
    # a course (true mean force and noise on v_x): same inputs and states at every step
    res_p, _ = nmpc.drive(with_preview, cfg, seed=0)
    res_n, timing = nmpc.drive(without, cfg, seed=0)
    assert timing["solves"] == cfg.max_steps == 25
    np.testing.assert_allclose(res_n.actions, res_p.actions, rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(res_n.states, res_p.states, rtol=0.0, atol=1e-9)
    assert np.max(np.abs(res_p.actions[:, 1])) > 0.1  # the mean force is compensated: not a trivial run
    # off the lane, sideways and turning, below speed: the whole plan agrees, and it steers
    for s0 in ([0.1, 0.02, 11.8, 0.05, 0.3, 3.0], [-0.2, -0.05, 12.3, -0.1, -0.4, 0.5]):
        with_preview.reset()
        without.reset()
        u_p, u_n = with_preview(np.array(s0)), without(np.array(s0))
        np.testing.assert_allclose(u_n, u_p, rtol=0.0, atol=1e-9)
        np.testing.assert_allclose(without.solution.u, with_preview.solution.u, rtol=0.0, atol=1e-9)
        assert np.max(np.abs(with_preview.solution.u[:, 0])) > 1e-3


def test_no_preview_predicts_on_the_tangent_line() -> None:
    """In the lane change, the plan's objective is the discounted eq. (54) cost against the tangent
    ``Y_ref(X_c) + tan(psi_ref(X_c)) (X - X_c)`` at the car's X, not against the path ahead; and the
    input differs from the one with preview."""
    model = DoubleLaneChangeModel()
    cfg, ref = model.config, model.reference
    gamma = 0.99
    s0 = _on_reference(40.0) + np.array([0.05, 0.01, -0.1, 0.02, 0.15, 0.0])
    without = nmpc.VehicleNMPC(horizon=0.5, gamma=gamma, force="prior", preview=False)
    with_preview = nmpc.VehicleNMPC(horizon=0.5, gamma=gamma, force="prior", preview=True)
    u_n, u_p = without(s0), with_preview(s0)
    sol = without.solution
    X_c = s0[5]
    np.testing.assert_allclose(without.line, [X_c, ref.lateral(X_c), math.tan(ref.heading(X_c))], rtol=1e-12)
    s_next, u = sol.x[1:], sol.u

    def cost(y_ref: np.ndarray) -> float:
        # l = T (45 (v_x - 12)^2 + 60 (Y - y_ref)^2 + 800 delta^2 + a_x^2), discounted by gamma^k
        stage = cfg.dt * (45.0 * (s_next[:, 2] - 12.0) ** 2 + 60.0 * (s_next[:, 4] - y_ref) ** 2
                          + 800.0 * u[:, 0] ** 2 + u[:, 1] ** 2)
        return float(np.sum(gamma ** np.arange(len(stage)) * stage))

    line = ref.lateral(X_c) + math.tan(ref.heading(X_c)) * (s_next[:, 5] - X_c)
    assert sol.objective == pytest.approx(cost(line), rel=1e-9, abs=1e-12)
    # the check discriminates: the same plan costs measurably more or less against the true path
    assert abs(cost(ref.lateral(s_next[:, 5])) - sol.objective) > 1e-3 * sol.objective
    # the path curves away from the tangent over the horizon: the inputs differ
    assert abs(u_n[0] - u_p[0]) > 1e-3
    assert with_preview.line is None


def test_no_preview_differs_from_preview_on_the_lane_change() -> None:
    """A few steps into the first lane change (X from 35 m): the two controllers steer differently."""
    cfg = make_config(None, course_length=36.0)
    start = _on_reference(35.0)
    runs = {}
    for preview in (True, False):
        ctrl = nmpc.VehicleNMPC(cfg, horizon=0.5, gamma=0.99, force="true", preview=preview)
        s, inputs = start.copy(), []
        for _ in range(5):
            u = ctrl(s)
            inputs.append(u)
            s = np.asarray(ctrl.model.step(s, u)).ravel()
        runs[preview] = np.array(inputs)
    assert np.all(np.abs(runs[True][:, 0] - runs[False][:, 0]) > 1e-3)


@pytest.mark.parametrize("preview", ["no", 0, 1, None, 1.0])
def test_preview_must_be_a_bool(preview: object) -> None:
    with pytest.raises(TypeError, match="^preview:"):
        nmpc.run_reference("nmpc", preview=preview)
    with pytest.raises(TypeError, match="^preview:"):
        nmpc.VehicleNMPC(horizon=0.05, preview=preview)


@pytest.mark.parametrize("controller", ["lqr", "optimum"])
def test_no_preview_is_for_the_nmpc_only(controller: str) -> None:
    with pytest.raises(ValueError, match="^preview:"):
        nmpc.run_reference(controller, preview=False)


def test_run_reference_without_preview() -> None:
    """A short run that starts inside a lane change (the first transition moved to X = -10 m): run_reference
    drives VehicleNMPC(preview=False), records it, and reports the real course's cost."""
    config = {"course_length": 1.2, "reference": {"x1": -10.0}}
    cfg = make_config(None, **config)
    out = nmpc.run_reference("nmpc", gamma=0.99, horizon=0.3, disturbance_mean="prior", seeds=(0,),
                             config=config, preview=False, keep_trajectory=True)
    assert out["preview"] is False and out["force_N"] == pytest.approx(150.0)
    res = out["trajectories"][0]
    runs = {p: nmpc.drive(nmpc.VehicleNMPC(cfg, horizon=0.3, gamma=0.99, force="prior", preview=p), cfg, seed=0)[0]
            for p in (True, False)}
    np.testing.assert_array_equal(res.actions, runs[False].actions)
    assert np.min(np.abs(res.actions[:, 0] - runs[True].actions[:, 0])) > 1e-4
    actions = iter(res.actions)
    replay = evaluate_tracking(lambda obs: next(actions), cfg, seed=0, start_state=res.states[0])
    assert out["cost"] == replay.total_cost
    assert "preview" not in nmpc.run_reference("lqr", seeds=(0,), config={"course_length": 1.2})


def test_horizon_theta_is_checked() -> None:
    cm = nmpc.casadi_tracking_model()
    ca = casadi
    s, u, th = ca.SX.sym("s", 6), ca.SX.sym("u", 2), ca.SX.sym("th", 3)
    cost = ca.Function("l", [s, u, th], [ca.sumsqr(s[4] - th[1]) + ca.sumsqr(u)])
    mpc = nmpc.RecedingHorizon(cm.step, cost, horizon_steps=3)
    assert mpc.n_theta == 3
    s0 = _on_reference(0.0)
    for bad in (None, [0.0, 1.0], [0.0, float("nan"), 0.0]):
        with pytest.raises(ValueError, match="^theta:"):
            mpc.solve(s0, theta=bad)
    plain = nmpc.RecedingHorizon(cm.step, cm.cost, horizon_steps=3)
    with pytest.raises(ValueError, match="^theta:"):
        plain.solve(s0, theta=[0.0, 0.0, 0.0])
