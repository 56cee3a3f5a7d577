"""The decision rules of the discrepancy workflow's candidate search: a candidate's evidence
against its null (held-out BIC score, fraction of the held-out excess over the noise floor
explained, RMS removed in noise floors), whether it names the candidate, whether a profile's
plateau reaches the null, the hull of the folds' intervals, and a dead time weighed against a
second-order lag."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from mocap.analysis.discrepancy.crossval import NO_LOCAL, CVFit, cv_candidate, n_parameters
from mocap.analysis.discrepancy.settings import DiscrepancySettings
from mocap.analysis.model.effects import CATALOGUE
from mocap.analysis.model.data import ModelData


def reaches_null(prof, cls) -> bool:
    """Whether a profile's plateau (the values that fit alike, ``prof.interval``) reaches the
    effect's null, the lower bound of its parameter (a dead band of 0): then the takes fit as
    well without the effect as with the value read, whatever the folds gained."""
    return prof.interval is not None and prof.interval[0] <= cls.bounds[0]


def fold_hull(prof, cls, fold_intervals: list):
    """A dead band read on command rows (``cls.command_grid``) whose profile on all takes has a
    single minimum while the folds' own profiles are flat over intervals
    (:attr:`~mocap.analysis.discrepancy.crossval.CVFit.intervals`): the whole session's
    minimum then wins by less than the folds disagree, and the widths the data allow are the hull of the folds' intervals and that
    minimum. Returns ``prof`` with that interval, its centre as the value (the model's band set
    to it, as :func:`mocap.analysis.model.profiles.profile_effect` does for a plateau) and the
    interval's width as its resolution; ``prof`` unchanged otherwise. Example: a Preisach face
    with straight paths, a coupling and a stick-slip band of 12, after the coupling: all takes
    prefer 7.0 by less than the fits' reproducibility, the folds are flat over 6.56-12.51 and
    6.50-9.49, and the band is reported as 9.5 in 6.50-12.51."""
    ivs = [iv for iv in fold_intervals if iv is not None]
    if not cls.command_grid or prof.interval is not None or not ivs:
        return prof
    lo = min([prof.best] + [iv[0] for iv in ivs])
    hi = max([prof.best] + [iv[1] for iv in ivs])
    centre = 0.5 * (lo + hi)
    model = prof.model.with_effects(tuple(cls(centre) if type(e) is cls else e
                                          for e in prof.model.effects))
    return replace(prof, best=centre, model=model, interval=(float(lo), float(hi)),
                   resolution=max(prof.resolution, hi - lo))


def candidate_evidence(name: str, cv: CVFit, current: CVFit, floor: float, n_eff: float) -> dict:
    """A fitted candidate's evidence against its null (``cv.null``: the candidate at 0 fitted
    along its own path; the current model when it has none): its held-out BIC score, the
    fraction of the held-out excess over the noise floor it explains and the RMS it removes (in
    the whole session and where it acts, :func:`~mocap.analysis.discrepancy.crossval.local_gain`),
    its fold values and whether they are plausible, and the form it was fitted in."""
    current = cv.null if cv.null is not None else current
    score = n_eff * np.log(cv.sse / current.sse) + n_parameters(cv.models[0], name) * np.log(n_eff)
    mse_cur = 3.0 * current.sse / max(current.n, 1)
    mse = 3.0 * cv.sse / max(cv.n, 1)
    excess = mse_cur - floor ** 2
    # with take shifts the base can fit under the trial noise floor: then any gain counts
    explained = (mse_cur - mse) / excess if excess > 0 else 1.0
    plausible = all(CATALOGUE[name](v).plausible() for v in (cv.values or [0.0]))
    return {"effect": name, "testable": True, "score": float(score),
            "heldout_rms_mm": cv.rms_mm, "explained": float(explained),
            "rms_gain_vs_noise": float((current.rms_mm - cv.rms_mm) / floor),
            "null_heldout_rms_mm": current.rms_mm,
            "fold_values": [float(v) for v in cv.values], "plausible": bool(plausible),
            "form": getattr(cv.cls, "form", None) if cv.cls is not None else None,
            "local": dict(cv.local or NO_LOCAL)}


def passes(e: dict, settings: DiscrepancySettings) -> bool:
    """Whether a candidate's evidence (:func:`candidate_evidence`) names it: testable, its score
    beyond the margin, its values plausible, and it explains enough of the held-out excess, in
    the whole session or where it acts."""
    if not e.get("testable") or e.get("screened_out"):
        return False
    loc = e.get("local") or NO_LOCAL
    overall = (e["explained"] >= settings.min_explained
               and e["rms_gain_vs_noise"] >= settings.min_rms_gain)
    local = (settings.local and loc["n"] >= settings.local_min_n
             and loc["explained"] >= settings.local_explained
             and loc["rms_gain_vs_noise"] >= settings.local_gain)
    return e["score"] < -settings.margin and e["plausible"] and (overall or local)


def lag_order_alternative(data: ModelData, current: CVFit, best: dict, n_eff: float,
                          margin: float) -> dict | None:
    """A dead time about to be named after a lag, weighed against a second-order lag of the
    same mean delay in place of the first-order one (one parameter fewer than lag + dead time).
    Both delay a ramp by their mean delay and differ only just after a step, so when the
    second-order lag's held-out score is within ``margin`` of the dead time's, the data cannot
    tell them apart: returns the alternative to report (and the dead time is not named), else
    None."""
    from mocap.analysis.model.effects import SecondOrderLag

    swap = cv_candidate(data, current, "lag", cls=SecondOrderLag)
    if swap is None:
        return None
    score = n_eff * np.log(swap.sse / current.sse)  # no parameter added: the lag is replaced
    if score > best["score"] + margin:
        return None
    return {"effects": ["deadtime", "second-order lag"],
            "evidence": {"deadtime_score": round(float(best["score"]), 1),
                         "second_order_lag_score": round(float(score), 1),
                         "second_order_lag_heldout_rms_mm": round(swap.rms_mm, 5),
                         "deadtime_heldout_rms_mm": round(float(best["heldout_rms_mm"]), 5),
                         "second_order_tau_s": [round(float(v), 5) for v in swap.values]},
            "reason": (f"after the lag, a dead time (fold values {best['fold_values']} s) "
                       f"scores {best['score']:.1f} held-out BIC units; the lag made second "
                       f"order instead (the same mean delay, one parameter fewer) scores "
                       f"{score:.1f}, no worse by more than the margin ({margin:g}): a "
                       "higher-order actuator and a lag plus a small dead time fit these takes "
                       "alike (the model keeps lag + dead time for its predictions); steps "
                       "sampled finely against the lag would tell them apart")}
