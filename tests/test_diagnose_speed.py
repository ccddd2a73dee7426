"""diagnose's small solves on one BLAS thread (onlinecal.diagnose.analysis.one_blas_thread, issues 13/15).

The speed-up changes where the arithmetic runs, not what it is: the thread-limited path must give the same
held-out gains, drift densities and fitted parameters as the library's default threading, and the limit
must be undone on exit (the caller's numpy keeps its threads)."""

from __future__ import annotations

import inspect

import numpy as np
import pytest
import threadpoolctl

from onlinecal.diagnose import diagnose
from onlinecal.diagnose.analysis import THREADED_ENV, one_blas_thread
from onlinecal.diagnose.score import solve
from onlinecal.sim import simulate


def _blas_threads() -> list[int]:
    return [int(i["num_threads"]) for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas"]


def test_one_blas_thread_limits_inside_and_restores_outside(monkeypatch) -> None:
    monkeypatch.delenv(THREADED_ENV, raising=False)
    # make the outside state something other than 1 even on a one-core runner, so "restored" can fail
    with threadpoolctl.threadpool_limits(2, user_api="blas"):
        before = _blas_threads()
        assert before and all(n == 2 for n in before)
        with one_blas_thread():
            assert all(n == 1 for n in _blas_threads())
        assert _blas_threads() == before
        monkeypatch.setenv(THREADED_ENV, "1")  # the switch back to the library's own threading
        with one_blas_thread():
            assert _blas_threads() == before


def test_diagnose_keeps_its_signature() -> None:
    # the decorator must not hide diagnose's keyword arguments from callers and introspection
    assert list(inspect.signature(diagnose).parameters) == ["logs", "g", "seed", "check", "calibration", "ukf",
                                                          "sampled"]


def test_solve_on_one_thread_equals_threaded_solve_to_1e10(monkeypatch) -> None:
    """A drift-sized normal-equation system (nuisance + banded knot block, 220 columns, the size that cost
    10–150 ms per factorisation with default threads on a loaded machine): same solution to 1e-10."""
    rng = np.random.default_rng(3)
    n, p_nuis, K = 4000, 40, 60
    t = np.linspace(0.0, 1.0, n)
    X_nuis = rng.normal(size=(n, p_nuis))
    knots = np.linspace(0.0, 1.0, K)
    hat = np.clip(1.0 - np.abs(t[:, None] - knots[None, :]) * (K - 1), 0.0, None)  # (n, K) hats
    X = np.column_stack([X_nuis] + [hat * rng.normal(1.0, 0.1, size=(n, 1)) for _ in range(3)])
    y = X @ rng.normal(size=X.shape[1]) + rng.normal(size=n)
    G, c = X.T @ X, X.T @ y
    with threadpoolctl.threadpool_limits(None):  # library default threading
        b_thr, inv_thr = solve(G, c, want_inv=True)
    with one_blas_thread():
        b_one, inv_one = solve(G, c, want_inv=True)
    np.testing.assert_allclose(b_one, b_thr, rtol=1e-10, atol=1e-10 * np.abs(b_thr).max())
    np.testing.assert_allclose(inv_one, inv_thr, rtol=1e-10, atol=1e-10 * np.abs(inv_thr).max())
    # and it is the least-squares solution (independent check, not the same code path)
    b_ref = np.linalg.lstsq(X, y, rcond=None)[0]
    np.testing.assert_allclose(b_one, b_ref, rtol=1e-8, atol=1e-8 * np.abs(b_ref).max())


@pytest.mark.slow
def test_diagnose_findings_equal_with_and_without_the_thread_limit(monkeypatch) -> None:
    """A short session with a drift candidate: findings, gains, thresholds and parameters equal (1e-8
    relative; quantities that are zero up to rounding compared absolutely)."""
    sim = simulate("paper", 5, duration=60.0)
    monkeypatch.setenv(THREADED_ENV, "1")
    a = diagnose([sim.data], check=False, ukf=False)
    monkeypatch.delenv(THREADED_ENV)
    b = diagnose([sim.data], check=False, ukf=False)
    assert a.verdict == b.verdict
    fa, fb = a.to_dict()["findings"], b.to_dict()["findings"]
    assert [(f["effect"], f["sensor"], f["axis"], f["significant"]) for f in fa] == \
        [(f["effect"], f["sensor"], f["axis"], f["significant"]) for f in fb]
    assert any(f["effect"] == "bias_drift" for f in fa)  # the drift density search ran

    def nums(x: object) -> list[float]:
        if isinstance(x, dict):
            return [v for k in sorted(x) for v in nums(x[k])]
        if isinstance(x, list):
            return [v for e in x for v in nums(e)]
        return [float(x)] if isinstance(x, float) else []

    va, vb = np.array(nums(fa)), np.array(nums(fb))
    assert va.size == vb.size and va.size > 20
    fin = np.isfinite(va)
    assert np.array_equal(fin, np.isfinite(vb))
    np.testing.assert_allclose(vb[fin], va[fin], rtol=1e-8, atol=1e-9)


def test_threaded_switch_is_read_per_call(monkeypatch) -> None:
    with threadpoolctl.threadpool_limits(2, user_api="blas"):
        monkeypatch.setenv(THREADED_ENV, "1")
        with one_blas_thread():
            assert all(n == 2 for n in _blas_threads())
        monkeypatch.setenv(THREADED_ENV, "0")  # only "1" switches the limit off
        with one_blas_thread():
            assert all(n == 1 for n in _blas_threads())
