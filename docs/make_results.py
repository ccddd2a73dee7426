"""onlinecal on measured data: writes docs/results.md.

Run from the repository root::

    python docs/make_results.py

Reads ``../shared/data`` (see its README): the MARG set (MPU6050 + HMC5883L, 15 hand-held sessions) and
the Ferraris session of the imucal project with its hand-marked sections. Compares onlinecal's batch
pipeline with the raw data and, on the Ferraris session, with the ``imucal`` package (optional; the
Ferraris part says so when it is missing). Deterministic: same data and code, same file.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.spatial.transform import Rotation

import onlinecal
from onlinecal.batch import run_batch
from onlinecal.batch.segment import moving_std
from onlinecal.io import ImuData, read_log
from onlinecal.model import Calibration, decompose
from onlinecal.sim.motion import G0

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
OUT = ROOT / "docs" / "results.md"
MARG = DATA / "marg-set1"
FERRARIS = DATA / "ferraris"
FACES = ("x_p", "x_a", "y_p", "y_a", "z_p", "z_a")
TURNS = ("x_rot", "y_rot", "z_rot")
FERRARIS_RATE = 102.4  # Hz, data README


# -- small helpers ---------------------------------------------------------------------------------------
def rms(x) -> float:
    x = np.asarray(x, float)
    return float(np.sqrt(np.mean(x * x)))


def f(x: float, nd: int = 3) -> str:
    return f"{x:.{nd}f}"


def vec(v, nd: int = 4) -> str:
    return "(" + ", ".join(f"{x:+.{nd}f}" for x in np.asarray(v, float)) + ")"


def table(head: list[str], rows: list[list]) -> str:
    out = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(out)


def issue11_magacc_section(cal, excluded: set[str]) -> tuple[list[str], dict]:
    """Issue 11's magnetometer and accelerometer bars on MARG set 1, with the evidence for what is not met:
    how much of each file's norm spread sits at one direction (no sensor calibration removes it), the
    per-file field (norm and gravity–field angle), a shape fit with a per-file field norm (nuisance), the
    `pan-y` ends matched by direction against the other files; and the accelerometer held out (fitted on
    the moving files' quasi-static holds only, checked on the unmoved files' static norm)."""
    from scipy.optimize import least_squares

    from onlinecal.batch.ellipsoid import fit_norm_lm, sphere_bin_weights, sym_from_vec
    from onlinecal.batch.sensors import quasi_static_holds, within_direction_spread

    files = sorted(MARG.glob("*.csv"))
    logs = {f.name: read_log(f) for f in files}
    rows, figs = [], {}
    for name, d in logs.items():
        m = cal.mag.apply(d.mag)
        n = np.linalg.norm(m, axis=1)
        wd, share = within_direction_spread(m)
        a = cal.accel.apply(d.acc)
        am, sd = moving_std(a, 50)
        qs = (np.linalg.norm(sd, axis=1) < 0.3) & (np.abs(np.linalg.norm(a, axis=1) - G0) < 0.3)
        dip = float("nan")
        if qs.sum() >= 10:
            mi = np.column_stack([np.interp(d.t_imu[qs], d.t_mag, m[:, k]) for k in range(3)])
            c = np.einsum("ij,ij->i", am[qs], mi) / np.linalg.norm(am[qs], axis=1) / np.linalg.norm(mi, axis=1)
            dip = float(np.degrees(np.median(np.arccos(np.clip(c, -1, 1)))))
        figs[name] = {"spread": float(100 * n.std() / n.mean()), "within": wd, "share": share,
                      "median_norm": float(np.median(n)), "grav_field_deg": dip}
    # the shape fit again, with one field norm per file (a nuisance parameter): shared ellipsoid, radius r_f
    names = [k for k in logs if k not in excluded]
    x = np.concatenate([logs[k].mag for k in names])
    fid = np.concatenate([np.full(logs[k].n_mag, i) for i, k in enumerate(names)])
    o0 = np.asarray(cal.mag.bias, float)
    _, sv, Vt = np.linalg.svd(cal.mag.matrix)
    M0 = Vt.T @ np.diag(sv) @ Vt  # the symmetric factor: ‖M0 (x − o)‖ = ‖M (x − o)‖
    w = sphere_bin_weights((x - o0) @ M0.T, per_bin=30)
    k = w > 0
    xk, fk, sw = x[k], fid[k], np.sqrt(w[k])
    iu = np.triu_indices(3)

    def resid(p):
        r = np.concatenate([[1.0], p[9:]])  # the first file's radius fixes the scale; renormalised below
        return sw * (np.linalg.norm((xk - p[:3]) @ sym_from_vec(p[3:9]), axis=1) - r[fk])

    sol = least_squares(resid, np.concatenate([o0, M0[iu], np.ones(len(names) - 1)]), method="lm")
    r_f = np.concatenate([[1.0], sol.x[9:]])
    Mr = sym_from_vec(sol.x[3:9]) / float(np.average(r_f, weights=np.bincount(fk, weights=w[k])))
    for name in names:
        nn = np.linalg.norm((logs[name].mag - sol.x[:3]) @ Mr, axis=1)
        figs[name]["spread_perfile_r"] = float(100 * nn.std() / nn.mean())
        figs[name]["r_f"] = float(np.median(nn))
    moving = [k for k in logs if not k.startswith("unmoved")]
    for name in logs:
        f_ = figs[name]
        rows.append([f"`{name}`", f"{f_['spread']:.2f}", f"{f_['within']:.2f} ({100 * f_['share']:.0f} %)",
                     f"{f_['median_norm']:.3f}", f"{f_['grav_field_deg']:.1f}" if np.isfinite(f_["grav_field_deg"])
                     else "–", f"{f_.get('r_f', float('nan')):.3f}" if "r_f" in f_ else "left out",
                     f"{f_['spread_perfile_r']:.2f}" if "spread_perfile_r" in f_ else "–"])
    pan = [k for k in moving if k.startswith("pan")]
    pan_within = ", ".join(f"{figs[k]['within']:.2f}" for k in pan)
    dr = [figs[k]["spread_perfile_r"] - figs[k]["spread"] for k in moving if "spread_perfile_r" in figs[k]]
    met = [k for k in moving if figs[k]["spread"] <= 1.0]
    met_r = [k for k in moving if figs[k].get("spread_perfile_r", 99) <= 1.0]
    # pan-y: its lowest and highest norms, at nearly one direction, against the other files there
    d = logs["pan-y-pointing-left.csv"]
    m = cal.mag.apply(d.mag)
    n = np.linalg.norm(m, axis=1)
    u = m / n[:, None]
    ends = []
    for sel in (n < np.percentile(n, 15), n > np.percentile(n, 85)):
        c = u[sel].mean(0)
        ends.append((c / np.linalg.norm(c), float(np.median(n[sel]))))
    sep = float(np.degrees(np.arccos(np.clip(ends[0][0] @ ends[1][0], -1, 1))))
    pair = []  # each other file's reading at the high end's direction over the low end's (both within 5°)
    for name, dd in logs.items():
        if name == "pan-y-pointing-left.csv":
            continue
        mm = cal.mag.apply(dd.mag)
        nn = np.linalg.norm(mm, axis=1)
        near = [(mm / nn[:, None]) @ c > np.cos(np.radians(5)) for c, _ in ends]
        if min(int(v.sum()) for v in near) >= 20:
            pair.append(float(np.median(nn[near[1]]) / np.median(nn[near[0]]) - 1))
    figs["pan-y-pointing-left.csv"]["ends"] = {"low": ends[0][1], "high": ends[1][1], "sep_deg": sep,
                                               "others_ratio_minus_1": pair}
    angles = [f_["grav_field_deg"] for k_, f_ in figs.items() if np.isfinite(f_["grav_field_deg"])]
    rf = [f_["r_f"] for f_ in figs.values() if "r_f" in f_]
    turns = [k for k in moving if not k.startswith("pan")]
    excess = [figs[k]["spread"] - 1.0 for k in turns] + [0.0]
    within_tr = [figs[k]["within"] for k in turns]
    # the pooled fit's own choices varied (weighting, cells, outlier rule, the per-file field check)
    def var_spreads(xv, **kw):
        fv = fit_norm_lm(xv, 1.0, o0, M0, **kw)
        nv = [np.linalg.norm((logs[k].mag - fv.o) @ fv.M.T, axis=1) for k in moving]
        return [float(100 * v.std() / v.mean()) for v in nv]

    x_all = np.concatenate([logs[k_].mag for k_ in logs])
    u0 = (x - o0) @ M0.T
    variants = [
        ("as the batch: 10° cells, ≤ 30 samples each, 5-MAD outliers, field check",
         dict(weights=sphere_bin_weights(u0, per_bin=30))),
        ("unweighted", {}),
        ("5° cells", dict(weights=sphere_bin_weights(u0, cell_deg=5.0, per_bin=30))),
        ("20° cells", dict(weights=sphere_bin_weights(u0, cell_deg=20.0, per_bin=30))),
        ("1/count weights, no cap", dict(weights=sphere_bin_weights(u0))),
        ("no outlier rule", dict(weights=sphere_bin_weights(u0, per_bin=30), rounds=0)),
        ("outliers at 3 MAD", dict(weights=sphere_bin_weights(u0, per_bin=30), reject_sigma=3.0)),
    ]
    var_rows = []
    for label, kw in variants:
        sp = var_spreads(x, **kw)
        var_rows.append([label, f"{sum(v <= 1.0 for v in sp)} of {len(moving)}", f"{min(sp):.2f}–{max(sp):.2f}",
                         f"{max(sp[moving.index(k_)] for k_ in moving if k_.startswith('pan')):.2f}"])
    sp = var_spreads(x_all, weights=sphere_bin_weights((x_all - o0) @ M0.T, per_bin=30))
    var_rows.append(["field check off (all 15 files)", f"{sum(v <= 1.0 for v in sp)} of {len(moving)}",
                     f"{min(sp):.2f}–{max(sp):.2f}",
                     f"{max(sp[moving.index(k_)] for k_ in moving if k_.startswith('pan')):.2f}"])
    xs_ = logs["tilt-sphere.csv"].mag
    fs_ = fit_norm_lm(xs_, 1.0, o0, M0, weights=sphere_bin_weights((xs_ - o0) @ M0.T, per_bin=30))
    ns_ = np.linalg.norm((xs_ - fs_.o) @ fs_.M.T, axis=1)
    own_sphere = float(100 * ns_.std() / ns_.mean())
    # accelerometer held out: fitted on the moving files' quasi-static holds only
    holds = np.concatenate([quasi_static_holds(logs[k].acc, logs[k].gyro, logs[k].imu_rate) for k in moving])
    wa = sphere_bin_weights(holds, per_bin=20)
    ka = wa > 0
    fa = fit_norm_lm(holds[ka], G0, np.zeros(3), np.eye(3) * G0 / np.linalg.norm(holds, axis=1).mean(),
                     model="diag", weights=wa[ka])
    acc_rows = []
    for name in sorted(k for k in logs if k.startswith("unmoved")):
        dd = logs[name]
        held = float(100 * (np.linalg.norm(((dd.acc - fa.o) @ fa.M.T).mean(0)) / G0 - 1))
        raw = float(100 * (np.linalg.norm(dd.acc.mean(0)) / G0 - 1))
        figs[name]["acc_heldout_pct"] = held
        acc_rows.append([f"`{name}`", f"{raw:+.3f}", f"{held:+.3f}",
                         f"{figs[name]['median_norm']:.3f}"])
    L = ["### Magnetometer and accelerometer bars: the evidence", "",
         "Per file, with the batch's calibration (all 15 files): *spread* = std/mean of the calibrated ‖m‖; "
         "*at one direction* = the RMS deviation of ‖m‖ from the mean of its 3° direction cell "
         "(`batch.sensors.within_direction_spread`; in brackets the share of samples in cells of ≥ 5): an "
         "error ε of one axis' scale moves the norm by ε cos²θ, within a 3° cell by at most 0.015 ε RMS (0.15 % "
         "for a 10 % error), so this part is a field that changed at the sensor, "
         "which no calibration of the sensor removes; the sensor's own noise is ≈ 0.3 % (the unmoved files). "
         "*median ‖m‖* shows the file's field against the pooled one; *gravity–field angle* the median angle "
         "between calibrated gravity and field at quasi-static samples (one place, one uniform field: one angle). "
         "*r_f* and *spread, per-file norm*: the shape fit again with one field norm per file as a nuisance "
         "parameter (shared ellipsoid, weighted by attitude bins as the batch is).", "",
         table(["file", "spread %", "at one direction %", "median ‖m‖", "gravity–field angle °", "r_f",
                "spread, per-file norm %"], rows), "",
         f"Bar ≤ 1 % met on {len(met)} of {len(moving)} moving files with the batch "
         f"({', '.join(f'`{k}`' for k in met)}); with a per-file field norm on {len(met_r)} of {len(moving)}. "
         "Why not on the others, by the columns above:", "",
         f"* **The pans carry a changing field** (local disturbance): on {', '.join(f'`{k}`' for k in pan)} "
         f"{pan_within} % "
         "RMS sits *at one direction* (noise ≈ 0.3 %). In `pan-y-pointing-left` the 15 % lowest norms "
         f"(median {ends[0][1]:.3f}) and the 15 % highest ({ends[1][1]:.3f}) lie {sep:.1f}° apart in the sensor "
         f"frame; each of the {len(pair)} other files that saw both directions (within 5°) reads them within "
         f"{100 * max(abs(v) for v in pair):.1f} % of each other, with the same calibration: a "
         f"{100 * (ends[1][1] / ends[0][1] - 1):.0f} % change over {sep:.0f}° (an ellipsoid would need an axis "
         f"error of {100 * (ends[1][1] / ends[0][1] - 1) / np.radians(sep):.0f} % for it) that no ellipsoid "
         "(hard or soft iron, pooled or per file) makes. The field at the sensor changed between the two ends "
         "of each pan (the board moved near a magnetic object, or a source nearby changed): a local disturbance, "
         "not a calibration error.",
         "* **The files see different fields** (per-file field strength): the per-file field norms *r_f* span "
         f"{min(rf):.3f}–{max(rf):.3f} (and `unmoved-x-pointing-up` "
         f"{figs['unmoved-x-pointing-up.csv']['median_norm']:.3f}, "
         f"left out by the batch's per-file field check), and the gravity–field angle spans {min(angles):.1f}–"
         f"{max(angles):.1f}° between files (one uniform field would give one angle): the recordings were "
         "made in different places or next to different objects. A per-file field norm is a legitimate nuisance "
         f"parameter of the shape fit; it moves the per-file spreads by {min(dr):+.2f} to {max(dr):+.2f} % and "
         "meets the bar on "
         f"{len(met_r)} files against {len(met)} — not enough to make it the default, and it cannot touch the part "
         "at one direction.",
         f"* **The tilts and turns** exceed 1 % by up to {max(excess):.2f} % while their part at one direction is "
         f"{min(within_tr):.2f}–{max(within_tr):.2f} % (noise ≈ 0.3 %): "
         "that part depends on the direction, i.e. on the shape, and the files disagree on the shape (the fit to "
         "`tilt-sphere` alone improves some files and worsens others: *Magnetometer norm spread* below): "
         "consistent with a field that differs from file to file and over the space the hand sweeps. "
         f"`tilt-sphere`, which sees every direction, keeps {own_sphere:.2f} % even with its own ellipsoid "
         "(fitted to it alone), against the sensor's 0.3 % noise: its field is not one field either.", "",
         "The pooled fit's own choices do not decide it (eq. 17 refitted from the batch's answer on the same "
         "samples, each choice varied alone):", "",
         table(["pooled fit", "moving files ≤ 1 %", "spread range %", "worst pan %"], var_rows), "",
         "**Accelerometer, held out.** Fitted (bias + per-axis scale, eq. 32, attitude-binned) on the "
         f"quasi-static holds of the 12 moving files only ({holds.shape[0]} one-second holds, {int(ka.sum())} "
         f"attitude cells; accel std < 0.5 m/s², rate within 0.5 rad/s of the median), and applied to the three "
         "unmoved files, which the fit never saw (bar: within 0.5 % of g on the files whose field and gravity are "
         "consistent):", "",
         table(["file", "raw ‖mean a‖/g − 1 %", "held-out calibrated ‖mean a‖/g − 1 %", "median ‖m‖ (field)"],
               acc_rows), "",
         f"The held-out fit: bias {vec(fa.o)} m/s², scales {vec(np.diag(fa.M))}; its σ of the bias "
         f"{vec(np.sqrt(np.diag(fa.cov)[:3]))} m/s² (x is the least seen axis). The batch's own static fit "
         "(three attitudes, three bias unknowns) is exact by construction; this is the check that counts.", ""]
    return L, figs


def short(path: str) -> str:
    return Path(path).name


def norm_err(acc, g: float = G0):
    return np.linalg.norm(acc, axis=1) - g


def spread(m) -> float:
    """Norm spread std/mean in %."""
    n = np.linalg.norm(m, axis=1)
    return float(100 * n.std() / n.mean())


def csv_rows_to_imu(path: Path, data, rows) -> np.ndarray:
    """Data-row indices of a flat CSV (0 = first row after the header) → IMU sample indices of ``data``.

    Goes through the row's time stamp, so it stays right when the reader dropped rows or the file
    holds mag-only rows; a row that is not an IMU sample in ``data`` raises.
    """
    t_csv = np.loadtxt(path, delimiter=",", skiprows=1, usecols=0, ndmin=1)
    rows = np.asarray(rows)
    last = rows == t_csv.size  # an exclusive end just past the last row
    t = t_csv[np.minimum(rows, t_csv.size - 1)]
    idx = np.searchsorted(data.t_imu, t)
    ok = (idx < data.n_imu) & np.isclose(data.t_imu[np.minimum(idx, data.n_imu - 1)], t, rtol=0, atol=1e-9)
    if not np.all(ok | last):
        raise ValueError(f"{path}: rows {rows[~(ok | last)]} are not IMU samples")
    return np.where(last, data.n_imu, idx)


def compose(inc) -> Rotation:
    """Product R_0 · R_1 · … of the body-frame rotation increments ``inc`` (n, 3), in order (pairwise)."""
    R = Rotation.from_rotvec(inc) if len(inc) else Rotation.from_rotvec(np.zeros((1, 3)))
    while len(R) > 1:
        odd = R[-1:] if len(R) % 2 else None
        R = R[0:len(R) - 1:2] * R[1::2]
        if odd is not None:
            R = Rotation.concatenate([R, odd])
    return R[0]


def increments(t, w, i0: int, i1: int) -> np.ndarray:
    """Trapezoid rotation increments of body rate w over rows [i0, i1)."""
    dt = np.diff(t[i0:i1])
    return 0.5 * (w[i0 + 1:i1] + w[i0:i1 - 1]) * dt[:, None]


def integrate(t, w, i0: int, i1: int) -> tuple[np.ndarray, float]:
    """Body rate w over rows [i0, i1): integrated rate vector ∫w dt (trapezoid) and the angle of the
    net attitude change (body-frame rates composed step by step)."""
    inc = increments(t, w, i0, i1)
    return inc.sum(axis=0), float(np.degrees(compose(inc).magnitude()))


# -- MARG set ----------------------------------------------------------------------------------------------
def without_mag(d: ImuData) -> ImuData:
    return ImuData(d.t_imu, d.gyro, d.acc, d.temp, np.zeros(0), np.zeros((0, 3)), d.source, list(d.warnings))


def gaps(d: ImuData, min_gap: float = 0.1) -> list[tuple[float, float, float]]:
    """IMU gaps > min_gap: (time since start, gap, samples in gap + 0.2 s after it / samples expected at the
    mean rate) — a ratio near 1 means a buffer was flushed late, not samples lost."""
    t = d.t_imu
    dt = np.diff(t)
    out = []
    for i in np.flatnonzero(dt > min_gap):
        n = np.count_nonzero((t >= t[i + 1]) & (t < t[i + 1] + 0.2))
        out.append((float(t[i] - t[0]), float(dt[i]), float(n / ((dt[i] + 0.2) * d.imu_rate))))
    return out


def marg_section() -> tuple[list[str], dict]:
    files = sorted(MARG.glob("*.csv"))
    logs = [read_log(p) for p in files]
    res = run_batch(logs)
    cal = res.calibration
    facts: dict = {}
    L: list[str] = ["## 1. MARG set (MPU6050 + HMC5883L, hand-held), all 15 sessions in one batch", ""]

    # files and timing
    rows = []
    all_gaps = []
    for d in logs:
        dt = np.diff(d.t_imu)
        gp = gaps(d)
        all_gaps += gp
        rows.append([short(d.source), d.n_imu, d.n_mag, f(d.duration, 1), f(d.imu_rate, 1),
                     f(d.n_mag / (d.t_mag[-1] - d.t_mag[0]), 1), f(1e3 * np.median(dt), 1),
                     f(100 * np.mean(dt < 0.002), 0),
                     ", ".join(f"{g:.2f} s at {t0:.1f} s" for t0, g, _ in gp) or "–",
                     f"{np.nanmin(d.temp):.2f}–{np.nanmax(d.temp):.2f}", "; ".join(d.warnings) or "–"])
    L += ["### Files, timing, temperature", "",
          table(["file", "IMU samples", "mag samples", "duration s", "IMU rate Hz (mean)", "mag rate Hz (mean)",
                 "median IMU Δt ms", "% Δt < 2 ms", "IMU gaps > 0.1 s", "temp °C", "reader warnings"], rows), ""]
    early = [g for g in all_gaps if g[0] < 0.5]
    late = [g for g in all_gaps if g[0] >= 0.5]
    ratios = [g[2] for g in all_gaps]
    facts["max_gap"] = max(g[1] for g in all_gaps)
    slow = [d for d in logs if np.median(np.diff(d.t_imu)) > 0.0015]
    fast = [d for d in logs if np.median(np.diff(d.t_imu)) <= 0.0015]

    def trange(ds):
        return f"{min(np.nanmin(d.temp) for d in ds):.1f}–{max(np.nanmax(d.temp) for d in ds):.1f} °C"

    L += [f"Timing: the IMU samples arrive in bursts (median Δt 0.9–2.2 ms, then a pause of ≈ 30 ms) at "
          f"≈ 100 Hz on average, so the time stamps are read times, not sample times. {len(early)} of the "
          f"{len(all_gaps)} gaps over 0.1 s (up to {facts['max_gap']:.2f} s) fall in the first 0.5 s of a "
          f"file, {len(late)} later. Each is followed by a catch-up burst: over the gap and the 0.2 s after it "
          f"the sample count is {min(ratios):.2f}–{max(ratios):.2f} × (median {np.median(ratios):.2f}) what the "
          "mean rate gives. The stamps cannot say exactly whether samples were lost; the mean rates of all "
          f"files lie within {100 * max(abs(d.imu_rate / 100 - 1) for d in logs):.1f} % of 100 Hz. Two "
          "recording set-ups show: "
          + ", ".join(f"`{short(d.source)}`" for d in slow)
          + f" (median Δt ≈ 2 ms, {trange(slow)}) and the other {len(fast)} (≈ 0.9 ms, {trange(fast)}).", ""]

    # warnings and segmentation
    L += ["### What the batch said (warnings, verbatim)", ""]
    L += [f"* `{w}`" for w in res.warnings] or ["* (none)"]
    L += ["", table(["file", "statics", "motions", "rotation phases"],
                    [[short(s.data.source), len(s.statics), len(s.motions),
                      ", ".join(f"{'xyz'[p.axis]} {np.degrees(p.angle):+.0f}°" for p in s.phases) or "–"]
                     for s in res.segmentations]), ""]
    resting = [short(s.data.source) for s in res.segmentations if s.rests]
    relaxed = any("quasi-static" in w for w in res.warnings)
    moving = [s for s in res.segmentations if not short(s.data.source).startswith("unmoved")]
    facts["motion_files_rest"] = sum(bool(s.statics) for s in moving)
    model = res.steps["accel"].figures.get("model") if "accel" in res.steps else None
    gyro_fitted = cal.gyro is not None and not np.allclose(cal.gyro.matrix, np.eye(3))
    facts.update(model=model, gyro_fitted=gyro_fitted, relaxed=relaxed)
    L += [f"Files with a true rest: {', '.join(f'`{r}`' for r in resting) or 'none'}. The hand-held motion "
          f"sessions {'never rest' if not facts['motion_files_rest'] else 'rest only briefly'}; the quasi-static "
          f"fallback (accel std < 0.25 m/s², rate < 0.1 rad/s for 0.5 s) "
          f"{'was used' if relaxed else 'found nothing usable in them either'}. Consequences, plainly:", ""]
    if model == "offset":
        L += [f"* accelerometer: {res.steps['accel'].figures.get('distinct_attitudes')} attitudes at rest, model "
              "`offset` — three bias unknowns from three static means is an exact solve, so the static norm "
              "error after calibration is zero *by construction* and says nothing; the held-out check below is "
              "the one that counts;"]
    else:
        L += [f"* accelerometer: {res.steps['accel'].figures.get('distinct_attitudes') if model else 0} attitudes, "
              f"model `{model}`;"]
    L += ["* gyroscope: " + ("bias, scale and axes fitted;" if gyro_fitted else
                             "only the bias is fitted; scale and misalignment stay at identity (no rest-to-rest "
                             "motion exists to fit them);"),
          "* magnetometer: fitted from every mag sample (ellipsoid), the only full fit in this batch.", ""]

    # calibration
    rows = []
    for name in ("gyro", "accel", "mag"):
        sc = cal.sensor(name)
        if sc is None:
            rows.append([name, "not calibrated", "", "", ""])
            continue
        rows.append([name, vec(sc.bias), vec(sc.scale), vec(np.degrees(sc.alpha), 2), vec(np.degrees(sc.xi), 2)])
    L += ["### Calibration from the batch", "",
          table(["sensor", "bias (raw unit)", "scale", "alpha °", "xi °"], rows), ""]
    if model == "offset" and not np.allclose(cal.accel.scale, 1):
        L += [f"The accelerometer warning says *scale 1*, but its matrix carries a common scale "
              f"{cal.accel.scale[0]:.4f} (= g / mean raw ‖a‖ of the rests, the start value kept fixed) and the "
              "alignment rotation from the one usable phase.", ""]

    # accel on unmoved
    unm = [d for d in logs if short(d.source).startswith("unmoved")]
    rows = []
    for d in unm + [None]:
        if d is None:
            a = np.vstack([x.acc for x in unm])
            name = "**all three**"
            m_raw = rms([np.linalg.norm(x.acc.mean(0)) - G0 for x in unm])
            m_cal = rms([np.linalg.norm(cal.accel.apply(x.acc).mean(0)) - G0 for x in unm])
        else:
            a = d.acc
            name = short(d.source)
            m_raw = abs(np.linalg.norm(a.mean(0)) - G0)
            m_cal = abs(np.linalg.norm(cal.accel.apply(a).mean(0)) - G0)
        er, ec = norm_err(a), norm_err(cal.accel.apply(a))
        rows.append([name, f(np.abs(er).mean(), 4), f(rms(er), 4), f(m_raw, 4),
                     f(np.abs(ec).mean(), 4), f(rms(ec), 4), f(m_cal, 4)])
    L += ["### Accelerometer norm on the static sessions (m/s²)", "",
          table(["file", "raw mean abs(‖a‖−g)", "raw RMS", "raw abs(‖mean a‖−g)",
                 "calibrated mean abs(‖a‖−g)", "calibrated RMS", "calibrated abs(‖mean a‖−g)"], rows), "",
          "In-sample: these three files are the whole accelerometer fit. For *all three* the per-file-mean "
          "columns give the RMS over the three file means. The raw file-mean norms are "
          + ", ".join(f"{np.linalg.norm(d.acc.mean(0)):.3f}" for d in unm) + " m/s².", ""]
    rows = [[short(d.source), vec(d.acc.mean(0), 3), vec(cal.accel.apply(d.acc).mean(0), 3)] for d in unm]
    L += [table(["file", "raw mean a (m/s²)", "calibrated mean a"], rows), "",
          "(`unmoved-x-pointing-up` reads ≈ −g on x: by the specific-force convention x pointed down, or the "
          "file name and the axis sign disagree.)", ""]

    # held-out accel: quietest windows of the motion sessions
    rows = []
    tot_r, tot_c = [], []
    for d in logs:
        if short(d.source).startswith("unmoved"):
            continue
        w = max(5, int(round(0.5 * d.imu_rate)))
        _, s = moving_std(d.acc, w)
        s = np.linalg.norm(s, axis=1)
        q = s <= np.percentile(s, 10)
        er, ec = norm_err(d.acc[q]), norm_err(cal.accel.apply(d.acc[q]))
        tot_r.append(er)
        tot_c.append(ec)
        rows.append([short(d.source), int(q.sum()), f(float(np.percentile(s, 10)), 2),
                     f(np.median(er), 3), f(rms(er), 3), f(np.median(ec), 3), f(rms(ec), 3)])
    n_better = sum(abs(float(r[5])) < abs(float(r[3])) for r in rows)
    er, ec = np.concatenate(tot_r), np.concatenate(tot_c)
    rows.append([f"**all {len(tot_r)}**", er.size, "", f(np.median(er), 3), f(rms(er), 3),
                 f(np.median(ec), 3), f(rms(ec), 3)])
    facts["held_out"] = (float(np.median(er)), float(np.median(ec)), n_better, len(tot_r))
    L += ["### Accelerometer, held out: the quietest 10 % of each motion session", "",
          "Samples whose 0.5 s windowed accel std (summed over axes) is in the file's lowest decile: the hand "
          "is nearly still (not at rest: the thresholds are 0.14–0.9 m/s²), the attitudes are many, and none "
          "was used by the accelerometer fit.", "",
          table(["file", "samples", "std threshold m/s²", "raw median ‖a‖−g", "raw RMS",
                 "calibrated median ‖a‖−g", "calibrated RMS"], rows), "",
          f"The calibrated median is closer to g than the raw one in {n_better} of {len(tot_r)} files.", ""]

    # magnetometer
    sph = next(d for d in logs if short(d.source) == "tilt-sphere.csv")
    res_sph = run_batch([sph])
    cs = res_sph.calibration.mag
    allm = np.vstack([d.mag for d in logs])
    rows = [["**tilt-sphere.csv**", f(spread(sph.mag), 2), f(spread(cal.mag.apply(sph.mag)), 2),
             f(spread(cs.apply(sph.mag)), 2)],
            ["**all 15 files together**", f(spread(allm), 2), f(spread(cal.mag.apply(allm)), 2),
             f(spread(cs.apply(allm)), 2)]]
    for d in logs:
        rows.append([short(d.source), f(spread(d.mag), 2), f(spread(cal.mag.apply(d.mag)), 2),
                     f(spread(cs.apply(d.mag)), 2)])
    facts["mag_sphere"] = (spread(sph.mag), spread(cal.mag.apply(sph.mag)), spread(cs.apply(sph.mag)))
    mf = res.steps["mag"].figures
    L += ["### Magnetometer norm spread (std/mean of ‖m‖, %)", "",
          table(["data", "raw", "calibrated (batch of all 15)", "calibrated (batch of tilt-sphere alone)"], rows), "",
          f"The batch's own figures over all files: {mf.get('norm_std_percent', float('nan')):.2f} % after it "
          f"dropped {mf.get('outliers')} of {mf.get('samples')} samples as outliers (its *raw* figure, "
          f"{mf.get('raw_norm_std_percent', float('nan')):.2f} %, is the spread of the distance from the "
          "samples' centroid, not of ‖m‖).", ""]
    mean_norm = {short(d.source): float(np.linalg.norm(cs.apply(d.mag), axis=1).mean()) for d in logs}
    odd = max(mean_norm, key=lambda k: abs(mean_norm[k] - 1))
    facts["mag_odd"] = (odd, mean_norm[odd])
    L += [f"With the sphere's calibration every file's mean calibrated norm is within "
          f"{max(abs(v - 1) for k, v in mean_norm.items() if k != odd):.3f} of 1 except `{odd}` at "
          f"{mean_norm[odd]:.3f}: in that session the field at the sensor differed (a magnetic disturbance "
          f"near the board, by this data), and its {next(d.n_mag for d in logs if short(d.source) == odd)} "
          "samples at one attitude pull the pooled fit.", ""]

    # gyro bias
    rows = [["batch (all 15)", vec(cal.gyro.bias, 5), "", "", ""]]
    singles = []
    for d in unm:
        single = run_batch([without_mag(d)])
        singles.append(single.calibration.gyro.bias)
        rows.append([short(d.source), vec(singles[-1], 5), vec(d.gyro.mean(0), 5),
                     vec(d.gyro.std(0), 4), f(float(np.nanmean(d.temp)), 2)])
    singles = np.array(singles)
    temps = [float(np.nanmean(d.temp)) for d in unm]
    facts["gyro_bias"] = (cal.gyro.bias, np.ptp(singles, axis=0), max(temps) - min(temps))
    L += ["### Gyroscope bias (rad/s)", "",
          table(["source", "bias from batch", "raw mean gyro", "raw std", "mean temp °C"], rows), "",
          "The batch run singly on each `unmoved-*` file (magnetometer left out: one attitude cannot "
          "calibrate it) fits the gyro bias only; the accelerometer needs ≥ 3 attitudes, so pairs give "
          f"nothing more. Between the three sessions the bias moves by {vec(np.ptp(singles, axis=0), 5)} rad/s "
          f"while the mean temperature moves by {max(temps) - min(temps):.2f} °C — session to session rather "
          "than a temperature effect that this data could show (the whole set spans "
          f"{min(np.nanmin(d.temp) for d in logs):.1f}–{max(np.nanmax(d.temp) for d in logs):.1f} °C).", ""]

    # rotate files: gyro scale and axes checked by accel and mag
    rows = []
    turns = []
    axis_map = {}
    for d in logs:
        name = short(d.source)
        if not name.startswith("rotate"):
            continue
        k = "xyz".index(name.split("around-")[1][0])
        i, j = (k + 1) % 3, (k + 2) % 3
        w = d.gyro - cal.gyro.bias
        th_st = increments(d.t_imu, w, 0, d.n_imu).sum(axis=0)
        th_un = w.sum(axis=0) / d.imu_rate
        a = cal.accel.apply(d.acc)
        ang_a = np.unwrap(np.arctan2(a[:, j], a[:, i]))
        ra = np.median(np.hypot(a[:, i], a[:, j]) / np.linalg.norm(a, axis=1))
        m = d.mag - cal.mag.bias
        mu = m / np.linalg.norm(m, axis=1, keepdims=True)
        nrm = np.linalg.svd(mu - mu.mean(0))[2][2]
        ka = int(np.argmax(np.abs(nrm)))
        # Sign: a body turn +θ about IMU k is a turn s·θ about mag ka if mag ka = s·(IMU k); the field then
        # turns by −s·θ in the mag frame.
        ia, ja = (ka + 1) % 3, (ka + 2) % 3
        phi = np.unwrap(np.arctan2(m[:, ja], m[:, ia]))
        sgn = int(-np.sign((phi[-1] - phi[0]) * th_st[k]))
        axis_map[k] = (ka, sgn)
        turns.append(abs(np.degrees(th_st[k])) / 360)
        rows.append([name, f"{np.degrees(th_st[k]):+.1f}", f"{np.degrees(th_un[k]):+.1f}",
                     f"{np.degrees(ang_a[-1] - ang_a[0]):+.1f}" + (" (axis ≈ vertical)" if ra < 0.3 else ""),
                     f"{'xyz'[k]} → mag {'+' if sgn > 0 else '−'}{'xyz'[ka]} ({abs(nrm[ka]):.2f})"])
    facts["turns"] = turns
    facts["mag_det"] = None
    facts["mag_axes_swapped"] = any(k != v[0] for k, v in axis_map.items())
    P = np.zeros((3, 3))
    for k, (ka, sgn) in axis_map.items():
        P[ka, k] = sgn
    det = float(np.linalg.det(P)) if len(axis_map) == 3 else 0.0
    facts["mag_det"] = det
    n_turns = sorted({int(round(x)) for x in turns})
    facts["stamp_effect"] = max(abs(float(r[1]) - float(r[2])) / abs(float(r[1])) for r in rows) * 100
    L += ["### The `rotate-360ccw-*` sessions, checked against accelerometer and magnetometer", "",
          "Integrated over the whole file with the batch's gyro calibration (bias only), on the time stamps and "
          "on a uniform 1/mean-rate time base; the gravity column is the unwrapped angle of the calibrated "
          "accelerometer in the plane normal to the named axis (a body turning +θ sees gravity turn −θ); the "
          "last column is the raw-mag axis closest to the normal of the plane the field sweeps.", "",
          table(["file", "∫ω about the axis, stamps °", "same, uniform 1/rate °",
                 "calibrated gravity turned about the axis °", "IMU turn axis seen as raw mag axis (abs cos)"],
                rows), "",
          f"Each session holds **{' or '.join(map(str, n_turns))} full turn{'s' if n_turns != [1] else ''}** "
          "(by the gyro and, where the axis is horizontal, independently by gravity), not one. Stamps vs a "
          f"uniform time base change the integrated angle by up to {facts['stamp_effect']:.1f} %."]
    if facts["mag_axes_swapped"]:
        al_warn = [w for w in res.warnings if w.startswith("mag:")]
        what = {1.0: "a proper rotation: the HMC5883L's frame is turned against the MPU6050's (a rotated "
                      "mounting, or the X, Z, Y register order of the HMC5883L read as X, Y, Z plus a sign)",
                -1.0: "a reflection: two axes exchanged (the HMC5883L's X, Z, Y register order read as X, Y, "
                      "Z?) — no rotation T_R can undo it"}.get(round(det), "not a clean permutation")
        L += ["The magnetometer's axes are not the IMU's: "
              + "; ".join(f"a turn about IMU {'xyz'[k]} shows about mag {'+' if v[1] > 0 else '−'}{'xyz'[v[0]]}"
                          for k, v in axis_map.items())
              + f". As a signed permutation (determinant {det:+.0f}) this is {what}. "
              + (f"The batch's magnetometer alignment said only `{al_warn[0]}`." if al_warn else "")]
    L += [""]
    return L, facts


# -- Ferraris session ----------------------------------------------------------------------------------------
def imucal_calibration(data, sec_imu: dict[str, tuple[int, int]]):
    """imucal's FerrarisCalibration from the hand-marked sections; None if imucal is not installed.

    Input units: m/s² and rad/s (the CSV's); imucal's gyro output is in the unit of ``expected_angle``
    per second, so with −360 (turns clockwise, raw rate negative) it is deg/s: converted to rad/s here.
    ``grav`` = 9.80665 like onlinecal (imucal's default 9.81 would scale all norms by 1.00034).
    """
    try:
        import pandas as pd
        from imucal import FerrarisCalibration, ferraris_regions_from_section_list
    except ImportError:
        return None
    df = pd.DataFrame(np.hstack([data.acc, data.gyro]),
                      columns=["acc_x", "acc_y", "acc_z", "gyr_x", "gyr_y", "gyr_z"])
    sl = pd.DataFrame({k: {"start": a, "end": b} for k, (a, b) in sec_imu.items()}).T
    regions = ferraris_regions_from_section_list(df, sl)
    info = FerrarisCalibration(grav=G0, expected_angle=-360).compute(
        regions, FERRARIS_RATE, from_acc_unit="m/s^2", from_gyr_unit="rad/s")
    return info


def imucal_apply(info, acc, gyr):
    a, g = info.calibrate(acc, gyr, acc_unit="m/s^2", gyr_unit="rad/s")
    return a, np.radians(g)


def ferraris_section() -> list[str]:
    csv = FERRARIS / "imucal-example-session.csv"
    d = read_log(csv)
    sec = json.loads((FERRARIS / "manual-sections.json").read_text())
    n_rows = sum(1 for _ in open(csv)) - 1
    sec_imu = {}
    for k, v in sec.items():
        i0, i1 = csv_rows_to_imu(csv, d, [v["start"], v["end"]])
        sec_imu[k] = (int(i0), int(i1))
    same = all(sec_imu[k] == (v["start"], v["end"]) for k, v in sec.items())
    res = run_batch([d])
    cal = res.calibration
    seg = res.segmentations[0]
    t = d.t_imu
    L = ["## 2. Ferraris session (imucal example data): onlinecal, automatic, vs imucal from hand-marked sections",
         "",
         f"The CSV has {n_rows} data rows, all IMU samples at {d.imu_rate:.1f} Hz; the reader kept {d.n_imu} "
         f"({'no row dropped' if not d.warnings else '; '.join(d.warnings)}). The section indices are data-row "
         "indices (imucal slices `data.iloc[start:end]`, end exclusive); mapped through the row time stamps "
         f"to IMU samples they are {'unchanged' if same else 'shifted'}.", "",
         "onlinecal gets the CSV alone (no sections). Its warnings, verbatim:", ""]
    L += [f"* `{w}`" for w in res.warnings] or ["* (none)"]
    rows = []
    for k in FACES + TURNS:
        a, b = sec_imu[k]
        ov = [s for s in seg.statics if s.i0 < b and s.i1 > a]
        mo = [m for m in seg.motions if m.i0 < b and m.i1 > a]
        rows.append([k, f"{a}–{b}", ", ".join(f"{s.i0}–{s.i1}" for s in ov) or "–",
                     ", ".join(f"{m.i0}–{m.i1}" for m in mo) or "–"])
    L += ["", table(["section", "hand-marked rows", "onlinecal statics overlapping", "onlinecal motions overlapping"],
                    rows), "",
          f"onlinecal found {len(seg.statics)} rests, {len(seg.motions)} motions and rotation phases "
          + ", ".join(f"{'xyz'[p.axis]} ({p.i0}–{p.i1}, raw {np.degrees(p.angle):+.1f}°)" for p in seg.phases) + ".",
          ""]

    info = imucal_calibration(d, sec_imu)
    if info is None:
        L += ["**imucal is not installed** (`pip install imucal`): the comparison below is skipped.", ""]
        return L, None
    ao, go = cal.accel.apply(d.acc), cal.gyro.apply(d.gyro)
    ai, gi = imucal_apply(info, d.acc, d.gyro)

    # (a) accel norms on the faces
    rows = []
    allf = np.concatenate([np.arange(*sec_imu[k]) for k in FACES])
    for k, idx in [(k, np.arange(*sec_imu[k])) for k in FACES] + [("**all six**", allf)]:
        no, ni = np.linalg.norm(ao[idx], axis=1), np.linalg.norm(ai[idx], axis=1)
        rows.append([k, len(idx), f(100 * rms((no - ni) / ni), 3), f(rms(norm_err(d.acc[idx])), 4),
                     f(rms(no - G0), 4), f(rms(ni - G0), 4), f(no.mean() - G0, 4), f(ni.mean() - G0, 4)])
    acc_rel = float(rows[-1][2])
    L += ["### (a) Accelerometer norms on all static samples (the six hand-marked faces)", "",
          table(["face", "samples", "RMS rel. diff onlinecal vs imucal ‖a‖ %", "raw RMS ‖a‖−g",
                 "onlinecal RMS ‖a‖−g", "imucal RMS ‖a‖−g", "onlinecal mean ‖a‖−g", "imucal mean ‖a‖−g"], rows),
          "", f"Target ≤ 0.3 % RMS: **{acc_rel:.3f} %** — {'met' if acc_rel <= 0.3 else 'MISSED'}. Both tools' "
          "residual is the per-sample noise; imucal's face means are g by construction (its fit is exact "
          f"on the six means), onlinecal's within {1e3 * max(abs(float(r[6])) for r in rows[:-1]):.1f} mm/s².",
          ""]

    # (b) gyro norms during the turns
    rows = []
    allt = np.concatenate([np.arange(*sec_imu[k]) for k in TURNS])
    res_b = {}
    for k, idx in [(k, np.arange(*sec_imu[k])) for k in TURNS] + [("**all three**", allt)]:
        no, ni = np.linalg.norm(go[idx], axis=1), np.linalg.norm(gi[idx], axis=1)
        fast = ni >= 0.5
        r_fast = 100 * rms((no[fast] - ni[fast]) / ni[fast])
        res_b[k] = r_fast
        rows.append([k, len(idx), int(fast.sum()), f(r_fast, 2), f(100 * rms(no - ni) / rms(ni), 2),
                     f(100 * np.median((no[fast] - ni[fast]) / ni[fast]), 2), f(100 * rms((no - ni) / ni), 1)])
    L += ["### (b) Gyro norms during the three hand-marked turns", "",
          table(["turn", "samples", "samples with ‖ω‖ ≥ 0.5 rad/s", "RMS rel. diff ‖ω‖ % (‖ω‖ ≥ 0.5)",
                 "RMS diff / RMS ‖ω‖ % (all)", "median rel. diff % (onlinecal − imucal)",
                 "RMS rel. diff % (every sample)"], rows), "",
          "The marked turn sections include the board at rest before and after (‖ω‖ down to 1e-4 rad/s); "
          "there a relative difference is a bias difference divided by almost nothing, which is what "
          "the last column shows. The turning samples (first figure) are the meaningful comparison. "
          f"Target ≤ 1 %: {'met' if res_b['**all three**'] <= 1 else 'MISSED'} over all three turns "
          f"({res_b['**all three**']:.2f} %); per turn x {res_b['x_rot']:.2f} %, y {res_b['y_rot']:.2f} %, "
          f"z {res_b['z_rot']:.2f} %"
          + ("" if all(res_b[k] <= 1 for k in TURNS) else
             f" — per turn **missed for {', '.join(k for k in TURNS if res_b[k] > 1)}** (onlinecal's y scale is "
             "below imucal's; see (c))") + ".", ""]

    # (c) turn angles over the whole motion, rest to rest
    rows = []
    turn_deg = {}
    for n_ax, k in enumerate(TURNS):
        a, b = sec_imu[k]
        mo = max((m for m in seg.motions if m.i0 < b and m.i1 > a), key=lambda m: min(m.i1, b) - max(m.i0, a))
        for tool, w in (("onlinecal", go), ("imucal", gi)):
            v, net = integrate(t, w, mo.i0, mo.i1)
            vs, _ = integrate(t, w, a, b)
            about = -np.degrees(v[n_ax])
            if tool == "onlinecal":
                turn_deg[k] = about
            rows.append([k, tool, f"{mo.i0}–{mo.i1}", f(np.degrees(np.linalg.norm(v)), 2), f(about, 2),
                         f(net, 2), f(-np.degrees(vs[n_ax]), 2)])
    L += ["### (c) Each turn's integrated angle, rest before → rest after", "",
          "Integrated over onlinecal's motion segment that contains the marked turn (from the last sample of "
          "the rest before to the first of the rest after; a hand-marked section may clip the turn). "
          "Turns are clockwise (raw rate negative), shown positive. imucal's are in-sample (its gyro scale "
          "is fitted so that each marked section integrates to 360°); onlinecal's gyro scale comes from the "
          "face-to-face transitions, not from the turns.", "",
          table(["turn", "tool", "motion rows", "‖∫ω dt‖ °", "∫ω about the turn axis °",
                 "net attitude change °", "∫ω about the axis, marked section only °"], rows), ""]
    miss = [k for k in TURNS if abs(turn_deg[k] - 360) > 1]
    L += ["Target: onlinecal's turns at 360° within 1° — "
          + ("met for all three." if not miss else
             f"met for {', '.join(k for k in TURNS if k not in miss) or 'none'}, **missed for "
             f"{', '.join(miss)}** ({', '.join(f'{turn_deg[k]:.2f}°' for k in miss)})."), ""]

    # who is right about y? re-fit one imucal axis scale to the face transitions
    trans = [m for m in seg.motions]

    def rest_dir(acc, i0, i1):
        v = acc[i0:i1].mean(0)
        return v / np.linalg.norm(v)

    def trans_errors(acc, w):
        errs = []
        for m in trans:
            before = next(s for s in seg.statics if s.i1 - 1 == m.i0)
            after = next(s for s in seg.statics if s.i0 == m.i1 - 1)
            R = compose(increments(t, w, m.i0, m.i1))
            pred = R.inv().apply(rest_dir(acc, before.i0, before.i1))
            errs.append(np.degrees(np.arccos(np.clip(pred @ rest_dir(acc, after.i0, after.i1), -1, 1))))
        return np.array(errs)

    e_o, e_i = trans_errors(ao, go), trans_errors(ai, gi)
    refit = {}
    for ax in range(3):
        def cost(s, ax=ax):
            w = gi.copy()
            w[:, ax] *= s
            return rms(trans_errors(ai, w))
        refit[ax] = float(minimize_scalar(cost, bounds=(0.95, 1.05), method="bounded",
                                          options={"xatol": 1e-5}).x)
    rows = []
    for m, x, y in zip(trans, e_o, e_i, strict=True):
        v, _ = integrate(t, go, m.i0, m.i1)
        rows.append([f"{m.i0}–{m.i1}", vec(np.degrees(v), 1), f(x, 2), f(y, 2)])
    rows.append(["**RMS**", "", f(rms(e_o), 2), f(rms(e_i), 2)])
    L += ["Which y scale is right? Every motion between two rests also tests the gyro: integrate it, carry "
          "the gravity direction of the rest before through the rotation, compare with the rest after. This "
          "is in-sample for onlinecal (it fitted its gyro matrix to exactly this) but out-of-sample for "
          "imucal, whose gyro fit saw only the turns.", "",
          table(["motion rows", "onlinecal ∫ω dt (°)", "onlinecal gravity error °", "imucal gravity error °"], rows),
          "",
          "Re-fitting one of imucal's gyro axis scales to these transitions (others fixed) gives factors "
          + ", ".join(f"{'xyz'[ax]} {refit[ax]:.4f}" for ax in range(3))
          + f": the transitions want imucal's y rate {100 * (1 - refit[1]):.1f} % smaller, so by them the y turn "
          f"was ≈ {360 * refit[1]:.1f}° of real rotation, not 360°.", ""]

    # (d) parameters side by side
    Mi_a = np.linalg.inv(info.R_a) @ np.linalg.inv(info.K_a)
    Mi_g = np.radians(np.linalg.inv(info.R_g) @ np.linalg.inv(info.K_g))
    rows = []
    for name, sc, bi, Mi in (("accel", cal.accel, info.b_a, Mi_a), ("gyro", cal.gyro, info.b_g, Mi_g)):
        s, al, xi = decompose(Mi)
        rows.append([name, "onlinecal", vec(sc.bias, 5), vec(sc.scale, 4), vec(np.degrees(sc.alpha), 2),
                     vec(np.degrees(sc.xi), 2)])
        rows.append([name, "imucal", vec(bi, 5), vec(s, 4), vec(np.degrees(al), 2), vec(np.degrees(xi), 2)])
    kga = np.abs(info.K_ga).max()
    L += ["### (d) Both calibrations", "",
          "`calibrated = matrix @ (raw − bias)`; imucal's `inv(R)·inv(K)` decomposed the same way as "
          "onlinecal's matrix (scale, alpha, xi; model.py eqs. 1–6). Units m/s² and rad/s.", "",
          table(["sensor", "tool", "bias", "scale", "alpha °", "xi °"], rows), "",
          f"imucal also fits a g-sensitivity of the gyro (K_ga, largest entry {kga:.1e} (rad/s)/(m/s²), i.e. "
          f"{kga * G0:.1e} rad/s at 1 g), which onlinecal does not model."]
    if res.steps["accel"].figures.get("model") == "diag":
        L += ["onlinecal's accelerometer has only bias + per-axis scale (six attitudes; no rotation phase "
              "usable for the alignment of eqs. 25–27, all three turns being about the vertical), so its alpha "
              "and xi are zero where imucal's are not: its body frame is the accelerometer's own axes, imucal's "
              "is the frame of the six faces."]
    L += [""]
    summary = {"acc_rel": acc_rel, "gyro_rel": res_b, "turns": turn_deg, "refit": refit,
               "trans_rms": (rms(e_o), rms(e_i))}
    return L, summary


def findings(mf: dict, fs: dict | None) -> list[str]:
    L = ["## What the real data shows", "",
         "Findings only: where the measured data departs from the paper's model or from what the pipeline "
         "assumes.", ""]
    if not mf["motion_files_rest"]:
        L += ["* **Hand-held sessions never rest.** The paper's procedure needs rests (gyro bias, static "
              "positions, rest-to-rest turns). No MARG motion file has one"
              + ("" if mf["relaxed"] else ", not even a quasi-static one")
              + "; only the `unmoved` files rest"
              + (", so the accelerometer fit is an exact three-point solve" if mf["model"] == "offset" else "")
              + ("" if mf["gyro_fitted"] else " and the gyro gets a bias and nothing else") + "."]
    ho = mf["held_out"]
    L += [f"* **Still, the accelerometer bias it finds generalises**: on the quietest samples of the motion "
          f"sessions the median ‖a‖−g goes from {ho[0]:+.3f} (raw) to {ho[1]:+.3f} m/s² (better in {ho[2]} of "
          f"{ho[3]} files).",
          f"* **Time stamps are read times.** The MARG logger stamps buffered reads in bursts; gaps of up to "
          f"{mf['max_gap']:.2f} s are followed by a catch-up burst. Integrating the gyro over the stamps or over a "
          f"uniform time base differs by up to {mf['stamp_effect']:.1f} % of the angle (rotate sessions)."]
    if mf["mag_axes_swapped"]:
        L += ["* **The magnetometer's axes are not the IMU's**: y and z exchanged"
              + (", one with its sign — a 90° rotation about x" if mf["mag_det"] > 0 else " — a reflection")
              + ". The paper treats T_R(alpha) as a small correction (eq. 5); onlinecal's model takes any angle, "
              "but finding a 90° offset from rotation phases (eqs. 25–27) needs phases about two axes, and this "
              "set has phases about one; the batch finds it instead from the constant angle between gravity and "
              "the field at quasi-static attitudes (first section)."]
    odd, val = mf["mag_odd"]
    L += [f"* **The field is not the same in every session.** `{odd}` reads a norm {100 * (val - 1):+.0f} % off "
          "the others after a sphere calibration; pooled unweighted (thousands of samples at one attitude) it "
          "spoiled the pooled mag fit — the batch now names it and leaves it out, and weights the rest by "
          f"attitude bins (tilt-sphere spread {mf['mag_sphere'][1]:.1f} % vs {mf['mag_sphere'][2]:.1f} % "
          f"with the sphere alone; raw {mf['mag_sphere'][0]:.1f} %).",
          f"* **The gyro bias is large** (x {mf['gyro_bias'][0][0]:.3f} rad/s) and moves by up to "
          f"{mf['gyro_bias'][1].max():.1e} rad/s between sessions {mf['gyro_bias'][2]:.2f} °C apart.",
          "* **The `rotate-360ccw` files contain "
          + " or ".join(str(n) for n in sorted({int(round(x)) for x in mf["turns"]})) + " turns each**, not one."]
    if fs is not None:
        tr = fs["turns"]
        L += [f"* **A hand-made Ferraris turn is not exactly 360°.** imucal's gyro scale assumes it is; "
              f"onlinecal's (from the face-to-face transitions) integrates the turns to x {tr['x_rot']:.2f}°, "
              f"y {tr['y_rot']:.2f}°, z {tr['z_rot']:.2f}°. The transitions side with onlinecal on y: imucal's "
              f"transition error is {fs['trans_rms'][1]:.2f}° RMS against onlinecal's {fs['trans_rms'][0]:.2f}° "
              f"(in-sample for onlinecal), and re-fitted to them imucal's y scale drops by "
              f"{100 * (1 - fs['refit'][1]):.1f} %. Every turn here is about the vertical, so gravity says "
              "nothing about its angle; no tool can decide the y turn from this session beyond that.",
              f"* **The accelerometers agree**: {fs['acc_rel']:.3f} % RMS between the two tools' ‖a‖ on the "
              "faces; after either calibration the static norm error is the sensor's noise."]
    return L + [""]


# Figures of the batch at commit 8429a95 (before issue 11's work), measured with the same code below
# (same closure tool, same files) and kept here because that pipeline no longer exists in this tree.
BEFORE_8429A95: dict[str, dict[str, float]] = {
    'pan-x-pointing-forward.csv':
        {'mag_spread_pct': 1.284, 'closure_deg': 27.641, 'turned_deg': 318.445},
    'pan-y-pointing-left.csv':
        {'mag_spread_pct': 3.221, 'closure_deg': 3.51, 'turned_deg': 304.372},
    'pan-z-pointing-up.csv':
        {'mag_spread_pct': 1.667, 'closure_deg': 12.792, 'turned_deg': 512.116},
    'rotate-360ccw-around-x-pointing-forward.csv':
        {'mag_spread_pct': 1.841, 'closure_deg': 13.845, 'turned_deg': 809.138},
    'rotate-360ccw-around-y-pointing-left.csv':
        {'mag_spread_pct': 7.073, 'closure_deg': 18.289, 'turned_deg': 821.859},
    'rotate-360ccw-around-z-pointing-up.csv':
        {'mag_spread_pct': 1.184, 'closure_deg': 6.077, 'turned_deg': 840.859},
    'tilt-around-x-pointing-forward.csv':
        {'mag_spread_pct': 1.81, 'closure_deg': 20.611, 'turned_deg': 2274.841},
    'tilt-around-x-pointing-up.csv':
        {'mag_spread_pct': 9.237, 'closure_deg': 10.501, 'turned_deg': 2903.054},
    'tilt-around-y-pointing-left.csv':
        {'mag_spread_pct': 8.268, 'closure_deg': 31.222, 'turned_deg': 2799.354},
    'tilt-around-y-pointing-up.csv':
        {'mag_spread_pct': 4.817, 'closure_deg': 3.712, 'turned_deg': 2398.986},
    'tilt-around-z-pointing-up.csv':
        {'mag_spread_pct': 2.206, 'closure_deg': 15.06, 'turned_deg': 3222.96},
    'tilt-sphere.csv':
        {'mag_spread_pct': 7.116, 'closure_deg': 35.391, 'turned_deg': 7089.777},
    'unmoved-x-pointing-forward.csv':
        {'mag_spread_pct': 0.377, 'static_acc_norm_err_pct': 0.0},
    'unmoved-x-pointing-up.csv':
        {'mag_spread_pct': 0.214, 'static_acc_norm_err_pct': 0.0},
    'unmoved-z-pointing-left.csv':
        {'mag_spread_pct': 0.324, 'static_acc_norm_err_pct': 0.0},
}
TOOLS = ROOT.parent / "shared" / "tools"


def issue11_section() -> tuple[list[str], dict]:
    """Issue 11 acceptance figures, per MARG file, before (commit 8429a95) and now: gyro attitude closure
    (../shared/tools/gyro_closure.py, imported, not copied), calibrated mag norm spread, static accel norm."""
    sys.path.insert(0, str(TOOLS))
    import gyro_closure as gc  # the out-of-fit check shared by the project

    files = sorted(MARG.glob("*.csv"))
    res = run_batch([read_log(f) for f in files])
    cal = res.calibration
    tmp = ROOT / "docs" / ".issue11-cal.json"
    cal.save(tmp)
    cj = json.loads(tmp.read_text())
    tmp.unlink()
    excluded = {Path(w.split(": ")[1]).name for w in res.steps["mag"].warnings
                if "left out of the magnetometer fit" in w}
    L2, mfigs = issue11_magacc_section(cal, excluded)
    rows, after = [], {}
    for f in files:
        d = read_log(f)
        n = np.linalg.norm(cal.mag.apply(d.mag), axis=1)
        r = {"mag_spread_pct": float(100 * n.std() / n.mean())}
        if f.name.startswith("unmoved"):
            # held out: the accelerometer fitted on the moving files' holds only (issue11_magacc_section)
            r["static_acc_norm_err_pct"] = mfigs[f.name]["acc_heldout_pct"]
        else:
            r["closure_deg"], r["turned_deg"] = gc.closure(gc.read_csv(str(f)), cj)
        after[f.name] = r
        b = BEFORE_8429A95.get(f.name, {})
        rows.append([f"`{f.name}`", f"{r['turned_deg']:.0f}" if "turned_deg" in r else "–",
                     f"{b['closure_deg']:.1f}" if "closure_deg" in b else "–",
                     f"{r['closure_deg']:.1f}" if "closure_deg" in r else "–",
                     f"{b['mag_spread_pct']:.2f}", f"{r['mag_spread_pct']:.2f}",
                     f"{r['static_acc_norm_err_pct']:+.3f}" if "static_acc_norm_err_pct" in r else "–"])
    cb = [v["closure_deg"] for v in BEFORE_8429A95.values() if "closure_deg" in v]
    ca = [v["closure_deg"] for v in after.values() if "closure_deg" in v]
    mv = [v["mag_spread_pct"] for k, v in after.items() if not k.startswith("unmoved")]
    gf = res.steps["gyro"].figures
    mfig = res.steps["mag"].figures
    rot = mfig.get("to_accel_rotation", {})
    L = ["## Issue 11: the batch on hand-held sessions, before and after", "",
         "All 15 MARG files in one batch. *Closure*: `../shared/tools/gyro_closure.py` (accelerometer + "
         "magnetometer attitude over the first half second, the calibrated gyro integrated on a nominal clock, "
         "compared with the attitude over the last half second). It is out of fit: the gyro fit "
         "(`gyro.fit_gyro_kinematic`) uses only 0.5-s spans of the magnetometer direction (v' = v × ω), never "
         "the end-to-end attitudes. *Before*: commit 8429a95, same tool, same files.", "",
         table(["file", "turned °", "closure ° before", "closure ° now", "mag spread % before",
                "mag spread % now", "static ‖a‖/g − 1 %, held out"], rows), "",
         f"Closure over the 12 moving files: median {np.median(cb):.1f}° → **{np.median(ca):.1f}°**, max "
         f"{max(cb):.1f}° → **{max(ca):.1f}°** (issue bar: median ≤ 3°, max ≤ 8° — **not met**). Calibrated mag "
         f"spread on the moving files: {min(mv):.2f}–{max(mv):.2f} % (bar ≤ 1 % on every file — met on "
         f"{sum(x <= 1.0 for x in mv)} of {len(mv)}).", "",
         f"What the batch did: gyro method `{gf.get('method')}`; {gf.get('any_rotation', {}).get('spans', 0)} "
         f"spans, {gf.get('any_rotation', {}).get('spans_dropped', 0)} dropped as outliers; magnetometer "
         f"weighted by attitude bins ({mfig.get('fit_samples')} of {mfig.get('samples')} samples carry weight), "
         f"{mfig.get('files_excluded')} file(s) left out for their field; the magnetometer frame turned by "
         f"{rot.get('angle_deg', float('nan')):.1f}° (σ {rot.get('sigma_deg', float('nan')):.2f}°) onto the "
         "accelerometer's from the constant gravity–field angle (the HMC5883L sits 90° about x against the "
         "MPU6050); burst-read stamps replaced by a fitted clock on every file.", "",
         "Why the bars are not met, with the evidence in the tables below: (1) the static accelerometer column is "
         "held out (an accelerometer fitted on the moving files' quasi-static holds only, applied to the unmoved "
         "files; the batch's own three-attitude fit is exact by construction and says nothing); (2) the "
         "magnetometer: the pans carry a field that changes at one sensor direction (a local disturbance), and "
         "the files see different fields (per-file field strength and gravity–field angle); *Magnetometer and "
         "accelerometer bars: the evidence*; (3) the gyro closure: the next subsection "
         "(the bias per recording, the clipped gyro on `tilt-sphere`, the clock of the ≈ 2 ms set-up).", ""]
    return L + L2, {"closure_median": float(np.median(ca)), "closure_max": float(max(ca)), "magacc": mfigs}


def imutk_section() -> list[str]:
    """imu_tk Xsens session against imu_tk's own result, in frame-free quantities."""
    from itertools import combinations

    d = read_log(DATA / "imutk-xsens" / "xsens-session.csv")
    ref = json.loads((DATA / "imutk-xsens" / "imu_tk-result.json").read_text())
    res = run_batch([d], g=ref["gravity_m_s2"])
    c = res.calibration
    units = {"accel": 415.0, "gyro": 4770.0}
    peer = {k: (np.array(ref[k]["T"]) @ np.diag(ref[k]["K_diag"]) * u, (np.array(ref[k]["b_counts"]) - 32768) / u)
            for k, u in units.items()}

    def gains(M):
        return np.linalg.norm(np.linalg.inv(M), axis=1)

    def angles(M):
        A = np.linalg.inv(M)
        A = A / np.linalg.norm(A, axis=1, keepdims=True)
        return np.degrees([np.arccos(A[i] @ A[j]) for i, j in combinations(range(3), 2)])

    def polar(M):
        U, _, Vt = np.linalg.svd(M)
        return U @ Vt

    R1 = polar(np.linalg.inv(c.accel.matrix) @ c.gyro.matrix)
    R2 = polar(np.linalg.inv(peer["accel"][0]) @ peer["gyro"][0])
    g2a = float(np.degrees(np.arccos(np.clip((np.trace(R1 @ R2.T) - 1) / 2, -1, 1))))
    rows = [["accel bias (m/s²)", f"{np.abs(c.accel.bias - peer['accel'][1]).max():.2e}", "≤ 1e-3"]]
    for k in ("accel", "gyro"):
        M = c.sensor(k).matrix
        rows.append([f"{k} per-axis gain (rel.)", f"{np.abs(gains(M) / gains(peer[k][0]) - 1).max():.2e}", "≤ 3e-4"])
        rows.append([f"{k} axis angles (°)", f"{np.abs(angles(M) - angles(peer[k][0])).max():.4f}", "≤ 0.02"])
    rows.append(["gyro-to-accel rotation (°)", f"{g2a:.4f}", "≤ 0.02"])
    return ["## imu_tk Xsens session against imu_tk", "",
            "Largest difference from imu_tk's own calibration of the same session (frame-free quantities, "
            f"`tests/test_batch_peers.py`); gyro method `{res.steps['gyro'].figures.get('method')}`.", "",
            table(["quantity", "largest difference", "bar"], rows), ""]


# The online gyro on MARG set 1 with earlier code: `onlinecal replay` of the 15 files with its default batch start,
# closure by ../shared/tools/gyro_closure.py with the batch's accel + mag — per file (session 15's code, 8c2066a,
# measured in session 16; session 16's final code, 06f9987, measured in session 17). Session 16's accelerometer,
# from the same runs: held-out quiet-sample and bench-file ‖a‖ − g RMS in m/s², as _accel_norm_rms computes them
ONLINE_EARLIER = {  # file: (8c2066a, 06f9987)
    "pan-x-pointing-forward.csv": (9.9, 8.7), "pan-y-pointing-left.csv": (4.3, 2.4),
    "pan-z-pointing-up.csv": (6.0, 4.1), "rotate-360ccw-around-x-pointing-forward.csv": (15.9, 11.3),
    "rotate-360ccw-around-y-pointing-left.csv": (26.8, 11.1), "rotate-360ccw-around-z-pointing-up.csv": (24.8, 8.9),
    "tilt-around-x-pointing-forward.csv": (7.6, 4.6), "tilt-around-x-pointing-up.csv": (15.1, 1.8),
    "tilt-around-y-pointing-left.csv": (25.5, 6.0), "tilt-around-y-pointing-up.csv": (2.1, 1.9),
    "tilt-around-z-pointing-up.csv": (7.2, 3.1), "tilt-sphere.csv": (27.6, 37.3),
}
ACCEL_SESSION16_06F9987 = (0.517, 0.724)


def _accel_norm_rms(cal: dict, logs: list) -> tuple[float, float]:
    """RMS of ‖calibrated accel‖ − g (m/s²) over the quietest 10 % of each moving file (0.5-s windowed std) and
    over the bench (``unmoved``) files, for the calibration JSON ``cal``."""
    c = Calibration.from_dict(cal)
    quiet, bench = [], []
    for d in logs:
        if short(d.source).startswith("unmoved"):
            bench.append(norm_err(c.accel.apply(d.acc)))
            continue
        _, s = moving_std(d.acc, max(5, int(round(0.5 * d.imu_rate))))
        s = np.linalg.norm(s, axis=1)
        quiet.append(norm_err(c.accel.apply(d.acc[s <= np.percentile(s, 10)])))
    return rms(np.concatenate(quiet)), rms(np.concatenate(bench))


def online_marg_section() -> list[str]:
    """The online filter on all 15 MARG files as a user runs it (`onlinecal batch`, `onlinecal replay` with its
    default batch start), its gyro judged out of fit by ../shared/tools/gyro_closure.py against the batch's, and
    its health."""
    import subprocess
    import tempfile

    sys.path.insert(0, str(TOOLS))
    import gyro_closure as gc

    files = sorted(MARG.glob("*.csv"))
    with tempfile.TemporaryDirectory() as td:
        out = {}
        for cmd in ("batch", "replay"):
            dst = Path(td) / f"{cmd}.json"
            subprocess.run([sys.executable, "-m", "onlinecal", "-q", cmd, *map(str, files), "--json", str(dst)],
                           capture_output=True, text=True, check=False)
            out[cmd] = json.loads(dst.read_text())
    hybrid = {**out["batch"], "gyro": out["replay"]["gyro"]}  # the online gyro, the batch's attitude reference
    rows, cb, co, cp, c16 = [], [], [], [], []
    for fpath in files:
        if fpath.name.startswith("unmoved"):
            continue
        data = gc.read_csv(str(fpath))
        b, turned = gc.closure(data, out["batch"])
        o, _ = gc.closure(data, hybrid)
        before, s16 = ONLINE_EARLIER[fpath.name]
        cb.append(b)
        co.append(o)
        cp.append(before)
        c16.append(s16)
        rows.append([f"`{fpath.name}`", f"{turned:.0f}", f"{b:.1f}", f"{before:.1f}", f"{s16:.1f}", f"{o:.1f}"])
    h = out["replay"]["health"]
    nis = h["checks"]["nis"]
    logs = [read_log(f) for f in files]
    acc_b, acc_o = _accel_norm_rms(out["batch"], logs), _accel_norm_rms(out["replay"], logs)
    acc_16 = ACCEL_SESSION16_06F9987
    veh = out["replay"]["meta"]["online"]["observability"]["vehicle"]
    return [
        "## The online filter on MARG set 1, started from its batch (sessions 16–17)", "",
        "`onlinecal replay` of all 15 files with its default start (the batch of the same files). Its gyro is judged "
        "out of fit as the batch's is above: integrated over each moving file against the accelerometer + "
        "magnetometer attitude at its ends (`../shared/tools/gyro_closure.py`), the ends taken with the batch's "
        "accelerometer and magnetometer for both, so that the column compares gyros. *Online, session 15*: the "
        "same command with commit 8c2066a's code; *session 16*: with 06f9987's. (`tilt-sphere.csv` clips the gyro for "
        "≈ 113° of its turning: no calibration closes it.)", "",
        table(["file", "turned °", "closure ° batch", "closure ° online gyro, session 15",
               "closure ° online gyro, session 16", "closure ° online gyro now"], rows),
        "",
        f"Median over the 12 moving files: batch {np.median(cb):.1f}°, online session 15 {np.median(cp):.1f}°, "
        f"session 16 {np.median(c16):.1f}°, now **{np.median(co):.1f}°**; now at most the batch's + 1° on "
        f"{sum(o <= b + 1.0 for o, b in zip(co, cb, strict=True))} of 12 files (a slow test holds both: the median "
        "within 1° of the batch's, every file within 1°). Session 16's better median came from its gyro bias, an "
        "average over hand motion because no rest was found in the bench files (below); now those rests set it, as "
        "the batch's rests set the batch's (bias x 0.08024 against the batch's 0.07988 and session 16's 0.07948 "
        "rad/s). The files' own biases differ by up to 5.5e-4 rad/s (the batch's warning), ≈ 1° over a 30-s file: "
        "no single bias closes every file.", "",
        "The accelerometer, out of fit (‖f‖ = g): RMS of ‖calibrated a‖ − g over the quietest 10 % of each moving "
        "file (the hand nearly still, many attitudes, none a rest) and over the three bench files:", "",
        table(["calibration", "quiet samples of the moving files, m/s²", "bench files, m/s²"],
              [["batch (its three rests; in fit on the bench files)", f"{acc_b[0]:.3f}", f"{acc_b[1]:.4f}"],
               ["online, session 16 (06f9987)", f"{acc_16[0]:.3f}", f"{acc_16[1]:.4f}"],
               ["online now", f"{acc_o[0]:.3f}", f"{acc_o[1]:.4f}"]]), "",
        f"The hand is taken for a vehicle from t = {veh['since']:.1f} s of the first file ({veh['reason']}).", "",
        f"Health of the online result now: **{h['verdict']}**; magnetometer NIS mean {nis['mag']['mean']:.2f} "
        f"(3 expected; session 15: 448), {h['checks']['divergences']} divergence(s) (session 15: 1). Its reasons, "
        "verbatim:", "",
        *[f"* {r}" for r in h["reasons"]], "",
        f"Terms it says hand motion alone determined (`checks.motion_only`; `export` leaves them out): "
        f"{', '.join(h['checks'].get('motion_only', [])) or 'none'}.", "",
        "What was wrong, each found on these files and each fixed with a test (the figures are per-file replays from "
        "the batch with the code of the step before):", "",
        "1. **Burst-read stamps.** Only the batch replaced them by a fitted clock; the filter took its rate from the "
        "median Δt (0.9 ms: 1 100 Hz), so its blocks were 1.1 s long (29 for `pan-x`'s 33.7 s) and every "
        "per-sample noise was scaled for 11× the samples. Replays now use the batch's clock "
        "(`batch.clock.regularise_for_filter`, streamed by `ReclockedReader`); a live source's bursts set the rate "
        "from the mean period (event `clock`). The trace also restarted only once the log time passed the "
        "previous logs' end: each log now has its trace.",
        "2. **A gyro rail reached in short stretches.** `tilt-sphere` clips 271 samples in 32 stretches, none of "
        "40 in a row, so the filter's run rule never learnt the rail; the clipped readings went in as rates and "
        "the lost rotation into the gyro scale (x 1.042 ± 0.001 on that file alone). The filter now also learns a "
        "rail the batch's way (the largest magnitude recurring in 10 samples, `specs.rail_samples`): 0.996 ± 0.002.",
        "3. **The field is not one vector over 15 hand-held files.** The batch's own fit leaves 2.0 % of the field "
        "(`norm_std_percent`), 5–20× a block mean's noise; the filter weighed each block mean by its noise alone "
        "(mean NIS 448). That misfit now enters the magnetometer's R (`MagModel.variance`, beyond the noise only; "
        "0 on a simulated session), also in a rest's per-block NIS (`unmoved-x-pointing-forward` alone: NIS 41 "
        "and a divergence → 1.5).",
        "4. **A file recorded in another field** (`unmoved-x-pointing-up`, +32 %, which the batch leaves out) was "
        "let back in after the disturbance gate's 45 s, diverged the filter and restarted the gyro and mag terms at "
        "the cold prior's σ. A log that disagrees from its first block now stays out for the log.", "",
        "5. **The hand's accelerations pulled the accelerometer (session 17).** Once the batch stopped claiming its "
        "three-rest accelerometer to ±1e-16 (*Calibration from the batch*), session 16's filter moved it: accel.bias.x "
        "0.20 → 0.77 m/s², bench-file ‖a‖ − g RMS 0.72 m/s². Three faults, each measured here: (a) in `pan-x` the "
        "gate dropped 148 of 338 accelerometer updates as motion the platform model lacks, and those it let through "
        "walked the bias — the norm test could not see the hand while the scale's σ was the prior's 5 %; (b) once a "
        "push did switch the vehicle detector on (in the third file, `pan-z`), the rest test judged every later file "
        "against the accelerometer's *spec* noise (a rule for vibrating vehicles; MARG's noise is 2.3× its spec), "
        "so the three bench files had no rest and the accelerometer was never a gravity reference; (c) with the "
        "vehicle on, the magnetometer's tilt corrections (NIS 5–14 in motion) still moved the accelerometer's terms "
        "through their correlation with the attitude (accel.bias.x 0.2 → 1.5 m/s² in one file). Now the gate's drops "
        "(5 of 20 moving blocks) switch the detector on, the spec-noise rule is kept to a vehicle detected by its "
        "vibration, and in vehicle motion the accelerometer's terms are consider states that only rests update "
        "(`tests/test_vehicle_handheld.py`; the flights' statistics, docs/flight.md, session 17).", "",
        "What the three bench attitudes (+z, −x, +y up) cannot split — the bias and scale of an axis never rested "
        "with its other face up — stays listed as determined through motion alone, and `export` leaves it out.", "",
        "6. **The batch's magnetometer σ took a file's samples for independent draws (session 17).** The cross-check "
        "with the batch (`health.checks.start_agreement`) named the batch's magnetometer bias 6–16σ from the online "
        "one: its σ (≈ 3e-4 of a 0.5 field) treated 6 744 weighted samples as independent while the field differs "
        "by file (per-file mean calibrated norm −3.2 … +2.6 %). Where the files' means differ beyond their noise "
        "(χ², p < 1e-3) the batch now adds a delete-one-file jackknife's excess to its σ (`sensors."
        "_file_jackknife_cov`) and says so: on this set the bias σ 3e-4 → 4e-3 of the raw unit, and two fits on "
        "disjoint halves of the files (odd/even) agree within 1.4σ where the per-sample σ called them 27σ apart "
        "(`tests/test_mag_cluster_sigma.py`; drawn hand-held files in fields 2 % apart: the centre's z RMS 11.7 → "
        "1.2). The cross-check now names no magnetometer term; it still names the gyro's ξ_x (online 0.0001 against "
        "the batch's 0.0196 ± 0.0023). **Found, not fixed:** the batch's any-rotation gyro fit (eq. 36 over 0.5-s "
        "windows of every file) has the same fault — its σ take a file's windows for independent draws. Batches on "
        "the odd and on the even files differ by up to 0.10 rad in α and ξ (31σ with those σ); a delete-one-file "
        "jackknife varies 597× more than the windows' σ in its worst direction (one file, "
        "`tilt-around-z-pointing-up`, carries the x alignment: without it G moves by 0.043) and would widen α_x and "
        "ξ_x to σ ≈ 0.05 rad (halves then ≤ 7σ apart). Tried in session 17 and not landed: started from that batch "
        "the online filter took the magnetometer for its gauge (the gyro's α no longer the tightest) and, in the "
        "first file alone (`pan-x`, turns about the vertical), walked the gyro's α_x and ξ_x together from "
        "0.04/0.02 to 0.43/0.43 rad with σ 0.04 — a confident wrong pair — then diverged twice (magnetometer, then "
        "accelerometer NIS) and restarted cold. So the online filter, too, cannot be trusted with a wide prior on "
        "the gyro's x alignment from hand pans (a finding for the filter's nonlinearity, not fixed). The batch's "
        "gyro alignment from these hand-held files is known to a few degrees, not the 0.1° its σ claim. "
        "**Session 18** (`pan-x` alone from the batch with the gyro's α and ξ σ set to 0.05 rad): not the "
        "unscented transform's spread — α 0.3, 0.5, 0.7 and 1.0 all end at α_x 0.37–0.38, ξ_x 0.50 — nor the "
        "vehicle switch (`vehicle` \"vehicle\" and \"platform\" the same). With the magnetometer's terms held "
        "at the batch's (σ 1e-6) the file reads α_x 0.39 ± 0.03 at a mag NIS of 3.2, consistent within the file; "
        "with them wide (σ 0.05 rad) the gyro becomes the gauge and ξ_x takes 0.19 ± 0.08. So this file's own "
        "data put the gyro's z axis ~20° from where the session's 15 files put it relative to the magnetometer — "
        "not physical for one rigid board. Two suspects: a field distortion in this file (the files' field norms "
        "differ by −3.2 … +2.6 %), which the model has no term for, and the null-space leak found this session "
        "(docs/flight.md, *Started from the truth*: the unscented update, repeated at a geometry that changes "
        "little, reads the curvature of a direction the data cannot see as information). Started from the batch, "
        "the health verdict names it (\"moved from its start calibration beyond both σ\", failed).", "",
    ]


def main() -> int:
    if not DATA.is_dir():
        print(f"measured data not found at {DATA}", file=sys.stderr)
        return 2
    marg, mf = marg_section()
    ferr, fs = ferraris_section()
    L = ["# onlinecal on measured data", "",
         f"Generated by `docs/make_results.py` with onlinecal {onlinecal.__version__}; do not edit by hand. "
         "Data: `../shared/data` (its README has sources and licences). g = 9.80665 m/s².", ""]
    i11, _ = issue11_section()
    from results_gyro import issue11_gyro_section  # the gyro evidence of issue 11 (docs/results_gyro.py)

    gyr, _ = issue11_gyro_section()
    L += i11 + gyr + online_marg_section() + marg + ferr + imutk_section() + findings(mf, fs)
    OUT.write_text("\n".join(L))
    print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
