"""The two eq. 17 fits side by side on the clouds the UKF's cold magnetometer start really fits.

The cold start (:func:`onlinecal.ukf.attitude_init.ellipsoid_gn`, hand-written LM with the analytic
Jacobian) and the batch's :func:`onlinecal.batch.ellipsoid.fit_norm_lm` (scipy ``least_squares``, method
"lm", analytic Jacobian) are run on the same raw clouds (recorded from cold replays of simulated paper
sessions) from the same sphere start. Prints the time per call of each and the largest parameter
difference in units of the cold fit's σ. Issue 14 asks for one eq. 17 fit if the batch's is not slower.

    python benchmarks/bench_eq17_fits.py [--seeds 1 2 3] [--repeat 5]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import onlinecal.ukf.attitude_init as ai
from onlinecal.batch.ellipsoid import fit_norm_lm
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
    t_gn = t_lm = 0.0
    dz = []
    for x, o0, M0 in cs:
        t0 = time.perf_counter()
        for _ in range(a.repeat):
            o1, M1, c1, _ = ai.ellipsoid_gn(x, o0, M0)
        t1 = time.perf_counter()
        for _ in range(a.repeat):
            f = fit_norm_lm(x, 1.0, o0, M0, model="full", max_nfev=80)
        t2 = time.perf_counter()
        t_gn, t_lm = t_gn + t1 - t0, t_lm + t2 - t1
        sd = np.sqrt(np.clip(np.diag(c1), 1e-300, None))
        dz.append(float(np.max(np.abs(np.concatenate([o1, M1[iu]]) - np.concatenate([f.o, f.M[iu]])) / sd)))
    k = a.repeat * len(cs)
    print(f"{len(cs)} clouds of {[c[0].shape[0] for c in cs]} samples")
    print(f"per call: ellipsoid_gn {t_gn / k * 1e3:.2f} ms, fit_norm_lm {t_lm / k * 1e3:.2f} ms "
          f"(ratio {t_lm / t_gn:.2f})")
    print(f"largest parameter difference: {max(dz):.3g} σ of the cold fit")


if __name__ == "__main__":
    main()
