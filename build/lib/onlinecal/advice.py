"""Motion advice derived from the data: which of the six faces (an axis up or down) the sensor rested on.

The accelerometer's bias and scale on axis k are separable only with gravity along +k and along −k at rest
(paper Sec. III: ‖S'(a − o)‖ = g, eq. 32, needs opposite attitudes per axis). Advice that asks for a face
must therefore come from the faces the data holds, not from a σ that did not shrink: a filter started from
a batch fit whose σ is already small cannot halve it however many faces it sees, and asking for "y up and
y down" after the session held both contradicts the data.

Convention: the direction is that of the specific force at rest (what a resting accelerometer reads,
pointing up), so ``+y`` is "y up" and ``-y`` "y down".
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np
from numpy.typing import ArrayLike

AXES = ("x", "y", "z")
FACES = ("+x", "-x", "+y", "-y", "+z", "-z")
FACE_TOL_DEG = 30.0  # a rest counts for a face when gravity is within this angle of the axis


def faces_at_rest(f_dirs: ArrayLike, tol_deg: float = FACE_TOL_DEG) -> list[str]:
    """The faces (``"+x"`` … ``"-z"``, in FACES order) that the specific force at rest pointed along within
    ``tol_deg``. ``f_dirs`` (K, 3): the mean calibrated (or raw: a few % of scale error moves a direction by
    far less than the tolerance) accelerometer reading of each static segment, any length > 0."""
    f = np.asarray(f_dirs, float).reshape(-1, 3)
    n = np.linalg.norm(f, axis=1)
    f = f[np.isfinite(n) & (n > 0)] / n[np.isfinite(n) & (n > 0), None]
    if not f.size:
        return []
    c = math.cos(math.radians(tol_deg))
    seen = np.concatenate([(f > c).any(axis=0)[:, None], (-f > c).any(axis=0)[:, None]], axis=1).ravel()
    return [face for face, s in zip(FACES, seen, strict=True) if s]


def missing_faces(seen: Iterable[str], axes: Sequence[str] = AXES) -> list[str]:
    """The faces of ``axes`` (e.g. ``["y"]``) not in ``seen``, in FACES order."""
    have = set(seen)
    return [f for f in FACES if f[1] in axes and f not in have]


def face_words(face: str) -> str:
    """``"+y"`` → ``"y up"``, ``"-z"`` → ``"z down"``."""
    return f"{face[1]} {'up' if face[0] == '+' else 'down'}"


def faces_advice(missing: Sequence[str], seconds: float = 5.0) -> str | None:
    """One sentence asking for exactly the ``missing`` faces, or None when none is missing."""
    if not missing:
        return None
    return f"hold still for {seconds:g} s with " + " and with ".join(face_words(f) for f in missing)


def accel_face_advice(seen: Iterable[str], terms: Iterable[str]) -> str | None:
    """The face advice for the accelerometer terms ``terms`` (``"accel.bias.y"``, ``"accel.scale.x"``…) that
    the data left undetermined: the faces of their axes the data lacks, or None when it holds them all
    (the σ did not shrink for another reason: a start σ already small, or too short a rest)."""
    axes = sorted({t.split(".")[2] for t in terms if t.split(".")[1] in ("bias", "scale")})
    return faces_advice(missing_faces(seen, axes))
