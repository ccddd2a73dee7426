"""The first run's kernels compiled in worker processes (onlinecal.ukf.warmup, issue 15).

What must hold: the plan's signatures are the ones a replay gives its kernels (else the workers compile
versions nobody loads); after a warm-up from an empty cache the filter's process compiles none of the filter's
kernels and no kernel is compiled twice (stage order and signatures right); the result is the same bits as a
filter whose kernels were compiled in its own process; a failing worker or a lock held by another process
never fails the caller."""

from __future__ import annotations

import fcntl
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from onlinecal.ukf import kernels, warmup

ROOT = Path(__file__).resolve().parents[1]


def test_plan_and_signatures_name_the_same_kernels():
    """Every kernel the plan compiles has a signature, every signature is in the plan once, and each entry has
    as many argument types as its function has parameters."""
    import inspect

    planned = [n for stage in warmup.PLAN for job in stage for n in job]
    assert sorted(planned) == sorted(warmup.SIGNATURES)
    assert len(set(planned)) == len(planned)
    for name, code in warmup.SIGNATURES.items():
        fn = warmup.dispatcher(name).py_func
        assert len(warmup._types(code)) == len(inspect.signature(fn).parameters), name


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba not installed")
def test_signatures_are_those_a_replay_compiles():
    """A replay that takes every planned kernel from Python (a cold start on a paper session: rest and motion
    blocks, the rail detector's pass, the magnetometer's cold fit) gives the kernels it calls directly exactly
    the plan's argument types. (The two halves of the motion kernel are its callees and have no signature of
    their own in a process that loaded it: the end-to-end test below checks them.)"""
    from onlinecal.sim import simulate
    from onlinecal.ukf import replay

    d = simulate("paper", 5).data
    with kernels.use_backend("numba"):
        replay([d.slice_imu(0, 30000)], None)
    for name in ("fastpath:motion_kernel", "fastpath:rest_update_kernel", "kernels_detectors:rail_pass_kernel",
                 "blocks:_seg_median_kernel", "kernels_magfit:mag_fit_figures"):
        sigs = [tuple(s) for s in warmup.dispatcher(name).signatures]
        assert warmup._types(warmup.SIGNATURES[name]) in sigs, (name, sigs)


_E2E = r"""
import json, os, sys
from numba.core import event
compiled = []
class L(event.Listener):
    def on_start(self, e): pass
    def on_end(self, e):
        f = e.data["dispatcher"].py_func
        compiled.append(f.__module__ + ":" + f.__qualname__)
from onlinecal.ukf import warmup
todo = warmup.missing()
w = warmup.start()
event.register("numba:compile", L())
from onlinecal.sim import simulate
from onlinecal.ukf import replay
d = simulate("paper", 5).data.slice_imu(0, 30000)
res = replay([d], None)  # (the calibrator waits for the warm-up)
print(json.dumps({"todo": todo, "report": w.report if w else None, "main": compiled,
                  "x": res.calibration.to_dict()}))
"""


@pytest.mark.slow
@pytest.mark.skipif(not kernels.HAVE_NUMBA or warmup._cpus() < 2, reason="needs numba and two CPUs")
def test_warmup_from_an_empty_cache_leaves_nothing_to_compile(tmp_path):
    """From an empty cache (a fresh NUMBA_CACHE_DIR) in a new process: the warm-up runs with two workers and
    no error; stage 2 compiles only its own kernels (their callees came from stage 1's cache: the stage order
    and the callees' signatures are right); no function of the package is compiled by two workers; the
    replay's own process compiles none of the package's kernels; and its result is the same bits as this
    process's replay (kernels compiled or loaded here)."""
    from onlinecal.sim import simulate
    from onlinecal.ukf import replay

    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"), PYTHONPATH=str(ROOT),
               ONLINECAL_KERNELS="numba", ONLINECAL_WARMUP="1", ONLINECAL_FASTPATH="1")
    out = subprocess.run([sys.executable, "-c", _E2E], env=env, capture_output=True, text=True, timeout=900,
                         cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert sorted(r["todo"]) == sorted(warmup.SIGNATURES)  # the cache was empty: everything to do
    rep = r["report"]
    assert rep["errors"] == [] and rep["workers"] == 2 and not rep["waited_for_other"]
    assert len(rep["stages"]) == len(warmup.PLAN)
    for row in rep["stages"][1]:
        own = {f"onlinecal.ukf.{n}" for n in row["job"]}
        mine = {c for c in row["compiled"] if c.startswith("onlinecal.")}
        assert mine == own, (row["job"], sorted(mine - own))
    ours = [c for st in rep["stages"] for row in st for c in row["compiled"] if c.startswith("onlinecal.")]
    assert len(ours) == len(set(ours)), sorted(c for c in set(ours) if ours.count(c) > 1)
    assert [c for c in r["main"] if c.startswith("onlinecal.")] == []
    with kernels.use_backend("numba"):
        here = replay([simulate("paper", 5).data.slice_imu(0, 30000)], None).calibration.to_dict()
    for s in ("gyro", "accel", "mag"):
        there = r["x"][s]
        for k in ("bias", "matrix"):
            assert np.array_equal(np.asarray(there[k]), np.asarray(here[s][k])), (s, k)
        for k, v in here[s]["sigma"].items():
            assert np.array_equal(np.asarray(there["sigma"][k]), np.asarray(v)), (s, "sigma", k)


def test_a_failing_worker_is_reported_not_raised(tmp_path):
    """A plan naming a kernel that does not exist: the worker answers with the error, wait() says False and the
    report has the line; nothing is raised (the filter's process then compiles what it needs itself). (Its own
    lock file: another test process may be warming up the real cache just now.)"""
    w = warmup.Warmup(((("fastpath:no_such_kernel",),),), ["fastpath:no_such_kernel"], tmp_path / "lock")
    ok = w.wait(120)
    assert ok is False
    assert any("no_such_kernel" in e for e in w.report["errors"]), w.report
    assert w.report["workers"] == 1 and w._done.is_set()


def test_a_second_process_waits_for_the_one_compiling(tmp_path):
    """While another process holds the lock (here: this test, on the same lock file), a warm-up starts no
    worker: it waits until the lock is free, then returns with ``waited_for_other`` (the kernels are then
    in the cache, or compiled by the caller as before)."""
    lock = tmp_path / "lock"
    fh = lock.open("ab")
    fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
    try:
        w = warmup.Warmup(((("fastpath:no_such_kernel",),),), [], lock)
        released = threading.Timer(1.0, fh.close)
        t0 = time.monotonic()
        released.start()
        assert w.wait(60) is True
        assert time.monotonic() - t0 >= 0.9
    finally:
        if not fh.closed:
            fh.close()
    assert w.report["waited_for_other"] is True and w.report["workers"] == 0 and w.report["stages"] == []
