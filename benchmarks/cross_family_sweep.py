"""The discrepancy workflow across base-face families the model does not share (issue #15).

Every base family (``mocap.simulate.families.FAMILIES``: 4 hysteresis operators x 3 path shapes,
with per-take bias shifts and per-marker scatter) x {none, each effect, lag + drift, coupling +
backlash} x seeds; the hidden effects in the simulator's own form on odd seeds and in its "alt"
form (``effects_alt``: equations the model does not share) on even ones (a case may name its
form: FAMILY:EFFECT:SEED:FORM, e.g. alt2, the third coupling law). Each case: a small
labeled session (4 DUs, 20 markers, 3 trials, the identification battery, smiles A and C,
0.03 mm capture noise), run through the workflow, which sees only the session; scored against
the simulator's truth (truth/truth.json).

Targets (issue #15): hidden set named exactly in >= 95 % of cases; something named with no
hidden effect in <= 5 %; each named parameter within 20 % of the truth; final held-out RMS
<= 1.5 x the noise floor (aim 1.2).

The cases run in a seeded shuffled order (each seed's own order, the seeds taken in turn), so a
partial run samples every family, effect and form; ``--skip`` resumes a sweep across sittings.
Shards run side by side (one process each) and append JSON lines; ``--summarise`` merges them
(a case given twice counts once, its row from the later file: a case run again on newer code).

    python benchmarks/cross_family_sweep.py --seeds 1,2,3 --shard 0/2 > /tmp/sweep0.jsonl
    python benchmarks/cross_family_sweep.py --seeds 1,2,3 --shard 1/2 > /tmp/sweep1.jsonl
    python benchmarks/cross_family_sweep.py --summarise /tmp/sweep0.jsonl /tmp/sweep1.jsonl
    python benchmarks/cross_family_sweep.py --cases pi-bow:lag:2,boucwen-bow:lag+drift:2 > x.jsonl
    python benchmarks/cross_family_sweep.py --cases pi-bow:coupling:6:alt2 > y.jsonl
    python benchmarks/cross_family_sweep.py --summarise x.jsonl --out /tmp/subset  # not the page
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

EFFECTS = ["none", "lag", "deadtime", "backlash", "coupling", "drift", "saturation", "lag,drift",
           "coupling,backlash"]
PARAM = {"lag": "tau_s", "deadtime": "delay_s", "backlash": "halfwidth", "coupling": "kappa",
         "drift": "beta_per_trial", "saturation": "limit_mm"}


def cases(seeds) -> list[tuple[str, str, int]]:
    from mocap.simulate.families import FAMILIES

    per_seed = []
    for seed in seeds:
        block = [(fam, eff, seed) for fam in FAMILIES for eff in EFFECTS]
        order = np.random.default_rng(1000 + seed).permutation(len(block))
        per_seed.append([block[i] for i in order])
    # the seeds' shuffled orders taken in turn: a partial run samples both forms of every effect
    return [c for row in zip(*per_seed) for c in row]


def truth_parameters(truth: dict) -> dict[str, float]:
    """{parameter name: true value} of a single or combined hidden effect."""
    p = truth.get("parameters", {})
    if p and all(isinstance(v, dict) for v in p.values()):
        return {k: float(v) for d in p.values() for k, v in d.items()}
    return {k: float(v) for k, v in p.items()}


def realised_drift(info: dict) -> float:
    """The drift the session's takes hold, command units per trial
    (:func:`mocap.simulate.truth.realised_session_drift`: the drift's k plus the trend of the
    face's random trial shifts). With 3 trials a trial shift of SD s moves a DU's slope by about
    s / sqrt(2): seed 1's response trials give 3.32, 3.43, 4.99 and 0.83 per DU for k = 4 on
    every family, so k is not what any estimator can read from these takes; drift is scored
    against this (its error against k is kept in the JSON, ``relative_errors_vs_k``)."""
    from mocap.simulate.truth import realised_session_drift

    return realised_session_drift(info)


# hidden effects whose form the base model holds by construction: a saturation applied to each
# DU's own displacement before the sum (the alt forms) is, marker by marker, a change of that
# DU's path (the multi-DU takes add the compressed paths exactly as the model adds its measured
# ones: tests/test_simulate_families.py, "per DU, then summed"), so no take can tell it from the
# path shape the base measures (README, docs/discrepancy.md); only a compression of the total
# (the model form) is an effect to name. Such a case is exact when nothing else is named.
HELD_BY_BASE = {("saturation", "alt"), ("saturation", "alt2")}


def expected_named(hidden: list[str], form: str | None) -> list[str]:
    """The hidden effects a workflow can name: ``hidden`` less those the base holds."""
    return [h for h in hidden if (h, form) not in HELD_BY_BASE]


def seed_form(seed: int) -> str:
    """The hidden effects' form of a case without its own: model on odd seeds, alt on even."""
    return "model" if seed % 2 else "alt"


def _simulate(family: str, effect: str, seed: int, root: Path, plans=("A", "C"),
              form: str | None = None) -> Path:
    from mocap.simulate import preset, simulate
    from mocap.simulate.effects import make_effect

    form = form or seed_form(seed)
    cfg = preset("small", seed=seed, labeled=True, n_markers=20, labeled_noise_mm=0.03,
                 motion_plans=plans, face_family=family, effect=make_effect(effect, form=form))
    d = root / f"{family}_{effect.replace(',', '_')}_{seed}"
    simulate(cfg, d)
    return d


def rescore(row: dict) -> dict:
    """A row of an earlier run scored as this version scores: its expected set
    (:func:`expected_named`), and with the session simulated again (the same seed makes the same
    truth) the errors of a drift without its realised value, and of a coupling always (the truth
    in travel may be newer than the row), taken against what the takes hold."""
    hidden = row.get("hidden", [])
    if "error" not in row:  # the expected set as this version scores it
        expected = expected_named(hidden, row.get("form"))
        row = {**row, "expected": expected,
               "exact": sorted(row["named"]) == sorted(expected)}
    drift = "drift" in hidden and "beta_per_trial" not in row.get("realised", {})
    if "error" in row or not (drift or "coupling" in hidden):
        return row
    with tempfile.TemporaryDirectory() as tmp:
        d = _simulate(row["family"], row["effect"], row["seed"], Path(tmp), form=row.get("form"))
        info = json.loads((d / "truth" / "truth.json").read_text())
    if "coupling" in hidden:
        if "relative_errors_vs_law" in row:  # back to the error against the law first
            row = {**row, "relative_errors": {**row["relative_errors"],
                                              **row["relative_errors_vs_law"]}}
        row = _realised_errors(row, "coupling", "kappa", realised_coupling(info),
                               "relative_errors_vs_law")
    return _drift_errors(row, realised_drift(info)) if drift else row


def _realised_errors(row: dict, effect: str, parameter: str, realised: float, vs: str) -> dict:
    """``row`` with ``effect``'s error taken against what the takes hold (``realised``), the
    error against the equation's parameter kept under ``vs``."""
    row = {**row, "realised": {**row.get("realised", {}), parameter: round(realised, 5)}}
    est = row["parameters"].get(parameter)
    if effect in row["named"] and est is not None:
        errs = dict(row["relative_errors"])
        row[vs] = {effect: errs.get(effect)}
        errs[effect] = round((est - realised) / realised, 4)
        row["relative_errors"] = errs
    return row


def _drift_errors(row: dict, realised: float) -> dict:
    return _realised_errors(row, "drift", "beta_per_trial", realised, "relative_errors_vs_k")


def run_case(family: str, effect: str, seed: int, root: Path, local: bool | None = None,
             form: str | None = None) -> dict:
    from mocap.analysis.discrepancy.settings import DiscrepancySettings
    from mocap.workflows.discrepancy.results import run

    form = form or seed_form(seed)
    d = _simulate(family, effect, seed, root, form=form)
    t0 = time.perf_counter()
    settings = DiscrepancySettings(jobs=1)
    if local is not None:
        settings = replace(settings, local=local)
    res = run(d / "session", d / "out", settings, recording=False)
    info = json.loads((d / "truth" / "truth.json").read_text())
    truth = info["effect"]
    hidden = [] if effect == "none" else effect.split(",")
    named = list(res.named)
    params = {k: v for s in res.steps for k, v in s.parameters.items()}
    true_p = truth_parameters(truth)
    errors = {}
    for name in named:
        k = PARAM.get(name)
        if k and k in true_p and k in params and true_p[k]:
            errors[name] = round((params[k] - true_p[k]) / true_p[k], 4)
    expected = expected_named(hidden, form)
    row = {"family": family, "effect": effect, "form": form, "seed": seed, "hidden": hidden,
            "expected": expected, "named": named, "exact": sorted(named) == sorted(expected),
            "parameters": {k: round(v, 5) for k, v in params.items()},
            "truth": true_p, "relative_errors": errors,
            "alternatives": [a["effects"] for a in res.alternatives],
            "base_ratio": round(res.stages[0]["heldout_rms_mm"] / res.noise_floor_mm, 4),
            "final_ratio": round(res.final_heldout_rms_mm / res.noise_floor_mm, 4),
            "noise_floor_mm": round(res.noise_floor_mm, 5),
            "intervals": {k: [round(a, 4), round(b, 4)] for s in res.steps
                          for k, (a, b) in s.interval.items()},
            "forms": {s.effect: s.form for s in res.steps if s.form},
            "evidence": [[_brief(e) for e in s.evidence] for s in res.steps]
            + [[_brief(e) for e in res.final_evidence]],
            "seconds": round(time.perf_counter() - t0, 1)}
    row["local"] = settings.local
    if "coupling" in hidden:
        row = _realised_errors(row, "coupling", "kappa", realised_coupling(info),
                               "relative_errors_vs_law")
    return _drift_errors(row, realised_drift(info)) if "drift" in hidden else row


def realised_coupling(info: dict) -> float:
    """The coupling's loss the takes show, in travel along each marker's path
    (:func:`mocap.simulate.truth.realised_coupling_kappa`): the law's kappa on straight and
    bowed paths; on paths that end off the chord the travel runs ahead of the simulator's drive
    (0.29-0.31 for kappa 0.35), and the drive is the simulator's parametrisation of the path,
    which no estimator can read from the takes. kappa is scored against this (its error against
    the law's kappa is kept in the JSON, ``relative_errors_vs_law``)."""
    from mocap.simulate.truth import realised_coupling_kappa

    return realised_coupling_kappa(info)




def _brief(e: dict) -> list:
    """A candidate's evidence in a few numbers: effect, score, explained, RMS gain / noise,
    and where it acts: residuals moved, explained, RMS gain / noise; plausible."""
    loc = e.get("local") or {}
    return [e["effect"], round(e.get("score", 0.0), 1), round(e.get("explained", 0.0), 3),
            round(e.get("rms_gain_vs_noise", 0.0), 4), loc.get("n", 0),
            round(loc.get("explained", 0.0), 3), round(loc.get("rms_gain_vs_noise", 0.0), 3),
            bool(e.get("plausible", False))]


def _in_interval(row: dict, name: str) -> bool:
    """Whether the parameter's reported interval holds the value the row scores against (what
    the takes hold, ``realised``, where the row has it: a drift; else the truth)."""
    k = PARAM.get(name)
    iv = row.get("intervals", {}).get(k)
    truth = row.get("realised", {}).get(k, row["truth"].get(k))
    return bool(iv) and truth is not None and iv[0] <= truth <= iv[1]


def summarise(rows: list[dict], planned: int | None) -> tuple[dict, str]:
    failed = [r for r in rows if "error" in r]
    rows = [r for r in rows if "error" not in r]
    n = len(rows)
    exact = sum(r["exact"] for r in rows)
    none = [r for r in rows if r["effect"] == "none"]
    false = sum(bool(r["named"]) for r in none)
    errs = [abs(e) for r in rows for name, e in r["relative_errors"].items() if name in r["hidden"]]
    within = sum(e <= 0.2 for e in errs)
    # a parameter the data resolve only to an interval (a stick-slip band's half-width between
    # two command rows' thresholds): within 20 %, or the truth inside the reported interval
    within_iv = sum(abs(e) <= 0.2 or _in_interval(r, name)
                    for r in rows for name, e in r["relative_errors"].items() if name in r["hidden"])
    rms15 = sum(r["final_ratio"] <= 1.5 for r in rows)
    rms12 = sum(r["final_ratio"] <= 1.2 for r in rows)
    by_eff: dict[str, list[int]] = {}
    by_fam: dict[str, list[int]] = {}
    for r in rows:
        by_eff.setdefault(r["effect"], [0, 0])
        by_eff[r["effect"]][0] += r["exact"]
        by_eff[r["effect"]][1] += 1
        by_fam.setdefault(r["family"], [0, 0])
        by_fam[r["family"]][0] += r["exact"]
        by_fam[r["family"]][1] += 1
    pct = lambda a, b: f"{100 * a / b:.0f} %" if b else "-"  # noqa: E731
    codes: dict[str, int] = {}
    for r in rows:
        if "code" in r:
            codes[r["code"]] = codes.get(r["code"], 0) + 1
    cpu = [r["cpu_s"] for r in rows if "cpu_s" in r]
    summary = {"codes": codes, "cases_run": n, "cases_failed": len(failed), "cases_planned": planned, "exact": exact,
               "false_naming_none": false, "none_cases": len(none),
               "parameters_within_20pct": within, "parameters_within_20pct_or_interval": within_iv,
               "parameters_scored": len(errs),
               "final_rms_le_1_5": rms15, "final_rms_le_1_2": rms12,
               "by_effect": by_eff, "by_family": by_fam}
    L = ["# Cross-family sweep of the discrepancy workflow", "",
         "Small labeled sessions (4 DUs, 20 markers, 3 trials, identification battery, smiles A "
         "and C, 0.03 mm noise) of every base-face family x hidden effect; model-form effects on "
         "odd seeds, alt forms (equations the model does not share) on even seeds. Scored "
         "against the simulator's truth; a drift against the drift the takes hold (k plus the "
         "trend of the face's random trial shifts over 3 trials, realised_drift(); its "
         "error against k is in the JSON); a coupling against its kappa in travel along the "
         "paths (realised_coupling()); a saturation of each DU's own displacement (the alt "
         "forms) is a path shape the base holds, so nothing need be named for it "
         "(HELD_BY_BASE). Generated by benchmarks/cross_family_sweep.py.", "",
         f"**Cases run: {n}" + (f" of {planned} planned" if planned else "") + "**" +
         (" (a partial run: the cases ran in a seeded shuffled order, so they sample every "
          "family and effect)" if planned and n < planned else "") + ".", "",
         *(["Code: " + ", ".join(f"{c} ({k} cases)" for c, k in sorted(codes.items())) + "; "
            f"CPU {sum(cpu) / 3600:.1f} h over {len(cpu)} timed cases "
            f"(median {np.median(cpu):.0f} s a case).", ""] if codes else []),
         "| target | result |", "|---|---|",
         f"| hidden set named exactly (>= 95 %) | {exact} / {n} = {pct(exact, n)} |",
         f"| something named with none hidden (<= 5 %) | {false} / {len(none)} = {pct(false, len(none))} |",
         f"| named parameters within 20 % of truth | {within} / {len(errs)} = {pct(within, len(errs))} |",
         f"| ... or the truth inside the interval the data allow | {within_iv} / {len(errs)} = "
         f"{pct(within_iv, len(errs))} |",
         f"| final held-out RMS <= 1.5 x noise floor (every case) | {rms15} / {n} = {pct(rms15, n)} |",
         f"| final held-out RMS <= 1.2 x noise floor (aim) | {rms12} / {n} = {pct(rms12, n)} |",
         *(["", f"Cases that failed with an error (not scored): {len(failed)}: " + "; ".join(
             f"{r['family']} {r['effect']} seed {r['seed']}: {r['error'][:120]}" for r in failed)]
           if failed else []),
         "", "Exact by hidden effect: " + ", ".join(f"{k} {a}/{b}" for k, (a, b) in sorted(by_eff.items())) + ".",
         "", "Exact by family: " + ", ".join(f"{k} {a}/{b}" for k, (a, b) in sorted(by_fam.items())) + ".",
         "", "| family | hidden | form | seed | named | alternatives | parameters (truth) | "
         "rel. error | base / noise | final / noise | s |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in sorted(rows, key=lambda r: (r["family"], EFFECTS.index(r["effect"]), r["seed"])):
        held = [h for h in r["hidden"] if h not in r.get("expected", r["hidden"])]
        L.append(f"| {r['family']} | {r['effect'].replace(',', '+')}"
                 f"{' (held by the base)' if held == r['hidden'] else ' (' + ', '.join(held) + ' held by the base)' if held else ''} | "
                 f"{r['form']} | {r['seed']} | "
                 f"{', '.join(r['named']) or '-'}{'' if r['exact'] else ' **x**'} | "
                 f"{'; '.join(' or '.join(a) for a in r['alternatives']) or ''} | "
                 f"{json.dumps(r['parameters'])} ({json.dumps(r['truth'])}"
                 f"{'; the takes hold ' + json.dumps(r['realised']) if 'realised' in r else ''}) | "
                 f"{json.dumps(r['relative_errors'])} | {r['base_ratio']:.2f} | "
                 f"{r['final_ratio']:.2f} | {r['seconds']} |")
    return summary, "\n".join(L) + "\n"


def case_key(row: dict) -> tuple:
    """(family, effect, seed, form): the case a row ran."""
    return row["family"], row["effect"], int(row["seed"]), row.get("form") or seed_form(int(row["seed"]))


def latest_rows(rows: list[dict]) -> list[dict]:
    """One row per case, the last one given (files in the order given, lines in file order): a
    case run again on newer code, in a later file, supersedes its earlier row."""
    last = {case_key(r): r for r in rows}
    return list(last.values())


def code_version() -> str:
    """The commit the cases run on, with "+dirty" when the package's sources differ from it (a
    sweep resumed across sittings must say which code each row comes from)."""
    import subprocess

    root = HERE.parent
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, text=True,
                              capture_output=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "mocap", "analysis", "calib"],
                               cwd=root, text=True, capture_output=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+dirty" if dirty else "")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", default="1,2,3")
    ap.add_argument("--shard", default="0/1", help="i/n: run every n-th case from the i-th")
    ap.add_argument("--summarise", nargs="*", type=Path, help="JSON-lines files of earlier runs")
    ap.add_argument("--note", default="", help="a paragraph added to the table (how it was run)")
    ap.add_argument("--cases", default="", help="FAMILY:EFFECT:SEED[:FORM],... run just these "
                    "(effects joined by '+', e.g. pi-bow:lag+drift:2; FORM model, alt or alt2, "
                    "default by the seed's parity) instead of the seeds' whole grid")
    ap.add_argument("--local", action=argparse.BooleanOptionalAction, default=None,
                    help="name on the local criterion too, or not (DiscrepancySettings.local; "
                    "default: the library's default)")
    ap.add_argument("--skip", nargs="*", type=Path, default=[],
                    help="JSON-lines files of earlier runs: their cases are not run again (a sweep "
                    "resumed across sittings; the rows say which commit ran them)")
    ap.add_argument("--out", default="cross_family_sweep",
                    help="file stem of the summary in benchmarks/ (.md and .json)")
    args = ap.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    chosen = [(p[0], p[1].replace("+", ","), int(p[2]), p[3] if len(p) > 3 else None)
              for p in (c.split(":") for c in args.cases.split(",") if c)]
    planned = len(chosen) if chosen else len(cases(seeds))
    if args.summarise is not None:
        rows = latest_rows([rescore(json.loads(line)) for p in args.summarise
                            for line in p.read_text().splitlines() if line.startswith("{")])
        summary, md = summarise(rows, planned)
        if args.note:
            head, sep, tail = md.partition("| target |")
            md = head + args.note.strip() + "\n\n" + sep + tail
        (HERE / f"{args.out}.json").write_text(json.dumps({"summary": summary, "rows": rows},
                                                           indent=1) + "\n")
        (HERE / f"{args.out}.md").write_text(md)
        print(md.split("| family |")[0])
        return 0
    i, n = (int(v) for v in args.shard.split("/"))
    done = {case_key(r) for p in args.skip
            for r in map(json.loads, p.read_text().splitlines()) if "error" not in r}
    todo = [(fam, eff, seed, form) for fam, eff, seed, form in
            (chosen or [(*c, None) for c in cases(seeds)])
            if (fam, eff, seed, form or seed_form(seed)) not in done]
    code = code_version()
    with tempfile.TemporaryDirectory() as tmp:
        for k, (fam, eff, seed, form) in enumerate(todo):
            if k % n != i:
                continue
            cpu0 = time.process_time()
            try:
                row = run_case(fam, eff, seed, Path(tmp), args.local, form)
            except Exception as exc:  # a failed case is a result too
                row = {"family": fam, "effect": eff, "seed": seed, "form": form or seed_form(seed),
                       "error": repr(exc)}
            row["cpu_s"] = round(time.process_time() - cpu0, 1)
            row["code"] = code
            print(json.dumps(row), flush=True)
            shutil.rmtree(Path(tmp) / f"{fam}_{eff.replace(',', '_')}_{seed}", ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
