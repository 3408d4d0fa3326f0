"""Physical validation of eq. (53) with the Fiala tire, against textbook vehicle dynamics.

Reference values are computed here from textbook formulas (linear bicycle model, Fiala law as written
in EQUATIONS.md), never from the code under test.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.optimize import root

from mixedrl.envs.vehicle import VehicleDynamics, VehicleParams, fiala_lateral_force

P = VehicleParams()
T = 1.0 / 200.0


def textbook_fiala(alpha: float, C: float, mu: float, Fz: float) -> float:
    """The piecewise Fiala law exactly as written in EQUATIONS.md ("Facts")."""
    alpha_sl = math.atan(3.0 * mu * Fz / C)
    if abs(alpha) < alpha_sl:
        t = math.tan(alpha)
        return -C * t + C**2 / (3 * mu * Fz) * abs(t) * t - C**3 / (27 * mu**2 * Fz**2) * t**3
    return -mu * Fz * math.copysign(1.0, alpha)


# ------------------------------------------------------------------------------------------------------
# parameters
# ------------------------------------------------------------------------------------------------------
def test_paper_parameters() -> None:
    assert (P.m, P.I_z, P.a, P.b, P.C_f, P.C_r, P.mu) == (1500.0, 2420.0, 1.14, 1.40, 88000.0, 94000.0, 1.0)
    assert P.F_zf + P.F_zr == pytest.approx(P.m * P.g, rel=1e-14)
    # moment balance about the centre of gravity: F_zf a = F_zr b
    assert P.F_zf * P.a == pytest.approx(P.F_zr * P.b, rel=1e-14)


@pytest.mark.parametrize("field", ["m", "I_z", "a", "b", "C_f", "C_r", "mu", "g"])
@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
def test_params_reject_bad_values(field: str, bad: float) -> None:
    with pytest.raises(ValueError, match=f"^{field}"):
        VehicleParams(**{field: bad})


# ------------------------------------------------------------------------------------------------------
# Fiala tire
# ------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("C, Fz", [(P.C_f, P.F_zf), (P.C_r, P.F_zr)])
def test_fiala_matches_piecewise_textbook_law(C: float, Fz: float) -> None:
    alphas = np.linspace(-0.8, 0.8, 4001)
    got = fiala_lateral_force(alphas, C, P.mu, Fz)
    want = np.array([textbook_fiala(a, C, P.mu, Fz) for a in alphas])
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9 * Fz)
    # same values from the torch and float paths
    np.testing.assert_allclose(fiala_lateral_force(torch.tensor(alphas), C, P.mu, Fz).numpy(), want,
                               rtol=0, atol=1e-9 * Fz)
    assert fiala_lateral_force(float(alphas[1234]), C, P.mu, Fz) == pytest.approx(want[1234], abs=1e-9 * Fz)


@pytest.mark.parametrize("C, Fz", [(P.C_f, P.F_zf), (P.C_r, P.F_zr)])
def test_fiala_slope_continuity_saturation(C: float, Fz: float) -> None:
    mu = P.mu
    # slope -C at zero slip (central difference, truncation error O(h^2) ~ C h^2 / (mu Fz) ~ 1e-6 C)
    h = 1e-6
    slope = (fiala_lateral_force(h, C, mu, Fz) - fiala_lateral_force(-h, C, mu, Fz)) / (2 * h)
    assert slope == pytest.approx(-C, rel=1e-5)
    # continuity at alpha_sl (value and slope): jump -> 0 as the gap shrinks
    alpha_sl = math.atan(3 * mu * Fz / C)
    for eps in (1e-4, 1e-6):
        left = fiala_lateral_force(alpha_sl - eps, C, mu, Fz)
        right = fiala_lateral_force(alpha_sl + eps, C, mu, Fz)
        assert abs(left - right) < 1e-3 * mu * Fz * (eps / 1e-4) ** 2 + 1e-9 * Fz
    # saturation at mu F_z, sign opposite to the slip, and never larger in magnitude
    for a in (alpha_sl, 0.5, 1.0, 1.5):
        assert fiala_lateral_force(a, C, mu, Fz) == pytest.approx(-mu * Fz, rel=1e-12)
        assert fiala_lateral_force(-a, C, mu, Fz) == pytest.approx(mu * Fz, rel=1e-12)
    grid = np.linspace(-1.5, 1.5, 3001)
    F = fiala_lateral_force(grid, C, mu, Fz)
    assert np.all(np.abs(F) <= mu * Fz * (1 + 1e-12))
    assert np.all(F[grid > 0] < 0) and np.all(F[grid < 0] > 0)


def test_fiala_rejects_bad_parameters() -> None:
    with pytest.raises(ValueError, match="^F_z"):
        fiala_lateral_force(0.1, C=1.0, mu=1.0, F_z=-1.0)


# ------------------------------------------------------------------------------------------------------
# eq. (53): steady state, signs, straight driving
# ------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("delta", [0.001, 0.005])
def test_steady_state_yaw_gain_matches_linear_bicycle(delta: float) -> None:
    """At 12 m/s, r/delta = v / (L + K_us v^2), K_us = m b/(L C_f) - m a/(L C_r), within 2%."""
    dyn = VehicleDynamics(P)
    v = 12.0

    def residual(z: np.ndarray) -> np.ndarray:
        vy, r, ax = z  # a_x holds v_x constant (cruise control), as the textbook steady state assumes
        return dyn.derivatives(np.array([vy, r, v, 0.0, 0.0]), np.array([delta, ax]))[:3]

    sol = root(residual, np.zeros(3), method="hybr", tol=1e-14)
    assert np.max(np.abs(residual(sol.x))) < 1e-9
    L = P.a + P.b
    K_us = P.m * P.b / (L * P.C_f) - P.m * P.a / (L * P.C_r)
    gain_textbook = v / (L + K_us * v**2)
    gain = sol.x[1] / delta
    assert abs(gain / gain_textbook - 1.0) < 0.02
    # the steady state is also reached by the discrete f (forward Euler) from rest in the yaw plane
    x = np.array([0.0, 0.0, v, 0.0, 0.0])
    for _ in range(2000):  # 10 s >> lateral time constants (~0.1 s)
        x = dyn(x, np.array([delta, sol.x[2]]))
    assert x[1] / delta == pytest.approx(gain, rel=1e-6)


def test_left_steer_turns_left() -> None:
    dyn = VehicleDynamics(P)
    x = np.array([0.0, 0.0, 12.0, 0.0, 0.0, 0.0])
    for _ in range(200):  # 1 s of a small left steer
        x = dyn(x, np.array([0.02, 0.0]))
    vy, r, vx, phi, Y, X = x
    assert r > 0 and phi > 0 and Y > 0  # yaw rate, heading and lateral position all to the left
    assert X > 11.0
    # and a right steer is the mirror image (the model is symmetric)
    x_r = np.array([0.0, 0.0, 12.0, 0.0, 0.0, 0.0])
    for _ in range(200):
        x_r = dyn(x_r, np.array([-0.02, 0.0]))
    np.testing.assert_allclose(x_r * np.array([-1, -1, 1, -1, -1, 1]), x, rtol=0, atol=1e-12)


def test_no_input_no_disturbance_goes_straight() -> None:
    dyn = VehicleDynamics(P)
    x = np.array([0.0, 0.0, 12.0, 0.0, 0.0, 0.0])
    for _ in range(1000):
        x = dyn(x, np.zeros(2))
    np.testing.assert_array_equal(x[[0, 1, 3, 4]], 0.0)
    assert x[2] == 12.0
    assert x[5] == pytest.approx(12.0 * 1000 * T, rel=1e-12)


def test_derivatives_rows_are_eq53() -> None:
    """Each row of eq. (53), recomputed here from the textbook Fiala law."""
    dyn = VehicleDynamics(P)
    rng = np.random.default_rng(0)
    for _ in range(20):
        vy, r, vx, phi, Y, X = rng.normal(0, 0.3), rng.normal(0, 0.3), rng.uniform(5, 20), rng.normal(0, 0.5), 0.3, 7.0
        delta, ax, f_dis = rng.normal(0, 0.1), rng.normal(0, 1), rng.normal(261, 6)
        fyf = textbook_fiala(math.atan((vy + P.a * r) / vx) - delta, P.C_f, P.mu, P.F_zf)
        fyr = textbook_fiala(math.atan((vy - P.b * r) / vx), P.C_r, P.mu, P.F_zr)
        want = [
            (fyf * math.cos(delta) + fyr) / P.m - vx * r,
            (P.a * fyf * math.cos(delta) - P.b * fyr) / P.I_z,
            ax + vy * r - fyf * math.sin(delta) / P.m + f_dis / P.m,
            r,
            vx * math.sin(phi) + vy * math.cos(phi),
            vx * math.cos(phi) - vy * math.sin(phi),
        ]
        got = dyn.derivatives(np.array([vy, r, vx, phi, Y, X]), np.array([delta, ax]), f_dis)
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
        got5 = dyn.derivatives(np.array([vy, r, vx, phi, Y]), np.array([delta, ax]), f_dis)
        np.testing.assert_array_equal(got5, got[:5])


# ------------------------------------------------------------------------------------------------------
# discretisation
# ------------------------------------------------------------------------------------------------------
def test_euler_step_is_x_plus_T_xdot(rng: np.random.Generator) -> None:
    dyn = VehicleDynamics(P)
    x = np.column_stack([rng.normal(0, 0.3, 50), rng.normal(0, 0.2, 50), rng.uniform(8, 16, 50),
                         rng.normal(0, 0.2, 50), rng.normal(0, 1, 50), rng.uniform(0, 100, 50)])
    u = np.column_stack([rng.normal(0, 0.05, 50), rng.normal(0, 1, 50)])
    np.testing.assert_allclose(dyn(x, u), x + T * dyn.derivatives(x, u), rtol=1e-15, atol=1e-13)


def test_scheme_orders_of_accuracy() -> None:
    """Forward Euler is first order and RK4 fourth order on eq. (53) (errors vs a fine RK4 solution)."""
    x0 = np.array([0.0, 0.0, 12.0, 0.0, 0.0, 0.0])
    u = np.array([0.03, 0.5])
    horizon = 0.5

    def run(scheme: str, dt: float) -> np.ndarray:
        dyn = VehicleDynamics(P, dt=dt, scheme=scheme)
        x = x0.copy()
        for _ in range(round(horizon / dt)):
            x = dyn(x, u)
        return x

    ref = run("rk4", 1 / 6400)
    e_euler = [np.max(np.abs(run("euler", dt) - ref)) for dt in (1 / 200, 1 / 400)]
    e_rk4 = [np.max(np.abs(run("rk4", dt) - ref)) for dt in (1 / 50, 1 / 100)]
    assert 1.8 < e_euler[0] / e_euler[1] < 2.2
    assert 12.0 < e_rk4[0] / e_rk4[1] < 20.0


# ------------------------------------------------------------------------------------------------------
# torch path: batching, dtypes, gradients, backends agree
# ------------------------------------------------------------------------------------------------------
def random_states(n: int, gen: torch.Generator, dtype: torch.dtype = torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    x = torch.stack([
        0.3 * torch.randn(n, generator=gen, dtype=dtype), 0.2 * torch.randn(n, generator=gen, dtype=dtype),
        8 + 8 * torch.rand(n, generator=gen, dtype=dtype), 0.2 * torch.randn(n, generator=gen, dtype=dtype),
        torch.randn(n, generator=gen, dtype=dtype), 100 * torch.rand(n, generator=gen, dtype=dtype)], dim=-1)
    u = torch.stack([0.05 * torch.randn(n, generator=gen, dtype=dtype), torch.randn(n, generator=gen, dtype=dtype)], -1)
    return x, u


def test_torch_numpy_float_paths_agree() -> None:
    dyn = VehicleDynamics(P)
    x, u = random_states(64, torch.Generator().manual_seed(1))
    t = dyn(x, u).numpy()
    n = dyn(x.numpy(), u.numpy())
    np.testing.assert_allclose(t, n, rtol=1e-14, atol=1e-14)
    for i in range(0, 64, 13):
        s = dyn.step_scalar(tuple(x[i].tolist()), tuple(u[i].tolist()))
        np.testing.assert_allclose(s, n[i], rtol=1e-14, atol=1e-14)


def test_batched_over_leading_dims_and_dtypes() -> None:
    dyn = VehicleDynamics(P)
    x, u = random_states(12, torch.Generator().manual_seed(2))
    out = dyn(x.reshape(3, 4, 6), u.reshape(3, 4, 2))
    assert out.shape == (3, 4, 6)
    np.testing.assert_array_equal(out.reshape(12, 6).numpy(), dyn(x, u).numpy())
    out32 = dyn(x.float(), u.float())
    assert out32.dtype == torch.float32
    np.testing.assert_allclose(out32.double().numpy(), dyn(x, u).numpy(), rtol=1e-5, atol=1e-5)
    # the paper's 5-state x gives the first five components of the tracking step
    np.testing.assert_array_equal(dyn(x[:, :5], u).numpy(), dyn(x, u)[:, :5].numpy())


def test_gradcheck_f_float64() -> None:
    dyn = VehicleDynamics(P)
    x, u = random_states(6, torch.Generator().manual_seed(3))
    x[:3, 0] += 4.0  # |alpha| ~ 0.3-0.5 rad > alpha_sl: both tires in the saturated branch
    x.requires_grad_(True)
    u.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: dyn(a, b), (x, u), eps=1e-6, atol=1e-6, rtol=1e-5)
    assert torch.autograd.gradcheck(lambda a, b: dyn.derivatives(a, b), (x, u), eps=1e-6, atol=1e-5, rtol=1e-5)


def test_bad_inputs_raise() -> None:
    dyn = VehicleDynamics(P)
    with pytest.raises(ValueError, match="^x"):
        dyn(np.zeros(4), np.zeros(2))
    with pytest.raises(ValueError, match="^u"):
        dyn(np.zeros(5), np.zeros(3))
    with pytest.raises(ValueError, match="^u"):
        dyn(np.array([0, 0, 12.0, 0, 0]), np.array([np.nan, 0.0]))
    with pytest.raises(ValueError, match="^x"):
        dyn(torch.zeros(5), np.zeros(2))
    with pytest.raises(ValueError, match="^u"):
        dyn(torch.zeros(5), torch.zeros(2, dtype=torch.float64))
    with pytest.raises(ValueError, match="^dt"):
        VehicleDynamics(P, dt=0.0)
    with pytest.raises(ValueError, match="^scheme"):
        VehicleDynamics(P, scheme="midpoint")
    with pytest.raises(ValueError, match="^params"):
        VehicleDynamics({"m": 1500.0})  # type: ignore[arg-type]


def test_compiled_equals_eager() -> None:
    """torch.compile path (one float64 compile, ~10 s) equals eager, values and gradients."""
    eager = VehicleDynamics(P)
    fused = VehicleDynamics(P, compile=True)
    x, u = random_states(256, torch.Generator().manual_seed(4))
    x.requires_grad_(True)
    y_c = fused(x, u)
    y_e = eager(x, u)
    assert not fused._compile_failed, "torch.compile fell back to eager"
    np.testing.assert_allclose(y_c.detach().numpy(), y_e.detach().numpy(), rtol=1e-13, atol=1e-12)
    (g_c,) = torch.autograd.grad(y_c.square().sum(), x)
    (g_e,) = torch.autograd.grad(y_e.square().sum(), x)
    np.testing.assert_allclose(g_c.numpy(), g_e.numpy(), rtol=1e-11, atol=1e-11)
