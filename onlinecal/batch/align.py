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
