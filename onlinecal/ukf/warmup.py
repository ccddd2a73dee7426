"""The filter's kernels compiled side by side in worker processes, once, on a first run (issue 15: a first
run's cost; ``onlinecal demo`` under a minute including its compilation).

numba compiles one function after another, under one lock per process. With an empty cache that is ~50 s of
a replay on this project's 2-core machine (docs/benchmarks.md, *First run*): more than the demo's own work,
and more than any per-sample gain left. numba has no parallel compilation, but its on-disk cache
(``cache=True``, :func:`.kernels._njit`) is shared by processes: workers compile their share into it, and the
process that runs the filter loads the results (~0.5 s) instead of compiling them.

**The plan** (:data:`PLAN`) is a list of stages; the jobs of a stage run side by side, one per worker, and a
stage starts when the one before it has finished. That order matters: a kernel compiled before its callees are
in the cache compiles them again itself (numba compiles a callee inside its caller's compilation, and saves
it). Stage 1 compiles the motion block's two halves (:func:`.fastpath.predict_kernel` and
:func:`.fastpath.update_fold_kernel`, each with everything it calls; they share no callee) and the small
kernels a replay calls directly; stage 2 the two kernels built from them (:func:`.fastpath.motion_kernel`,
:func:`.fastpath.rest_update_kernel`). Each job names a kernel and the argument types a replay gives it
(:data:`SIGNATURES`, checked by ``tests/test_warmup.py`` against what a replay compiles, and end to end: after
the warm-up a replay from an empty cache compiles nothing).

**When** (:func:`start`, :func:`ensure`): on the numba backend, with at least two CPUs, where one of the
plan's kernels is not in the cache yet (read from numba's cache index: the same key it looks up itself), and
unless ``ONLINECAL_WARMUP=0``. Commands that run the filter start it first thing (so that it overlaps reading
the log, the demo's simulation and batch); the calibrator waits for it when it is built. A second process
that finds another one compiling (a file lock beside the cache) waits for it instead of compiling the same
kernels again (pytest's workers, a fleet's). Nothing here changes what runs: the kernels are the same
functions, compiled by the same numba from the same source, whichever process compiled them. Any failure (a
worker that errs or dies, a plan that no longer matches the code, a timeout) only means that the filter's
process compiles what is missing itself, as it always did; :attr:`Warmup.report` says what happened.

Cost: two more Python processes for ~35 s on a first run, each with numba and LLVM loaded (~0.25 GB of memory
each while it compiles, measured); none on a warm cache (a look at nine index files, ~10 ms).
"""

from __future__ import annotations

import atexit
import contextlib
import hashlib
import importlib
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import IO, Any

from . import kernels

# argument types, one code per argument: f float64, i int64, b boolean; A/I/B + ndim a C-contiguous,
# writable, aligned array of float64/int64/bool (what numba's typeof gives the arrays a replay passes)
SIGNATURES: dict[str, str] = {
    "fastpath:predict_kernel": "A1 A2 f I1 A2 A2 A1 A1 b I1 A1 A1 A1 f f b f f f b A1 f f f f f A1 A1 f f i i i i",
    "fastpath:update_fold_kernel": "A2 A2 A1 A2 A2 A2 A2 A3 A1 b f A1 b f i i f A1 A1 A1 B1 f A2 f",
    "fastpath:motion_kernel": "A1 A2 f I1 A2 A2 A1 I1 A1 b I1 A1 A1 A1 f f b f f f b A1 f f f f A1 A1 f f i i i i f "
                              "b f f f A1 f i i A1 B1 f f A1 A1 f A1 A2",
    "fastpath:interp_weights_kernel": "I1 A1 i",
    "fastpath:field_cell_kernel": "A1 A1 A2",
    "fastpath:rest_update_kernel": "A1 A2 f I1 A2 A1 A1 b A1 f b A1 f A1 A1 i i i f f A1 B1 f i i i i",
    "kernels_detectors:rail_pass_kernel": "A2 I3 A2 A2 I1 A1 b A1 I1 b b f i",
    "blocks:_seg_median_kernel": "A1 B1 I1 i i A1",
    "kernels_magfit:mag_fit_figures": "A2",
}

# stages of jobs (a job: kernels compiled in that order by one worker); see the module's docstring
PLAN: tuple[tuple[tuple[str, ...], ...], ...] = (
    (("fastpath:predict_kernel", "kernels_detectors:rail_pass_kernel", "blocks:_seg_median_kernel"),
     ("fastpath:update_fold_kernel", "kernels_magfit:mag_fit_figures", "fastpath:interp_weights_kernel",
      "fastpath:field_cell_kernel")),
    (("fastpath:motion_kernel",), ("fastpath:rest_update_kernel",)),
)

TIMEOUT_S = 600.0  # a warm-up that takes longer is stopped; the filter's process compiles what is left


def _types(code: str) -> tuple[Any, ...]:
    """numba argument types of a :data:`SIGNATURES` entry."""
    from numba import types

    scalars = {"f": types.float64, "i": types.int64, "b": types.boolean}
    dtypes = {"A": types.float64, "I": types.int64, "B": types.boolean}
    out: list[Any] = []
    for c in code.split():
        if c in scalars:
            out.append(scalars[c])
        else:
            out.append(types.Array(dtypes[c[0]], int(c[1:]), "C"))
    return tuple(out)


def dispatcher(name: str) -> Any:
    """The compiled function named ``module:function`` (module within :mod:`onlinecal.ukf`)."""
    mod, fn = name.split(":")
    return getattr(importlib.import_module(f"{__package__}.{mod}"), fn)


def cached(name: str) -> bool | None:
    """Whether numba's on-disk cache holds ``name`` for its :data:`SIGNATURES` entry: the key numba's
    ``Dispatcher.compile`` looks up (``Cache._index_key``) against the index file it reads. None where that
    cannot be told (numba's internals changed, no cache): the caller then does nothing."""
    try:
        d = dispatcher(name)
        c = d._cache
        key = c._index_key(_types(SIGNATURES[name]), d.targetctx.codegen())
        return key in c._cache_file._load_index()
    except Exception:  # noqa: BLE001 - private API of numba: unknown means "leave it to numba"
        return None


def missing() -> list[str] | None:
    """The plan's kernels not in the cache (empty: nothing to do), or None where that cannot be told."""
    out = []
    for stage in PLAN:
        for job in stage:
            for name in job:
                c = cached(name)
                if c is None:
                    return None
                if not c:
                    out.append(name)
    return out


def _cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _lock_path() -> Path:
    """A lock file per cache location (numba's cache directory, or this package's own next to its files)."""
    where = os.environ.get("NUMBA_CACHE_DIR") or str(Path(__file__).resolve().parent)
    tag = hashlib.sha256(where.encode()).hexdigest()[:16]
    uid = os.getuid() if hasattr(os, "getuid") else "user"
    return Path(tempfile.gettempdir()) / f"onlinecal-warmup-{uid}-{tag}.lock"


class Warmup:
    """A warm-up under way: workers compiling :data:`PLAN`'s stages into numba's cache, driven by a thread of
    this process; or, where another process holds the lock, the wait for that one. :meth:`wait` joins it.

    ``report``: ``started`` (what was missing), ``workers``, ``stages`` (per stage, per job: the kernels asked
    for, every function the worker compiled rather than loaded, seconds), ``errors`` (one line each),
    ``waited_for_other`` (another process was compiling), ``seconds`` (wall)."""

    def __init__(self, plan: tuple[tuple[tuple[str, ...], ...], ...] = PLAN, todo: list[str] | None = None,
                 lock_path: Path | None = None) -> None:
        self.plan = plan
        self.lock_path = lock_path or _lock_path()  # (tests give their own: a real warm-up may hold the default)
        self.report: dict[str, Any] = {"started": list(todo or []), "workers": 0, "stages": [], "errors": [],
                                       "waited_for_other": False, "seconds": 0.0}
        self._t0 = time.perf_counter()
        self._procs: list[subprocess.Popen[str]] = []
        self._lock_fh: IO[bytes] | None = None
        self._thread = threading.Thread(target=self._drive, name="onlinecal-warmup", daemon=True)
        self._done = threading.Event()
        self._thread.start()

    # ---- the lock: one process compiles, the others wait for it
    def _acquire(self) -> bool:
        """True: this process compiles; False: another one was, and has finished (or the lock is unusable)."""
        try:
            import fcntl
        except ImportError:  # (Windows: no lock; the workers may then compile beside another process's)
            return True
        try:
            fh = self.lock_path.open("ab")
        except OSError:
            return True
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            self.report["waited_for_other"] = True
            deadline = time.monotonic() + TIMEOUT_S
            while time.monotonic() < deadline:  # (a blocking flock cannot time out)
                try:
                    fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except OSError:
                    time.sleep(0.2)
            else:
                self.report["errors"].append(f"another process held {self.lock_path} for {TIMEOUT_S:.0f} s")
            fh.close()
            return False
        self._lock_fh = fh
        return True

    def _drive(self) -> None:
        try:
            if not self._acquire():
                return
            n = max(len(stage) for stage in self.plan)
            env = dict(os.environ)
            root = Path(__file__).resolve().parents[2]
            if root.name not in ("site-packages", "dist-packages"):
                # a source tree, or one a program put on sys.path itself: the workers must compile these very
                # files (numba's cache is kept per source file); an installed package they find as this one did
                env["PYTHONPATH"] = str(root) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
            for _ in range(n):
                self._procs.append(subprocess.Popen(
                    [sys.executable, "-m", "onlinecal.ukf.warmup"], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                    stderr=subprocess.DEVNULL, text=True, env=env))
            self.report["workers"] = n
            for stage in self.plan:
                rows = []
                for p, job in zip(self._procs, stage, strict=False):
                    assert p.stdin is not None
                    p.stdin.write(" ".join(job) + "\n")
                    p.stdin.flush()
                for p, job in zip(self._procs, stage, strict=False):
                    assert p.stdout is not None
                    line = p.stdout.readline()
                    if not line:
                        self.report["errors"].append(f"{' '.join(job)}: the worker stopped (exit {p.poll()})")
                        rows.append({"job": list(job), "compiled": [], "seconds": None})
                        continue
                    r = json.loads(line)
                    if r.get("error"):
                        self.report["errors"].append(f"{' '.join(job)}: {r['error']}")
                    rows.append({"job": list(job), "compiled": r.get("compiled", []), "seconds": r.get("seconds")})
                self.report["stages"].append(rows)
        except Exception as e:  # noqa: BLE001 - a warm-up that fails leaves the compiling to the filter's process
            self.report["errors"].append(f"{type(e).__name__}: {e}")
        finally:
            self._finish()

    def _finish(self) -> None:
        for p in self._procs:
            with contextlib.suppress(OSError, ValueError):
                if p.stdin is not None:
                    p.stdin.close()
        for p in self._procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
            if p.stdout is not None:
                p.stdout.close()
        if self._lock_fh is not None:
            self._lock_fh.close()  # (releases the flock)
            self._lock_fh = None
        self.report["seconds"] = round(time.perf_counter() - self._t0, 2)
        self._done.set()

    def wait(self, timeout: float = TIMEOUT_S) -> bool:
        """Wait for the warm-up (at most ``timeout`` s: then its workers are stopped). True where it finished
        without an error."""
        if not self._done.wait(timeout):
            self.report["errors"].append(f"stopped after {timeout:.0f} s")
            for p in self._procs:
                with contextlib.suppress(OSError):
                    p.kill()
            self._done.wait(30)
        return not self.report["errors"]


_current: Warmup | None = None
_checked = False
_guard = threading.Lock()


def enabled() -> bool:
    """On the numba backend with the fast path on (the plan's kernels are the fast path's), two CPUs or more,
    and not ``ONLINECAL_WARMUP=0``."""
    flag = os.environ.get("ONLINECAL_WARMUP", "1").strip().lower() not in ("0", "false", "no", "off")
    if not (flag and kernels.backend() == "numba" and _cpus() >= 2):
        return False
    from . import fastpath

    return fastpath.enabled()


def _stop_at_exit() -> None:
    """A process that ends while its warm-up runs stops the workers (they would otherwise finish their job)."""
    w = _current
    if w is not None and not w._done.is_set():
        for p in w._procs:
            with contextlib.suppress(OSError):
                p.kill()


def start() -> Warmup | None:
    """Start the warm-up where :func:`enabled` and a kernel of the plan is missing from the cache; at most once
    per process (later calls return the same one, or None where there was nothing to do). Cheap where the
    cache is warm: a look at the index files of the plan's seven kernels."""
    global _current, _checked
    with _guard:
        if _checked:
            return _current
        if not enabled():  # (not marked as checked: a later call on the numba backend may still warm up)
            return None
        _checked = True
        todo = missing()
        if todo:
            _current = Warmup(PLAN, todo)
            atexit.register(_stop_at_exit)
        return _current


def ensure(timeout: float = TIMEOUT_S) -> Warmup | None:
    """:func:`start` if it was not, and wait for it: after this the plan's kernels load from the cache, or the
    caller compiles what a failed warm-up left (as without one). Returns the warm-up, None where none ran."""
    w = start()
    if w is not None:
        w.wait(timeout)
    return w


def _worker() -> None:
    """A worker: reads jobs (kernel names, one job a line) on stdin, compiles each into the cache, answers one
    JSON line per job: every function it compiled (not loaded), seconds, an error. Ends at end of input."""
    from numba.core import event

    compiled: list[str] = []

    class _Listener(event.Listener):
        def on_start(self, ev: Any) -> None:
            pass

        def on_end(self, ev: Any) -> None:
            f = ev.data["dispatcher"].py_func
            compiled.append(f"{f.__module__}:{f.__qualname__}")

    event.register("numba:compile", _Listener())
    for line in sys.stdin:
        compiled.clear()
        t0 = time.perf_counter()
        err = ""
        try:
            for name in line.split():
                dispatcher(name).compile(_types(SIGNATURES[name]))
        except Exception as e:  # noqa: BLE001 - reported to the driver, which leaves it to the filter's process
            err = f"{type(e).__name__}: {e}".splitlines()[0]
        sys.stdout.write(json.dumps({"compiled": list(compiled), "seconds": round(time.perf_counter() - t0, 2),
                                     "error": err}) + "\n")
        sys.stdout.flush()


if __name__ == "__main__":
    _worker()
