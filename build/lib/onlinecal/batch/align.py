"""Rotation of a sensor frame to the body frame from rotation phases (eqs. 25–27).

During a phase about body axis e_k, any vector fixed in the world (field, gravity) keeps a constant
component along e_k (eq. 25): its calibrated samples lie on a circle in a plane normal to e_k. The
paper states this as max/min conditions on that component (eqs. 26–27); here it is solved in the
least-squares sense — the plane normal is the direction of least variance of the phase's samples —
and the rotation T_R that carries the normals onto e_x, e_y, e_z is the orthogonal Procrustes
solution (Kabsch).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def phase_plane_normal(v: Array, axis: int) -> tuple[Array, float, float]:
    """Normal of the circle traced by v (N, 3) during a phase about ``axis`` (eq. 25).

    Returns (unit normal with positive ``axis`` component, circle radius, swept share): the radius is
    the RMS distance from the centre in the plane, the share the ratio of the two in-plane spreads
    (1 for a full circle, 0 for a line), so callers can weigh or reject a phase.
    """
    c = v - v.mean(axis=0)
    w, V = np.linalg.eigh(c.T @ c / max(1, v.shape[0]))
    n = V[:, 0]
    if n[axis] < 0:
        n = -n
    radius = float(np.sqrt(max(w[1] + w[2], 0.0)))
    share = float(np.sqrt(max(w[1], 0.0) / w[2])) if w[2] > 0 else 0.0
    return n, radius, share


def rotation_to_axes(normals: dict[int, tuple[Array, float]]) -> Array:
    """Rotation Q with Q n_k ≈ e_k for the measured normals (eqs. 26–27 in least squares).

    ``normals`` maps an axis index to (unit normal in the sensor frame, weight). With two or three axes
    this is Kabsch's orthogonal Procrustes solution; with one, the smallest rotation that carries that
    normal onto its axis; with none, the identity.
    """
    if not normals:
        return np.eye(3)
    if len(normals) == 1:
        (k, (n, _)), = normals.items()
        e = np.eye(3)[k]
        v = np.cross(n, e)
        s, c = np.linalg.norm(v), float(n @ e)
        if s < 1e-15:
            return np.eye(3)
        K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]]) / s
        ang = np.arctan2(s, c)
        return np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K
    H = sum(w * np.outer(np.eye(3)[k], n) for k, (n, w) in normals.items())
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def cube_rotations() -> list[Array]:
    """The 24 proper rotations that map the coordinate axes onto ± axes (start points for any angle)."""
    out = []
    for perm in ((0, 1, 2), (1, 2, 0), (2, 0, 1), (0, 2, 1), (2, 1, 0), (1, 0, 2)):
        for sx in (1, -1):
            for sy in (1, -1):
                for sz in (1, -1):
                    R = np.zeros((3, 3))
                    R[0, perm[0]], R[1, perm[1]], R[2, perm[2]] = sx, sy, sz
                    if np.linalg.det(R) > 0:
                        out.append(R)
    return out


def rotvec_to_matrix(r: Array) -> Array:
    """exp([r]×) (3, 3) for a rotation vector r (3,), exact for any angle (Rodrigues)."""
    a = float(np.linalg.norm(r))
    K = np.array([[0, -r[2], r[1]], [r[2], 0, -r[0]], [-r[1], r[0], 0]])
    s = np.sinc(a / np.pi)
    c = 0.5 * np.sinc(a / (2 * np.pi)) ** 2
    return np.eye(3) + s * K + c * (K @ K)


def align_by_dip(a: Array, m: Array, weights: Array | None = None) -> tuple[Array, float, float, Array]:
    """Rotation P of the magnetometer frame onto the accelerometer frame from quasi-static samples.

    Gravity and the field are both world-fixed, so the angle between them (90° − dip) is the same at
    every attitude: ``(P m̂) · â = c`` for all samples. a, m (N, 3) calibrated vectors at the same
    times; P (any angle: Levenberg–Marquardt from each of the 24 axis-aligned rotations, the best kept)
    and c fitted together. Needs attitudes that tilt gravity about two axes. Returns (P (3, 3), c,
    residual RMS, covariance of (rotation vector, c) (4, 4)).
    """
    from scipy.optimize import least_squares

    ah = a / np.linalg.norm(a, axis=1, keepdims=True)
    mh = m / np.linalg.norm(m, axis=1, keepdims=True)
    sw = np.ones(ah.shape[0]) if weights is None else np.sqrt(np.asarray(weights, float))

    def resid(p: Array, R0: Array) -> Array:
        R = rotvec_to_matrix(p[:3]) @ R0
        return sw * (np.einsum("ij,ij->i", mh @ R.T, ah) - p[3])

    best = None
    for R0 in cube_rotations():
        c0 = float(np.median(np.einsum("ij,ij->i", mh @ R0.T, ah)))
        sol = least_squares(resid, np.array([0, 0, 0, c0]), args=(R0,), method="lm", x_scale="jac", max_nfev=60)
        if best is None or sol.cost < best[0].cost:
            best = (sol, R0)
    assert best is not None
    sol, R0 = best
    sol = least_squares(resid, sol.x, args=(R0,), method="lm", x_scale="jac")  # the winner to convergence
    P = rotvec_to_matrix(sol.x[:3]) @ R0
    r = sol.fun
    dof = max(1, r.size - 4)
    s2 = float(r @ r / dof)
    try:
        cov = np.linalg.inv(sol.jac.T @ sol.jac) * s2
    except np.linalg.LinAlgError:
        cov = np.full((4, 4), np.inf)
    return P, float(sol.x[3]), float(np.sqrt(s2)), cov
