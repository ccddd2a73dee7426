"""Compiled twins of the raw-data detectors (issue 15): the rail detector's per-block rule
(:meth:`.detectors.RailDetector.check` for the usual block, 1 < L < ``rail_run``) over every block of a feed in
one call, instead of a Python call per block. The same comparisons on the same floats in the same order, so the
same decisions, rails and events (``tests/test_speed_fastpath.py``)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .kernels import _njit

Array = NDArray[np.float64]
_REL = 1 - 1e-9  # a reading at the rail: ≥ rail × (1 − 1e-9), as the Python rule


@_njit
def rail_pass_kernel(absmax: Array, runs: NDArray[np.intp], v0: Array, v1: Array, L: NDArray[np.intp],
                     rail: Array, learnt: bool, carry_v: Array, carry_n: NDArray[np.intp], has_carry: bool,
                     clip_on: bool, rail_min: float, rail_run: int
                     ) -> tuple[NDArray[np.bool_], NDArray[np.bool_], Array, bool, bool, bool]:
    """One sensor's rail detector over nb blocks, each 1 < L[b] < rail_run samples long.

    absmax (nb, 3) the block's largest |reading| per axis; runs (nb, 2, 3) its first and last runs of
    identical readings (:func:`.detectors.block_runs`); v0, v1 (nb, 3) its first and last readings. State, in
    place: rail (3,) the learnt rail per axis (inf where not learnt; ``learnt``: any axis learnt, the Python
    dict's key), carry_v (3,), carry_n (3,) the open run per axis (value, length; ``has_carry``), ``clip_on``.

    Returns (hit (nb,): the block reads at the rail; event (nb,): a clipped stretch starts; rail_at (nb, 3) the
    rail at each event; learnt, has_carry, clip_on after the last block)."""
    nb = absmax.shape[0]
    hit = np.zeros(nb, np.bool_)
    event = np.zeros(nb, np.bool_)
    rail_at = np.full((nb, 3), np.nan)
    nv = np.empty(3)
    nn = np.empty(3, np.intp)
    for b in range(nb):
        h = False
        if learnt:
            for k in range(3):
                if absmax[b, k] >= rail[k] * _REL:
                    h = True
        below = True
        for k in range(3):
            if not absmax[b, k] < rail_min:
                below = False
        if below:
            has_carry = False
        else:
            for k in range(3):  # .detectors._short_runs_given
                f = runs[b, 0, k]
                if has_carry and v0[b, k] == carry_v[k]:
                    f += carry_n[k]
                nv[k] = v1[b, k]
                nn[k] = runs[b, 1, k] if runs[b, 1, k] >= 0 else f
                val = abs(v0[b, k])
                if f >= rail_run and val >= rail_min:
                    if not learnt:
                        learnt = True
                        rail[0] = rail[1] = rail[2] = np.inf
                    if val < rail[k]:  # min(rail, val): val is a number here
                        rail[k] = val
                    h = True
            for k in range(3):
                carry_v[k] = nv[k]
                carry_n[k] = nn[k]
            has_carry = True
        if h and not clip_on:
            event[b] = True
            for k in range(3):
                rail_at[b, k] = rail[k]
        clip_on = h
        hit[b] = h
    return hit, event, rail_at, learnt, has_carry, clip_on
