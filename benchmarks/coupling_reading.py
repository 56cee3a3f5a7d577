"""How well the coupling's kappa is read, against the simulator's truth (issue #15).

For each face: the sweep's small 4-DU session (20 markers, 3 trials, 0.03 mm, smile plans A and
C, the pair takes of DUs 1 + 4 and 7 + 12), the base model fitted on all takes, and kappa read
two ways on it: in travel along each marker's measured path where the multi-DU takes hold their
DUs at full command (``coupling.coupling_kappa``, the workflow's reading), and by refitting the
scalar law in the model's drive y on the whole multi-DU takes (``coupling.law_kappa``, the
reading before, now its fallback). Both against the simulator's kappa in travel
(``truth.json`` ``coupling_travel_kappa``: the law's kappa on straight and bowed paths) and its
law's kappa. Writes benchmarks/coupling_reading.md and .json.

    python benchmarks/coupling_reading.py [--cases FAMILY:FORM:SEED[:EFFECT],...]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent

CASES = ("boucwen-bow:model:3,boucwen-bow:alt2:8,boucwen-offchord:alt2:2,boucwen-straight:alt2:6,"
         "branchplay-bow:alt2:4,branchplay-offchord:model:1,branchplay-offchord:alt2:2,"
         "branchplay-straight:alt2:8,pi-bow:alt2:2,pi-straight:alt2:8,preisach-bow:alt2:6,"
         "preisach-offchord:alt2:8,preisach-straight:alt:4,preisach-straight:alt2:4,"
         "pi-bow:alt:4:coupling+backlash,preisach-bow:model:1:coupling+backlash")


def read_case(family: str, form: str, seed: int, effect: str = "coupling") -> dict:
    from mocap.analysis.discrepancy.crossval import fit_base
    from mocap.analysis.discrepancy.prepare import prepare
    from mocap.analysis.discrepancy.settings import DiscrepancySettings
    from mocap.analysis.model.face_model import make_effects
    from mocap.analysis.model.effects import BASE
    from mocap.analysis.model.coupling import coupling_kappa, law_kappa
    from mocap.analysis.model.data import multi_du_takes
    from mocap.workflows.discrepancy.inputs import load_measured
    from mocap.simulate.truth import effect_parameters, realised_coupling_kappa

    from cross_family_sweep import _simulate  # the sweep's session of a case

    with tempfile.TemporaryDirectory() as tmp:
        d = _simulate(family, effect.replace("+", ","), seed, Path(tmp), form=form)
        info = json.loads((d / "truth" / "truth.json").read_text())
        ms = load_measured(d / "session", work_dir=Path(tmp) / "w")
        prep = prepare(ms.session.fps, ms.marker_names, ms.rest_mm, ms.takes, ms.rest_X,
                       DiscrepancySettings())
    data = prep.data
    takes = list(range(len(data.takes)))
    model = fit_base(data, make_effects(BASE), takes)
    t0 = time.perf_counter()
    travel = coupling_kappa(data, model, takes)
    t_travel = time.perf_counter() - t0
    t0 = time.perf_counter()
    drive = law_kappa(data, model, multi_du_takes(data, takes))
    t_drive = time.perf_counter() - t0
    truth = realised_coupling_kappa(info)
    law = effect_parameters(info)["coupling"]["kappa"]
    return {"family": family, "effect": effect, "form": form, "seed": seed,
            "truth_travel": round(truth, 4),
            "truth_law": law, "travel": round(travel, 4), "weighting": model.info["coupling_law"],
            "drive": round(drive, 4), "travel_error": round(travel / truth - 1, 4),
            "drive_error": round(drive / truth - 1, 4),
            "seconds": {"travel": round(t_travel, 3), "drive": round(t_drive, 3)}}


def markdown(rows: list[dict], wall: float) -> str:
    def pct(v):
        return f"{100 * v:+.1f} %"

    out = ["# Reading the coupling's kappa", "",
           "`python benchmarks/coupling_reading.py`: the sweep's small 4-DU sessions with a hidden "
           "coupling (kappa 0.35; forms: model = pull-weighted y_n (1 - kappa sum y_n' o), alt = "
           "uniform y_n (1 - kappa sum y_n'), alt2 = strain-stiffening y_n (1 - kappa sum "
           "y_n'^2)), the base model fitted on all takes, kappa read in travel where the multi-DU "
           "takes hold their DUs at full command (`coupling_kappa`, the workflow's reading) and "
           "by the scalar law refitted in the model's drive (`law_kappa`, a second reading for comparison). "
           "Full command: every DU's command at its highest for 0.5 s (`full_command`). "
           "Errors against the simulator's kappa in travel (`coupling_travel_kappa`: kappa on "
           "straight and bowed paths).", "",
           "| family | hidden | form | seed | truth in travel (law) | travel reading | weighting | "
           "error | drive reading | error |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['family']} | {r['effect']} | {r['form']} | {r['seed']} | {r['truth_travel']:.3f} "
                   f"({r['truth_law']}) | {r['travel']:.3f} | {r['weighting']} | "
                   f"{pct(r['travel_error'])} | {r['drive']:.3f} | {pct(r['drive_error'])} |")
    te = [abs(r["travel_error"]) for r in rows]
    de = [abs(r["drive_error"]) for r in rows]
    out += ["", f"Travel reading: largest error {100 * max(te):.1f} %, {sum(e <= 0.1 for e in te)} "
            f"of {len(te)} within 10 %. Drive reading: largest {100 * max(de):.1f} %, "
            f"{sum(e <= 0.1 for e in de)} of {len(de)} within 10 %. The travel reading takes "
            f"{max(r['seconds']['travel'] for r in rows):.2f} s at most, the drive reading "
            f"{max(r['seconds']['drive'] for r in rows):.2f} s. {wall:.0f} s in all.", ""]
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=CASES)
    args = ap.parse_args()
    t0 = time.perf_counter()
    rows = []
    for spec in args.cases.split(","):
        family, form, seed, *effect = spec.split(":")
        rows.append(read_case(family, form, int(seed), *effect))
        print(json.dumps(rows[-1]), flush=True)
    (HERE / "coupling_reading.json").write_text(json.dumps(rows, indent=1) + "\n")
    (HERE / "coupling_reading.md").write_text(markdown(rows, time.perf_counter() - t0))


if __name__ == "__main__":
    main()
