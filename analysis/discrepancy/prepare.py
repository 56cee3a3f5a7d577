"""A session made ready for the discrepancy workflow: the two cross-validation folds over its
takes, the noise floor (mm, from repeated trials or the rest take), the markers each DU moves and
the markers scored, and each sample's phase of the command (an index into :data:`PHASES`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mocap.analysis.discrepancy.settings import DiscrepancySettings
from mocap.analysis.model.effects import ScheduleSummary, command_moves, summarize_schedules
from mocap.analysis.model.data import ModelData, TakeData

PHASES = ("rest", "hold", "rise-fast", "rise", "rise-slow", "fall-fast", "fall", "fall-slow",
          "reversal")


# ----------------------------------------------------------------------------------------------
# data preparation


def schedule_class(t: TakeData) -> tuple[int, bool]:
    """What a take's schedule can reveal, as a sortable key: the median ramp rate of its moving
    command rows in octaves (log2 of command units/s, rounded) and whether it turns back inside
    the range (a minor loop)."""
    rates, inner = [], False
    for _du, g in t.rows.groupby("du"):
        step_rate, _, turns_inside = command_moves(g)
        if step_rate.size:
            rates.append(step_rate)
            inner |= turns_inside
    octave = int(np.round(np.log2(np.median(np.concatenate(rates))))) if rates else 0
    return octave, inner


def assign_folds(takes: list[TakeData]) -> None:
    """Two folds that each see every DU set at as many ramp rates as the session has.

    Within each DU set, the takes fall in three strata by :func:`schedule_class`: ramps at
    another rate than the set's most common one, schedules with minor loops, and the rest (the
    reference schedule and its repetitions, multi-DU takes). Ordered by DU set, rate, schedule
    and trial, each stratum alternates between the folds with its own running count over all
    DU sets (minor loops starting in the other fold). So each fold holds some trials of every
    repeated schedule; a DU's fast and slow ramps land in different folds instead of both in
    one (a fold that sees a DU at one rate cannot tell a lag from a wider hysteresis, and its
    fit then misleads the other fold's score); and the minor loops of successive DUs alternate,
    so both folds can test what only reversals inside the range reveal."""
    by_set: dict[tuple, list[int]] = {}
    for i, t in enumerate(takes):
        by_set.setdefault(t.dus, []).append(i)
    seen = {"rate": 0, "minor": 1, "reference": 0}
    for _, idx in sorted(by_set.items()):
        cls = {i: schedule_class(takes[i]) for i in idx}
        octaves, counts = np.unique([cls[i][0] for i in idx], return_counts=True)
        modal = octaves[np.argmax(counts)]
        order = sorted(idx, key=lambda i: (takes[i].kind != "motion", cls[i], takes[i].group,
                                           takes[i].trial, takes[i].name))
        for i in order:
            k = "rate" if cls[i][0] != modal else ("minor" if cls[i][1] else "reference")
            takes[i].fold = seen[k] % 2
            seen[k] += 1


def trial_noise(takes: list[TakeData], markers: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """Noise floor from repeated trials: what no deterministic model can predict.

    For every schedule played in n >= 2 trials, each trial's deviation from the trials' fit
    (the mean for 2 trials, a straight line over the trial number from 3, so that a drift across
    trials is not counted as noise), scaled to unbiased (sqrt(n / (n - p))), per marker.

    Returns (floor_mm, per_marker_mm (M,)): the RMS 3D deviation over all markers (or
    ``markers``) and per marker; NaN when no schedule was repeated.
    """
    groups: dict[str, list[TakeData]] = {}
    for t in takes:
        groups.setdefault(t.group, []).append(t)
    M = takes[0].X.shape[1]
    ss = np.zeros(M)
    cnt = np.zeros(M)
    for g in groups.values():
        n = len(g)
        if n < 2 or len({t.n_frames for t in g}) != 1:
            continue
        X = np.stack([t.X for t in g])  # (n, F, M, 3)
        tr = np.array([t.trial for t in g], float)
        if n >= 3 and np.unique(tr).size == n:
            A = np.column_stack([np.ones(n), tr - tr.mean()])
            p = 2
        else:
            A = np.ones((n, 1))
            p = 1
        ok = np.isfinite(X).all(axis=(0, 3))  # (F, M) frames seen in every trial
        Xf = np.where(ok[None, ..., None], X, 0.0)
        coef, *_ = np.linalg.lstsq(A, Xf.reshape(n, -1), rcond=None)
        fit = (A @ coef).reshape(X.shape)
        dev = np.sum((Xf - fit) ** 2, axis=-1) * n / (n - p)  # (n, F, M)
        ss += np.sum(np.where(ok[None], dev, 0.0), axis=(0, 1))
        cnt += n * ok.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        per = np.sqrt(ss / cnt)
    sel = np.ones(M, bool) if markers is None else markers
    sel = sel & (cnt > 0)
    floor = float(np.sqrt(ss[sel].sum() / cnt[sel].sum())) if sel.any() else float("nan")
    return floor, per


def rest_noise(rest_X: np.ndarray | None) -> tuple[float, np.ndarray]:
    """Noise floor from the rest take: RMS 3D deviation from each marker's mean (mm)."""
    if rest_X is None or not np.isfinite(rest_X).any():
        return float("nan"), np.full(0, np.nan)
    with np.errstate(invalid="ignore"):
        dev = np.sum((rest_X - np.nanmean(rest_X, axis=0)) ** 2, axis=-1)
        per = np.sqrt(np.nanmean(dev, axis=0))
    return float(np.sqrt(np.nanmean(dev))), per


@dataclass
class Prepared:
    """A session ready for the workflow: the model data, the noise floor and what can be tested."""

    data: ModelData
    noise_floor_mm: float
    noise_source: str
    per_marker_noise_mm: np.ndarray
    excluded: list[str]
    schedules: ScheduleSummary
    phase_labels: list[np.ndarray]  # per take, the phase (index into PHASES) of each sample


def prepare(fps: float, marker_names, rest_mm: np.ndarray, takes: list[TakeData],
            rest_X: np.ndarray | None = None,
            settings: DiscrepancySettings = DiscrepancySettings()) -> Prepared:
    """Folds, noise floor, moving markers per DU and the markers scored.

    Markers whose trial noise is over 3 x the median marker's (a badly seen marker) are left out
    of the scores and named in ``excluded``.
    """
    assign_folds(takes)
    floor, per = trial_noise(takes)
    source = "repeated trials"
    if not np.isfinite(floor):
        floor, per = rest_noise(rest_X)
        source = "rest take"
    if not np.isfinite(floor) or floor <= 0:
        raise ValueError("discrepancy: the noise floor cannot be measured: no command schedule was "
                         "played in two or more trials and there is no rest take")
    M = len(marker_names)
    used = np.ones(M, bool)
    if per.size == M and np.isfinite(per).any():
        med = np.nanmedian(per)
        used = ~(per > 3.0 * med)
        floor_used, _ = trial_noise(takes, used) if source == "repeated trials" else (floor, per)
        if np.isfinite(floor_used):
            floor = floor_used
    du_ids = tuple(sorted({d for t in takes for d in t.dus}))
    active = np.zeros((len(du_ids), M), bool)
    strong = np.zeros((len(du_ids), M), bool)
    n_frames = 0
    for n, du in enumerate(du_ids):
        ds = [np.linalg.norm(t.X - rest_mm, axis=-1) for t in takes if t.dus == (du,)]
        if not ds:
            continue
        n_frames = max(n_frames, sum(d.shape[0] for d in ds))
        with np.errstate(invalid="ignore"):
            p95 = np.nanpercentile(np.concatenate(ds), 95, axis=0)
        active[n] = (p95 > settings.active_mm) & used
        peak = np.nanmax(np.where(active[n], p95, np.nan)) if active[n].any() else 0.0
        strong[n] = active[n] & (p95 >= settings.strong_fraction * peak)
    # samples per DU bounded: a long study is read at a coarser stride
    stride = max(settings.stride, int(np.ceil(n_frames / settings.max_samples_per_du)))
    data = ModelData(fps=fps, marker_names=tuple(marker_names), rest_mm=rest_mm, takes=takes,
                     du_ids=du_ids, used=used, active=active, strong=strong, stride=stride)
    summary = summarize_schedules([(t.rows, t.trial, t.group) for t in takes], fps)
    excluded = [str(marker_names[i]) for i in np.flatnonzero(~used)]
    labels = [phases(t, data.samples(k), fps) for k, t in enumerate(takes)]
    return Prepared(data, floor, source, per, excluded, summary, labels)


# ----------------------------------------------------------------------------------------------
# phases of the command


def phases(t: TakeData, frames: np.ndarray, fps: float, reversal_s: float = 0.3) -> np.ndarray:
    """Phase label index (into :data:`PHASES`) of each frame of a take, from its commands.

    Each command row's rate is its change over the time since the row before (command units/s);
    a frame takes the rate of the row in force for each DU and the DU changing fastest decides:
    rise / fall, fast above 400 units/s, slow below 150 (the paper's ramp is 255 per second);
    ``hold`` when the row in force changed nothing, ``rest`` when every command is 0;
    ``reversal`` for ``reversal_s`` after a DU's command turns back inside its range.
    """
    from mocap.core.schedules import TIME_TOL_S

    times = frames / fps
    n = len(times)
    best_rate = np.zeros(n)
    best_sign = np.zeros(n)
    level = np.zeros(n)
    out = np.full(n, PHASES.index("hold"))
    for du in t.dus:
        g = t.rows[t.rows["du"] == du].sort_values("time_s", kind="stable")
        cc = g["command"].to_numpy(float)
        tt = g["time_s"].to_numpy(float)
        if cc.size == 0:
            continue
        dc = np.diff(cc, prepend=0.0)
        dt = np.diff(tt, prepend=tt[0] - 1.0)
        rate = np.abs(dc) / np.maximum(dt, 1e-6)
        idx = np.searchsorted(tt, times + TIME_TOL_S, side="right") - 1
        i = np.maximum(idx, 0)
        # a row's change is in force for one step (its own duration), then the command holds
        ok = (idx >= 0) & (times - tt[i] < np.maximum(dt[i], 1e-6))
        r = np.where(ok, rate[i], 0.0)
        sg = np.where(ok, np.sign(dc[i]), 0.0)
        c_now = np.where(idx >= 0, cc[i], 0.0)
        take = r > best_rate
        best_rate = np.where(take, r, best_rate)
        best_sign = np.where(take, sg, best_sign)
        level = np.maximum(level, c_now)
        # reversals inside the range
        mv = np.flatnonzero(np.diff(cc) != 0)
        if mv.size >= 2:
            s = np.sign(np.diff(cc)[mv])
            for k in mv[1:][s[1:] != s[:-1]]:
                if 0.05 * 255 < cc[k] < 0.95 * 255:
                    t0 = tt[k]
                    out[(times >= t0) & (times < t0 + reversal_s)] = -1
    rev = out == -1
    out[:] = PHASES.index("hold")
    out[(level == 0) & (best_rate == 0)] = PHASES.index("rest")
    for sign, name in ((1, "rise"), (-1, "fall")):
        m = best_sign == sign
        out[m & (best_rate > 400)] = PHASES.index(f"{name}-fast")
        out[m & (best_rate <= 400) & (best_rate >= 150)] = PHASES.index(name)
        out[m & (best_rate < 150)] = PHASES.index(f"{name}-slow")
    out[rev] = PHASES.index("reversal")
    return out
