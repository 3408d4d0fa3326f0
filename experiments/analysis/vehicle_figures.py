"""Make the figures of docs/vehicle.rst: the reference path and one run of the double lane change.

The run uses a discounted LQR designed on the linearisation of the shared ``f`` at 12 m/s straight
driving (python-control ``dlqr`` with the eq. (54) weights), acting on the paper's 5-dim observation
``[v_y, r, v_x - 12, e_phi, e_y]``; it knows nothing of the disturbance. It is a reference controller
for the docs, not one of the paper's methods.

Usage: ``PYTHONPATH=. python experiments/analysis/vehicle_figures.py [outdir]`` (default ``docs/_static``).
"""

from __future__ import annotations

import sys
from pathlib import Path

import control
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from mixedrl.envs import DoubleLaneChangeModel, evaluate_tracking  # noqa: E402


def lqr_gain(model: DoubleLaneChangeModel, gamma: float = 0.99) -> np.ndarray:
    """Gain ``K`` of ``u = -K o`` from the central-difference linearisation of ``f`` in the error coordinates."""
    cfg = model.config

    def f5(z: np.ndarray, u: np.ndarray) -> np.ndarray:
        s = np.array([z[0], z[1], z[2] + cfg.v_des, z[3], z[4], 0.0])  # straight road section: e = (phi, Y)
        n = model.step(s, u)
        return np.array([n[0], n[1], n[2] - cfg.v_des, n[3], n[4]])

    h = 1e-6
    A = np.column_stack([(f5(h * e, np.zeros(2)) - f5(-h * e, np.zeros(2))) / (2 * h) for e in np.eye(5)])
    B = np.column_stack([(f5(np.zeros(5), h * e) - f5(np.zeros(5), -h * e)) / (2 * h) for e in np.eye(2)])
    Q = cfg.dt * np.diag([0.0, 0.0, cfg.q_speed, 0.0, cfg.q_lateral])
    R = cfg.dt * np.diag([cfg.r_steer, cfg.r_accel])
    K, _, _ = control.dlqr(np.sqrt(gamma) * A, np.sqrt(gamma) * B, Q, R)
    return np.asarray(K)


def main(outdir: Path) -> None:
    outdir.mkdir(parents=True, exist_ok=True)
    model = DoubleLaneChangeModel()
    ref = model.reference
    X = np.linspace(0.0, model.config.course_length, 1201)

    fig, ax = plt.subplots(2, 1, figsize=(7, 4.2), sharex=True)
    ax[0].plot(X, ref.lateral(X), "k")
    ax[0].set_ylabel(r"$Y_{ref}$ [m]")
    ax[1].plot(X, ref.heading(X), "k")
    ax[1].set_ylabel(r"$\psi_{ref}$ [rad]")
    ax[1].set_xlabel(r"$X$ [m]")
    ax[0].set_title("Double-lane-change reference")
    for a in ax:
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(outdir / "vehicle_reference.png", dpi=110)
    plt.close(fig)

    K = lqr_gain(model)
    res = evaluate_tracking(lambda o: -K @ o[:5], seed=0)
    t, s = res.time, res.states
    fig, ax = plt.subplots(4, 1, figsize=(7, 8), sharex=True)
    ax[0].plot(t, ref.lateral(s[:, 5]), "k--", label=r"$Y_{ref}(X)$")
    ax[0].plot(t, s[:, 4], "C0", label=r"$Y$")
    ax[0].set_ylabel("[m]")
    ax[0].legend(loc="upper right")
    ax[0].set_title(f"LQR on the 5-dim observation: mean |e_y| = {res.mean_abs_lateral_error:.3f} m, "
                    f"mean |v_x - 12| = {res.mean_abs_speed_error:.3f} m/s", fontsize=9)
    ax[1].plot(t, res.lateral_error, "C0")
    ax[1].set_ylabel(r"$e_y$ [m]")
    ax[2].plot(t, res.speed_error, "C1")
    ax[2].set_ylabel(r"$v_x - 12$ [m/s]")
    ax[3].plot(t[1:], res.actions[:, 0], "C2", label=r"$\delta$ [rad]")
    ax[3].plot(t[1:], res.actions[:, 1] / 10, "C3", label=r"$a_x / 10$ [m/s$^2$]")
    ax[3].set_ylabel("input")
    ax[3].set_xlabel("t [s]")
    ax[3].legend(loc="upper right")
    for a in ax:
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(outdir / "vehicle_run.png", dpi=110)
    plt.close(fig)
    (outdir / "vehicle_run.txt").write_text(
        f"gain K =\n{np.array2string(K, precision=5)}\n"
        f"mean_abs_lateral_error_m {res.mean_abs_lateral_error:.6f}\n"
        f"mean_abs_speed_error_mps {res.mean_abs_speed_error:.6f}\n"
        f"max_abs_lateral_error_m {res.max_abs_lateral_error:.6f}\n"
        f"max_abs_speed_error_mps {res.max_abs_speed_error:.6f}\n")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("docs/_static"))
