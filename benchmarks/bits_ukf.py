"""Bit-identity check of the online filter across code changes (issue 15's rounds: a speed change must keep the
filter's arithmetic). Replays six logs and saves, or compares with a saved run, the final state x, covariance P,
attitude R_nom, the events with their details, the NIS bookkeeping, the motion coverage (rates, angles, flight time,
the field cells swept and the rests' gravity directions) and every trace row —
``np.array_equal``, NaN-aware, not a tolerance.

The logs: a cold 120-s flight whose vehicle detector switches on, the 10-min benchmark flight
(``bench_ukf.py``'s) cold and from its calibration (the magnetometer in use at every block), a cold 200-s
paper session (the magnetometer's cold start, hold offsets), a 90-s multirotor flight and an 80-s paper
session with a magnetic disturbance started from the truth.

    PYTHONPATH=. python benchmarks/bits_ukf.py save /tmp/before.pkl   # on the commit before
    PYTHONPATH=. python benchmarks/bits_ukf.py cmp /tmp/before.pkl    # on the change: exit 1 if any differs

``cmp`` also prints, for a log that differs, its largest relative differences (x against max(|x|, σ), P against
σ_i σ_j, the trace's estimates against max(|value|, σ)) and whether the events with their details are the same:
a change that reorders arithmetic is judged by them (issue 15, eighth round: rounding level, the same events).

``--backend numpy`` checks the reference path; ``ONLINECAL_FASTPATH=0`` in the environment the general numba path.
"""

from __future__ import annotations

import argparse
import math
import os
import pickle
import re
import sys
import warnings
from typing import Any

for _v in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402

from onlinecal.sim import simulate  # noqa: E402
from onlinecal.sim.effects import MagDisturbance  # noqa: E402
from onlinecal.ukf import OnlineCalibrator, kernels  # noqa: E402


def logs() -> Any:
    """(name, data, init) of the six logs."""
    yield "flight120", simulate("flight", 3, duration=120, imu_rate=200).data, None
    sim = simulate("flight", 0, duration=600, imu_rate=200)
    yield "flight600", sim.data, None
    # the same flight from its calibration: the magnetometer in use at every block (replay's default start)
    yield "flight600warm", sim.data, sim.truth.calibration
    yield "paper200", simulate("paper", 1, duration=200).data, None
    yield "multirotor90", simulate("multirotor", 2, duration=90, imu_rate=200).data, None
    eff = MagDisturbance(start=55.0, duration=6.0, amplitude=0.5, direction=(1.0, 0.5, 0.0))
    sim = simulate("paper", 1, duration=80.0, effects=[eff])
    yield "paperdist", sim.data, sim.truth.calibration


def snapshot(cal: OnlineCalibrator) -> dict[str, Any]:
    cov = cal._coverage
    return {"x": cal.x.copy(), "P": cal.P.copy(), "R": cal.R_nom.copy(),
            "events": [(e["kind"], e["t"], e["detail"]) for e in cal.events], "nis": repr(cal._nis.stats),
            "coverage": (cov.max_rate.copy(), cov.angle.copy(), cov.flight_s, cov.mag_dirs.copy(),
                         np.asarray(cov.rest_dirs, float)), "blocks": cal._n_blocks,
            "trace": [list(r.items()) for r in cal.trace_rows()]}


def same(a: dict[str, Any], b: dict[str, Any]) -> bool:
    """Every field equal to the last bit (NaN equal to NaN in the trace)."""
    if not (np.array_equal(a["x"], b["x"]) and np.array_equal(a["P"], b["P"]) and np.array_equal(a["R"], b["R"])
            and a["events"] == b["events"] and a["nis"] == b["nis"] and a["blocks"] == b["blocks"]
            and all(np.array_equal(u, v) for u, v in zip(a["coverage"], b["coverage"], strict=True))
            and len(a["trace"]) == len(b["trace"])):
        return False
    for ra, rb in zip(a["trace"], b["trace"], strict=True):
        if [k for k, _ in ra] != [k for k, _ in rb]:
            return False
        if not np.array_equal([v for _, v in ra], [v for _, v in rb], equal_nan=True):
            return False
    return True


def _rounded(text: str) -> str:
    """A repr with every float to 8 significant digits (the NIS bookkeeping's sums and window means)."""
    return re.sub(r"-?\d+\.\d+(e-?\d+)?", lambda m: f"{float(m.group(0)):.8g}", text)


def differences(a: dict[str, Any], b: dict[str, Any]) -> tuple[float, float, float, bool, bool]:
    """Where not bit-identical: the largest relative difference of x (against max(|x|, σ)), of P (against
    σ_i σ_j) and of the trace (an estimate against max(|value|, its σ in that row), a σ or NIS against
    max(|value|, the column's largest)); whether the events with their details and the block count are the
    same; whether the NIS bookkeeping is, its floats to 8 digits (σ from b)."""
    sb = np.sqrt(np.abs(np.diag(b["P"])))
    dx = float(np.max(np.abs(a["x"] - b["x"]) / np.maximum(np.maximum(np.abs(b["x"]), sb), 1e-300)))
    dP = float(np.max(np.abs(a["P"] - b["P"]) / np.maximum(np.outer(sb, sb), 1e-300)))
    dt = math.inf
    keys = [k for k, _ in b["trace"][0]] if b["trace"] else []
    if len(a["trace"]) == len(b["trace"]) and all([k for k, _ in r] == keys for r in a["trace"]):
        va = np.array([[v for _, v in r] for r in a["trace"]], dtype=float)
        vb = np.array([[v for _, v in r] for r in b["trace"]], dtype=float)
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            colmax = np.nanmax(np.abs(vb), axis=0)
            scale = np.empty_like(vb)
            for j, k in enumerate(keys):
                sig = f"{k}.sigma"
                scale[:, j] = np.abs(vb[:, keys.index(sig)]) if sig in keys else colmax[j]
            d = np.abs(va - vb) / np.maximum(np.maximum(np.abs(vb), scale), 1e-300)
            d[np.isnan(va) & np.isnan(vb)] = 0.0
            dt = float(np.nanmax(d)) if d.size else 0.0
    same_events = a["events"] == b["events"] and a["blocks"] == b["blocks"]
    return dx, dP, dt, same_events, _rounded(a["nis"]) == _rounded(b["nis"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mode", choices=["save", "cmp"])
    ap.add_argument("path")
    ap.add_argument("--backend", default="numba", choices=["numba", "numpy"])
    args = ap.parse_args()
    out = {}
    with kernels.use_backend(args.backend), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the disturbance's and the cold start's warnings: the events say it
        for name, d, init in logs():
            cal = OnlineCalibrator(init)
            cal.feed(d)
            cal.flush()
            out[name] = snapshot(cal)
            print(f"{name}: {cal._n_blocks} blocks, events {sorted({e[0] for e in out[name]['events']})}")
    if args.mode == "save":
        with open(args.path, "wb") as f:
            pickle.dump(out, f)
        print(f"saved {args.path}")
        return
    with open(args.path, "rb") as f:
        ref = pickle.load(f)  # noqa: S301 (a file this script wrote)
    ok = True
    for name, snap in out.items():
        eq = same(snap, ref[name])
        ok &= eq
        print(f"{name}: {'bit-identical' if eq else 'DIFFERS'} ({len(snap['trace'])} trace rows)")
        if not eq:
            dx, dP, dt, ev, nis = differences(snap, ref[name])
            print(f"  largest relative difference: x {dx:.2e} (of max(|x|, σ)), P {dP:.2e} (of σ_i σ_j), trace "
                  f"{dt:.2e} (of max(|value|, σ)); events with their details and blocks "
                  f"{'identical' if ev else 'DIFFER'}; NIS bookkeeping to 8 digits {'identical' if nis else 'DIFFERS'}")
    print("all bit-identical" if ok else "some differ")
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
