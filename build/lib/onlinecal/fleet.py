"""Fleet replay: many logs, each an independent unit, in parallel processes or on a dask.distributed cluster.

``onlinecal replay --jobs N LOGS...`` runs :func:`process_log` once per log (read → batch initialisation →
UKF replay) in a ``concurrent.futures.ProcessPoolExecutor``; ``--executor dask --scheduler ADDR`` submits the
same function through a ``dask.distributed.Client`` (the optional extra ``onlinecal[dask]``). Each log gives
one JSON object (schema ``onlinecal.fleet/1``, documented in docs/json.md); a log that fails gives an object
with ``ok: false`` and the error instead of stopping the run. :func:`fleet_summary` orders the logs by their
start time and reports, per calibration parameter, first/last/span and the trend per day (weighted least
squares on the filter's σ) — the drift of a sensor across a fleet's logs.
"""

from __future__ import annotations

import math
import struct
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .model import PARAMS, SENSORS, Calibration

FLEET_SCHEMA = "onlinecal.fleet/1"
SUMMARY_SCHEMA = "onlinecal.fleet-summary/1"
REPLAY_CHUNK = 8192  # IMU samples fed to the filter per call (the CLI always feeds this way: see replay_chunked)
DASK_HINT = "pip install onlinecal[dask]"
# Unix seconds 2000-01-01 … 2100-01-01: a time stamp in this range is taken for wall-clock time
_EPOCH_LO, _EPOCH_HI = 946_684_800.0, 4_102_444_800.0


class DaskMissing(ImportError):
    """dask.distributed is not installed (it is the optional extra ``onlinecal[dask]``)."""


class SchedulerUnreachable(ConnectionError):
    """The dask scheduler address given could not be connected to."""


def replay_chunked(logs: list[Any], init: Calibration | None, trace_path: str | Path | None = None,
                   on_progress: Callable[[int, int], None] | None = None, chunk: int = REPLAY_CHUNK,
                   config: Any = None) -> Any:
    """:func:`onlinecal.ukf.replay` with the logs fed in blocks of ``chunk`` IMU samples, calling
    ``on_progress(samples_done, samples_total)`` as it goes (within a log and across logs).

    Every CLI replay feeds this way whether or not a bar is drawn, so a result never depends on the terminal.
    Against feeding each log in one call (``replay(..., chunk=None)``) the result differs only in rounding
    (~1e-9 relative): the filter estimates its sample rate from the first samples it is given. ``config``:
    the filter's UKFConfig (None: the defaults).
    """
    from .ukf import replay

    return replay(logs, init, config, chunk=chunk, trace_path=trace_path, on_progress=on_progress)


def log_start_time(path: str | Path, data: Any = None) -> tuple[float | None, str | None]:
    """Wall-clock start of a log in Unix seconds, and where it came from.

    ``.tlog``: the first record's 8-byte big-endian µs time stamp (the ground station's clock) → "tlog";
    otherwise the first IMU time if it already looks like Unix time (2000–2100, e.g. a CSV with absolute
    ``time_s``) → "log"; else (None, None) — boot-relative clocks carry no date.
    """
    p = Path(path)
    if p.suffix.lower() == ".tlog":
        try:
            with p.open("rb") as fh:
                head = fh.read(8)
            if len(head) == 8:
                s = struct.unpack(">Q", head)[0] * 1e-6
                if _EPOCH_LO <= s <= _EPOCH_HI:
                    return s, "tlog"
        except OSError:
            pass
    if data is not None and int(getattr(data, "n_imu", 0) or 0) > 0:
        t0 = float(data.t_imu[0])
        if _EPOCH_LO <= t0 <= _EPOCH_HI:
            return t0, "log"
    return None, None


def _json_safe(x: Any) -> Any:
    """Plain JSON (RFC 8259) through the package's one sanitiser (:func:`onlinecal.files.sanitize`)."""
    from .files import sanitize

    return sanitize(x)


def process_log(path: str, init: str | dict[str, Any] | None = "batch", scales: dict[str, float | None] | None = None,
                g: float = 9.80665, gps: bool = True) -> dict[str, Any]:
    """One fleet unit: read ``path``, initialise (``"batch"``: the paper's pipeline on this log alone;
    ``None``/``"none"``: cold start; a dict: that calibration JSON), replay the UKF, and return the
    ``onlinecal.fleet/1`` record. Never raises for a bad log: the record then has ``ok: false`` and ``error``.
    ``gps``: the Earth's rotation is taken out at the latitude of the log's own GPS fix where it has one, with
    the World Magnetic Model's declination there (:func:`onlinecal.place.earth_rate_config`; the calibration's
    observability says so).
    """
    from .batch import run_batch
    from .batch.ellipsoid import FitError
    from .io import read_log
    from .io.base import LogError

    t0 = time.perf_counter()
    rec: dict[str, Any] = {
        "schema": FLEET_SCHEMA, "log": str(path), "ok": False, "error": None, "calibration": None,
        "init": init if isinstance(init, str) else ("none" if init is None else "file"),
        "n_imu": 0, "log_s": 0.0, "wall_s": 0.0, "t_start": None, "t_start_source": None, "warnings": [],
        "health": None,
    }
    try:
        sc: dict[str, Any] = dict(scales or {})
        d = read_log(path, **sc)
        rec["n_imu"], rec["log_s"] = d.n_imu, d.duration
        rec["t_start"], rec["t_start_source"] = log_start_time(path, d)
        warnings = list(d.warnings)
        config = None
        if gps:
            from .place import earth_rate_config

            setting = earth_rate_config(None, None, [path])
            config = setting.config
            warnings += setting.warnings
        if init == "batch":
            b = run_batch([d], g=g, latitude_deg=None if config is None else config.latitude_deg)
            from .health import filter_start

            cal0, notes = filter_start(b.calibration, d.mag if d.n_mag else None)
            warnings += b.warnings + notes
        elif init is None or init == "none":
            cal0 = None
        elif isinstance(init, dict):
            cal0 = Calibration.from_dict(init)
        else:
            raise ValueError(f"init must be 'batch', 'none' or a calibration dict, not {init!r}")
        res = replay_chunked([d], cal0, config=config)
        warnings += list(getattr(res, "warnings", []))
        from .health import assess

        health = assess(res.calibration, nis=res.nis, events=res.events, observability=res.observability,
                        mag_raw=d.mag if d.n_mag else None, raw={"gyro": d.gyro, "accel": d.acc},
                        mag_start=None if cal0 is None else ("batch" if init == "batch" else "file"))
        rec["calibration"] = res.calibration.replace(health=health).to_dict()
        rec["health"] = health
        rec["warnings"] = list(dict.fromkeys(warnings))
        # a calibration that failed its health check is no result: it is kept out of the drift summary
        rec["ok"] = health["verdict"] != "failed"
    except LogError as e:
        rec["error"] = str(e)
    except FitError as e:
        rec["error"] = f"{path}: too little usable data: {e}"
    except Exception as e:  # noqa: BLE001 - one bad log must not stop a fleet; the record says what happened
        rec["error"] = f"{path}: {type(e).__name__}: {e}"
    rec["wall_s"] = time.perf_counter() - t0
    return _json_safe(rec)


def _failed(path: str, e: BaseException) -> dict[str, Any]:
    return _json_safe({"schema": FLEET_SCHEMA, "log": str(path), "ok": False, "calibration": None,
                       "error": f"{path}: worker failed: {type(e).__name__}: {e}", "init": None, "n_imu": 0,
                       "log_s": 0.0, "wall_s": 0.0, "t_start": None, "t_start_source": None, "warnings": [],
                       "health": None})


def run_fleet(paths: Sequence[str], init: str | dict[str, Any] | None = "batch", jobs: int = 1,
              executor: str = "process", scheduler: str | None = None,
              scales: dict[str, float | None] | None = None, g: float = 9.80665,
              on_record: Callable[[dict[str, Any]], None] | None = None,
              on_progress: Callable[[float, str], None] | None = None, gps: bool = True) -> list[dict[str, Any]]:
    """Run :func:`process_log` over ``paths``; returns the records in the order of ``paths``.

    ``executor="process"``: a pool of ``jobs`` spawned worker processes (also for ``jobs == 1``), each with
    single-threaded BLAS so N workers use N cores. A log's result does not depend on which worker ran it or
    how many there are, up to floating-point rounding: SIMD/BLAS kernels round differently with the
    alignment of the arrays in memory, which differs from process to process; the filter carries such
    last-bit differences to ~1e-12 relative (measured), far below any parameter's σ.
    ``executor="dask"``: a ``dask.distributed.Client`` on ``scheduler`` (an address such as
    ``tcp://10.0.0.5:8786``; the logs must be readable at the same path on the workers), or, without one, a
    ``LocalCluster`` of ``jobs`` single-threaded worker processes. ``on_record`` is called with each record
    as it completes (completion order); ``on_progress(logs_done, note)`` drives a progress bar. ``gps``: each
    log's filter told the latitude of that log's GPS fix (see :func:`process_log`).
    """
    paths = [str(p) for p in paths]
    work = [str(Path(p).absolute()) for p in paths]  # workers may run elsewhere (dask); records keep the name given
    out: dict[int, dict[str, Any]] = {}

    def done(i: int, rec: dict[str, Any]) -> None:
        rec["log"] = paths[i]
        out[i] = rec
        if on_record is not None:
            on_record(rec)
        if on_progress is not None:
            on_progress(len(out), Path(paths[i]).name)

    if executor == "process":
        if jobs < 1:
            raise ValueError("jobs must be ≥ 1")
        _run_pool(work, init, jobs, scales, g, done, gps)
    elif executor == "dask":
        _run_dask(work, init, jobs, scheduler, scales, g, done, gps=gps)
    else:
        raise ValueError(f"executor must be 'process' or 'dask', not {executor!r}")
    return [out[i] for i in range(len(paths))]


_BLAS_ENV = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def _run_pool(paths: list[str], init: Any, jobs: int, scales: Any, g: float,
              done: Callable[[int, dict[str, Any]], None], gps: bool = True) -> None:
    import multiprocessing as mp
    import os
    from concurrent.futures import ProcessPoolExecutor, as_completed

    # One BLAS thread per worker, or N workers on N cores oversubscribe them. Spawned (not forked) workers read
    # these when they load BLAS; the parent's BLAS is already loaded and unaffected. Restored afterwards so
    # nothing else this process starts inherits them.
    saved = {k: os.environ.get(k) for k in _BLAS_ENV}
    os.environ.update({k: "1" for k in _BLAS_ENV})
    try:
        with ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn")) as pool:
            futs = {pool.submit(process_log, p, init, scales, g, gps): i for i, p in enumerate(paths)}
            try:
                for f in as_completed(futs):
                    i = futs[f]
                    try:
                        rec = f.result()
                    except Exception as e:  # noqa: BLE001 - a crashed worker process (BrokenProcessPool)
                        rec = _failed(paths[i], e)
                    done(i, rec)
            except BaseException:
                # Ctrl-C (or a failing callback): do not start the logs still queued; leaving the block waits
                # only for the ones already running
                pool.shutdown(wait=False, cancel_futures=True)
                raise
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def require_dask() -> None:
    """Raise :class:`DaskMissing` (naming ``pip install onlinecal[dask]``) unless dask.distributed imports."""
    try:
        import dask.distributed  # noqa: F401
    except ImportError as e:
        raise DaskMissing(f"--executor dask needs dask.distributed, which is not installed ({e}); "
                          f"install the extra: {DASK_HINT}") from e


def _run_dask(paths: list[str], init: Any, jobs: int, scheduler: str | None, scales: Any, g: float,
              done: Callable[[int, dict[str, Any]], None], connect_timeout_s: float = 20.0, gps: bool = True) -> None:
    require_dask()
    from dask.distributed import Client, LocalCluster, as_completed

    cluster = None
    if scheduler:
        try:
            client = Client(scheduler, timeout=connect_timeout_s)
        except (OSError, TimeoutError, ValueError) as e:
            raise SchedulerUnreachable(f"--scheduler {scheduler}: cannot connect to a dask scheduler ({e})") from e
    else:
        cluster = LocalCluster(n_workers=max(1, jobs), threads_per_worker=1, processes=True,
                               dashboard_address=None)
        client = Client(cluster)
    try:
        futs = client.map(process_log, paths, init=init, scales=scales, g=g, gps=gps, pure=False)
        index = {f.key: i for i, f in enumerate(futs)}
        for f in as_completed(futs):
            i = index[f.key]
            try:
                rec = f.result()
            except Exception as e:  # noqa: BLE001 - a lost worker or a serialisation error
                rec = _failed(paths[i], e)
            done(i, rec)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


# -- drift across the fleet -------------------------------------------------------------------------

def _param_table(rec: dict[str, Any]) -> dict[str, tuple[float, float | None]]:
    """name → (value, 1σ or None) for every sensor.param.axis in a record's calibration."""
    out: dict[str, tuple[float, float | None]] = {}
    cal = Calibration.from_dict(rec["calibration"])
    for s in SENSORS:
        c = cal.sensor(s)
        if c is None:
            continue
        for p in PARAMS:
            sig = c.sigma.get(p)
            for j, a in enumerate("xyz"):
                sj = None if sig is None else float(np.asarray(sig)[j])
                out[f"{s}.{p}.{a}"] = (float(c.params()[p][j]), sj)
    return out


def weighted_trend(x: Any, y: Any, sigma: Any | None) -> tuple[float, float | None]:
    """Slope of y over x by least squares and its 1σ.

    With σ_i known and > 0: weights w_i = 1/σ_i², slope = Σw(x−x̄)(y−ȳ)/Σw(x−x̄)², σ_slope = 1/√Σw(x−x̄)²
    (x̄, ȳ weighted means) — the σ the filter's own covariances imply — times the Birge ratio
    max(1, √(χ²/(n−2))) when n ≥ 3 (χ² = Σw r², r the residuals about the line). Otherwise ordinary least
    squares with σ_slope from the residuals (needs ≥ 3 points, else None).
    """
    x, y = np.asarray(x, float), np.asarray(y, float)
    s = None if sigma is None else np.asarray(sigma, float)
    if s is not None and np.all(np.isfinite(s)) and np.all(s > 0):
        w = 1.0 / s**2
    else:
        s, w = None, np.ones_like(x)
    xm, ym = np.sum(w * x) / w.sum(), np.sum(w * y) / w.sum()
    sxx = float(np.sum(w * (x - xm) ** 2))
    slope = float(np.sum(w * (x - xm) * (y - ym)) / sxx)
    r = y - ym - slope * (x - xm)
    if s is not None:
        # Birge ratio: where the scatter about the line exceeds what the σ_i claim (chi²/dof > 1), the σ_i are
        # too small (an overconfident filter) and σ_slope is widened by sqrt(chi²/dof); it is never narrowed.
        birge = math.sqrt(max(1.0, float(np.sum(w * r**2)) / (x.size - 2))) if x.size > 2 else 1.0
        return slope, birge / math.sqrt(sxx)
    if x.size < 3:
        return slope, None
    return slope, float(math.sqrt(np.sum(r**2) / (x.size - 2) / sxx))


def fleet_summary(records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Drift of every calibration parameter across the logs that succeeded.

    Logs are ordered by ``t_start`` when every successful log has one (and at least two differ); the trend is
    then per day (:func:`weighted_trend` over days since the first log). Otherwise they keep the given order
    and no trend is computed. Per parameter: n, first, last, change (last − first), span (max − min).
    """
    ok = [r for r in records if r.get("ok") and r.get("calibration")]
    failed = [r["log"] for r in records if not r.get("ok")]
    timed = bool(ok) and all(r.get("t_start") is not None for r in ok) and len({r["t_start"] for r in ok}) >= 2
    order = sorted(ok, key=lambda r: r["t_start"]) if timed else list(ok)
    tables = [_param_table(r) for r in order]
    days = np.array([(r["t_start"] - order[0]["t_start"]) / 86400.0 for r in order]) if timed else None
    names = [n for n in (tables[0] if tables else {}) if all(n in t for t in tables)]
    from .report import _unit

    params = []
    for n in names:
        v = np.array([t[n][0] for t in tables])
        sg = [t[n][1] for t in tables]
        row: dict[str, Any] = {"param": n, "unit": _unit(*n.split(".")[:2]), "n": int(v.size),
                               "first": float(v[0]), "last": float(v[-1]), "change": float(v[-1] - v[0]),
                               "span": float(v.max() - v.min()), "trend_per_day": None, "trend_sigma": None,
                               "trend_n_sigma": None}
        if days is not None and v.size >= 2:
            sig = None if any(x is None for x in sg) else np.array(sg, float)
            slope, ss = weighted_trend(days, v, sig)
            row["trend_per_day"], row["trend_sigma"] = slope, ss
            row["trend_n_sigma"] = abs(slope) / ss if ss else None
        params.append(row)
    return _json_safe({
        "schema": SUMMARY_SCHEMA, "ordered_by": "t_start" if timed else "input",
        "logs": [{"log": r["log"], "t_start": r.get("t_start")} for r in order], "failed": failed,
        "days": None if days is None else days.tolist(), "params": params,
    })


def summary_table(summary: dict[str, Any]) -> str:
    """The summary as a text table (one row per parameter); trend flagged '*' when beyond 3σ."""
    timed = summary["ordered_by"] == "t_start"
    n_ok, n_bad = len(summary["logs"]), len(summary["failed"])
    lines = [f"fleet: {n_ok} logs ok, {n_bad} failed; ordered by "
             + (f"start time over {summary['days'][-1]:.2f} days" if timed else
                "the order given (no wall-clock start times: no trend per day)")]
    head = f"{'parameter':<16}{'unit':>7}{'first':>13}{'last':>13}{'span':>11}{'trend/day':>12}{'± σ':>10}"
    lines += [head, "-" * (len(head) + 2)]
    for r in summary["params"]:
        tr = "—" if r["trend_per_day"] is None else f"{r['trend_per_day']:+.3e}"
        ts = "—" if r["trend_sigma"] is None else f"{r['trend_sigma']:.1e}"
        flag = " *" if (r["trend_n_sigma"] or 0) > 3 else ""
        lines.append(f"{r['param']:<16}{r['unit']:>7}{r['first']:>+13.6f}{r['last']:>+13.6f}{r['span']:>11.2e}"
                     f"{tr:>12}{ts:>10}{flag}")
    for f in summary["failed"]:
        lines.append(f"failed: {f}")
    return "\n".join(lines)
