"""Information leaking into a direction the data cannot see: repeated magnetometer updates at one attitude.

At one attitude a magnetometer's 3-vector cannot separate the heading from the bias across the field, nor the dip
from the bias in the north-up plane: a 2-D null space. A consistent filter keeps its σ along it however many
samples arrive. This script measures, side by side:

1. the project's own unscented update (:func:`onlinecal.ukf.unscented.update`, the scaled sigma points of
   :func:`onlinecal.ukf.unscented.sigma_points`) on a 5-term model — heading ψ, dip δ, bias b (3) —
   h = Rz(ψ)ᵀ (0, F cos δ, −F sin δ) + b, padded to the filter's 40 states with unrelated terms, the truth at the
   prior's mean: N sequential updates, and the same N samples as one update of their mean (what a rest does);
   and the remedy of :mod:`onlinecal.ukf.learning` (session 19): the first look learns, the others hold the bias
   and dip as consider states;
2. the filter itself (:class:`onlinecal.ukf.OnlineCalibrator`) on the first 34 s of a simulated 180-s fixed-wing
   flight, its disarmed ground rest (still), started from the truth (σ of ``flight_stats.truth_start``): with its
   rest update (one measurement per rest), with rests turned off (``rest_blocks`` = 10⁹: every block a motion
   update, as an armed vehicle on the ground or a straight and level leg gets), and the same with every motion
   block learning (``learn_angle_deg`` = 0: the filter before session 19).

    PYTHONPATH=. python benchmarks/nullspace_leak.py
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from onlinecal.sim import simulate
from onlinecal.ukf import OnlineCalibrator, UKFConfig
from onlinecal.ukf.layout import NAMES
from onlinecal.ukf.unscented import Gating, Measurement, merwe_weights, sigma_points, update

sys.path.insert(0, str(Path(__file__).resolve().parent))
from flight_stats import truth_start  # noqa: E402

F, DIP = 0.5, np.radians(64.0)  # raw field and dip of the simulator's field
PRIOR = (0.1, 0.04, 0.02, 0.02, 0.02)  # σ ψ (rad), δ (rad), b (raw)


def _h(X: np.ndarray) -> np.ndarray:
    c, s = np.cos(X[:, 0]), np.sin(X[:, 0])
    hy, hz = F * np.cos(X[:, 1]), -F * np.sin(X[:, 1])
    return np.stack([s * hy + X[:, 2], c * hy + X[:, 3], hz + X[:, 4]], 1)


def toy(alpha: float, sigma_r: float, n_updates: int, pad: int = 35, seed: int = 0) -> dict[str, float]:
    """σ of ψ and its error in σ after ``n_updates`` sequential updates, and after one update of their mean."""
    n = 5 + pad
    x0 = np.zeros(n)
    x0[1] = DIP
    P0 = np.diag([s**2 for s in PRIOR] + [0.01**2] * pad)
    truth = x0.copy()
    rng = np.random.default_rng(seed)
    zs = _h(truth[None])[0] + rng.normal(0.0, sigma_r, (n_updates, 3))
    Wm, Wc = merwe_weights(n, alpha, 2.0, 0.0)
    perm = np.arange(n)
    none = np.zeros(n, bool)
    gate = Gating({"mag": 1e12}, True)

    def one(x: np.ndarray, P: np.ndarray, z: np.ndarray, r: float) -> tuple[np.ndarray, np.ndarray]:
        X = sigma_points(x, P, alpha, 0.0, perm, True)
        res = update(X - x, x, P, [Measurement("mag", z, _h(X), np.full(3, r))], Wm, Wc, gate, none)
        return res.x, 0.5 * (res.P + res.P.T)

    x, P = x0, P0
    for z in zs:
        x, P = one(x, P, z, sigma_r**2)
    xm, Pm = one(x0, P0, zs.mean(0), sigma_r**2 / n_updates)
    held = np.zeros(n, bool)
    held[1:5] = True
    xh, Ph = x0, P0
    for k, z in enumerate(zs):
        X = sigma_points(xh, Ph, alpha, 0.0, perm, True)
        res = update(X - xh, xh, Ph, [Measurement("mag", z, _h(X), np.full(3, sigma_r**2))], Wm, Wc, gate,
                     held if k else none)
        xh, Ph = res.x, 0.5 * (res.P + res.P.T)
    return {"seq_sigma": float(np.sqrt(P[0, 0])), "seq_z": float((x[0] - truth[0]) / np.sqrt(P[0, 0])),
            "mean_sigma": float(np.sqrt(Pm[0, 0])), "mean_z": float((xm[0] - truth[0]) / np.sqrt(Pm[0, 0])),
            "held_sigma": float(np.sqrt(Ph[0, 0])), "held_z": float((xh[0] - truth[0]) / np.sqrt(Ph[0, 0]))}


def still_flight(rest: bool, seconds: int = 34, learn_angle_deg: float | None = None
                 ) -> list[tuple[float, float, float, float]]:
    """(t, σ heading °, σ mag.bias.y, its error in σ) of the filter on the fixed-wing's ground rest."""
    sim = simulate("fixedwing", 3, duration=180.0, imu_rate=200.0, mag_rate=50.0, earth_rate=False)
    T = sim.truth.calibration
    assert T.mag is not None
    c = UKFConfig() if rest else UKFConfig(rest_blocks=10**9)
    if learn_angle_deg is not None:
        c = replace(c, learn_angle_deg=learn_angle_deg)
    cal = OnlineCalibrator(truth_start(T), c)
    cal.new_log()
    i = NAMES.index("mag.bias.y")
    out = []
    for k in range(seconds):
        cal.feed(sim.data.slice_imu(200 * k, 200 * (k + 1)))
        if k + 1 in (1, 3, 5, 10, 20, seconds):
            up = cal.R_nom[2]
            sh = float(np.degrees(np.sqrt(up @ cal.P[:3, :3] @ up)))
            sb = float(np.sqrt(cal.P[i, i]))
            out.append((k + 1.0, sh, sb, float((cal.x[i] - T.mag.bias[1]) / sb)))
    return out


def main() -> None:
    print("1. the unscented update on h = Rz(psi)^T (0, F cos dip, -F sin dip) + b, 40 states, truth at the prior mean")
    print(f"   prior sigma psi {PRIOR[0]} rad; N samples applied one by one vs once as their mean")
    for alpha in (0.3, 1.0):
        for sr in (5e-4, 5e-5):
            for n in (10, 100, 400):
                r = toy(alpha, sr, n)
                print(f"   alpha {alpha:3.1f}  sigma_r {sr:.0e}  N {n:4d}: one by one sigma psi {r['seq_sigma']:.4f}"
                      f" (error {r['seq_z']:+5.2f} sigma) | their mean once {r['mean_sigma']:.4f}"
                      f" ({r['mean_z']:+5.2f} sigma) | held after the first {r['held_sigma']:.4f}"
                      f" ({r['held_z']:+5.2f} sigma)")
    print("2. the filter on a still sensor (fixed-wing seed 3's ground rest, started from the truth)")
    for rest, angle in ((True, None), (False, None), (False, 0.0)):
        label = "rest updates (default)" if rest else "every block a motion update (rest_blocks = 1e9)"
        if angle is not None:
            label += ", every one learning (learn_angle_deg = 0: before session 19)"
        print(f"   {label}:")
        for t, sh, sb, z in still_flight(rest, learn_angle_deg=angle):
            print(f"     t {t:4.0f} s: sigma heading {sh:5.2f} deg, mag.bias.y sigma {sb:.4f}, error {z:+5.2f} sigma")


if __name__ == "__main__":
    main()
