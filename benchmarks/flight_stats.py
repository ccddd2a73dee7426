"""The online filter in the air (issue 10's Numbers): multirotor and fixed-wing profiles, cold and
started from a bench calibration of the same unit.

Per profile × start × seed: simulate a flight (default 10 min at 200 Hz, mag 50 Hz, healthy vibration);
replay it through the UKF either cold (``--init none``) or from the batch result of a paper session of
the same unit (same truth, another seed: the bench calibration); express the truth in the filter's body
frame (its gauge, :func:`onlinecal.ukf.gauge.align_gauge`) and report

* coverage: share of the 36 terms within 3σ of the truth, the largest |error|/σ;
* NEES over the estimated terms (the gauge's held terms excluded), against its 99 % chi-square band;
  over the determined terms; and with the prior taken out (:func:`onlinecal.testing.nees.data_only_nees`, over
  the directions the data determined: the simulated unit is not a draw from the filter's prior);
* divergence events;
* the gyro bias error 60 s after take-off (from the trace, once a second);
* the determined terms (final σ < ½ prior σ): how many, and whether each is within 3σ;
* the real-time factor.

    PYTHONPATH=. python benchmarks/flight_stats.py [--seeds 20] [--start 0] [--minutes 10] [--rate 200]
        [--profiles multirotor,fixedwing] [--starts cold,bench[,wrongbench][,truth]]

``wrongbench`` starts from the bench calibration with a 0.3 m/s² accelerometer bias error its σ does not
cover: the runs the health verdict must call not ok. ``truth`` starts from the flight's own truth with
moderate σ (:func:`truth_start`: a bench calibration whose errors happen to be zero, its σ a user's own rather
than a 309-s paper session's ~1e-4): nothing can be learnt that moves it beyond 3σ (session 18's finding).

The machine this runs on may be shared: the real-time factor is wall-clock and says so.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.stats import chi2

import onlinecal.ukf.start as _ukf_start
from onlinecal.batch.pipeline import run_batch
from onlinecal.health import assess
from onlinecal.model import PARAMS, SENSORS, Calibration, SensorCalibration
from onlinecal.sim import simulate
from onlinecal.sim.motion import DEFAULT_LATITUDE_DEG
from onlinecal.testing.nees import data_only_nees
from onlinecal.ukf import replay
from onlinecal.ukf.checkpoint import decode
from onlinecal.ukf.filter import UKFConfig
from onlinecal.ukf.gauge import align_gauge

NAMES = [f"{s}.{p}.{a}" for s in SENSORS for p in PARAMS for a in "xyz"]
GYRO_BIAS = np.array([nm.startswith("gyro.bias.") for nm in NAMES])
# the NEES of the determined terms, split by group (where a conservative or optimistic σ comes from)
GROUPS = {"gyro bias": ("gyro.bias.",), "gyro scale": ("gyro.scale.",),
          "gyro misalignment": ("gyro.alpha.", "gyro.xi."), "accel": ("accel.",), "mag": ("mag.",)}
GROUP_MASK = {g: np.array([nm.startswith(pre) for nm in NAMES]) for g, pre in GROUPS.items()}


@dataclass
class FlightRun:
    profile: str
    start: str
    seed: int
    z: np.ndarray  # (36,) error / σ
    err: np.ndarray  # (36,) error
    held: np.ndarray  # (36,) bool: gauge terms (held at the prior)
    determined: np.ndarray  # (36,) bool: final σ < ½ prior σ
    gyro_bias_err_60s: float  # rad/s, largest axis, 60 s after take-off
    divergences: int
    events: dict[str, int]
    realtime: float
    observability: dict[str, Any]
    verdict: str = "ok"  # onlinecal.health.assess on the replay, as the command line judges it
    reasons: tuple[str, ...] = ()
    nis_out: bool = False  # some NIS stream's mean outside its band (the health check's figures)
    accel_nis: float = float("nan")  # mean NIS of the accel updates whose R is the sensor noise (rests)
    accel_vehicle_nis: float = float("nan")  # vehicle-disturbed accel updates, NIS·k against σ_v²
    data_nees: float = float("nan")  # the prior taken out (onlinecal.testing.nees): over the determined directions
    data_dof: int = 0

    @property
    def coverage(self) -> float:
        return float(np.mean(np.abs(self.z) < 3))

    @property
    def nees(self) -> float:
        e = ~self.held
        return float(np.sum(self.z[e] ** 2))

    @property
    def nees_dof(self) -> int:
        return int(np.sum(~self.held))

    @property
    def nees_determined(self) -> tuple[float, int]:
        """NEES over the determined terms only (σ from the data, not the prior) and its dof."""
        d = self.determined & ~self.held
        return float(np.sum(self.z[d] ** 2)), int(d.sum())

    @property
    def nees_determined_no_gyro_bias(self) -> tuple[float, int]:
        """The same without the gyro bias (whose σ is floored by the zero-rate update's 5e-5 rad/s
        allowance, :attr:`UKFConfig.rest_rate_sigma`: the Earth's rotation a real gyro sees at rest, which
        the filter does not model and the flight profiles' gyro now senses)."""
        d = self.determined & ~self.held & ~GYRO_BIAS
        return float(np.sum(self.z[d] ** 2)), int(d.sum())

    def nees_group(self, mask: np.ndarray) -> tuple[float, int]:
        """NEES over the determined terms in ``mask`` (36,) and its dof."""
        d = self.determined & ~self.held & mask
        return float(np.sum(self.z[d] ** 2)), int(d.sum())

    @property
    def bad(self) -> bool:
        """Truth says the result is not to be trusted: a term > 5σ off, or a NIS out of its band."""
        return bool(np.abs(self.z[~self.held]).max() > 5 or self.nis_out)


def bench_calibration(truth: Calibration, seed: int) -> Calibration:
    """The batch result of a paper session of the same unit (same truth), another seed's motion/noise."""
    sim = simulate("paper", 100_000 + seed, truth=truth)
    return run_batch([sim.data]).calibration


WRONG_ACCEL_BIAS = np.array([0.0, 0.0, 0.3])  # m/s²
TRUTH_START_SIGMA = {"gyro": 2e-3, "accel": 0.05, "mag": 0.01}  # bias σ: rad/s, m/s², raw (a field of ~0.5)
TRUTH_START_SIGMA_DIMLESS = 0.005  # σ of every scale (relative), alpha and xi (rad)


def truth_start(truth: Calibration) -> Calibration:
    """The truth itself with σ :data:`TRUTH_START_SIGMA` on the biases and 0.005 on every scale and angle."""
    out = {}
    for s in SENSORS:
        c = truth.sensor(s)
        assert c is not None
        d = TRUTH_START_SIGMA_DIMLESS
        out[s] = c.with_sigma({"bias": [TRUTH_START_SIGMA[s]] * 3, "scale": [d] * 3, "alpha": [d] * 3,
                               "xi": [d] * 3})
    return truth.replace(**out)


def wrong_bench(bench: Calibration | None) -> Calibration:
    """A broken start (issue 12's other direction): the bench calibration with its accelerometer z bias
    0.3 m/s² off while its σ still says ~1e-3 — a unit re-mounted or recalibrated since, a stale file.
    The replay must end with that term > 5σ from the truth and the verdict not ok."""
    assert bench is not None and bench.accel is not None
    a = bench.accel
    return bench.replace(accel=SensorCalibration(a.bias + WRONG_ACCEL_BIAS, a.matrix, a.sigma))


def config_from_gps(data: Any, config: UKFConfig | None) -> UKFConfig:
    """What ``replay`` takes from a log's GPS position (onlinecal.io.position, onlinecal.place: the fix's latitude,
    the World Magnetic Model's declination) on top of ``config``: ``data`` (a simulation with ``gps``) written as a
    .bin and read back as a user's log is."""
    import tempfile

    from onlinecal.io import write_log
    from onlinecal.io.position import log_position
    from onlinecal.place import config_at

    with tempfile.TemporaryDirectory() as tmp:
        path = f"{tmp}/flight.bin"
        write_log(path, data)
        where = log_position(path)
        if where is None:
            raise RuntimeError(f"{path}: the simulated log's GPS position was not read back")
        out, _ = config_at(where, where.describe(path), None, config)
    return out


def run_flight(profile: str, seed: int, start: str = "cold", minutes: float = 10.0, rate: float = 200.0,
               config: UKFConfig | None = None, latitude: float | None = DEFAULT_LATITUDE_DEG,
               declination: float | None = None, gps: bool = False) -> FlightRun:
    """One flight, replayed cold (``start="cold"``), from the bench calibration (``"bench"``), from a wrong one
    (``"wrongbench"``, :func:`wrong_bench`) or from its truth (``"truth"``, :func:`truth_start`). The flight's
    gyro senses the Earth's rotation at ``latitude`` (deg; None: not at all); the bench session is the paper
    profile's, without it (as the paper figures were set); the field's horizontal part ``declination`` deg east of
    true north (None: 0, with ``gps`` the WMM's at the home). ``gps``: the flight is written as a .bin with its
    GPS position and the filter is told what ``replay`` takes from such a log (onlinecal.io.position,
    onlinecal.place: the fix's latitude, the World Magnetic Model's declination) on top of ``config``."""
    sim = simulate(profile, seed, duration=60.0 * minutes, imu_rate=rate, mag_rate=50.0,
                   latitude=DEFAULT_LATITUDE_DEG if latitude is None else latitude, earth_rate=latitude is not None,
                   declination=declination, gps=gps)
    if gps:
        config = config_from_gps(sim.data, config)
    truth = sim.truth.calibration
    init = None if start == "cold" else truth_start(truth) if start == "truth" else bench_calibration(truth, seed)
    if start == "wrongbench":
        init = wrong_bench(init)
    applied: dict[int, np.ndarray] = {}  # the prior variance each (re)started slice was given, by its start
    orig = _ukf_start.reset_states

    def _record(x: np.ndarray, P: np.ndarray, idx: Any, value: Any, cov: Any) -> None:
        if isinstance(idx, slice) and np.ndim(cov) == 2:
            applied[idx.start] = np.diag(cov).copy()
        orig(x, P, idx, value, cov)

    _ukf_start.reset_states = _record  # only the mag's cold fit and its raw prior go through start.py
    try:
        t0 = time.perf_counter()
        res = replay([sim.data], init, config, keep_state=True)
        wall = time.perf_counter() - t0
    finally:
        _ukf_start.reset_states = orig
    cal = res.calibration
    g = cal.meta["online"]["gauge"]
    gs = g["sensor"]
    gcal = cal.sensor(gs) if gs else None
    tr = align_gauge(truth, gs, gcal.alpha) if gcal is not None else truth
    err, z, held = [], [], []
    for s in SENSORS:
        c, t = cal.sensor(s), tr.sensor(s)
        assert c is not None and t is not None
        for p in PARAMS:
            e = np.asarray(c.params()[p]) - np.asarray(t.params()[p])
            err += list(e)
            z += list(e / np.asarray(c.sigma[p]))
            held += [s == gs and p in g["terms"]] * 3
    ratios = res.observability
    dn = _data_nees(res.state, applied, tr, np.array(held))
    det = np.array([ratios[nm]["ratio"] < 0.5 if nm in ratios else False for nm in NAMES])
    t_to = sim.truth.vehicle.get("takeoff_at") or 0.0
    rows = [r for r in res.trace if r["t"] >= t_to + 60.0]
    gb = np.nan
    if rows:
        r = rows[0]
        gb = float(max(abs(r[f"gyro.bias.{a}"] - truth.gyro.bias[i]) for i, a in enumerate("xyz")))  # type: ignore[union-attr]
    kinds: dict[str, int] = {}
    for ev in res.events:
        kinds[ev["kind"]] = kinds.get(ev["kind"], 0) + 1
    h = assess(cal, nis=res.nis, events=res.events, observability=res.observability,
               raw={"gyro": sim.data.gyro, "accel": sim.data.acc},  # as the command line (cli.online_health)
               mag_raw=sim.data.mag if sim.data.n_mag else None,
               mag_start=None if init is None else "file", start=init)  # as `replay --init CAL.json`
    figs = h["checks"].get("nis", {})
    nis_out = any(v.get("mean") is not None and "band" in v and not v["band"][0] <= v["mean"] <= v["band"][1]
                  for v in figs.values())
    return FlightRun(profile, start, seed, np.array(z), np.array(err), np.array(held), det, gb,
                     kinds.get("divergence", 0), kinds, sim.data.duration / wall,
                     cal.meta.get("online", {}).get("observability", {}), h["verdict"], tuple(h["reasons"]),
                     nis_out, _mean(figs.get("accel")), _mean(figs.get("accel_vehicle")), dn.nees, dn.dof)


def _data_nees(state: dict[str, Any] | None, applied: dict[int, np.ndarray], truth: Calibration, held: np.ndarray
               ) -> Any:
    """The prior-free NEES (:func:`onlinecal.testing.nees.data_only_nees`) of the 36 calibration terms less
    the gauge's held ones: the final x and P of the replay's state, its prior (x₀ and the variance each
    slice was given: the initial diagonal, or the magnetometer's cold-fit σ where that fit started it)."""
    assert state is not None
    names = list(state["names"])
    idx = np.array([names.index(nm) for nm in NAMES])
    x, P = np.asarray(state["x"]), np.asarray(state["P"])
    x0 = np.asarray(decode(state["state"]["prior_x"]), float)
    v0 = np.asarray(decode(state["state"]["prior_sigma"]), float) ** 2
    for start, var in applied.items():
        v0[start : start + var.shape[0]] = var
    t = np.concatenate([np.asarray(truth.sensor(s).params()[p]) for s in SENSORS for p in PARAMS])  # type: ignore[union-attr]
    k = idx[~held]
    return data_only_nees(x[k], P[np.ix_(k, k)], x0[k], v0[k], t[~held])


def _mean(fig: dict[str, Any] | None) -> float:
    m = (fig or {}).get("mean")
    return float(m) if isinstance(m, (int, float)) else float("nan")


def summary(runs: list[FlightRun]) -> list[str]:
    """Lines of the per-(profile, start) summary."""
    out = []
    for key in sorted({(r.profile, r.start) for r in runs}):
        rs = [r for r in runs if (r.profile, r.start) == key]
        Z = np.array([r.z for r in rs])
        cov = np.mean(np.abs(Z) < 3)
        worst = float(np.abs(Z).max())
        dof = rs[0].nees_dof
        lo, hi = chi2.ppf([0.005, 0.995], dof)
        nees = np.array([r.nees for r in rs])
        n = len(rs)
        lo_m, hi_m = chi2.ppf([0.005, 0.995], dof * n) / n
        det = np.array([r.determined for r in rs])
        det_ok = np.abs(Z[det]) < 3
        nd = np.array([r.nees_determined for r in rs])
        k_d = int(nd[:, 1].sum())
        lo_d, hi_d = chi2.ppf([0.005, 0.995], max(k_d, 1))
        gb = np.array([r.gyro_bias_err_60s for r in rs])
        div = sum(r.divergences for r in rs)
        out.append(
            f"{key[0]:10s} {key[1]:5s} seeds {n:2d}: within 3σ {100 * cov:5.1f} % (36 terms), worst {worst:5.2f}σ, "
            f"beyond 5σ {int(np.sum(np.abs(Z) > 5))}; NEES ({dof} dof) mean {nees.mean():6.1f} [99 % band of the "
            f"mean {lo_m:.1f}, {hi_m:.1f}], seeds inside [{lo:.1f}, {hi:.1f}]: "
            f"{np.mean((nees >= lo) & (nees <= hi)):.2f}; "
            f"divergences {div}; gyro bias 60 s after take-off max {np.nanmax(gb):.2e} rad/s; determined terms "
            f"{det.sum(1).mean():.1f}/36 per seed, within 3σ {det_ok.sum()}/{det.sum()}; "
            f"real time ×{np.median([r.realtime for r in rs]):.0f} (median, wall clock)")
        out.append(f"    NEES over the determined terms, all seeds: {nd[:, 0].sum():.1f} for {k_d} dof, 99 % band "
                   f"[{lo_d:.1f}, {hi_d:.1f}] (terms at their prior are left out: the truth is not drawn from the "
                   "cold prior, so their z only says the prior was wide)")
        dn = np.array([(r.data_nees, r.data_dof) for r in rs])
        k_n = int(dn[:, 1].sum())
        if k_n:
            lo_n, hi_n = chi2.ppf([0.005, 0.995], k_n)
            inside = "inside" if lo_n <= dn[:, 0].sum() <= hi_n else ("below" if dn[:, 0].sum() < lo_n else "ABOVE")
            out.append(f"    NEES with the prior taken out (onlinecal.testing.nees, determined directions), all seeds: "
                       f"{dn[:, 0].sum():.1f} for {k_n} dof, 99 % band [{lo_n:.1f}, {hi_n:.1f}]: {inside}")
        nb = np.array([r.nees_determined_no_gyro_bias for r in rs])
        k_b = int(nb[:, 1].sum())
        if k_b:
            lo_b, hi_b = chi2.ppf([0.005, 0.995], k_b)
            out.append(f"    the same without the gyro bias: {nb[:, 0].sum():.1f} for {k_b} dof, 99 % band "
                       f"[{lo_b:.1f}, {hi_b:.1f}]")
        else:
            out.append("    no determined term besides the gyro bias")
        parts = []
        for g, mask in GROUP_MASK.items():
            ng = np.array([r.nees_group(mask) for r in rs])
            k_g = int(ng[:, 1].sum())
            if k_g:
                lo_g, hi_g = chi2.ppf([0.005, 0.995], k_g)
                parts.append(f"{g} {ng[:, 0].sum():.1f}/{k_g} [{lo_g:.1f}, {hi_g:.1f}]")
        out.append("    NEES of the determined terms per group (sum/dof [99 % band]): " + "; ".join(parts))
        zb = np.array([[r.z[i] if r.determined[i] and not r.held[i] else np.nan for i in range(3)] for r in rs])
        zm = [float(np.mean(c[np.isfinite(c)])) if np.isfinite(c).any() else float("nan") for c in zb.T]
        out.append("    gyro bias z (determined), per axis: mean " + ", ".join(
            f"{a} {zm[i]:+.2f}" for i, a in enumerate("xyz")) + "; z² sum " + ", ".join(
            f"{a} {np.nansum(zb[:, i] ** 2):.1f}/{int(np.sum(np.isfinite(zb[:, i])))}" for i, a in enumerate("xyz"))
            + " (the Earth rate's vertical part, Ω_E sin φ on a level body's z, is one offset on every seed)")
        ver = [r.verdict for r in rs]
        good = [not r.bad for r in rs]
        out.append(f"    health: ok {ver.count('ok')}/{n}; good (no term > 5σ, NIS in band) → ok "
                   f"{sum(g and v == 'ok' for g, v in zip(good, ver, strict=True))}/{sum(good)}, bad → not ok "
                   f"{sum((not g) and v != 'ok' for g, v in zip(good, ver, strict=True))}/{n - sum(good)}; accel "
                   f"mean NIS at rest {np.nanmean([r.accel_nis for r in rs]):.2f} (3 expected), in flight "
                   f"(against σ_v²) {np.nanmean([r.accel_vehicle_nis for r in rs]):.2f} (≤ 3 expected)")
        # which terms are determined, on how many seeds
        frac = det.mean(0)
        out.append("    determined on ≥ half the seeds: "
                   + (", ".join(nm for nm, f in zip(NAMES, frac, strict=True) if f >= 0.5) or "none"))
        bad = [(NAMES[i], float(np.abs(Z[:, i]).max())) for i in range(36) if np.abs(Z[:, i]).max() > 3]
        if bad:
            out.append("    beyond 3σ on some seed: " + ", ".join(f"{nm} ({v:.1f}σ)" for nm, v in bad))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--rate", type=float, default=200.0)
    ap.add_argument("--profiles", default="multirotor,fixedwing")
    ap.add_argument("--starts", default="cold,bench")
    ap.add_argument("--save", default=None, metavar="JSON", help="per-run z-scores and flags")
    ap.add_argument("--rest-rate-sigma", type=float, default=None,
                    help="diagnostic only: the zero-rate update's allowance (rad/s; default the config's)")
    ap.add_argument("--vehicle-accel-sigma", type=float, default=None,
                    help="diagnostic only: the vehicle-acceleration model's σ_v (m/s²; default the config's)")
    ap.add_argument("--vehicle-accel-tau", type=float, default=None,
                    help="diagnostic only: the vehicle-acceleration model's τ_v (s; default the config's)")
    ap.add_argument("--sp-alpha", type=float, default=None,
                    help="diagnostic only: the scaled unscented transform's spread α (default the config's)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=JSON",
                    help="diagnostic only: a UKFConfig field for this run (e.g. update_damping=0)")
    ap.add_argument("--latitude", type=float, default=DEFAULT_LATITUDE_DEG,
                    help=f"deg, where the flights' gyro senses the Earth's rotation (default {DEFAULT_LATITUDE_DEG})")
    ap.add_argument("--no-earth-rate", action="store_true", help="diagnostic: flights without the Earth's rotation")
    ap.add_argument("--filter-latitude", action="store_true",
                    help="the filter is told the flights' latitude (UKFConfig.latitude_deg, `replay --latitude`): "
                         "it takes the Earth's rotation out of the gyro (onlinecal.ukf.earth)")
    ap.add_argument("--declination-sigma", type=float, default=None,
                    help="with --filter-latitude: σ of the declination the filter assumes (deg; default the config's)")
    ap.add_argument("--gps", action="store_true",
                    help="the flights are written with their GPS position and the filter told what `replay` takes "
                         "from such a log: the fix's latitude and the World Magnetic Model's declination")
    ap.add_argument("--summary-of", default=None, metavar="JSON",
                    help="print the summary of a --save file (a run stopped early: the seeds it completed)")
    args = ap.parse_args()
    if args.summary_of:
        for line in summary(_load(args.summary_of)):
            print(line)
        return
    over = {k: v for k, v in (("rest_rate_sigma", args.rest_rate_sigma),
                              ("vehicle_accel_sigma", args.vehicle_accel_sigma),
                              ("vehicle_accel_tau", args.vehicle_accel_tau),
                              ("sp_alpha", args.sp_alpha),
                              ("latitude_deg", args.latitude if args.filter_latitude else None),
                              ("declination_sigma_deg", args.declination_sigma)) if v is not None}
    over.update({k: json.loads(v) for k, v in (kv.split("=", 1) for kv in args.set)})
    config = UKFConfig(**over) if over else None
    print("# flights' gyro: " + ("no Earth rate (diagnostic)" if args.no_earth_rate else
          f"Earth rate at latitude {args.latitude:g}°") + "; bench sessions: paper profile, no Earth rate"
          + ("; the filter is given the latitude" if args.filter_latitude else "")
          + ("; the flights' .bin carry their GPS position, the filter is told what replay reads from it" if args.gps
             else ""), flush=True)
    runs = []
    # seeds outermost: a run stopped early still holds the same count for every profile and start
    for seed in range(args.start, args.start + args.seeds):
        for prof in args.profiles.split(","):
            for st in args.starts.split(","):
                r = run_flight(prof, seed, st, args.minutes, args.rate, config,
                               None if args.no_earth_rate else args.latitude, gps=args.gps)
                runs.append(r)
                print(f"{prof:10s} {st:5s} seed {seed:2d}: within 3σ {100 * r.coverage:5.1f} %, worst "
                      f"{np.abs(r.z).max():5.2f}σ ({NAMES[int(np.argmax(np.abs(r.z)))]}), NEES {r.nees:6.1f}/"
                      f"{r.nees_dof}, data NEES {r.data_nees:5.1f}/{r.data_dof}, determined "
                      f"{int(r.determined.sum())}, gyro bias @60 s "
                      f"{r.gyro_bias_err_60s:.1e}, events {r.events or '-'}, health {r.verdict}, accel NIS "
                      f"{r.accel_nis:.2f}/{r.accel_vehicle_nis:.2f}, ×{r.realtime:.0f}", flush=True)
                if args.save:
                    _save(args.save, runs)
    print()
    for line in summary(runs):
        print(line)


def _save(path: str, runs: list[FlightRun]) -> None:
    import json

    with open(path, "w") as fh:
        json.dump([{"profile": r.profile, "start": r.start, "seed": r.seed, "z": r.z.tolist(),
                    "determined": r.determined.tolist(), "held": r.held.tolist(),
                    "gyro_bias_err_60s": r.gyro_bias_err_60s, "events": r.events, "realtime": r.realtime,
                    "verdict": r.verdict, "reasons": list(r.reasons), "nis_out": r.nis_out,
                    "accel_nis": r.accel_nis, "accel_vehicle_nis": r.accel_vehicle_nis,
                    "data_nees": r.data_nees, "data_dof": r.data_dof} for r in runs], fh)


def _load(path: str) -> list[FlightRun]:
    """The runs of a ``--save`` file, for :func:`summary` (errors and observability are not saved)."""
    import json

    with open(path) as fh:
        rows = json.load(fh)
    return [FlightRun(d["profile"], d["start"], d["seed"], np.array(d["z"]), np.full(36, np.nan), np.array(d["held"]),
                      np.array(d["determined"]), d["gyro_bias_err_60s"], d["events"].get("divergence", 0), d["events"],
                      d["realtime"], {}, d["verdict"], tuple(d["reasons"]), d["nis_out"], d["accel_nis"],
                      d["accel_vehicle_nis"], d.get("data_nees", float("nan")), d.get("data_dof", 0)) for d in rows]


if __name__ == "__main__":
    main()
