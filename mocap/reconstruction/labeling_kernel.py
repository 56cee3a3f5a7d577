"""Compiled (numba) tracklet linking: mutual nearest neighbours between frames.

The same rule as the former k-d tree implementation (kept as
:func:`mocap.reconstruction.reference.link_tracklets_reference`), in one call per take: points are
grouped by frame and sorted by x within each frame, so a nearest-neighbour query scans only the
points within the gate in x. Compiled on first use and cached on disk.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _frame_buckets(fidx, x, n_frames):
    """Points grouped by frame index, sorted by x within each frame.

    fidx (n,) int in [0, n_frames); x (n,) mm. Returns ptr (n_frames + 1,), order (n,) and xs (n,)
    the points' x in ``order`` order.
    """
    n = fidx.size
    ptr = np.zeros(n_frames + 1, np.int64)
    for i in range(n):
        ptr[fidx[i] + 1] += 1
    for f in range(n_frames):
        ptr[f + 1] += ptr[f]
    fill = ptr[:-1].copy()
    order = np.empty(n, np.int64)
    for i in range(n):
        order[fill[fidx[i]]] = i
        fill[fidx[i]] += 1
    for f in range(n_frames):
        s, e = ptr[f], ptr[f + 1]
        if e - s > 1:
            seg = order[s:e].copy()
            o = np.argsort(x[seg], kind="mergesort")
            for r in range(e - s):
                order[s + r] = seg[o[r]]
    xs = np.empty(n)
    for r in range(n):
        xs[r] = x[order[r]]
    return ptr, order, xs


@njit(cache=True)
def _nearest(ptr, order, xs, X, f, q0, q1, q2, gate):
    """Index of the point of frame index f nearest to (q0, q1, q2) mm and closer than ``gate``
    mm (strictly), -1 if none."""
    s, e = ptr[f], ptr[f + 1]
    lo = q0 - gate
    while s < e:  # first position with x > q0 - gate
        mid = (s + e) // 2
        if xs[mid] <= lo:
            s = mid + 1
        else:
            e = mid
    e = ptr[f + 1]
    best = -1
    best_d = gate
    for r in range(s, e):
        d0 = xs[r] - q0
        if d0 >= gate:
            break
        j = order[r]
        d1 = X[j, 1] - q1
        d2 = X[j, 2] - q2
        d = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        if d < best_d:
            best_d = d
            best = j
    return best


@njit(cache=True)
def link_chains(fidx, X, n_frames, gate, max_gap):
    """Successor and predecessor (n,) of every point (-1 for none).

    fidx (n,) int frame index in [0, n_frames); X (n, 3) mm. For gap = 1 .. max_gap + 1 frames,
    every point still without a successor (all points for gap 1) is linked to its nearest point
    ``gap`` frames later when closer than ``gate`` mm, that point has no predecessor yet and the
    point is also its nearest ``gap`` frames back; one link per target (the lowest index wins).
    """
    n = fidx.size
    nxt = np.full(n, -1, np.int64)
    prv = np.full(n, -1, np.int64)
    ptr, order, xs = _frame_buckets(fidx, X[:, 0].copy(), n_frames)
    src = np.empty(n, np.int64)
    dst = np.empty(n, np.int64)
    taken = np.zeros(n, np.bool_)
    for gap in range(1, max_gap + 2):
        m = 0
        n_cand = 0
        for i in range(n):
            if gap > 1 and nxt[i] >= 0:
                continue
            n_cand += 1
            f = fidx[i] + gap
            if f >= n_frames:
                continue
            j = _nearest(ptr, order, xs, X, f, X[i, 0], X[i, 1], X[i, 2], gate)
            if j < 0 or prv[j] >= 0:
                continue
            if _nearest(ptr, order, xs, X, fidx[j] - gap, X[j, 0], X[j, 1], X[j, 2], gate) != i:
                continue
            src[m] = i
            dst[m] = j
            m += 1
        if n_cand == 0:
            break
        for r in range(m):  # links found in this pass, applied together
            if not taken[dst[r]]:
                taken[dst[r]] = True
                nxt[src[r]] = dst[r]
                prv[dst[r]] = src[r]
        for r in range(m):
            taken[dst[r]] = False
    return nxt, prv


@njit(cache=True)
def chain_labels(nxt, prv):
    """Tracklet id (n,) of every point: chains numbered in order of their lowest point index."""
    n = nxt.size
    label = np.full(n, -1, np.int64)
    count = 0
    for i in range(n):
        if label[i] >= 0:
            continue
        label[i] = count
        j = nxt[i]
        while j >= 0:
            label[j] = count
            j = nxt[j]
        j = prv[i]
        while j >= 0:
            label[j] = count
            j = prv[j]
        count += 1
    return label
