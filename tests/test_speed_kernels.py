"""The compiled kernels (onlinecal.ukf.kernels) against the numpy reference they replace: equal within 1e-9
relative on random inputs of the filter's shapes, and the whole filter on both backends."""

from __future__ import annotations

import math
import os
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
from filterpy.kalman import MerweScaledSigmaPoints

from onlinecal.ukf import kernels
from onlinecal.ukf.layout import model_pair, rot_log
from onlinecal.ukf.propagate import BlockPrediction, propagate_block, propagate_block_numpy

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba not installed: only the numpy path exists")

RTOL = 1e-9


def _close(a: np.ndarray, b: np.ndarray, scale: float | None = None) -> None:
    """|a − b| ≤ 1e-9 × the reference's magnitude (its largest |entry| unless ``scale`` is given)."""
    b = np.asarray(b, float)
    s = float(np.max(np.abs(b))) if scale is None else scale
    err = float(np.max(np.abs(np.asarray(a, float) - b)))
    assert err <= RTOL * s, (err, s)


def _random_block(rng: np.random.Generator, S: int = 81, Sd: int = 31, L: int = 20, big: bool = False):
    n = 40
    X = rng.normal(0, 0.02, (S, n))
    X[:, 0:3] = rng.normal(0, 0.5 if big else 0.01, (S, 3))  # attitude errors, past 0.05 rad: the sinc branch
    X[:, 6:9] += 1.0  # gyro scale
    X[:, 39] = 1.1 + rng.normal(0, 0.05, S)  # dip
    dyn = np.concatenate([[0], np.sort(rng.choice(np.arange(1, S), Sd - 1, replace=False))])
    R_nom = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    R_nom *= np.sign(np.linalg.det(R_nom))
    w = rng.normal(0, 3.0 if big else 0.5, (L + 1, 3))
    dt = 0.005 * (1 + 0.1 * rng.random(L))
    c = rng.random(L + 1)
    o_g, M_g, _ = model_pair(X[dyn, 3:15])
    return X, R_nom, w, dt, c / c.sum(), dyn, (o_g, M_g)


@pytest.mark.parametrize("case", ["plain", "mag", "mag+extra", "fast-turns", "one-sample"])
def test_propagate_kernel_equals_numpy(case):
    rng = np.random.default_rng(zlib.crc32(case.encode()))  # not hash(): salted per process
    X, R_nom, w, dt, c, dyn, gyro = _random_block(rng, big=case == "fast-turns", L=1 if case == "one-sample" else 20)
    c_mag = None if case == "plain" else c
    extra = rng.normal(0, 0.05, (dyn.size, w.shape[0], 3)) if case == "mag+extra" else None
    with kernels.use_backend("numba"):
        a = propagate_block(X, R_nom, w, dt, c_mag, dyn, gyro, extra)
    b = propagate_block_numpy(X, R_nom, w, dt, c_mag, dyn, gyro, extra)
    assert isinstance(a, BlockPrediction)
    for f in ("R_end", "f_body", "h_body", "o_gyr", "M_gyr"):
        va, vb = getattr(a, f), getattr(b, f)
        if vb is None:
            assert va is None
            continue
        assert va.shape == vb.shape
        _close(va, vb, 1.0)  # entries of rotations and unit vectors: magnitude 1
    # the rotations stay rotations
    assert np.allclose(a.R_end @ a.R_end.transpose(0, 2, 1), np.eye(3), atol=1e-12)


def test_backend_switch():
    old = kernels.backend()
    with kernels.use_backend("numpy"):
        assert kernels.backend() == "numpy"
    assert kernels.backend() == old
    with pytest.raises(ValueError):
        kernels.set_backend("fortran")


def test_model_pair_kernel_equals_layout():
    rng = np.random.default_rng(3)
    p = np.concatenate([rng.normal(0, 0.1, (193, 3)), 1 + rng.normal(0, 0.1, (193, 3)),
                        rng.normal(0, 0.05, (193, 6))], axis=1)
    ref = model_pair(p)
    got = kernels.model_pair_kernel(p)
    for a, b in zip(got, ref, strict=True):
        _close(a, b)
    # M⁻¹ is the inverse of M: the two halves of the kernel agree with each other, not only with layout
    assert np.allclose(got[1] @ got[2], np.eye(3), atol=1e-13)


def test_rot_log_rel_kernel_equals_layout():
    rng = np.random.default_rng(4)
    from onlinecal.ukf.layout import rodrigues

    R = rodrigues(rng.normal(0, 0.8, (31, 3)))
    R[5] = R[0]  # zero relative rotation: the series branch
    ref = rot_log(R[0].T @ R)
    _close(kernels.rot_log_rel_kernel(R), ref, 1.0)


def _spd(rng: np.random.Generator, n: int) -> np.ndarray:
    A = rng.normal(size=(n, n)) * np.logspace(-4, 0, n)
    return A @ A.T + 1e-10 * np.eye(n)


def test_sigma_points_kernel_equals_numpy_and_filterpy():
    rng = np.random.default_rng(5)
    n = 40
    P, x = _spd(rng, n), rng.normal(size=n)
    perm = rng.permutation(n)
    alpha = 0.3
    lam = alpha**2 * n - n
    X, ok = kernels.sigma_points_kernel(x, P, lam + n, perm.astype(np.intp))
    assert ok
    U = np.linalg.cholesky((lam + n) * P[np.ix_(perm, perm)]).T
    D = np.empty((n, n))
    D[:, perm] = U
    ref = np.vstack([x, x + D, x - D])
    _close(X, ref)
    # any square root gives the same first two moments: mean x and covariance P (filterpy's weights)
    sp = MerweScaledSigmaPoints(n, alpha=alpha, beta=2.0, kappa=0.0)
    m = sp.Wm @ X
    Y = X - m
    _close(m, x)
    _close((Y.T * sp.Wc) @ Y, P)
    bad = P.copy()
    bad[3, 3] = -1.0
    assert not kernels.sigma_points_kernel(x, bad, 1.0, perm.astype(np.intp))[1]
    assert not kernels.sigma_points_kernel(x, P * np.nan, 1.0, perm.astype(np.intp))[1]


def test_unscented_innovation_and_gain_kernels_equal_numpy():
    rng = np.random.default_rng(6)
    n, S, m = 40, 81, 6
    sp = MerweScaledSigmaPoints(n, alpha=0.3, beta=2.0, kappa=0.0)
    Wm, Wc = sp.Wm, sp.Wc
    X = rng.normal(size=(S, n)) * 0.1
    q = rng.random(n) * 1e-6
    x_pred, Y, P_pred = kernels.unscented_kernel(X, Wm, Wc, q)
    xr = Wm @ X
    Yr = X - xr
    Pr = (Yr.T * Wc) @ Yr + np.diag(q)
    _close(x_pred, xr)
    _close(Y, Yr)
    _close(P_pred, Pr)
    Z = rng.normal(size=(S, m))
    z = rng.normal(size=m)
    r = rng.random(m) + 0.1
    z_pred, S_zz, hph, Pxz, nu, nis = kernels.innovation_kernel(Y, Z, z, Wm, Wc, r, np.ones(2, bool))
    zr = Wm @ Z
    Zc = Z - zr
    Sr = Zc.T @ (Zc * Wc[:, None])
    _close(z_pred, zr)
    _close(hph, np.diag(Sr))
    Sr = Sr + np.diag(r)
    _close(S_zz, Sr)
    _close(Pxz, Yr.T @ (Zc * Wc[:, None]))
    _close(nu, z - zr)
    nis_ref = [float(nu[k:k + 3] @ np.linalg.solve(Sr[k:k + 3, k:k + 3], nu[k:k + 3])) for k in (0, 3)]
    _close(nis, np.array(nis_ref))
    consider = np.zeros(n, bool)
    consider[[7, 20]] = True
    S_gain = Sr + np.diag(rng.random(m))
    x_new, P_new, ok = kernels.gain_update_kernel(x_pred, P_pred, Pxz, Sr, S_gain, nu, consider)
    assert ok
    K = np.linalg.solve(S_gain, Pxz.T).T
    K[consider] = 0.0
    KP = K @ Pxz.T
    _close(x_new, xr + K @ nu)
    _close(P_new, Pr - KP - KP.T + (K @ Sr) @ K.T)
    assert np.all(x_new[consider] == x_pred[consider])
    # a linear-Gaussian case with the optimal gain: the Kalman update exactly
    H = rng.normal(size=(m, n))
    Pk = _spd(rng, n)
    R = np.diag(r)
    Sk = H @ Pk @ H.T + R
    Pxz_k = Pk @ H.T
    xk, Pk_new, ok = kernels.gain_update_kernel(np.zeros(n), Pk, Pxz_k, Sk, Sk, nu, np.zeros(n, bool))
    Kk = Pxz_k @ np.linalg.inv(Sk)
    _close(Pk_new, (np.eye(n) - Kk @ H) @ Pk, float(np.max(np.abs(Pk))))
    _close(xk, Kk @ nu)


@pytest.mark.slow
def test_numba_cache_dir_falls_back_when_package_dir_is_unwritable(tmp_path):
    """With no cache directory possible next to the kernels (``__pycache__`` there is a plain file, which
    no user, root included, can create files in) and no NUMBA_CACHE_DIR, the kernels module picks a
    writable user cache dir ($XDG_CACHE_HOME/onlinecal/numba), compiles there, and a second process loads
    the cache instead of compiling again."""
    import shutil

    src = Path(kernels.__file__).resolve().parents[1]
    pkg = tmp_path / "copy" / "onlinecal"
    shutil.copytree(src, pkg, ignore=shutil.ignore_patterns("__pycache__", "*.nbi", "*.nbc"))
    (pkg / "ukf" / "__pycache__").write_text("not a directory")
    cache = tmp_path / "xdg" / "onlinecal" / "numba"
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env.update(PYTHONPATH=str(pkg.parent), XDG_CACHE_HOME=str(tmp_path / "xdg"), PYTHONDONTWRITEBYTECODE="1",
               NUMBA_DEBUG_CACHE="1")
    code = ("import os, numpy as np; from onlinecal.ukf import kernels as k; "
            "print(os.environ.get('NUMBA_CACHE_DIR')); "
            "print(k.rot_log_rel_kernel(np.eye(3)[None]).sum())")
    outs = []
    for _ in range(2):
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300,
                             cwd=tmp_path)
        assert out.returncode == 0, out.stderr[-2000:]
        assert out.stdout.split()[0] == str(cache)
        assert float(out.stdout.split()[-1]) == 0.0
        outs.append(out.stdout)
    assert list(cache.rglob("*.nbi")), "nothing cached"
    assert "data saved" in outs[0] and "data loaded" in outs[1], outs[1][-1000:]
    assert (pkg / "ukf" / "__pycache__").is_file()


def _meas_case(rng: np.random.Generator, S: int, names: list[str], scale: float):
    from onlinecal.ukf.unscented import Measurement

    out = []
    for s in names:
        Z = rng.normal(size=(S, 3)) * 0.1 + rng.normal(size=3)
        z = Z.mean(axis=0) + rng.normal(size=3) * scale  # scale: how far the reading is (NIS size)
        out.append(Measurement(s, z, Z, rng.random(3) * 0.01 + 0.001))
    return out


@pytest.mark.parametrize("case", ["accel+mag", "accel-dropped", "mag-soft", "rest-static", "all-dropped", "damped"])
def test_update_equals_unscented_update(case):
    """kernels_unscented.update against onlinecal.ukf.unscented.update (the numpy reference): posterior,
    NIS with its status (ok / soft / drop) and the posterior measurement prediction, on every gating path."""
    from onlinecal.ukf import kernels_unscented as ku
    from onlinecal.ukf import unscented as un

    # a seed fixed per case (hash() is salted per process: 11 draws in 3000 left the +5 reading inside the gate)
    rng = np.random.default_rng(zlib.crc32(case.encode()))
    n = 40
    S = 2 * n + 1
    Wm, Wc = un.merwe_weights(n, 0.3, 2.0, 0.0)
    X = rng.normal(size=(S, n)) * 0.05
    x_pred, Y, P_pred = un.predict_moments(X, Wm, Wc, rng.random(n) * 1e-6)
    names = {"accel+mag": ["accel", "mag"], "accel-dropped": ["accel", "mag"], "mag-soft": ["accel", "mag"],
             "rest-static": ["accel", "mag", "rest"], "all-dropped": ["accel"], "damped": ["accel", "mag"]}[case]
    meas = _meas_case(rng, S, names, 0.05)
    if case in ("accel-dropped", "all-dropped"):
        meas[0].z = meas[0].z + 5.0
    if case == "mag-soft":
        meas[1].z = meas[1].z + 5.0
    gates = {"accel": 16.27, "mag": 21.1}
    gating = un.Gating(gates, static=case == "rest-static")
    consider = np.zeros(n, bool)
    consider[[6, 7, 8]] = True
    damp = 4.0 if case == "damped" else 0.0
    want_post = case in ("rest-static", "mag-soft")
    ref = un.update(Y, x_pred, P_pred, meas, Wm, Wc, gating, consider, damp, want_post)
    with kernels.use_backend("numba"):
        got = ku.update(Y, x_pred, P_pred, meas, Wm, Wc, gating, consider, damp, want_post)
    _close(got.x, ref.x)
    _close(got.P, ref.P)
    assert [(s, st) for s, _, st in got.nis] == [(s, st) for s, _, st in ref.nis]
    _close(np.array([v for _, v, _ in got.nis]), np.array([v for _, v, _ in ref.nis]))
    expected_status = {"accel-dropped": "drop", "all-dropped": "drop", "mag-soft": "soft"}.get(case)
    if expected_status:
        assert expected_status in [st for _, _, st in got.nis]
    assert set(got.post) == set(ref.post)
    for k in ref.post:
        _close(got.post[k][0], ref.post[k][0])
        _close(got.post[k][1], ref.post[k][1])
    if case == "all-dropped":
        assert np.array_equal(got.x, x_pred) and np.array_equal(got.P, P_pred)


def test_sigma_points_and_moments_equal_unscented():
    from onlinecal.ukf import kernels_unscented as ku
    from onlinecal.ukf import unscented as un

    rng = np.random.default_rng(8)
    n = 40
    P, x = _spd(rng, n), rng.normal(size=n)
    perm = rng.permutation(n).astype(np.intp)
    for pid in (True, False):
        ref = un.sigma_points(x, P, 0.3, 0.0, perm, pid)
        with kernels.use_backend("numba"):
            got = ku.sigma_points(x, P, 0.3, 0.0, perm, pid)
            with pytest.raises(np.linalg.LinAlgError):
                ku.sigma_points(x, -P, 0.3, 0.0, perm, pid)
        _close(got, ref)
    Wm, Wc = un.merwe_weights(n, 0.3, 2.0, 0.0)
    q = rng.random(n)
    ref3 = un.predict_moments(ref, Wm, Wc, q)
    with kernels.use_backend("numba"):
        got3 = ku.predict_moments(ref, Wm, Wc, q)
    for a, b in zip(got3, ref3, strict=True):
        _close(a, b)


@pytest.mark.slow
def test_unknown_backend_in_the_environment_warns_and_runs_on_the_default(tmp_path):
    env = {**os.environ, "ONLINECAL_KERNELS": "fortran",
           "PYTHONPATH": str(Path(kernels.__file__).resolve().parents[2])}
    out = subprocess.run([sys.executable, "-c", "from onlinecal.ukf import kernels as k; print(k.backend())"],
                         env=env, capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "numba"
    assert "ONLINECAL_KERNELS='fortran'" in out.stderr and "Traceback" not in out.stderr


def _cholesky_row_by_row(A: np.ndarray) -> tuple[np.ndarray, bool]:
    """The Cholesky kernel's loop before issue 15's fifth round, one row at a time, on Python floats (the same
    IEEE operations as the compiled scalar loop: numba contracts nothing without fastmath)."""
    n = A.shape[0]
    L = [[0.0] * n for _ in range(n)]
    a = A.tolist()
    for j in range(n):
        d = a[j][j]
        for k in range(j):
            d -= L[j][k] * L[j][k]
        if not d > 0.0:
            return np.array(L), False
        L[j][j] = math.sqrt(d)
        inv = 1.0 / L[j][j]
        for i in range(j + 1, n):
            acc = a[i][j]
            for k in range(j):
                acc -= L[i][k] * L[j][k]
            L[i][j] = acc * inv
    return np.array(L), True


def test_cholesky_four_rows_at_once_is_bit_identical_to_row_by_row() -> None:
    """cholesky_kernel, eight rows of a column at a time, against the row-by-row loop: the same factor bit for
    bit on SPD matrices of 1–41 rows with scales over 8 decades, and the same refusal of an indefinite one."""
    from onlinecal.ukf.kernels_update import cholesky_kernel

    rng = np.random.default_rng(15)
    for trial in range(120):
        n = 1 + trial % 41
        B = rng.normal(size=(n, n)) * 10 ** rng.uniform(-6, 2, n)
        A = B @ B.T + np.diag(10 ** rng.uniform(-12, 0, n))
        if trial % 10 == 9:
            A[n // 2, n // 2] = -1.0
        L1, ok1 = cholesky_kernel(A)
        L2, ok2 = _cholesky_row_by_row(A)
        assert ok1 == ok2, trial
        if ok1:
            assert np.array_equal(L1, L2), trial


def _pxz_in_place(Y: np.ndarray, Zc: np.ndarray) -> np.ndarray:
    """innovation_kernel's Pxz as it was accumulated (s outer, in place), on Python floats."""
    S, n = Y.shape
    m = Zc.shape[1]
    P = [[0.0] * m for _ in range(n)]
    y, zc = Y.tolist(), Zc.tolist()
    for s in range(S):
        for i in range(n):
            for j in range(m):
                P[i][j] += y[s][i] * zc[s][j]
    return np.array(P)


def _gain_P_one_at_a_time(P_pred, Kt, Pxz, S_zz) -> np.ndarray:
    """gain_update_kernel's covariance as it was formed, one entry at a time, on Python floats."""
    n, m = Pxz.shape
    kt, pxz, szz, pp = Kt.tolist(), Pxz.tolist(), S_zz.tolist(), P_pred.tolist()
    KS = [[0.0] * m for _ in range(n)]
    for i in range(n):
        for a in range(m):
            if kt[a][i] != 0.0:
                for b in range(m):
                    KS[i][b] += kt[a][i] * szz[a][b]
    P = [[0.0] * n for _ in range(n)]
    for i in range(n):
        for j in range(i, n):
            acc = pp[i][j]
            for a in range(m):
                acc += -kt[a][i] * pxz[j][a] - pxz[i][a] * kt[a][j] + KS[i][a] * kt[a][j]
            P[i][j] = P[j][i] = acc
    return np.array(P)


def test_update_loops_several_chains_at_once_are_bit_identical() -> None:
    """innovation_kernel's Pxz (a row of Y at a time, into its transpose) and gain_update_kernel's covariance
    (four entries at a time) against the one-at-a-time loops they replace: the same bits for n of 1–41 states,
    m of 3, 6 and 9 measurement components and consider states zeroing rows of the gain."""
    from onlinecal.ukf.kernels_update import _solve_small, gain_update_kernel, innovation_kernel

    rng = np.random.default_rng(16)
    for trial in range(60):
        n, m = 1 + trial % 41, 3 * (1 + trial % 3)
        S = 2 * n + 1
        Y = rng.normal(size=(S, n)) * 10 ** rng.uniform(-4, 1, n)
        Z = rng.normal(size=(S, m))
        Wm = np.full(S, 1.0 / S)
        z_pred, S_zz, _, Pxz, nu, _ = innovation_kernel(Y, Z, rng.normal(size=m), Wm, Wm, np.ones(m),
                                                         np.ones(m // 3, np.bool_))
        Zc = (Z - z_pred) * Wm[:, None]
        assert np.array_equal(Pxz, _pxz_in_place(Y, Zc)), trial
        B = rng.normal(size=(n, n))
        P_pred = B @ B.T + np.eye(n)
        consider = rng.random(n) < 0.2
        x, P, ok = gain_update_kernel(np.zeros(n), P_pred, Pxz, S_zz, S_zz, nu, consider)
        Kt, _ = _solve_small(S_zz, Pxz.T.copy())
        Kt[:, consider] = 0.0
        assert ok and np.array_equal(P, _gain_P_one_at_a_time(P_pred, Kt, Pxz, S_zz)), trial
