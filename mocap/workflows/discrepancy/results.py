"""`mocap discrepancy`: run the workflow of :mod:`mocap.analysis.discrepancy.workflow` on a session or a run's
output and write ``discrepancy.json``, ``discrepancy.md``, ``figures/`` and ``discrepancy.rrd``
(the last two through the writers :mod:`mocap.outputs.discrepancy` passes in).
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from mocap.analysis.discrepancy.prepare import PHASES, Prepared, prepare
from mocap.analysis.discrepancy.result import DiscrepancyResult
from mocap.analysis.discrepancy.settings import DiscrepancySettings
from mocap.analysis.discrepancy.workflow import run_discrepancy
from mocap.analysis.model.effects import CATALOGUE
from mocap.core.atomic import write_text
from mocap.workflows.discrepancy.inputs import load_measured


def _r(x, nd=5):
    return None if x is None or not np.isfinite(x) else round(float(x), nd)


def result_json(res: DiscrepancyResult, prep: Prepared, meta: dict) -> dict:
    """discrepancy.json (docs/outputs.md, plus the localisation and per-DU/marker gaps per stage)."""
    floor = res.noise_floor_mm

    def evidence(items):
        return [{k: (_r(v) if isinstance(v, float) else v) for k, v in e.items()} for e in items]

    steps = []
    for i, s in enumerate(res.steps):
        before, after = res.stages[i], res.stages[i + 1]
        steps.append({
            "effect": s.effect,
            "named": s.named,
            "meaning": (s.meaning or CATALOGUE[s.effect].meaning),
            **({"form": s.form} if s.form else {}),
            "parameters": {k: _r(v, 6) for k, v in s.parameters.items()},
            **({"reading": s.reading} if s.reading else {}),
            "uncertainty": {k: _r(v, 6) for k, v in s.uncertainty.items()},
            **({"interval": {k: [_r(a, 6), _r(b, 6)] for k, (a, b) in s.interval.items()}}
               if s.interval else {}),
            **({"interval_note": s.interval_note} if s.interval_note else {}),
            "per_du": {str(du): _r(v, 6) for du, v in s.per_du.items()},
            "heldout_rms_before_mm": _r(s.heldout_rms_before_mm),
            "heldout_rms_after_mm": _r(s.heldout_rms_after_mm),
            "noise_floor_mm": _r(floor),
            "gap_shrink": _r(1.0 - _excess(s.heldout_rms_after_mm, floor)
                             / max(_excess(s.heldout_rms_before_mm, floor), 1e-12), 4),
            "explained_excess": _r(s.explained, 4),
            "per_du_before": before["dus"], "per_du_after": after["dus"],
            "per_marker_before": before["markers"], "per_marker_after": after["markers"],
            "evidence": evidence(s.evidence),
        })
    return {
        "named": list(res.named),
        "conclusion": (f"named {', '.join(res.named)}" if res.named else "no missing effect found"),
        "steps": steps,
        "final_heldout_rms_mm": _r(res.final_heldout_rms_mm),
        "noise_floor_mm": _r(floor),
        "noise_floor_source": res.noise_source,
        "final_ratio_to_noise": _r(res.final_heldout_rms_mm / floor, 3) if floor > 0 else None,
        "base_model": list(res.base_effects) or ["static"],
        "final_model": {"effects": res.final_model.effect_names,
                        "parameters": {k: _r(v, 6) for k, v in res.final_model.parameters().items()}},
        "untestable": res.untestable,
        "base_report": res.base_report,
        "alternatives": res.alternatives,
        "final_evidence": evidence(res.final_evidence) if not res.steps or
        res.final_evidence is not res.steps[-1].evidence else [],
        "excluded_markers": res.excluded_markers,
        "localisation": [{k: v for k, v in st.items()} for st in res.stages],
        "schedules": prep.schedules.__dict__,
        "takes": [{"name": t.name, "dus": list(t.dus), "trial": t.trial, "fold": t.fold}
                  for t in prep.data.takes],
        **meta,
    }


def _excess(rms: float, floor: float) -> float:
    """The part of a held-out RMS above the noise floor: sqrt(max(rms^2 - floor^2, 0)) (mm)."""
    return float(np.sqrt(max(rms ** 2 - floor ** 2, 0.0)))


def result_markdown(res: DiscrepancyResult, prep: Prepared, figures: dict, meta: dict) -> str:
    floor = res.noise_floor_mm
    L = ["# Model discrepancy", ""]
    L.append(f"Input: {meta['source']}. {len(prep.data.takes)} commanded takes in two folds "
             f"(each scored by the model fitted on the other fold); {int(prep.data.used.sum())} "
             f"markers scored" + (f", left out (abnormal noise): {', '.join(prep.excluded)}"
                                  if prep.excluded else "") + ".")
    L.append(f"Noise floor: **{floor:.4f} mm** (RMS 3D deviation of a trial from the "
             f"{'trials' if res.noise_source == 'repeated trials' else 'rest take'}; "
             f"source: {res.noise_source}). A residual above {1.5:.1f} x the floor is a "
             "disagreement.")
    L.append("")
    L.append(f"**Conclusion: {'named ' + ', '.join(res.named) if res.named else 'no missing effect found'}.**"
             f" Held-out RMS {res.stages[0]['heldout_rms_mm']:.4f} mm "
             f"({res.stages[0]['heldout_rms_mm'] / floor:.2f} x noise) with the base model "
             f"({', '.join(res.base_effects) or 'static, no hysteresis'}) -> "
             f"{res.final_heldout_rms_mm:.4f} mm ({res.final_heldout_rms_mm / floor:.2f} x noise).")
    if res.base_report:
        b = res.base_report
        L += ["", "The base model holds what every face has (not missing effects): each marker's "
              "own path" + (f" (median mid-range bow {b['path_bow']:.3f} of the displacement)"
                            if "path_bow" in b else "") +
              ", a Prandtl-Ishlinskii density of play widths" +
              (" (loop widths per DU: " + ", ".join(f"DU {k}: {v:.1f}" for k, v in
                                                    b.get("loop_width", {}).items()) + ")"
               if b.get("loop_width") else "") +
              (f", a bias shift per take and DU (SD {b['take_shift_sd']:.2f} command units)"
               if "take_shift_sd" in b else "") + "."]
    for alt in res.alternatives:
        first = alt["effects"][0]
        which = (f"{first} named, the other beside it" if first in res.named else "neither named")
        L += ["", f"Two explanations fit equally well ({' or '.join(alt['effects'])}), {which}: "
              f"{alt['reason']}."]
    if res.untestable:
        L += ["", "Effects these takes cannot tell apart (not named, whatever the residuals):"]
        L += [f"- {k}: not testable, {v}" for k, v in res.untestable.items()]
    for i, st in enumerate(res.stages):
        L += ["", f"## Stage {i}: model {st['model']}", "",
              f"Held-out RMS {st['heldout_rms_mm']:.4f} mm = {st['ratio_to_noise']:.2f} x noise.", ""]
        L += ["| phase | RMS (mm) | / noise |", "|---|---|---|"]
        for ph in PHASES:
            if ph in st["phases"]:
                v = st["phases"][ph]
                flag = " **beyond noise**" if v["ratio"] and v["ratio"] > 1.5 else ""
                L.append(f"| {ph} | {v['rms_mm']:.4f} | {v['ratio']:.2f}{flag} |")
        L += ["", "| DUs | RMS (mm) | / noise |", "|---|---|---|"]
        for k, v in st["dus"].items():
            L.append(f"| {k} | {v['rms_mm']:.4f} | {v['ratio']:.2f} |")
        worst = sorted(st["takes"].items(), key=lambda kv: -(kv[1]["rms_mm"] or 0))[:5]
        L += ["", "Largest gaps: " + ", ".join(f"{k} ({v['ratio']:.2f} x)" for k, v in worst) + "."]
        if i < len(res.steps):
            s = res.steps[i]
            L += ["", f"### Candidates after stage {i}", "",
                  "| effect | held-out RMS (mm) | score (BIC units, < -10 to name) | explains | "
                  "fold estimates | |", "|---|---|---|---|---|---|"]
            for e in s.evidence:
                L.append(_evidence_row(e))
            unit = CATALOGUE[s.effect].unit
            head = ("Named" if s.named else
                    "Kept in the model, not named (an alternative explains it as well)")
            edge = bool(s.evidence and s.evidence[0].get("dead_band_edge"))
            why = (s.interval_note or ("the onset read with a rise of another shape" if edge else
                                       "fits alike: the band releases at the same command rows"))
            L += ["", f"**{head}: {s.effect}** ({(s.meaning or CATALOGUE[s.effect].meaning)}): " + ", ".join(
                f"{k} = {v:.4g} +- {s.uncertainty.get(k, float('nan')):.2g} {unit}"
                + (f" ({'' if s.interval_note else 'any value '}in [{s.interval[k][0]:.4g}, "
                   f"{s.interval[k][1]:.4g}]: {why})"
                   if k in s.interval else "")
                for k, v in s.parameters.items()) +
                f"{' (read ' + s.reading + ')' if s.reading else ''}"
                f". Held-out RMS {s.heldout_rms_before_mm:.4f} -> {s.heldout_rms_after_mm:.4f} mm."]
            item = s.evidence[0]
            if edge and s.heldout_rms_after_mm > s.heldout_rms_before_mm:
                L += ["", f"The held-out RMS rises, but take by take the play predicts "
                      f"{item['takes_better']} held-out takes better and {item['takes_worse']} "
                      f"worse (the median take's SSE x {item['takes_median_ratio']:.3f}); the "
                      f"total is carried by {item['most_worse_take']['take']} "
                      f"({item['most_worse_take']['sse_mm2'][0]:.4g} -> "
                      f"{item['most_worse_take']['sse_mm2'][1]:.4g} mm^2 held out without and "
                      "with the play)."]
            if s.per_du:
                L += ["", "Per DU, from each DU's own takes: " + ", ".join(
                    f"DU {du}: {v:.4g}" for du, v in s.per_du.items()) + f" {unit}."]
    if not res.steps or res.final_evidence is not res.steps[-1].evidence:
        L += ["", "## Last candidates (none named)", "",
              "| effect | held-out RMS (mm) | score | explains | fold estimates | |",
              "|---|---|---|---|---|---|"]
        L += [_evidence_row(e) for e in res.final_evidence]
    if figures:
        L += ["", "## Figures", ""]
        L += [f"![{k}]({v})" for k, v in figures.items()]
    st = meta.get("settings") or asdict(DiscrepancySettings())
    where = (f"or where it acts (on at least {st['local_min_n']} held-out residual vectors it moves "
             f"by more than half the noise floor) explains {100 * st['local_explained']:.0f} % of "
             f"their excess and removes {st['local_gain']:g} of a noise floor; for a stick-slip "
             "dead band, on the rows where it holds a DU's actuator, the markers that DU moves"
             if st["local"] else
             "the gain where it acts, on the held-out residuals it moves by more than half the "
             "noise floor, is reported beside but not used: a dead band acts at reversals only")
    L += ["", "Method: two-fold cross-validation over takes; each candidate is fitted on one fold "
          "beside its null (the effect at 0 fitted along the same path) and scored on the other: "
          "score = n_eff ln(SSE_cand / SSE_null) + k ln(n_eff) on held-out takes (n_eff: the "
          f"residuals' effective sample size); an effect is named when its score is below "
          f"-{st['margin']:g}, it explains at least {100 * st['min_explained']:.0f} % of the "
          f"held-out excess over the noise floor and removes at least "
          f"{100 * st['min_rms_gain']:.0f} % of a noise floor from the held-out RMS ({where}), its "
          "parameter is plausible in both folds and on all takes, and the takes can test it. A "
          "candidate with several forms (backlash: a play, a stick-slip dead band; coupling: pair "
          "vectors, a pull-weighted or uniform law with pair vectors) is fitted in each and keeps "
          "the form with the larger held-out gain on its own null. After the search, a backlash "
          "the hysteresis density absorbed is read as the onset of the profile of a play forced "
          "before the final model (the widest band the takes allow), named when it is at least "
          "half a command step and the held-out takes are predicted no worse with it."]
    return "\n".join(L) + "\n"


def _evidence_row(e: dict) -> str:
    if not e.get("testable", True):
        return f"| {e['effect']} | | | | | not testable: {e.get('reason', '')} |"
    if e.get("screened_out"):
        return f"| {e['effect']} | | | | | no held-out gain on the first fold |"
    if e.get("dead_band_edge"):  # backlash, read as the onset of a forced play's profile
        hw = e.get("halfwidth")
        onset = "no onset" if hw is None else f"onset {hw:.3g} (threshold {e['threshold']:.3g})"
        return (f"| {e['effect']} | {e['heldout_rms_mm']:.4f} | | | {onset} | dead-band step"
                f"{': ' + e['reason'] if e.get('reason') else ''} |")
    if "shifts" in e:  # drift, decided from the trend of the takes' bias shifts
        return (f"| {e['effect']} | | | | slope {e.get('slope', 0):.3g} per trial | "
                f"{abs(e.get('t', 0)):.1f} standard errors of the takes' scatter |")
    fv = ", ".join(f"{v:.4g}" for v in e.get("fold_values", []))
    notes = [] if e.get("plausible", True) else ["implausible value"]
    if e.get("form") and e["form"] != "play":
        notes.append(f"form: {e['form']}")
    loc = e.get("local") or {}
    if loc.get("n"):
        at = "where it holds" if loc.get("where") == "held" else "where it acts"
        notes.append(f"{at} ({loc['n']} residuals): explains {loc['explained']:.2f}")
    note = "; ".join(notes)
    return (f"| {e['effect']} | {e['heldout_rms_mm']:.4f} | {e['score']:.1f} | "
            f"{e['explained']:.2f} | {fv} | {note} |")


@dataclass(frozen=True)
class DiscrepancyWriters:
    """The workflow's output writers, from the outputs layer
    (:data:`mocap.outputs.discrepancy.WRITERS`); None: not written.

    figures(res, prep, fig_dir) -> {caption: "figures/<file>.png"}
        the workflow's figures into ``fig_dir`` (linked from discrepancy.md)
    recording(path, res, data, session_name) -> Path
        discrepancy.rrd (``data``: ``prep.data``)
    """

    figures: Callable[[DiscrepancyResult, Prepared, Path], dict] | None = None
    recording: Callable[..., Path] | None = None


def run(path, out_dir, settings: DiscrepancySettings = DiscrepancySettings(),
        progress=None, recording: bool = True,
        writers: DiscrepancyWriters = DiscrepancyWriters()) -> DiscrepancyResult:
    """The workflow end to end on ``path`` (session or mocap run output), outputs in ``out_dir``:
    discrepancy.json and .md, and with ``writers`` (``mocap.outputs.discrepancy.WRITERS``, as
    ``mocap discrepancy`` passes) figures/ and (``recording``) discrepancy.rrd."""
    say = progress or (lambda m: None)
    t0 = time.perf_counter()
    out = Path(out_dir)
    from mocap.core.paths import check_output_path, session_dir_of

    check_output_path(out, sessions=[s for s in [session_dir_of(path)] if s], option="out_dir",
                      kind="folder")
    out.mkdir(parents=True, exist_ok=True)
    ms = load_measured(path, work_dir=out / "reconstruction", progress=say)
    t_load = time.perf_counter() - t0
    say(f"{len(ms.takes)} commanded takes, {len(ms.marker_names)} markers ({ms.source})")
    prep = prepare(ms.session.fps, ms.marker_names, ms.rest_mm, ms.takes, ms.rest_X, settings)
    res = run_discrepancy(prep, settings, progress=say)
    t_fit = time.perf_counter() - t0 - t_load
    figures = writers.figures(res, prep, out / "figures") if writers.figures is not None else {}
    meta = {"source": ms.source, "session": ms.session.name,
            "settings": {k: (list(v) if isinstance(v, tuple) else v)
                         for k, v in settings.__dict__.items()},
            "timings_s": {"load": round(t_load, 2), "workflow": round(t_fit, 2)}}
    if recording and writers.recording is not None:
        t = time.perf_counter()
        writers.recording(out / "discrepancy.rrd", res, prep.data, ms.session.name)
        meta["timings_s"]["recording"] = round(time.perf_counter() - t, 2)
    meta["timings_s"]["total"] = round(time.perf_counter() - t0, 2)
    write_text(out / "discrepancy.json", json.dumps(result_json(res, prep, meta), indent=2) + "\n")
    write_text(out / "discrepancy.md", result_markdown(res, prep, figures, meta))
    return res
