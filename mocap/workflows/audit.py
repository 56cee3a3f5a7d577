"""The capture-quality audit: is this capture good enough to trust an analysis?

Items and their verdicts (pass / warn / fail), thresholds in ``THRESHOLDS`` (documented here and
written into audit.json):

- calibration: the calibration's rating (excellent or good: pass, poor: fail; commercial
  systems call "good" usable);
- per camera (raw sessions): its wand reprojection RMS (px); ghost rate, the share of its blobs
  that ended in no labeled marker (reflections, noise); dropout rate, the share of frames in
  which it missed a marker it normally sees (it contributes to at least half of that marker's
  reconstructed frames), over all face takes;
- per marker: cameras that see it (those contributing to at least half its frames; fewer than
  the reconstruction's minimum, ``min_cameras`` as the run was given, fails), gaps (count, longest, and the share of face-take frames missing), noise floor
  (rest take, per-axis sd; warn above 2x and fail above 4x the markers' median), across-trial
  spread (fail when rejected for abnormal spread);
- rejections: every marker and trajectory left out, with its reason;
- missing markers: a template marker (markers.csv) that was never reconstructed fails by name
  (no camera pair sees it, or it fell off);
- analyses: a session with nothing to analyse (no response take; and no command file, no DU)
  warns, and the verdict names why (:func:`nothing_to_analyse`).
- command alignment: per commanded take, the lag of its motion after its commands (capture
  time, ``commands_offset_s`` applied) read from the motion
  (:func:`mocap.reconstruction.align.motion_lags`, searched within ``ALIGNMENT_SEARCH_S``); a take
  whose motion precedes its commands by more than ``MISALIGNED_BEFORE_S`` or follows them by
  more than ``MISALIGNED_AFTER_S`` warns, by name. A take of uniform steps alone (a trapezoid)
  cannot tell a delay of whole steps from hysteresis: it is read as the lag the session's plan
  or motion takes pin (0, what the manifest says, when none does), so a trapezoid misaligned
  alone by whole steps passes.

The overall verdict is the worst item's, except that markers bring it to "warn" at most (a few
bad markers are left out by the rejections; a failing calibration or camera condemns the capture).

Pure computation in ``audit_capture``; ``write_audit`` writes audit.json and audit.md; the two
figures (visibility per marker and camera; noise floor per marker on the face) are drawn by
``mocap.outputs.figures.audit_figures`` (the outputs layer).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from mocap.core.atomic import write_text
from mocap.reconstruction.align import MISALIGNED_AFTER_S, MISALIGNED_BEFORE_S, motion_lags
from mocap.reconstruction.trials import marker_spread

THRESHOLDS = {
    "camera_reprojection_rms_px": {"warn": 0.2, "fail": 0.4},
    "camera_ghost_rate": {"warn": 0.08, "fail": 0.2},
    "camera_dropout_rate": {"warn": 0.05, "fail": 0.15},
    "marker_missing_fraction": {"warn": 0.05, "fail": 0.2},
    "marker_noise_vs_median": {"warn": 2.0, "fail": 4.0},
}
ORDER = {"pass": 0, "warn": 1, "fail": 2}
ALIGNMENT_SEARCH_S = 0.6
"""The audit looks for a take's motion lag within this many seconds of its commands."""


def command_alignment(session, reconstruction, min_cameras: int = 3) -> dict:
    """Each commanded take's motion lag after its commands, s (NaN when not read): the
    ``alignment`` of :func:`audit_capture`. Commands in capture time (offsets applied)."""
    from mocap.reconstruction.camera_count import usable_positions

    takes = {t.name: (usable_positions(reconstruction.takes[t.name], min_cameras),
                      session.read_commands(t.name))
             for t in session.takes if t.commands is not None and t.name in reconstruction.takes}
    if not takes:
        return {}
    lags = motion_lags(takes, session.fps, max_lag_s=ALIGNMENT_SEARCH_S, centre_s=0.0,
                       refine=False, prior_s=0.0)
    return {name: e.lag_s for name, e in lags.takes.items()}


def _verdict(value: float, th: dict) -> str:
    if not np.isfinite(value):
        return "warn"
    return "fail" if value > th["fail"] else "warn" if value > th["warn"] else "pass"


def nothing_to_analyse(session) -> str | None:
    """Why ``session`` (a ``mocap.core.session.Session``) gives the analyses nothing, or None.

    The paper's analyses, and the motion takes' evaluation that builds on them, need response
    takes. Without one the message names what is missing: response takes, and command files and
    DUs when there are none either, with the takes the session has by kind.
    """
    if session.takes_of_kind("response"):
        return None
    why = ["no response takes"]
    if not any(t.commands is not None for t in session.takes):
        why.append("no command files")
    if not session.dus:
        why.append("no DU")
    kinds: dict[str, int] = {}
    for t in session.takes:
        kinds[t.kind] = kinds.get(t.kind, 0) + 1
    has = ", ".join(f"{n} {k}" for k, n in kinds.items())
    return (f"nothing to analyse: {', '.join(why)} (the session has {has} take(s)); only the "
            "trajectories and the audit are written. Declare the response takes in session.toml "
            "(kind = \"response\", du, trial, commands) and the DUs ([[dus]]); 'mocap import' "
            "does it from a take table (--takes) or a name pattern (--pattern)")


def audit_capture(session_name: str, calibration, reconstruction, averages, rejections,
                  *, min_cameras: int = 3, unanalysable: str | None = None,
                  alignment: dict | None = None) -> dict:
    """The audit of a run as a JSON-ready dict.

    calibration : ``mocap.calib.wand_calibration.CalibrationResult`` (raw sessions) or None;
    reconstruction : ``mocap.reconstruction.takes.Reconstruction``; averages : the DUs'
    ``TrialAverage``; rejections : the rejections table; min_cameras : the cameras a 3D point
    needed in the reconstruction (a marker seen by fewer fails); unanalysable : why the session
    has nothing to analyse (:func:`nothing_to_analyse`), or None: a warning item, kept in
    ``nothing_to_analyse`` and named beside the verdict; alignment : take name -> the lag of its
    motion after its commands, s (:func:`command_alignment`), or None.
    """
    recon = reconstruction
    names = list(recon.markers.names)
    cap = recon.capture
    items = []
    report: dict = {"thresholds": THRESHOLDS, "session": session_name, "min_cameras": min_cameras}
    if calibration is not None:
        q = calibration.quality
        rating = q.get("rating", "poor")
        v = {"excellent": "pass", "good": "pass"}.get(rating, "fail")
        report["calibration"] = {"rating": rating, "verdict": v,
                                 "reprojection_rms_px": q.get("reprojection_rms_px"),
                                 "wand_length_error_mean_mm": q.get("wand_length_error_mean_mm"),
                                 "wand_length_error_sd_mm": q.get("wand_length_error_sd_mm")}
        items.append(("calibration", "calibration", v, f"rating {rating}"))
        cams = []
        ids = list(calibration.rig.ids)
        views = cap.views
        mf = np.maximum(cap.marker_frames, 1)
        sees = views >= 0.5 * mf[None]
        for i, cid in enumerate(ids):
            blobs = int(cap.camera_blobs[i])
            ghost = 1.0 - cap.camera_labeled_blobs[i] / max(blobs, 1)
            expected = mf[sees[i]].sum()
            dropout = 1.0 - views[i][sees[i]].sum() / max(expected, 1)
            rms = float(q["reprojection_rms_px"].get(cid, np.nan))
            verdicts = {"reprojection_rms_px": _verdict(rms, THRESHOLDS["camera_reprojection_rms_px"]),
                        "ghost_rate": _verdict(ghost, THRESHOLDS["camera_ghost_rate"]),
                        "dropout_rate": _verdict(dropout, THRESHOLDS["camera_dropout_rate"])}
            worst = max(verdicts.values(), key=ORDER.get)
            cams.append({"camera": cid, "blobs": blobs, "ghost_rate": float(ghost),
                         "dropout_rate": float(dropout), "reprojection_rms_px": rms,
                         "markers_seen": int(sees[i].sum()), "verdicts": verdicts, "verdict": worst})
            items.append(("camera", cid, worst, ", ".join(f"{k} {w}" for k, w in verdicts.items()
                                                          if w != "pass") or "ok"))
        report["cameras"] = cams
    # markers
    noise = recon.noise_per_marker_mm
    noise_m = np.sqrt(np.nanmean(noise**2, axis=1)) if noise is not None else np.full(len(names), np.nan)
    med_noise = float(np.nanmedian(noise_m)) if np.isfinite(noise_m).any() else np.nan
    rej = rejections if rejections is not None else pd.DataFrame(columns=["du", "marker", "reason"])
    spread_bad = set(rej.loc[rej["reason"] == "abnormal_spread", "marker"])
    spread_m = marker_spread(list(averages)) if averages else np.full(len(names), np.nan)
    frames = max(int(cap.frames), 1)
    markers = []
    for m, name in enumerate(names):
        missing = 1.0 - cap.marker_frames[m] / frames
        n_cam = None
        verdicts = {"missing": _verdict(missing, THRESHOLDS["marker_missing_fraction"])}
        if cap.views is not None:
            v = cap.views[:, m]
            n_cam = int(np.sum(v >= 0.5 * max(cap.marker_frames[m], 1)))
            verdicts["cameras"] = "fail" if n_cam < min_cameras else "pass"
        ratio = noise_m[m] / med_noise if np.isfinite(med_noise) and med_noise > 0 else np.nan
        verdicts["noise"] = _verdict(ratio, THRESHOLDS["marker_noise_vs_median"]) if np.isfinite(ratio) else "pass"
        verdicts["spread"] = "fail" if name in spread_bad else "pass"
        worst = max(verdicts.values(), key=ORDER.get)
        markers.append({"marker": name, "cameras": n_cam, "gaps": int(cap.gaps[m]),
                        "longest_gap_frames": int(cap.longest_gap[m]),
                        "missing_fraction": float(missing), "noise_floor_mm": float(noise_m[m]),
                        "across_trial_spread_mm": float(spread_m[m]), "verdicts": verdicts,
                        "verdict": worst})
        if worst != "pass":
            items.append(("marker", name, worst, ", ".join(f"{k} {w}" for k, w in verdicts.items()
                                                           if w != "pass")))
    report["markers"] = markers
    missing = list(getattr(recon.markers, "missing_from_template", ()))
    report["missing_markers"] = missing
    for name in missing:
        items.append(("marker", name, "fail", "never reconstructed (in markers.csv, not found in "
                      "the rest take: no camera pair sees it, or it fell off)"))
    report["nothing_to_analyse"] = unanalysable
    if unanalysable:
        items.append(("session", "analyses", "warn", unanalysable))
    if alignment is not None:
        report["command_alignment"] = {
            "thresholds_s": {"motion_before_commands": MISALIGNED_BEFORE_S,
                             "motion_after_commands": MISALIGNED_AFTER_S},
            "lag_s": {k: (None if not np.isfinite(v) else float(v)) for k, v in alignment.items()}}
        for name, lag in alignment.items():
            if np.isfinite(lag) and (lag < -MISALIGNED_BEFORE_S or lag > MISALIGNED_AFTER_S):
                when = (f"{-lag:.3f} s before" if lag < 0 else f"{lag:.3f} s after")
                items.append(("take", name, "warn",
                              f"commands and motion look misaligned: the motion comes {when} "
                              "its commands; set the take's commands_offset_s (mocap import "
                              "--align-commands proposes one)"))
    report["min_cameras"] = int(min_cameras)
    report["noise_floor_mm"] = recon.noise_floor_mm
    report["rejections"] = [{"du": (None if pd.isna(r.du) else int(r.du)), "marker": r.marker,
                             "reason": r.reason, "value": float(r.value),
                             "threshold": float(r.threshold)} for r in rej.itertuples()]
    report["flagged"] = [{"kind": k, "item": i, "verdict": v, "why": w} for k, i, v, w in items
                         if v != "pass"]
    # a few bad markers are left out by the rejections and do not condemn the capture: they
    # bring the overall verdict to "warn" at most; calibration and cameras can fail it
    overall = [v if k != "marker" else min(v, "warn", key=ORDER.get) for k, _, v, _ in items]
    report["verdict"] = max(overall + ["pass"], key=ORDER.get)
    return report


def _markdown(a: dict) -> str:
    lines = [f"# Capture audit: {a['session']}", "", f"Overall verdict: **{a['verdict']}**", ""]
    if a.get("nothing_to_analyse"):
        lines[-2] += f" ({a['nothing_to_analyse'].split(';')[0]})"
    if a["flagged"]:
        lines += ["## Flagged", "", "| kind | item | verdict | why |", "|---|---|---|---|"]
        lines += [f"| {f['kind']} | {f['item']} | {f['verdict']} | {f['why']} |" for f in a["flagged"]]
        lines.append("")
    if "calibration" in a:
        c = a["calibration"]
        lines += ["## Calibration", "", f"Rating {c['rating']} ({c['verdict']}); wand length error "
                  f"{c['wand_length_error_mean_mm']:+.4f} +- {c['wand_length_error_sd_mm']:.4f} mm.", ""]
    if "cameras" in a:
        lines += ["## Cameras", "", "| camera | blobs | ghost rate | dropout rate | reprojection RMS (px) | verdict |",
                  "|---|---|---|---|---|---|"]
        lines += [f"| {c['camera']} | {c['blobs']} | {c['ghost_rate']:.3f} | {c['dropout_rate']:.3f} | "
                  f"{c['reprojection_rms_px']:.3f} | {c['verdict']} |" for c in a["cameras"]]
        lines.append("")
    lines += ["## Markers", "", f"Noise floor (session mean, per axis): {a['noise_floor_mm']:.4f} mm." if a["noise_floor_mm"] else "", "",
              "| marker | cameras | gaps | longest gap (frames) | missing | noise (mm) | spread (mm) | verdict |",
              "|---|---|---|---|---|---|---|---|"]
    lines += [f"| {m['marker']} | {m['cameras']} | {m['gaps']} | {m['longest_gap_frames']} | "
              f"{m['missing_fraction']:.3f} | {m['noise_floor_mm']:.4f} | {m['across_trial_spread_mm']:.4f} | "
              f"{m['verdict']} |" for m in a["markers"]]
    if a.get("missing_markers"):
        lines += ["", "## Missing markers", "", "In markers.csv, never reconstructed: "
                  + ", ".join(a["missing_markers"]) + "."]
    lines += ["", "## Rejections", ""]
    if a["rejections"]:
        lines += ["| DU | marker | reason | value | threshold |", "|---|---|---|---|---|"]
        lines += [f"| {r['du'] if r['du'] is not None else 'all'} | {r['marker']} | {r['reason']} | "
                  f"{r['value']:.4g} | {r['threshold']:.4g} |" for r in a["rejections"]]
    else:
        lines.append("None.")
    lines += ["", "## Thresholds", "", "```json", json.dumps(a["thresholds"], indent=1), "```", ""]
    return "\n".join(lines)


def write_audit(out: Path, audit: dict) -> list[Path]:
    """Write audit.json and audit.md into ``out``; return the files.

    The audit's figures are drawn by the outputs layer
    (:func:`mocap.outputs.figures.audit_figures`): a workflow returns data.
    """
    return [write_text(out / "audit.json", json.dumps(audit, indent=2, default=float)),
            write_text(out / "audit.md", _markdown(audit))]
