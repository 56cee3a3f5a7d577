"""Compiled (numba) kernels of the cross-camera correspondence search.

Each kernel runs over every blob or candidate of a take in one call (one Python call per camera
pair, none per frame or point); :mod:`mocap.reconstruction.correspondence` chains them with the
fused triangulation kernel (:func:`mocap.calib.triangulation_kernel.triangulate_normalized`). The
mathematics are those of the NumPy reference (:mod:`mocap.reconstruction.reference`) operation for
operation, so both find the same correspondences (a test checks it).

Conventions: blobs are indexed by their row in the take's blob table; ``cam`` (n,) int camera
index, ``fidx`` (n,) int frame index (frame - first frame); cameras are packed as ``K`` (C, 3, 3)
px, ``dist`` (C, 5) Brown-Conrady, ``R`` (C, 3, 3), ``t`` (C, 3) mm (camera-from-world, as
:class:`mocap.calib.camera.Camera`). Blobs of one camera and frame form a bucket ``k = cam * n_frames +
fidx``; ``ptr`` (C * n_frames + 1,) gives each bucket's slice of the ordering arrays.
Kernels are compiled on first use and cached on disk (``cache=True``).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from mocap.calib.distortion_kernel import BLOCK as _BLOCK
from mocap.calib.distortion_kernel import project_pixel, undistort_buffers, undistort_rounds

N_CELLS = 64  # column bands per image in the nearest-blob search


@njit(cache=True, error_model="numpy")
def normalize_blobs(uv, cam, K, dist, R, iterations):
    """Distorted pixels -> undistorted normalised coordinates and world viewing rays.

    uv (n, 2) px; cam (n,) int; returns xn (n, 2) and ray (n, 3) unit vectors (world frame).
    Same fixed-point undistortion as :func:`mocap.calib.camera.undistort_normalized`, run on blocks
    of blobs by :func:`mocap.calib.distortion_kernel.undistort_rounds` (vectorised; at most
    ``iterations`` rounds, stopping once a round leaves the whole block unchanged).
    """
    n = uv.shape[0]
    xn = np.empty((n, 2))
    ray = np.empty((n, 3))
    B = _BLOCK
    x0, y0, x, y, k1, k2, p1, p2, k3 = undistort_buffers(B)
    for s in range(0, n, B):
        m = min(B, n - s)
        for p in range(m):
            i = s + p
            c = cam[i]
            y0[p] = (uv[i, 1] - K[c, 1, 2]) / K[c, 1, 1]
            x0[p] = (uv[i, 0] - K[c, 0, 2] - K[c, 0, 1] * y0[p]) / K[c, 0, 0]
            x[p] = x0[p]
            y[p] = y0[p]
            k1[p] = dist[c, 0]
            k2[p] = dist[c, 1]
            p1[p] = dist[c, 2]
            p2[p] = dist[c, 3]
            k3[p] = dist[c, 4]
        undistort_rounds(x0, y0, x, y, k1, k2, p1, p2, k3, m, iterations)
        for p in range(m):
            i = s + p
            c = cam[i]
            xn[i, 0] = x[p]
            xn[i, 1] = y[p]
            d0 = x[p] * R[c, 0, 0] + y[p] * R[c, 1, 0] + R[c, 2, 0]
            d1 = x[p] * R[c, 0, 1] + y[p] * R[c, 1, 1] + R[c, 2, 1]
            d2 = x[p] * R[c, 0, 2] + y[p] * R[c, 1, 2] + R[c, 2, 2]
            norm = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            ray[i, 0] = d0 / norm
            ray[i, 1] = d1 / norm
            ray[i, 2] = d2 / norm
    return xn, ray


@njit(cache=True, error_model="numpy")
def _cell(x, x0, scale):
    """Column band (0 .. N_CELLS - 1) of image x (px) in a bucket whose bands start at ``x0`` px,
    ``1 / scale`` px wide; non-decreasing in x."""
    q = np.floor((x - x0) * scale)
    if not q > 0:  # also NaN
        return 0
    if q > N_CELLS - 1:
        return N_CELLS - 1
    return int(q)


@njit(cache=True, error_model="numpy")
def bucket_index(cam, fidx, uv, n_cams, n_frames):
    """Blobs grouped by (camera, frame), and sorted by x within each group.

    uv (n, 2) px. Returns ``ptr`` (n_cams * n_frames + 1,), ``order`` (n,) blob indices by
    bucket then blob index, ``order_x`` (n,) by bucket then image x, ``uv_x`` (n, 2) px the
    blobs' image points in ``order_x`` order, and the column bands of every bucket: N_CELLS equal
    bands spanning its blobs' x range, band q holding x with ``floor((x - x0) * scale) == q``
    (``x0``, ``scale`` (n_cams * n_frames,)), starting at ``cells[k, q]`` in ``order_x``
    (``cells`` (n_cams * n_frames, N_CELLS + 1), the last column the bucket's end).
    """
    n = cam.size
    nk = n_cams * n_frames
    ptr = np.zeros(nk + 1, np.int64)
    for i in range(n):
        ptr[cam[i] * n_frames + fidx[i] + 1] += 1
    for k in range(nk):
        ptr[k + 1] += ptr[k]
    fill = ptr[:-1].copy()
    order = np.empty(n, np.int64)
    xs = np.empty(n)  # image x of the blobs in ``order`` order: each bucket's read contiguously
    for i in range(n):
        k = cam[i] * n_frames + fidx[i]
        order[fill[k]] = i
        xs[fill[k]] = uv[i, 0]
        fill[k] += 1
    # counting sort of every bucket by column band, then insertion sort by x within each band
    order_x = np.empty(n, np.int64)
    x_x = np.empty(n)  # image x in ``order_x`` order
    cells = np.empty((nk, N_CELLS + 1), np.int64)
    x0 = np.zeros(nk)
    scale = np.zeros(nk)
    pos = np.empty(N_CELLS + 1, np.int64)
    band = np.empty(n, np.int64)
    for k in range(nk):
        s, e = ptr[k], ptr[k + 1]
        if e > s:
            lo = hi = xs[s]
            for r in range(s + 1, e):
                lo = min(lo, xs[r])
                hi = max(hi, xs[r])
            x0[k] = lo
            if hi > lo:
                scale[k] = N_CELLS / (hi - lo)
        pos[:] = 0
        for r in range(s, e):
            q = _cell(xs[r], x0[k], scale[k])
            band[r] = q
            pos[q + 1] += 1
        for q in range(N_CELLS):
            pos[q + 1] += pos[q]
        for q in range(N_CELLS + 1):
            cells[k, q] = s + pos[q]
        for r in range(s, e):
            q = band[r]
            o = s + pos[q]
            order_x[o] = order[r]
            x_x[o] = xs[r]
            pos[q] += 1
        for q in range(N_CELLS):
            c0 = cells[k, q]
            for r in range(c0 + 1, cells[k, q + 1]):
                i = order_x[r]
                x = x_x[r]
                h = r - 1
                while h >= c0 and x_x[h] > x:
                    order_x[h + 1] = order_x[h]
                    x_x[h + 1] = x_x[h]
                    h -= 1
                order_x[h + 1] = i
                x_x[h + 1] = x
    uv_x = np.empty((n, 2))
    for r in range(n):
        uv_x[r, 0] = x_x[r]
        uv_x[r, 1] = uv[order_x[r], 1]
    return ptr, order, order_x, uv_x, cells, x0, scale


@njit(cache=True, error_model="numpy")
def compact_buckets(ptr, order, used):
    """The buckets (ptr, order) without their used blobs (used (n_blobs,) bool); the order
    within each bucket is kept."""
    nk = ptr.size - 1
    ptr2 = np.zeros(nk + 1, np.int64)
    n = 0
    for k in range(nk):
        for r in range(ptr[k], ptr[k + 1]):
            if not used[order[r]]:
                n += 1
        ptr2[k + 1] = n
    order2 = np.empty(n, np.int64)
    n = 0
    for k in range(nk):
        for r in range(ptr[k], ptr[k + 1]):
            if not used[order[r]]:
                order2[n] = order[r]
                n += 1
    return ptr2, order2


@njit(cache=True, error_model="numpy")
def _epipolar_angle(ray, i, bn, e1, e2):
    """Angle (rad, [0, 2 pi]) about the baseline ``bn`` of blob i's epipolar plane, and the sine
    of the angle between blob i's ray and the baseline."""
    n0 = bn[1] * ray[i, 2] - bn[2] * ray[i, 1]
    n1 = bn[2] * ray[i, 0] - bn[0] * ray[i, 2]
    n2 = bn[0] * ray[i, 1] - bn[1] * ray[i, 0]
    return (np.arctan2(n0 * e2[0] + n1 * e2[1] + n2 * e2[2],
                       n0 * e1[0] + n1 * e1[1] + n2 * e1[2]) + np.pi,
            np.sqrt(n0 * n0 + n1 * n1 + n2 * n2))


@njit(cache=True, error_model="numpy")
def _angle_bound(gate_px, focal, xn, i, sin_ray):
    """Upper bound (rad) on the angle between blob i's epipolar plane and that of any blob whose
    symmetric epipolar distance to it is under ``gate_px`` px in blob i's image; inf when the
    geometry gives none.

    The epipolar line of the other blob is the trace of its plane: blob i's normalised point
    q = (x, y, 1) lies ``alg / |l|`` from that plane (``l`` the line's 3 coefficients, ``alg`` the
    algebraic error), and ``|l| >= hypot(l0, l1)``, so passing the test puts q under
    ``s = gate_px / focal`` from the plane; q is ``rho = |q| sin(ray, baseline)`` from the
    baseline's axis, which both planes contain, so the planes' angle phi has ``sin phi < s /
    rho``, and ``phi < asin(s / rho) <= (pi / 3) s / rho`` for ``s / rho <= 1 / 2``. Widened by a
    relative 1e-6 and 1e-8 rad against rounding (the keys are ``frame * 8 + angle``).
    """
    rho = np.sqrt(xn[i, 0] * xn[i, 0] + xn[i, 1] * xn[i, 1] + 1.0) * sin_ray
    s = gate_px / (focal * rho)
    if s <= 0.5:  # also rejects NaN
        return s * (np.pi / 3.0) * (1.0 + 1e-6) + 1e-8
    return np.inf


@njit(cache=True, error_model="numpy")
def _band_sort(keys, idx, n, keys2, idx2, start):
    """Sort keys[:n] ascending in place, idx[:n] along, without allocating: a counting sort
    into n equal bands of the keys' range, then insertion sort (each key moves only within its
    band). keys2, idx2 (>= n,) float and int scratch; start (>= n + 1,) int.

    Returns (lo, scale): key k lies in band ``q = int((k - lo) * scale)`` and band q's keys are
    ``keys[start[q]:start[q + 1]]``; scale is NaN when a key is not finite (then sorted by
    a stable ``np.argsort``, NaN last, and the bands are not set).
    """
    lo = hi = keys[0]
    finite = True
    for r in range(n):
        finite &= np.isfinite(keys[r])
        lo = min(lo, keys[r])
        hi = max(hi, keys[r])
    if not (finite and np.isfinite(hi - lo)):
        # element loops, and the stable sort the labeling compiles anyway: a quicksort and
        # array-to-array slice copies would compile ~4 CPU-s on a new install for a path
        # real keys never take
        o = np.argsort(keys[:n], kind="mergesort")
        for r in range(n):
            keys2[r] = keys[o[r]]
            idx2[r] = idx[o[r]]
        for r in range(n):
            keys[r] = keys2[r]
            idx[r] = idx2[r]
        return lo, np.nan
    scale = (n - 1) / (hi - lo) if hi > lo else 0.0
    start[: n + 1] = 0
    for r in range(n):
        start[int((keys[r] - lo) * scale) + 1] += 1
    for q in range(n):
        start[q + 1] += start[q]
    for r in range(n):
        q = int((keys[r] - lo) * scale)
        keys2[start[q]] = keys[r]
        idx2[start[q]] = idx[r]
        start[q] += 1
    for q in range(n, 0, -1):  # back from band ends to band starts
        start[q] = start[q - 1]
    start[0] = 0
    for r in range(n):
        k, i = keys2[r], idx2[r]
        h = r - 1
        while h >= 0 and keys[h] > k:
            keys[h + 1] = keys[h]
            idx[h + 1] = idx[h]
            h -= 1
        keys[h + 1] = k
        idx[h + 1] = i
    return lo, scale


@njit(cache=True, error_model="numpy")
def _first_at_least(keys, n, start, lo, scale, x):
    """First index r of the band-sorted keys[:n] (see :func:`_band_sort`) with keys[r] >= x
    (n if none): as ``np.searchsorted(keys[:n], x)``. Bands are non-decreasing in the key, so
    every key of an earlier band than x's is below x."""
    if scale != scale:  # bands not set
        return np.searchsorted(keys[:n], x)
    if not x == x:
        return n  # as searchsorted: NaN after every key
    q = (x - lo) * scale
    if q < 0.0:
        r = 0
    elif q >= n - 1:
        r = start[n - 1]
    else:
        r = start[int(q)]
    while r < n and keys[r] < x:
        r += 1
    return r


@njit(cache=True, error_model="numpy")
def pair_candidates(a, b, ptr, order, n_frames, frame, xn, ray, used, bn, e1, e2, E,
                    focal_a, focal_b, gate_px, dth):
    """Blob pairs (pa, pb) of cameras a and b passing the symmetric epipolar test.

    Per frame, the unused blobs of b are sorted by the angle of their epipolar plane about the
    baseline (unit ``bn``, with ``e1``, ``e2`` completing the basis); every unused blob of a takes
    those within ``dth`` rad of its own angle, then keeps those whose symmetric epipolar distance
    with the essential matrix ``E`` (3, 3; b from a) is under ``gate_px`` px in both images.
    Returns two (m,) int arrays of blob indices, by frame, then a's blob order, then angle.

    Only the b blobs within the angle bound of the test itself (:func:`_angle_bound`, from a's
    blob and from the frame's b blob nearest the baseline) are tried: no pair outside it can pass,
    and it is usually far narrower than ``dth``.
    """
    cap = 1024
    pa = np.empty(cap, np.int64)
    pb = np.empty(cap, np.int64)
    m = 0
    widest = 0
    for f in range(n_frames):
        widest = max(widest, ptr[b * n_frames + f + 1] - ptr[b * n_frames + f])
    keys = np.empty(widest)
    idx = np.empty(widest, np.int64)
    keys2 = np.empty(widest)
    idx2 = np.empty(widest, np.int64)
    start = np.empty(widest + 1, np.int64)
    # per sorted blob of b: normalised point, length of its epipolar line's normal in a, and the
    # algebraic error beyond which the test fails for sure (a cheap rejection before the exact test)
    xb = np.empty((widest, 2))
    hb = np.empty(widest)
    reject_b = np.empty(widest)
    slack = 1.0 + 1e-9
    for f in range(n_frames):
        na = 0
        for k in range(ptr[a * n_frames + f], ptr[a * n_frames + f + 1]):
            na += not used[order[k]]
        if na == 0:
            continue
        nb = 0
        for k in range(ptr[b * n_frames + f], ptr[b * n_frames + f + 1]):
            j = order[k]
            if not used[j]:
                keys[nb] = frame[j] * 8.0 + _epipolar_angle(ray, j, bn, e1, e2)[0]
                idx[nb] = j
                nb += 1
        if nb == 0:
            continue
        k_lo, k_scale = _band_sort(keys, idx, nb, keys2, idx2, start)
        kb = keys[:nb]
        jb = idx[:nb]
        for r in range(nb):
            j = jb[r]
            xb0, xb1 = xn[j, 0], xn[j, 1]
            lb0 = xb0 * E[0, 0] + xb1 * E[1, 0] + E[2, 0]  # epipolar line in a
            lb1 = xb0 * E[0, 1] + xb1 * E[1, 1] + E[2, 1]
            xb[r, 0] = xb0
            xb[r, 1] = xb1
            hb[r] = np.hypot(lb0, lb1)
            reject_b[r] = gate_px * hb[r] / focal_a * slack
        for k in range(ptr[a * n_frames + f], ptr[a * n_frames + f + 1]):
            i = order[k]
            if used[i]:
                continue
            th, sin_ray = _epipolar_angle(ray, i, bn, e1, e2)
            ka = frame[i] * 8.0 + th
            # b's blobs with ka - dth <= key < ka + dth, and within the test's own bound w <= dth
            w = min(dth, _angle_bound(gate_px, focal_a, xn, i, sin_ray))
            lo = _first_at_least(kb, nb, start, k_lo, k_scale, ka - w)
            hi = lo
            while hi < nb and kb[hi] < ka + dth and kb[hi] <= ka + w:
                hi += 1
            xa0, xa1 = xn[i, 0], xn[i, 1]
            la0 = xa0 * E[0, 0] + xa1 * E[0, 1] + E[0, 2]  # epipolar line in b
            la1 = xa0 * E[1, 0] + xa1 * E[1, 1] + E[1, 2]
            la2 = xa0 * E[2, 0] + xa1 * E[2, 1] + E[2, 2]
            ha = np.hypot(la0, la1)
            reject_a = gate_px * ha / focal_b * slack
            for r in range(lo, hi):
                alg = abs(xb[r, 0] * la0 + xb[r, 1] * la1 + la2)
                if alg >= reject_a or alg >= reject_b[r]:
                    continue
                db = alg / ha * focal_b
                da = alg / hb[r] * focal_a
                if db < gate_px and da < gate_px:
                    if m == cap:
                        cap *= 2
                        pa2 = np.empty(cap, np.int64)
                        pb2 = np.empty(cap, np.int64)
                        for q in range(m):  # (a slice copy compiles a shape check's error text)
                            pa2[q] = pa[q]
                            pb2[q] = pb[q]
                        pa, pb = pa2, pb2
                    pa[m] = i
                    pb[m] = jb[r]
                    m += 1
    return pa[:m].copy(), pb[:m].copy()


@njit(cache=True, error_model="numpy")
def _nearest_blob(cells, x0, scale, order_x, uv_x, k, u, v, gate_px):
    """Nearest blob of bucket k to (u, v) px closer than ``gate_px``; -1 if none.

    ``uv_x`` (n, 2) px holds the blobs in ``order_x`` order (sorted by x within each bucket);
    the scan starts at the column band of ``u - gate_px`` (see ``bucket_index``): bands are
    non-decreasing in x, so no blob right of ``u - gate_px`` lies in an earlier band.
    """
    lo = u - gate_px
    r = cells[k, _cell(lo, x0[k], scale[k])]
    e = cells[k, N_CELLS]
    while r < e and uv_x[r, 0] <= lo:
        r += 1
    best = -1
    best_d = gate_px
    while r < e:
        du = uv_x[r, 0] - u
        if du >= gate_px:
            break
        dv = uv_x[r, 1] - v
        d = np.sqrt(du * du + dv * dv)
        if d < best_d:
            best_d = d
            best = order_x[r]
        r += 1
    return best


@njit(cache=True, error_model="numpy")
def verify_candidates(X, pa, pb, a, b, fidx, cells, x0, scale, order_x, uv_x, n_frames, used, K,
                      dist, R, t, gates, max_depth_mm, min_cams, unique_pair):
    """Support of every epipolar candidate in the other cameras.

    X (m, 3) mm: the candidates' two-view points. A candidate must lie in front of both cameras
    and closer than ``max_depth_mm``; projected into every other camera c, the nearest blob of its
    frame within ``gates[c]`` px, when unused, joins its views. Returns views (m, C) int (blob
    per camera, -1 for none) and keep (m,) bool: seen by ``min_cams`` cameras, or, when
    ``min_cams`` is 2, by 3, or by 2 when ``unique_pair`` (m,) bool (its blobs have no other
    candidate).
    """
    m = pa.size
    C = K.shape[0]
    views = np.full((m, C), -1, np.int64)
    keep = np.zeros(m, np.bool_)
    for r in range(m):
        views[r, a] = pa[r]
        views[r, b] = pb[r]
        X0, X1, X2 = X[r, 0], X[r, 1], X[r, 2]
        depth_ok = True
        for c in (a, b):
            z = X0 * R[c, 2, 0] + X1 * R[c, 2, 1] + X2 * R[c, 2, 2] + t[c, 2]
            if not (z > 0 and z < max_depth_mm):
                depth_ok = False
        if not depth_ok:
            continue
        support = 2
        f = fidx[pa[r]]
        for c in range(C):
            if c == a or c == b:
                continue
            u, v = project_pixel(K, dist, R, t, c, X0, X1, X2)
            if not (np.isfinite(u) and np.isfinite(v)):
                continue
            j = _nearest_blob(cells, x0, scale, order_x, uv_x, c * n_frames + f, u, v, gates[c])
            if j >= 0 and not used[j]:
                views[r, c] = j
                support += 1
        if min_cams == 2:
            keep[r] = support >= 3 or unique_pair[r]
        else:
            keep[r] = support >= min_cams
    return views, keep


@njit(cache=True, error_model="numpy")
def _row_less(views, r, q):
    """Row r of views (m, C) before row q in lexicographic order."""
    for c in range(views.shape[1]):
        if views[r, c] != views[q, c]:
            return views[r, c] < views[q, c]
    return False


@njit(cache=True, error_model="numpy")
def lex_order(views):
    """Indices (m,) sorting the rows of views (m, C) int lexicographically (stable: as
    ``np.lexsort(views.T[::-1])``).

    A natural merge sort: the ascending runs already present are merged pairwise, so rows that
    come mostly in order (a pair's candidates come by frame, then by the first camera's blob)
    cost about one comparison each.
    """
    m = views.shape[0]
    idx = np.arange(m)
    if m < 2:
        return idx
    starts = np.empty(m + 1, np.int64)
    n_runs = 0
    starts[0] = 0
    for r in range(1, m):
        if _row_less(views, r, r - 1):
            n_runs += 1
            starts[n_runs] = r
    n_runs += 1
    starts[n_runs] = m
    if n_runs == 1:
        return idx
    buf = np.empty(m, np.int64)
    while n_runs > 1:
        k = 0
        for g in range(0, n_runs, 2):
            s = starts[g]
            if g + 1 == n_runs:  # an odd run out: copied as it is
                e = starts[g + 1]
                for q in range(s, e):
                    buf[q] = idx[q]
            else:
                mid, e = starts[g + 1], starts[g + 2]
                i, j, o = s, mid, s
                while i < mid and j < e:
                    if _row_less(views, idx[j], idx[i]):  # ties keep the left run first
                        buf[o] = idx[j]
                        j += 1
                    else:
                        buf[o] = idx[i]
                        i += 1
                    o += 1
                while i < mid:
                    buf[o] = idx[i]
                    i += 1
                    o += 1
                while j < e:
                    buf[o] = idx[j]
                    j += 1
                    o += 1
            starts[k] = s
            k += 1
        starts[k] = m
        n_runs = k
        idx, buf = buf, idx
    return idx


@njit(cache=True, error_model="numpy")
def pair_observations(pa, pb, xn):
    """(2, m, 2) normalised observations of the blob pairs (pa, pb) (m,)."""
    m = pa.size
    out = np.empty((2, m, 2))
    for r in range(m):
        out[0, r, 0] = xn[pa[r], 0]
        out[0, r, 1] = xn[pa[r], 1]
        out[1, r, 0] = xn[pb[r], 0]
        out[1, r, 1] = xn[pb[r], 1]
    return out


@njit(cache=True, error_model="numpy")
def gather_observations(views, xn):
    """(C, m, 2) normalised observations of candidate rows views (m, C); NaN where no view."""
    m, C = views.shape
    out = np.full((C, m, 2), np.nan)
    for r in range(m):
        for c in range(C):
            j = views[r, c]
            if j >= 0:
                out[c, r, 0] = xn[j, 0]
                out[c, r, 1] = xn[j, 1]
    return out


@njit(cache=True, error_model="numpy")
def reprojection_errors(X, views, uv, K, dist, R, t):
    """(C, m) distance (px) between each view's blob and the projection of X (m, 3) mm; NaN for
    cameras without a view (or behind which the point lies)."""
    m, C = views.shape
    err = np.full((C, m), np.nan)
    for r in range(m):
        for c in range(C):
            j = views[r, c]
            if j < 0:
                continue
            u, v = project_pixel(K, dist, R, t, c, X[r, 0], X[r, 1], X[r, 2])
            du = u - uv[j, 0]
            dv = v - uv[j, 1]
            err[c, r] = np.sqrt(du * du + dv * dv)
    return err


@njit(cache=True, error_model="numpy")
def candidate_scores(views, err):
    """Score (m,) of candidate rows: 1000 per view minus the RMS reprojection error (px) over
    the views with a finite error (1000 when there is none)."""
    m, C = views.shape
    score = np.empty(m)
    for r in range(m):
        support = 0
        s = 0.0
        n = 0
        for c in range(C):
            if views[r, c] >= 0:
                support += 1
            e = err[c, r]
            if e == e:
                s += e * e
                n += 1
        resid = np.sqrt(s / n) if n > 0 else 1e3
        score[r] = support * 1e3 - resid
    return score


@njit(cache=True, error_model="numpy")
def contested_rows(views, scratch):
    """Mask (m,) of the candidate rows views (m, C) sharing a blob with another row.

    ``scratch`` (n_blobs,) int, all -1 on entry and on return.
    """
    m, C = views.shape
    for r in range(m):
        for c in range(C):
            if views[r, c] >= 0:
                scratch[views[r, c]] += 1
    out = np.zeros(m, np.bool_)
    for r in range(m):
        for c in range(C):
            if views[r, c] >= 0 and scratch[views[r, c]] > 0:
                out[r] = True
    for r in range(m):
        for c in range(C):
            if views[r, c] >= 0:
                scratch[views[r, c]] = -1
    return out


@njit(cache=True, error_model="numpy")
def one_point_per_blob(views, score, best):
    """Alive mask (m,) keeping, for every blob, only its best-scoring candidate row.

    A row survives when it is the best (highest ``score``; the first row on ties) of every blob
    it uses; losers drop out and the contest is rerun among the survivors, at most three rounds.
    ``best`` (n_blobs,) int scratch, all -1 on entry and on return.
    """
    m, C = views.shape
    alive = np.ones(m, np.bool_)
    for _ in range(3):
        for r in range(m):
            if alive[r]:
                for c in range(C):
                    j = views[r, c]
                    if j >= 0 and (best[j] < 0 or score[r] > score[best[j]]):
                        best[j] = r
        changed = False
        new_alive = alive.copy()
        for r in range(m):
            if alive[r]:
                for c in range(C):
                    j = views[r, c]
                    if j >= 0 and best[j] != r:
                        new_alive[r] = False
                        changed = True
                        break
        for r in range(m):
            if alive[r]:
                for c in range(C):
                    j = views[r, c]
                    if j >= 0:
                        best[j] = -1
        if not changed:
            break
        alive = new_alive
    return alive


@njit(cache=True, error_model="numpy")
def mark_used(views, used):
    """Flag every blob of candidate rows views (m, C) in used (n_blobs,) bool, in place."""
    m, C = views.shape
    for r in range(m):
        for c in range(C):
            if views[r, c] >= 0:
                used[views[r, c]] = True


@njit(cache=True, error_model="numpy")
def drop_bad_views(views, err, gates):
    """Views (m, C) without the views whose error err (C, m) px exceeds their camera's gate;
    also returns the mask (m,) of changed rows."""
    m, C = views.shape
    out = views.copy()
    changed = np.zeros(m, np.bool_)
    for r in range(m):
        for c in range(C):
            if out[r, c] >= 0 and err[c, r] > gates[c]:
                out[r, c] = -1
                changed[r] = True
    return out, changed


@njit(cache=True, error_model="numpy")
def point_summary(views, err, frame):
    """Per row of views (m, C): number of views, RMS reprojection error (px) over them (NaN if
    any is NaN) and the frame of its blobs."""
    m, C = views.shape
    n_cam = np.zeros(m, np.int64)
    resid = np.empty(m)
    fr = np.empty(m, np.int64)
    for r in range(m):
        s = 0.0
        last = -1
        for c in range(C):
            j = views[r, c]
            if j >= 0:
                n_cam[r] += 1
                s += err[c, r] * err[c, r]
                last = max(last, j)
        resid[r] = np.sqrt(s / max(n_cam[r], 1))
        fr[r] = frame[last] if last >= 0 else -1
    return n_cam, resid, fr


@njit(cache=True, error_model="numpy")
def frame_order(frame, keep):
    """Indices of the rows with ``keep`` (m,) bool, stably ordered by ``frame`` (m,) int: as
    ``np.flatnonzero(keep)[np.argsort(frame[keep], kind="stable")]``, by a counting sort over
    the frames' range (argsort when the range is much wider than the rows)."""
    m = frame.size
    n = 0
    lo, hi = 0, -1
    for r in range(m):
        if keep[r]:
            if n == 0:
                lo = hi = frame[r]
            else:
                lo = min(lo, frame[r])
                hi = max(hi, frame[r])
            n += 1
    rows = np.empty(n, np.int64)
    if n == 0:
        return rows
    if hi - lo > 4 * n + 1024:
        k = 0
        for r in range(m):
            if keep[r]:
                rows[k] = r
                k += 1
        # as float64 (exact below 2**53): the stable argsort the labeling compiles anyway
        return rows[np.argsort(frame[rows].astype(np.float64), kind="mergesort")]
    start = np.zeros(hi - lo + 2, np.int64)
    for r in range(m):
        if keep[r]:
            start[frame[r] - lo + 1] += 1
    for q in range(hi - lo + 1):
        start[q + 1] += start[q]
    for r in range(m):
        if keep[r]:
            q = frame[r] - lo
            rows[start[q]] = r
            start[q] += 1
    return rows
