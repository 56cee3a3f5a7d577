"""Command schedules: the paper's trapezoid and the identification battery, as FORMAT.md rows.

A schedule is a pandas DataFrame with columns ``time_s`` (float, s from the take's first frame),
``du`` (int) and ``command`` (int, 0..255), one row per command change; the command of ``du``
holds until its next row and is 0 before its first row (FORMAT.md, "Command files").

Step commands follow the paper: ``c_s = 255 s / n_ramp`` rounded half up (13, 26, 38, ...).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pandas as pd

TIME_TOL_S = 1e-9  # FORMAT.md: frame f is driven by the last row with time_s <= f / fps (+ 1e-9)
COLUMNS = ["time_s", "du", "command"]


def round_half_up(x) -> np.ndarray:
    """Round half up to integers (255 * 1 / 20 = 12.75 -> 13, 25.5 -> 26)."""
    return np.floor(np.asarray(x, float) + 0.5).astype(np.int64)


def trapezoid_levels(n_ramp: int = 20, n_hold: int = 60) -> np.ndarray:
    """Command of each step s = 0 .. 2 n_ramp + n_hold of the paper's trapezoid.

    Step 0 is 0; s = 1..n_ramp rises as 255 s / n_ramp; n_hold steps at 255 follow the last rising
    step ... in the paper's numbering (n_ramp=20, n_hold=60): s=21..80 at 255, s=81..100 fall as
    255 (100 - s) / 20, so step 100 is 0 again. Returns (2 n_ramp + n_hold + 1,) int.
    """
    s = np.arange(2 * n_ramp + n_hold + 1)
    total = 2 * n_ramp + n_hold
    c = np.where(
        s <= n_ramp,
        255.0 * s / n_ramp,
        np.where(s <= n_ramp + n_hold, 255.0, 255.0 * (total - s) / n_ramp),
    )
    return round_half_up(c)


def steps_to_rows(levels: Sequence[int], du: int, step_s: float, t0_s: float = 0.0) -> pd.DataFrame:
    """One row per step: step k of ``levels`` starts at ``t0_s + k * step_s``."""
    levels = np.asarray(levels, dtype=np.int64)
    if levels.min(initial=0) < 0 or levels.max(initial=0) > 255:
        raise ValueError(f"schedule: expected commands in 0..255, got {levels.min()}..{levels.max()}")
    t = t0_s + step_s * np.arange(levels.size)
    return pd.DataFrame({"time_s": np.round(t, 9), "du": int(du), "command": levels})


def trapezoid(du: int, *, step_s: float = 0.05, n_ramp: int = 20, n_hold: int = 60,
              t0_s: float = 0.0) -> pd.DataFrame:
    """The paper's trapezoid for one DU (100 steps of 50 ms by default); ends back at 0."""
    return steps_to_rows(trapezoid_levels(n_ramp, n_hold), du, step_s, t0_s)


def ramp_through(levels: Sequence[float], *, du: int, step_units: float = 255.0 / 20,
                 step_s: float = 0.05, dwell_s: float = 0.25, t0_s: float = 0.0) -> pd.DataFrame:
    """Staircase ramps through a list of targets (command units), dwelling at each target.

    From 0, the command moves towards each target in steps of at most ``step_units`` every
    ``step_s`` (the paper's ramp rate by default), then holds ``dwell_s``. Used for partial
    sweeps with reversals inside the range (minor loops). The last target should be 0.
    """
    cur = 0.0
    t = t0_s
    times = [t]
    values = [0]
    for target in levels:
        n = int(np.ceil(abs(target - cur) / step_units - 1e-12))
        for k in range(1, n + 1):
            t += step_s
            times.append(t)
            values.append(int(round_half_up(cur + (target - cur) * k / n)))
        cur = float(target)
        t += dwell_s
    times.append(t)
    values.append(int(round_half_up(cur)))
    return pd.DataFrame({"time_s": np.round(times, 9), "du": int(du), "command": values})


def duration_s(rows: pd.DataFrame, tail_s: float = 0.0) -> float:
    """Time of the last row plus ``tail_s``."""
    return float(rows["time_s"].max()) + tail_s


def sample_commands(rows: pd.DataFrame, dus: Sequence[int], times_s) -> np.ndarray:
    """Command of each DU at each time, per FORMAT.md (last row with time_s <= t + 1e-9).

    Parameters
    ----------
    rows : schedule (time_s, du, command); rows of other DUs are ignored.
    dus : the DU ids, giving the column order.
    times_s : (n_times,) seconds from the take's first frame.

    Returns
    -------
    (n_times, n_dus) float array of commands (0 before a DU's first row).
    """
    times = np.asarray(times_s, float)
    out = np.zeros((times.size, len(dus)))
    if len(rows) == 0:
        return out
    order = np.argsort(rows["time_s"].to_numpy(), kind="stable")
    r_t = rows["time_s"].to_numpy(float)[order]
    r_du = rows["du"].to_numpy()[order]
    r_c = rows["command"].to_numpy(float)[order]
    for j, du in enumerate(dus):
        sel = r_du == du
        if not sel.any():
            continue
        t_du, c_du = r_t[sel], r_c[sel]
        idx = np.searchsorted(t_du, times + TIME_TOL_S, side="right") - 1
        out[:, j] = np.where(idx >= 0, c_du[np.maximum(idx, 0)], 0.0)
    return out


@dataclass(frozen=True)
class BatteryTake:
    """One take of an identification battery: a name, its DUs and its command rows."""

    name: str
    dus: tuple[int, ...]
    rows: pd.DataFrame
    purpose: str


MINOR_LOOP_LEVELS = (0.8, 0.3, 1.0, 0.1, 0.6, 0.0)  # fractions of 255: reversals inside the range


def identification_battery(dus: Sequence[int], pairs: Sequence[tuple[int, int]] = (),
                           *, fast_step_s: float = 0.025, slow_step_s: float = 0.3
                           ) -> list[BatteryTake]:
    """Takes that expose effects the paper's trapezoid cannot tell apart.

    Per DU: a fast trapezoid (20 steps up of ``fast_step_s``, 20 at 255, 20 down: 1.5 s at
    25 ms) and a slow one (10 steps up of ``slow_step_s``, 4 at 255, 10 down: 7.2 s at 0.3 s)
    (lag and dead time scale with the rate, static hysteresis does not), and a partial sweep with
    reversals inside the range 0 -> 0.8 -> 0.3 -> 1 -> 0.1 -> 0.6 -> 0 of full scale at the
    paper's ramp rate (minor loops: backlash, reversal memory). Per pair: both DUs' standard
    trapezoids at once (coupling, saturation), and the second shifted by 1.25 s.
    """
    takes: list[BatteryTake] = []
    for du in dus:
        takes.append(BatteryTake(f"du{du:02d}_fast", (du,), trapezoid(du, step_s=fast_step_s, n_hold=20),
                                 f"trapezoid at {fast_step_s * 1000:.0f} ms per step"))
        takes.append(BatteryTake(f"du{du:02d}_slow", (du,), trapezoid(du, step_s=slow_step_s, n_ramp=10, n_hold=4),
                                 f"trapezoid at {slow_step_s * 1000:.0f} ms per step"))
        takes.append(BatteryTake(f"du{du:02d}_minor", (du,),
                                 ramp_through([255 * f for f in MINOR_LOOP_LEVELS], du=du),
                                 "partial sweeps with reversals inside the range"))
    for a, b in pairs:
        both = pd.concat([trapezoid(a), trapezoid(b)], ignore_index=True)
        takes.append(BatteryTake(f"du{a:02d}_du{b:02d}_sync", (a, b), both,
                                 "two DUs' trapezoids at once"))
        shifted = pd.concat([trapezoid(a), trapezoid(b, t0_s=1.25)], ignore_index=True)
        takes.append(BatteryTake(f"du{a:02d}_du{b:02d}_shift", (a, b), shifted,
                                 "two DUs' trapezoids, the second 1.25 s later"))
    return takes


# The paper's time axis of a trapezoid take (reference METHOD.md: windows and t -> c conversion)

TIME_TOL_S = 1e-9  # frames within this of a window's edge are inside it (FORMAT.md's tolerance)


@dataclass(frozen=True)
class ScheduleTiming:
    """The paper's time axis of one take, in the take's own seconds (frame f at f / fps).

    t0_s: t = 0 (step s = 0); step_s: one command step; fwd_s: T_fwd; t_end_s: absolute time of
    t_end; bwd_s: T_bwd; top: the top command (255 for the paper).
    """

    t0_s: float
    step_s: float
    fwd_s: float
    t_end_s: float
    bwd_s: float
    top: float

    def frame_times(self, n_frames: int, fps: float) -> np.ndarray:
        """(n_frames,) t of each frame on the paper's axis (s; negative before step 0)."""
        return np.arange(n_frames) / float(fps) - self.t0_s

    def forward(self, n_frames: int, fps: float) -> tuple[np.ndarray, np.ndarray]:
        """(frames, c): the forward window's frame indices and their abscissa c = top t / T_fwd."""
        t = self.frame_times(n_frames, fps)
        f = np.flatnonzero((t >= -TIME_TOL_S) & (t <= self.fwd_s + TIME_TOL_S))
        return f, self.top * t[f] / self.fwd_s

    def backward(self, n_frames: int, fps: float) -> tuple[np.ndarray, np.ndarray]:
        """(frames, c): the backward window, c = top (t_end - t) / T_bwd."""
        t = self.frame_times(n_frames, fps)
        end = self.t_end_s - self.t0_s
        f = np.flatnonzero((t >= end - self.bwd_s - TIME_TOL_S) & (t <= end + TIME_TOL_S))
        return f, self.top * (end - t[f]) / self.bwd_s

    def schedule(self, n_frames: int, fps: float) -> np.ndarray:
        """(frames,) the schedule's frames, 0 <= t < t_end + one step (duration T_e)."""
        t = self.frame_times(n_frames, fps)
        end = self.t_end_s - self.t0_s + self.step_s
        return np.flatnonzero((t >= -TIME_TOL_S) & (t < end - TIME_TOL_S))

    def origin_frame(self, fps: float) -> int:
        """The frame at t = 0 (the first frame at or after step 0's start)."""
        return max(int(np.ceil(self.t0_s * float(fps) - 1e-6)), 0)


def schedule_timing(time_s, command, *, source: str = "command rows") -> ScheduleTiming:
    """The paper's time axis from one DU's command rows (a trapezoid: rise, hold, fall to 0).

    time_s, command : (n_rows,) the rows of one DU (any order; for equal times the later row
    wins, as FORMAT.md says). Raises ValueError naming ``source`` when the rows are not a
    rising ramp of several steps, a hold at the top, and a falling ramp back to 0.
    """
    t = np.asarray(time_s, float)
    c = np.asarray(command, float)
    if t.shape != c.shape or t.ndim != 1:
        raise ValueError(f"{source}: expected matching 1-D time_s and command, got {t.shape}, {c.shape}")
    order = np.argsort(t, kind="stable")
    t, c = t[order], c[order]
    last = np.r_[np.diff(t) > TIME_TOL_S, True]  # the last row of each time wins
    t, c = t[last], c[last]
    change = np.r_[True, np.diff(c) != 0]  # rows that change the command (repeats add nothing)
    t, c = t[change], c[change]
    if c.size == 0 or c[0] != 0:
        c = np.r_[0.0, c]  # the command is 0 before a DU's first row (FORMAT.md)
        t = np.r_[-np.inf, t]
    top = float(c.max())
    i_top = int(np.argmax(c == top))
    i_fall = i_top + int(np.argmax(c[i_top:] < top)) if np.any(c[i_top:] < top) else -1
    if top <= 0 or i_top < 2 or i_fall < 0:
        raise ValueError(f"{source}: expected a trapezoid (a rising ramp of several steps to the "
                         f"top command, a hold, a fall back to 0), got commands {c.tolist()[:12]}...")
    i_zero = i_fall + int(np.argmax(c[i_fall:] == 0)) if np.any(c[i_fall:] == 0) else -1
    rise = slice(1, i_top + 1)
    if i_zero < 0 or np.any(np.diff(c[rise]) <= 0) or np.any(np.diff(c[i_fall - 1: i_zero + 1]) >= 0):
        raise ValueError(f"{source}: expected a monotone rise to {top:g} and a monotone fall back "
                         "to 0 (the paper's trapezoid)")
    steps = np.diff(t[rise])
    step = float(np.median(steps))
    if not np.isfinite(step) or step <= 0:
        raise ValueError(f"{source}: cannot read the step time from the rising ramp's rows")
    t0 = float(t[1] - step)  # step 1 starts one step after t = 0
    fall0 = float(t[i_fall] - step)  # the last step at the top starts one step before the fall
    return ScheduleTiming(t0_s=t0, step_s=step, fwd_s=float(t[i_top] - t0),
                          t_end_s=float(t[i_zero]), bwd_s=float(t[i_zero] - fall0), top=top)


def timing_from_series(command: np.ndarray, fps: float) -> ScheduleTiming:
    """:func:`schedule_timing` from a per-frame command series (n_frames,): each change is a row
    at its frame's time. The step time is then known to a frame; prefer the command file."""
    c = np.asarray(command, float)
    f = np.r_[0, np.flatnonzero(np.diff(c) != 0) + 1]
    return schedule_timing(f / float(fps), c[f], source="command series")
