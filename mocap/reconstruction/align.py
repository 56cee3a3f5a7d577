"""Command / capture alignment: when does a take's motion follow its commands?

A take's ``commands_offset_s = o`` says its command file's time 0 is capture time ``o`` (a row
acts at capture time ``o + time_s``; command time = capture time - o). This module measures the
lag between a take's motion and its commands, to propose ``o`` and to audit it:

- :func:`motion_lags` reads the lag from the motion itself. The markers' motion is modelled as
  a static function of the commands shifted by ``tau``: ``Y(t) = sum_d g_d(c_d(t - tau),
  s_d(t - tau))``, each ``g_d`` piecewise linear in the command (knots every 32 units) with one
  branch for rising and one for falling commands (``s_d``: the sign of the DU's latest change),
  so that a rate-independent hysteresis is not read as a delay. ``Y`` is the take's largest
  principal components of marker motion. Each take's residual is profiled over lags a frame
  apart around the onset difference (first moved frame minus first nonzero command); between
  frames the residual is flat, so a take's lag is the middle of its flat minimum on a grid of a
  twentieth of a frame. A uniform staircase (the trapezoid of a response take) fits a delay of
  whole steps almost as well as the truth (the map relabels the steps): such a take is read
  within two frames of the lag the takes that do pin theirs share (plan and motion takes).
- :func:`sync_edge` reads a sync channel (an analog channel that steps when the command log
  starts): the capture time of its first edge, interpolated between samples.

Whatever is read from the motion is the commands' delay to the *motion*: the clock offset plus
the face's own dead time (and the mean delay of any lag). The two cannot be separated from the
motion alone; an offset so estimated removes the dead time the discrepancy workflow looks for.
A sync channel measures the clock offset alone.

Units: s, mm, command units (0..255). Pure functions; the session-level work is in
:mod:`mocap.interop.align` (import) and :mod:`mocap.workflows.audit` (the check).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from mocap.core.schedules import TIME_TOL_S

__all__ = ["LagEstimate", "MISALIGNED_AFTER_S", "MISALIGNED_BEFORE_S", "SessionLags", "motion_lags",
           "sync_edge"]

KNOTS = np.linspace(0.0, 255.0, 9)
"""Command values (units) of the piecewise linear map's knots."""
N_COMPONENTS = 4
"""Principal components of marker motion fitted."""
N_MARKERS = 12
"""Markers that move the most, used for the components."""
MISALIGNED_AFTER_S = 0.15
"""The audit flags a take whose motion follows its commands by more than this (s): longer than a
face's own dead time and lag."""
MISALIGNED_BEFORE_S = 0.05
"""The audit flags a take whose motion precedes its commands by more than this (s): a motion
cannot precede its cause."""
_CHI2_95 = 3.841  # chi-square, 1 degree of freedom, 95 %


@dataclass(frozen=True)
class LagEstimate:
    """The delay of a take's motion after its commands.

    lag_s : s; the motion at capture time t follows the commands at t - lag_s (positive: the
        motion comes later than the rows' times say). NaN when it could not be read.
    uncertainty_s : s, a 95 % half-width: the wider of the fit's likelihood-ratio interval and
        the flat minimum between frames (at least half a frame). Residuals that are correlated
        in time make the fit's part optimistic.
    method : "motion" or "sync".
    note : why ``lag_s`` is NaN, or what to know about it (several lags fitting alike), or "".
    """

    lag_s: float
    uncertainty_s: float
    method: str
    note: str = ""


def _motion_signal(X: np.ndarray) -> np.ndarray | None:
    """(n_frames, k) principal component scores of the markers that move the most (gaps filled
    linearly in time), or None when nothing is seen."""
    X = np.asarray(X, float)
    n, m, _ = X.shape
    seen = np.isfinite(X).all(axis=2)
    cover = seen.mean(axis=0)
    usable = np.flatnonzero(cover >= 0.8)
    if usable.size == 0 or n < 4:
        return None
    with np.errstate(all="ignore"):
        spread = np.nanstd(X[:, usable], axis=0)  # (n_usable, 3) mm
    order = np.argsort(-np.linalg.norm(spread, axis=1))
    pick = usable[order[:N_MARKERS]]
    frames = np.arange(n)
    cols = []
    for j in pick:
        ok = seen[:, j]
        for a in range(3):
            cols.append(np.interp(frames, frames[ok], X[ok, j, a]))
    Y = np.column_stack(cols)
    Y -= Y.mean(axis=0)
    w, v = np.linalg.eigh(Y.T @ Y)  # the principal axes of a tall, narrow Y
    w, v = w[::-1], v[:, ::-1]
    k = min(N_COMPONENTS, int(np.sum(w > 1e-18 * max(w[0], 1e-300))))
    return Y @ v[:, :k] if k else None


def _onset_frame(Y: np.ndarray) -> float | None:
    """The first frame the motion leaves its first frames' level by 8 noise sd, or None."""
    d = np.diff(Y, axis=0)
    noise = 1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0) / np.sqrt(2)
    noise = np.maximum(noise, 1e-12)
    base = np.median(Y[: max(3, Y.shape[0] // 50)], axis=0)
    moved = np.any(np.abs(Y - base) > 8 * noise, axis=1)
    return float(np.argmax(moved)) if moved.any() else None


def _schedule(rows: pd.DataFrame, dus) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per DU: its rows' times (sorted; the later of equal times wins), commands and the sign of
    each row's change (+1 for a rise or no change, -1 for a fall)."""
    out = []
    for du in dus:
        r = rows[rows["du"] == du]
        order = np.argsort(r["time_s"].to_numpy(float), kind="stable")
        t = r["time_s"].to_numpy(float)[order]
        c = r["command"].to_numpy(float)[order]
        prev = np.r_[0.0, c[:-1]]
        sign = np.where(c < prev, -1.0, 1.0)
        # a repeated command keeps the direction it had
        for i in np.flatnonzero(c == prev):
            sign[i] = sign[i - 1] if i > 0 else 1.0
        out.append((t, c, sign))
    return out


def _sampled(schedule, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n_times, n_dus) commands (0 before a DU's first row) and directions (+1 before it), by
    the rule of ``mocap.core.session.command_matrix`` (the last row with time_s <= t + 1e-9) at
    trial lags: the rows are already in capture time."""
    cmd = np.zeros((times.size, len(schedule)))
    sign = np.ones((times.size, len(schedule)))
    for j, (t, c, s) in enumerate(schedule):
        idx = np.searchsorted(t, times + TIME_TOL_S, side="right") - 1
        hit = idx >= 0
        cmd[hit, j] = c[idx[hit]]
        sign[hit, j] = s[idx[hit]]
    return cmd, sign


def _basis(command: np.ndarray, direction: np.ndarray | None) -> np.ndarray:
    """(n, n_dus n_knots [x 2]) hat functions of each DU's command; with ``direction``, one set
    for rising and one for falling commands."""
    width = KNOTS[1] - KNOTS[0]
    hats = np.clip(1.0 - np.abs(command[:, :, None] - KNOTS[None, None, :]) / width, 0.0, None)
    if direction is not None:
        up = (direction > 0)[:, :, None]
        hats = np.concatenate([hats * up, hats * ~up], axis=2)
    return hats.reshape(command.shape[0], -1)


def _rss(Y: np.ndarray, schedule, fps: float, lags: np.ndarray, branches: bool = True
         ) -> np.ndarray:
    """Residual sum of squares of the best map for each lag (normal equations, a tiny ridge)."""
    times = np.arange(Y.shape[0]) / fps
    yy = float(np.sum(Y**2))
    out = np.empty(lags.size)
    for i, tau in enumerate(lags):
        cmd, sign = _sampled(schedule, times - tau)
        B = _basis(cmd, sign if branches else None)
        B = B[:, B.any(axis=0)]
        G = B.T @ B
        G[np.diag_indices_from(G)] += 1e-9 * (np.trace(G) / G.shape[0] + 1e-300)
        BY = B.T @ Y
        coef = np.linalg.solve(G, BY)
        out[i] = max(yy - float(np.sum(coef * BY)), 0.0)
    return out


@dataclass(frozen=True)
class _Take:
    """A take prepared for the lag search: its motion components and command schedule."""

    Y: np.ndarray
    schedule: list
    first_command_s: float
    onset_s: float | None


def _prepare(X: np.ndarray, rows: pd.DataFrame, fps: float) -> _Take | str:
    dus = sorted({int(d) for d in rows.loc[rows["command"] > 0, "du"]})
    if not dus:
        return "no nonzero command"
    Y = _motion_signal(X)
    if Y is None:
        return "no marker seen in most frames"
    onset = _onset_frame(Y)
    return _Take(Y, _schedule(rows, dus),
                 float(rows.loc[rows["command"] > 0, "time_s"].min()),
                 None if onset is None else onset / fps)


def _local_minima(rss: np.ndarray, tol: float) -> np.ndarray:
    """Indices of the profile's local minima within (1 + tol) of its least."""
    r = rss / max(rss.min(), 1e-300)
    left = np.r_[np.inf, r[:-1]]
    right = np.r_[r[1:], np.inf]
    return np.flatnonzero((r <= left) & (r <= right) & (r <= 1 + tol))


def _refine(take: _Take, fps: float, around: float) -> tuple[float, float]:
    """(lag, 95 % half-width) from a 1/20-frame grid within 2 frames of ``around``."""
    fine = around + np.arange(-40, 41) / (20.0 * fps)
    rss = _rss(take.Y, take.schedule, fps, fine)
    i = int(np.argmin(rss))
    flat = rss <= rss[i] * (1 + 1e-9) + 1e-300
    lo, hi = i, i
    while lo > 0 and flat[lo - 1]:
        lo -= 1
    while hi < fine.size - 1 and flat[hi + 1]:
        hi += 1
    n, k = take.Y.shape
    n_par = 2 * len(take.schedule) * KNOTS.size
    sigma2 = rss[i] / max(n * k - n_par * k, 1)
    inside = np.flatnonzero(rss <= rss[i] + _CHI2_95 * sigma2)
    half = 0.5 * (fine[inside.max()] - fine[inside.min()])
    return 0.5 * (fine[lo] + fine[hi]), max(half, 0.5 * (fine[hi] - fine[lo]), 0.5 / fps)


@dataclass(frozen=True)
class SessionLags:
    """Lags of a session's takes read from their motion (:func:`motion_lags`).

    takes : take name -> LagEstimate.  session_lag_s : the lag the takes share best (their
    joint least squares), s, NaN when no take could be read.  spread_s : the largest minus the
    smallest take lag, s.
    """

    takes: dict
    session_lag_s: float
    spread_s: float


AMBIGUITY = 0.5
"""A take's profile minimum within this fraction of its least is another lag that fits it
(listed in its note)."""
DISTINCT_S = 0.04
"""Minima closer than this to a take's best (s) are its ripple, not another candidate."""
PINNED = 0.05
"""A take pins its lag when every minimum farther than ``DISTINCT_S`` from its best has a
residual over ``1 + PINNED`` times the least (a uniform staircase does not: a delay of whole
steps fits it almost as well)."""


def motion_lags(takes: dict, fps: float, *, max_lag_s: float = 2.0, centre_s: float | None = None,
                refine: bool = True, prior_s: float | None = None) -> SessionLags:
    """The lag of each take's motion after its commands, read from the motion, and the lag
    they share.

    Parameters
    ----------
    takes : name -> (X, rows): X (n_frames, n_markers, 3) mm (NaN unseen); rows the take's
        command rows (``time_s`` s, ``du``, ``command``) on the clock to check.
    fps : frames per second.
    max_lag_s : lags searched within this many seconds of ``centre_s``.
    centre_s : the search's centre; default the takes' median onset difference (first moved
        frame minus first nonzero command).
    refine : refine each lag to a twentieth of a frame (else to the coarse grid's frame).
    prior_s : the session lag to keep when no take pins its lag (the audit's 0: what the
        manifest says, which such takes cannot contradict); default their joint minimum.

    Each take's residual profile is computed on one grid of lags (a frame apart). A take pins
    its lag when no distant minimum fits nearly as well (``PINNED``); a uniform staircase (a
    trapezoid) does not: a delay of whole steps fits it almost as well, the map relabelling the
    steps. The session lag minimises the joint Gaussian likelihood (sum over takes of n/2 log
    RSS) of the takes that pin theirs (of all takes when none does, or ``prior_s``). A take
    that pins its lag keeps its own; any other is read within two frames of the session lag,
    and its note says so.
    """
    fps = float(fps)
    ready, out = {}, {}
    for name, (X, rows) in takes.items():
        t = _prepare(X, rows, fps)
        if isinstance(t, str):
            out[name] = LagEstimate(np.nan, np.nan, "motion", t)
        else:
            ready[name] = t
    if not ready:
        return SessionLags(out, np.nan, np.nan)
    if centre_s is None:
        diffs = [t.onset_s - t.first_command_s for t in ready.values() if t.onset_s is not None]
        centre_s = float(np.median(diffs)) if diffs else 0.0
    grid = centre_s + np.arange(-round(max_lag_s * fps), round(max_lag_s * fps) + 1) / fps
    profiles = {n: _rss(t.Y, t.schedule, fps, grid) for n, t in ready.items()}
    pinned = []
    for n, r in profiles.items():
        mins = _local_minima(r, np.inf)
        far = mins[np.abs(grid[mins] - grid[np.argmin(r)]) > DISTINCT_S]
        if far.size == 0 or r[far].min() > (1 + PINNED) * r.min():
            pinned.append(n)
    if not pinned and prior_s is not None:
        session = float(prior_s)
    else:
        use = pinned or list(ready)
        joint = sum(0.5 * ready[n].Y.size * np.log(np.maximum(profiles[n], 1e-300)) for n in use)
        session = float(grid[int(np.argmin(joint))])
    lags = []
    for name, t in ready.items():
        if name in pinned:
            pick = grid[int(np.argmin(profiles[name]))]
            note = ""
        else:
            pick = session
            cand = _local_minima(profiles[name], AMBIGUITY)
            others = grid[cand][np.abs(grid[cand] - pick) > DISTINCT_S]
            note = ("its lag is read near the session's" + (
                " (taken from the takes that pin theirs)" if pinned else
                " (no take of the session pins its lag)") + ": a uniform staircase cannot tell a "
                "delay of whole steps from hysteresis" + (
                    " (also fit: " + ", ".join(f"{v:+.3f}" for v in others[:4]) + " s)"
                    if others.size else ""))
        if refine:
            lag, half = _refine(t, fps, float(pick))
        else:
            lag, half = float(pick), 0.5 / fps
        out[name] = LagEstimate(float(lag), float(half), "motion", note)
        lags.append(lag)
    return SessionLags(out, session if not refine else float(np.median(lags)),
                       float(np.max(lags) - np.min(lags)))


def sync_edge(values: np.ndarray, rate_hz: float) -> LagEstimate:
    """The capture time of a sync channel's first edge: the command log's time 0.

    values : (n_samples,) the channel, sample 0 at the take's first frame; rate_hz : its rate.
    The edge is the first crossing of the level halfway between the channel's 5th and 95th
    percentiles, interpolated linearly between samples; uncertainty half a sample. NaN (with a
    note) when the channel never changes.
    """
    v = np.asarray(values, float)
    ok = np.isfinite(v)
    if ok.sum() < 2:
        return LagEstimate(np.nan, np.nan, "sync", "the channel holds no samples")
    lo, hi = np.percentile(v[ok], [5, 95])
    if not hi > lo:
        return LagEstimate(np.nan, np.nan, "sync", "the channel never changes (no edge)")
    mid = 0.5 * (lo + hi)
    above = v > mid
    start = above[np.argmax(ok)]
    change = np.flatnonzero(ok[1:] & ok[:-1] & (above[1:] != start) & (above[:-1] == start))
    if change.size == 0:
        return LagEstimate(np.nan, np.nan, "sync", "the channel never crosses its mid level")
    j = int(change[0])
    frac = (mid - v[j]) / (v[j + 1] - v[j])
    return LagEstimate(float((j + frac) / rate_hz), 0.5 / float(rate_hz), "sync")
