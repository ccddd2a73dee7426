"""The one eq. 17 fit against scipy's Levenberg–Marquardt on the clouds the UKF's cold magnetometer start fits.

The package has one geometric ellipsoid fit, :func:`onlinecal.batch.ellipsoid.fit_norm_lm` (the batch's mag
and accel fits; the UKF's cold start :func:`onlinecal.ukf.attitude_init.ellipsoid_gn` calls it): a
hand-written Levenberg–Marquardt (:func:`onlinecal.batch.ellipsoid.levenberg_marquardt`) with the analytic
Jacobian. Until issue 14 the batch minimised the same residuals with scipy's ``least_squares`` (method
"lm", ``x_scale="jac"``), 2–3× slower per call. This benchmark runs both minimisers on the same residuals
and Jacobian (:func:`onlinecal.batch.ellipsoid._resid_jac_full`), from the same sphere start, on the raw
clouds recorded from cold replays of simulated paper sessions, and prints the time per call of each and the
largest parameter difference in units of the fit's own σ.

    python benchmarks/bench_eq17_fits.py [--seeds 1 2 3] [--repeat 5]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.optimize import least_squares

import onlinecal.ukf.attitude_init as ai
from onlinecal.batch.ellipsoid import _resid_jac_full, levenberg_marquardt
from onlinecal.sim import simulate
from onlinecal.ukf import replay


def clouds(seeds: list[int]) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(x (N, 3), o0 (3,), M0 (3, 3)) of every cold-start ellipsoid fit in cold replays of these seeds."""
    out = []
    orig = ai.ellipsoid_gn

    def rec(x, o0, M0, *a, **k):  # type: ignore[no-untyped-def]
        out.append((x.copy(), o0.copy(), M0.copy()))
        return orig(x, o0, M0, *a, **k)

    ai.ellipsoid_gn = rec
    try:
        for seed in seeds:
            replay([simulate("paper", seed, duration=150.0).data], None)
    finally:
        ai.ellipsoid_gn = orig
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--repeat", type=int, default=5)
    a = ap.parse_args()
    cs = clouds(a.seeds)
    iu = np.triu_indices(3)
    t_own = t_scipy = 0.0
    dz = []
    for x, o0, M0 in cs:
        p0 = np.concatenate([o0, M0[iu]])

        def fun(p: np.ndarray, x: np.ndarray = x) -> tuple[np.ndarray, np.ndarray]:
            return _resid_jac_full(p, x, 1.0)

        t0 = time.perf_counter()
        for _ in range(a.repeat):
            p1 = levenberg_marquardt(fun, p0, 200)
        t1 = time.perf_counter()
        for _ in range(a.repeat):
            p2 = least_squares(lambda p: fun(p)[0], p0, jac=lambda p: fun(p)[1], method="lm", x_scale="jac",
                               max_nfev=200).x
        t2 = time.perf_counter()
        t_own, t_scipy = t_own + t1 - t0, t_scipy + t2 - t1
        r, J = fun(p1)
        sd = np.sqrt(np.diag(np.linalg.inv(J.T @ J)) * float(r @ r) / max(1, r.size - 9))
        dz.append(float(np.max(np.abs(p1 - p2) / sd)))
    k = a.repeat * len(cs)
    print(f"{len(cs)} clouds of {[c[0].shape[0] for c in cs]} samples")
    print(f"per call: levenberg_marquardt {t_own / k * 1e3:.2f} ms, scipy least_squares {t_scipy / k * 1e3:.2f} ms "
          f"(ratio {t_scipy / t_own:.2f})")
    print(f"largest parameter difference: {max(dz):.3g} σ of the fit")


if __name__ == "__main__":
    main()
