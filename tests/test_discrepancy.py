"""The face model and the model-discrepancy workflow against the simulator's hidden effects.

The workflow receives only the session (or a run's output); the truth (truth/truth.json,
truth/face.parquet) is read here to check what it found.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import make_session

from mocap.analysis.discrepancy.prepare import prepare, trial_noise
from mocap.analysis.discrepancy.settings import DiscrepancySettings
from mocap.analysis.discrepancy.workflow import run_discrepancy
from mocap.analysis.model.face_model import FaceModel
from mocap.analysis.model.hysteresis import play
from mocap.analysis.paper.hysteresis_fit import pi_logistic
from mocap.analysis.model.effects import CANDIDATES, CATALOGUE, Effect, summarize_schedules
from mocap.analysis.model.data import ModelData, TakeData
from mocap.analysis.model.fit import fit_curves
from mocap.analysis.model.profiles import profile_effect
from mocap.analysis.model.play_kernel import pi_logistic_from_table, play_table
from mocap.workflows.discrepancy.inputs import load_measured
from mocap.core.schedules import identification_battery, trapezoid
from mocap.simulate import preset
from mocap.simulate.effects import EFFECTS, HiddenEffect, make_effect
from mocap.simulate.motion import true_positions
from mocap.simulate.session_writer import virtual_rig_and_face

FPS = 120.0
# the missing effects the workflow names; curvature (each marker's own path) is in the base model
SINGLE = ["lag", "deadtime", "backlash", "coupling", "drift", "saturation"]


# ---------------------------------------------------------------------------------------------
# building blocks


def test_play_table_equals_the_play_operator():
    rng = np.random.default_rng(0)
    x = np.cumsum(rng.normal(0, 6, 900)).clip(0, 255)
    h = np.array([0.0, 0.5, 3.0, 12.25, 40.0])
    tab = play_table(x, 1, h)
    ref = play(x[:, None], h, 0.0)
    assert np.allclose(tab, ref, atol=1e-12)
    assert np.allclose(play_table(x, 3, h), ref[::3], atol=1e-12)


def test_pi_logistic_from_table_matches_reference_and_its_derivatives():
    rng = np.random.default_rng(1)
    c = np.concatenate([np.linspace(0, 255, 200), np.linspace(255, 60, 120), np.linspace(60, 200, 90),
                        np.linspace(200, 0, 150)]) + rng.normal(0, 0.5, 560)
    alpha, beta = np.array([0.03, 0.05, 0.02]), np.array([110.0, 150.0, 90.0])
    r = np.array([4.0, 11.0, 17.0])  # every play half-width on the table's grid: exact
    tab = play_table(c)
    y, dy = pi_logistic_from_table(tab, r, alpha, beta, derivatives=True)
    assert np.allclose(y, pi_logistic(c, alpha, beta, r), atol=1e-10)
    for j, (name, h) in enumerate((("alpha", 1e-6), ("beta", 1e-4), ("r", 1e-4))):
        p = [alpha.copy(), beta.copy(), r.copy()]
        p[j] = p[j] + h
        num = (pi_logistic_from_table(tab, p[2], p[0], p[1]) - y) / h
        assert np.allclose(dy[..., j], num, atol=2e-3 * np.abs(num).max() + 1e-9), name


def _model_from_truth(face, names_strengths) -> FaceModel:
    """The face model with the virtual face's own parameters and effects."""
    N, M = face.D_mm.shape[:2]
    effects = [CATALOGUE["hysteresis"]()]
    B = np.zeros((N, M, 0, 3))
    for name, v in names_strengths:
        if name == "curvature":
            side = np.cross(face.normals[None], face.D_mm)
            side /= np.linalg.norm(side, axis=-1, keepdims=True)
            B = np.zeros((N, M, CATALOGUE["curvature"].n_bases, 3))  # the bow is the first basis
            B[:, :, 0] = v * np.linalg.norm(face.D_mm, axis=-1, keepdims=True) * side
            effects.append(CATALOGUE["curvature"]())
        elif name == "saturation":
            effects.append(CATALOGUE["saturation"](1.0 / v))
        else:
            effects.append(CATALOGUE[name](v))
    return FaceModel(FPS, face.marker_names, face.rest_mm, face.du_ids, np.ones((N, M), bool),
                     face.alpha, face.beta, face.r_half, face.D_mm, B, tuple(effects))


@pytest.fixture(scope="module")
def face():
    return virtual_rig_and_face(preset("small", seed=4, n_markers=20))[2]


@pytest.mark.parametrize("name", ["none"] + SINGLE + ["curvature"])
def test_face_model_reproduces_the_virtual_face(face, name):
    """Same equations, two codes: the model with the true parameters predicts the true face."""
    pair = [b for b in identification_battery([1, 4], [(1, 4)]) if b.name == "du01_du04_shift"][0].rows
    minor = [b for b in identification_battery([7]) if b.name == "du07_minor"][0].rows
    eff = HiddenEffect.default(name)
    model = _model_from_truth(face, [] if name == "none" else [(name, eff.strength)])
    for rows, n in ((trapezoid(4), 620), (pair, 820), (minor, 730)):
        truth = true_positions(face, eff, rows, n, FPS, 3, None)
        pred = model.predict(rows, n, trial=3)
        assert np.abs(pred - truth).max() < 5e-3, (name, np.abs(pred - truth).max())


def test_two_hidden_effects_compose_in_the_simulator_and_the_model(face):
    eff = make_effect("lag,drift,coupling", "0.05,3,0.3")
    assert eff.name == "lag+drift+coupling"
    rows = [b for b in identification_battery([1, 4], [(1, 4)]) if b.name == "du01_du04_sync"][0].rows
    model = _model_from_truth(face, [("lag", 0.05), ("drift", 3.0), ("coupling", 0.3)])
    truth = true_positions(face, eff, rows, 700, FPS, 2, None)
    assert np.abs(model.predict(rows, 700, trial=2) - truth).max() < 5e-3


def test_second_order_pair_terms_are_the_plain_products():
    """pair_terms with the second order C2: y_a y_b C + y_a^2 y_b C2_0 + y_a y_b^2 C2_1 summed
    over the take's pairs, written out plainly for three DUs; first order alone without C2."""
    from mocap.analysis.model.face_model import pair_terms

    rng = np.random.default_rng(3)
    S, M = 7, 5
    y = rng.uniform(0, 1, (S, 3, M))
    dus, pairs = [1, 7, 12], ((1, 7), (1, 12), (4, 7), (7, 12))
    C, C2 = rng.normal(size=(4, M, 3)), rng.normal(size=(4, 2, M, 3))
    want = np.zeros((S, M, 3))
    want1 = np.zeros((S, M, 3))
    pos = {1: 0, 7: 1, 12: 2}
    for k, (a, b) in enumerate(pairs):
        if a not in pos or b not in pos:
            continue  # DU 4 is not in the take
        ya, yb = y[:, pos[a], :, None], y[:, pos[b], :, None]
        want1 += ya * yb * C[k]
        want += ya * yb * C[k] + ya * ya * yb * C2[k, 0] + ya * yb * yb * C2[k, 1]
    np.testing.assert_allclose(pair_terms(y, dus, pairs, C, C2), want, atol=1e-12)
    np.testing.assert_allclose(pair_terms(y, dus, pairs, C), want1, atol=1e-12)


def test_a_new_effect_plugs_in_without_editing_the_others():
    """An effect defined outside the catalogue (DUs that help each other: y_n (1 + g y_other))
    is predicted and identified by the same code, and its value recovered."""
    from dataclasses import dataclass
    from typing import ClassVar

    @dataclass(frozen=True)
    class Facilitation(Effect):
        name: ClassVar[str] = "facilitation"
        parameter: ClassVar[str] = "g"
        stage: ClassVar[str] = "interact"
        affects_curves: ClassVar[bool] = False
        grid: ClassVar[tuple] = (0.0, 0.2, 0.4, 0.6)
        bounds: ClassVar[tuple] = (-1.0, 2.0)

        def interact(self, y, D):
            return y * (1.0 + self.value * (y.sum(axis=1, keepdims=True) - y))

    face = virtual_rig_and_face(preset("small", seed=2, n_markers=8, du_ids=(4, 7)))[2]
    truth = _model_from_truth(face, [])
    truth = truth.with_effects(truth.effects + (Facilitation(0.3),))
    takes = []
    sync = [b for b in identification_battery([4, 7], [(4, 7)]) if b.name == "du04_du07_sync"][0].rows
    for k, rows in enumerate([trapezoid(4), trapezoid(7), sync]):
        dus = tuple(sorted(int(d) for d in pd.unique(rows["du"])))
        takes.append(TakeData(f"t{k}", "motion", 1, dus, rows, truth.predict(rows, 700), f"g{k}"))
    data = ModelData(FPS, face.marker_names, face.rest_mm, takes, (4, 7), np.ones(8, bool),
                     np.ones((2, 8), bool), stride=2)
    base = fit_curves(data, (CATALOGUE["hysteresis"](),), [0, 1, 2])
    prof = profile_effect(data, base, Facilitation(), [0, 1, 2])
    assert prof.model.effect_names == ["hysteresis", "facilitation"]
    assert prof.best == pytest.approx(0.3, abs=0.01)


def test_schedule_summary_says_what_can_be_tested():
    fps = FPS
    paper_only = [(trapezoid(d), k, f"d{d}") for d in (1, 4) for k in (1, 2)]
    s = summarize_schedules(paper_only, fps)
    assert s.n_rates == 1 and not s.inner_reversals and not s.multi_du and s.repeated_trials
    why = {n: CATALOGUE[n]().untestable(s) for n in CATALOGUE}
    assert {n for n, w in why.items() if w} == {"lag", "deadtime", "backlash", "coupling"}
    bat = [(b.rows, 1, b.name) for b in identification_battery([1, 4], [(1, 4)])]
    s2 = summarize_schedules(paper_only + bat, fps)
    assert s2.n_rates >= 3 and s2.inner_reversals and s2.multi_du
    assert not any(CATALOGUE[n]().untestable(s2) for n in CATALOGUE)


def test_no_noise_floor_is_a_clear_error():
    rows = trapezoid(1)
    X = np.zeros((620, 3, 3))
    takes = [TakeData("t1", "response", 1, (1,), rows, X, "g")]
    with pytest.raises(ValueError, match="noise floor cannot be measured"):
        prepare(FPS, ["a", "b", "c"], np.zeros((3, 3)), takes, rest_X=None)


def test_trial_noise_ignores_a_linear_drift_across_trials():
    rng = np.random.default_rng(3)
    base = np.cumsum(rng.normal(0, 0.1, (300, 5, 3)), axis=0)
    rows = trapezoid(1)
    takes = []
    for k in range(1, 7):
        X = base + 0.2 * k + rng.normal(0, 0.02, base.shape)  # drift 0.2 mm per trial
        takes.append(TakeData(f"t{k}", "response", k, (1,), rows, X, "g"))
    floor, per = trial_noise(takes)
    assert floor == pytest.approx(0.02 * np.sqrt(3), rel=0.05)
    assert per.shape == (5,)


# ---------------------------------------------------------------------------------------------
# the workflow on simulated sessions with a hidden effect


def _session(tmp_path_factory, effect: str, seed: int = 1, labeled: bool = True, **kw) -> Path:
    root = tmp_path_factory.mktemp(f"disc_{effect.replace(',', '_')}_{seed}")
    kw.setdefault("motion_plans", ("A", "C"))  # the DU pairs of the battery and two smiles
    return make_session(root, seed=seed, labeled=labeled, n_markers=kw.pop("n_markers", 20),
                        effect=make_effect(effect), **kw)


def _run(root: Path, out: Path | None = None, **settings):
    from mocap.workflows.discrepancy.results import run

    out = out or root / "discrepancy"
    res = run(root / "session", out, DiscrepancySettings(jobs=2, **settings), recording=False)
    return res, json.loads((out / "discrepancy.json").read_text())


def _truth(root: Path) -> dict:
    return json.loads((root / "truth" / "truth.json").read_text())["effect"]


def _gap_shrink(before, after, floor):
    ex = lambda r: np.sqrt(max(r ** 2 - floor ** 2, 0.0))
    return 1.0 - ex(after) / ex(before)


@pytest.mark.slow  # the whole workflow on a session: minutes under load
@pytest.mark.parametrize("effect", SINGLE)
def test_workflow_names_a_single_hidden_effect(tmp_path_factory, effect):
    root = _session(tmp_path_factory, effect)
    res, doc = _run(root)
    assert res.named and res.named[0] == effect, doc["steps"][0]["evidence"] if doc["steps"] else doc
    param, truth = EFFECTS[effect][0], _truth(root)["parameters"]
    est = doc["steps"][0]["parameters"][param]
    assert est == pytest.approx(truth[param], rel=0.2), (est, truth)
    assert doc["steps"][0]["uncertainty"][param] > 0
    floor = doc["noise_floor_mm"]
    step = doc["steps"][0]
    if effect == "backlash" and step["evidence"][0].get("dead_band_edge"):
        # the base's play density held the band (a play before the skin's plays is one operator
        # with wider plays); the edge of a forced play's profile names it, and the model with it
        # predicts the held-out takes no worse
        assert step["heldout_rms_after_mm"] <= 1.005 * step["heldout_rms_before_mm"]
    elif effect != "drift":  # the base holds each take's bias shift; drift names their trend
        assert _gap_shrink(step["heldout_rms_before_mm"], step["heldout_rms_after_mm"], floor) >= 0.6
    assert doc["final_heldout_rms_mm"] <= 1.5 * floor
    assert doc["named"] == [effect]  # nothing else is named
    if effect == "backlash":  # named, and where else such a band could sit is said beside it
        assert any(a["effects"] == ["backlash", "hysteresis dead band"]
                   and a["evidence"]["halfwidth"] == pytest.approx(est, rel=1e-3)
                   for a in doc["alternatives"]), doc["alternatives"]
    if effect == "backlash" and step["evidence"][0].get("dead_band_edge"):
        # each DU's own onset where its takes determine it to half a command step
        per_du = step["per_du"]
        assert per_du and set(per_du) <= {"1", "4", "7", "12"}, per_du
        assert all(v == pytest.approx(truth[param], rel=0.25) for v in per_du.values()), per_du
    elif effect in ("lag", "deadtime", "backlash", "drift", "saturation"):  # one value, every DU
        per_du = step["per_du"]
        assert set(per_du) == {"1", "4", "7", "12"}
        assert all(v == pytest.approx(truth[param], rel=0.25) for v in per_du.values()), per_du


@pytest.mark.slow  # the whole workflow on a session: minutes under load
def test_bowed_paths_are_held_by_the_base_and_reported_not_named(tmp_path_factory):
    """Paths that bow (the simulator's curvature, kappa 0.3): the base model holds each marker's
    path; nothing is named and the bow is reported with the base."""
    root = _session(tmp_path_factory, "curvature", seed=7)
    res, doc = _run(root)
    assert res.named == [], doc["named"]
    assert doc["base_report"]["path_bow"] == pytest.approx(0.3, rel=0.3)
    assert doc["final_heldout_rms_mm"] <= 1.5 * doc["noise_floor_mm"]


@pytest.mark.slow  # the whole workflow on a session: minutes under load
def test_workflow_names_nothing_without_a_hidden_effect(tmp_path_factory):
    root = _session(tmp_path_factory, "none", seed=2)
    res, doc = _run(root)
    assert res.named == [] and doc["conclusion"] == "no missing effect found"
    assert doc["final_heldout_rms_mm"] <= 1.5 * doc["noise_floor_mm"]
    md = (root / "discrepancy" / "discrepancy.md").read_text()
    assert "no missing effect found" in md


@pytest.mark.slow  # the whole workflow on a session: minutes under load
def test_workflow_finds_two_hidden_effects_one_after_the_other(tmp_path_factory):
    root = _session(tmp_path_factory, "lag,drift", seed=3)
    res, doc = _run(root)
    assert set(res.named[:2]) == {"lag", "drift"}, doc["named"]
    got = {k: v for s in doc["steps"] for k, v in s["parameters"].items()}
    assert got["tau_s"] == pytest.approx(0.08, rel=0.2)
    assert got["beta_per_trial"] == pytest.approx(4.0, rel=0.2)
    assert doc["final_heldout_rms_mm"] <= 1.5 * doc["noise_floor_mm"]
    rms = [s["heldout_rms_mm"] for s in doc["localisation"]]
    # the lag closes the gap; the drift is read last, as the trend of the takes' bias shifts
    # the model already holds, so its stage scores the same held-out residuals as the one before
    assert rms[0] > rms[1] and rms[2] == rms[1]
    assert doc["localisation"][2]["model"].endswith("+drift")


@pytest.mark.slow  # the whole workflow on a session: minutes under load
def test_workflow_finds_hysteresis_from_a_static_base_model(tmp_path_factory):
    """The paper's standard schedule only (trapezoids, 3 trials): a static model misses the
    hysteresis, and the workflow names it with the face's loop width."""
    root = _session(tmp_path_factory, "none", seed=4, battery=False, motion_plans=())
    res, doc = _run(root, out=root / "static", base=(), candidates=("hysteresis",) + CANDIDATES)
    assert res.named[:1] == ["hysteresis"], doc["named"]
    face = pd.read_parquet(root / "truth" / "face.parquet")
    true_width = float(np.median(2 * face["r_half"]))
    assert doc["steps"][0]["parameters"]["loop_width"] == pytest.approx(true_width, rel=0.2)
    assert doc["named"] == ["hysteresis"]


@pytest.mark.slow  # the whole workflow on a session: a minute under load
def test_untestable_effects_are_reported_not_named(tmp_path_factory):
    """The paper's trapezoids only: coupling hidden, but no take drives two DUs at once."""
    root = _session(tmp_path_factory, "coupling", seed=5, battery=False, motion_plans=())
    res, doc = _run(root)
    assert "coupling" not in res.named
    assert "coupling" in doc["untestable"] and "two DUs" in doc["untestable"]["coupling"]
    assert "lag" in doc["untestable"] and "backlash" in doc["untestable"]
    md = (root / "discrepancy" / "discrepancy.md").read_text()
    assert "coupling: not testable" in md


@pytest.mark.slow  # the whole workflow on a session: minutes under load
def test_cli_on_a_raw_session_writes_every_output(tmp_path_factory, monkeypatch, capsys):
    """A raw (2D) session with a hidden dead time, through `mocap discrepancy`: reconstruction,
    the workflow, discrepancy.json/md, figures and the Rerun recording."""
    from mocap.cli import main

    root = _session(tmp_path_factory, "deadtime", seed=6, labeled=False, n_markers=16,
                    motion_plans=("A",))
    out = root / "cli"
    assert main(["discrepancy", str(root / "session"), "--out", str(out), "--jobs", "2", "--quiet"]) == 0
    doc = json.loads((out / "discrepancy.json").read_text())
    assert doc["named"] == ["deadtime"]
    for key in ("steps", "final_heldout_rms_mm", "noise_floor_mm", "untestable", "localisation"):
        assert key in doc
    step = doc["steps"][0]
    assert {"effect", "parameters", "uncertainty", "heldout_rms_before_mm", "heldout_rms_after_mm",
            "noise_floor_mm", "evidence"} <= set(step)
    assert step["parameters"]["delay_s"] == pytest.approx(0.06, rel=0.2)
    assert {e["effect"] for e in step["evidence"]} == set(CANDIDATES) - {"drift"}  # drift: from shifts
    figs = sorted(p.name for p in (out / "figures").glob("*.png"))
    assert {"discrepancy_gap.png", "discrepancy_markers.png", "discrepancy_localisation_stage0.png",
            "discrepancy_localisation_stage1.png"} <= set(figs)
    assert any(f.startswith("discrepancy_traces_step1_deadtime") for f in figs)
    assert all((out / "figures" / f).stat().st_size > 5000 for f in figs)
    assert "deadtime" in (out / "discrepancy.md").read_text()
    from collections import Counter

    from rerun.chunk import RrdReader

    rows = Counter()
    for ch in RrdReader(out / "discrepancy.rrd").stream():
        rows[ch.entity_path] += ch.num_rows
    worst = max(doc["localisation"][0]["takes"].items(), key=lambda kv: kv[1]["rms_mm"])[0]
    for p in (f"/discrepancy/{worst}/measured", f"/discrepancy/{worst}/model_0",
              f"/discrepancy/{worst}/model_1", f"/plots/discrepancy/{worst}",
              "/charts/heldout_rms_mm", "/annotations/discrepancy"):
        assert rows[p] > 0, p
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    capsys.readouterr()
    assert main(["replay", str(out)]) == 0  # the output folder opens in the viewer
    assert "rerun discrepancy.rrd" in capsys.readouterr().out


def test_cli_reports_a_bad_input_clearly(tmp_path, capsys):
    from mocap.cli import main

    assert main(["discrepancy", str(tmp_path), "--out", str(tmp_path / "o"), "--quiet"]) == 1
    assert "neither a session" in capsys.readouterr().err
    assert main(["discrepancy", str(tmp_path), "--out", str(tmp_path / "o"), "--effects", "wobble"]) == 2


@pytest.mark.slow  # the whole workflow on a session: minutes under load
def test_workflow_reads_a_run_output_directory(small_run):
    """From `mocap run`'s output (the raw small session, no hidden effect): nothing is named."""
    ms = load_measured(small_run.out_dir)
    kinds = [t.kind for t in small_run.session.takes]
    assert "trajectories of" in ms.source
    assert len(ms.takes) == kinds.count("response") + kinds.count("motion")
    prep = prepare(ms.session.fps, ms.marker_names, ms.rest_mm, ms.takes, ms.rest_X)
    res = run_discrepancy(prep, DiscrepancySettings(jobs=2))
    assert res.named == []
    assert "backlash" in res.untestable  # no battery: no reversal inside the range


# ---------------------------------------------------------------------------------------------
# the sweep: naming rate over seeds and effects (slow; numbers in benchmarks/discrepancy.md)


@pytest.mark.slow
def test_confusion_matrix_over_seeds_and_effects(tmp_path_factory):
    effects = ["none"] + SINGLE
    seeds = [11, 12, 13]
    confusion = {e: {} for e in effects}
    for e in effects:
        for s in seeds:
            root = _session(tmp_path_factory, e, seed=s)
            res, _ = _run(root)
            got = res.named[0] if res.named else "none"
            confusion[e][got] = confusion[e].get(got, 0) + 1
    print(json.dumps(confusion, indent=1))
    single = sum(confusion[e].get(e, 0) for e in SINGLE) / (len(SINGLE) * len(seeds))
    false = 1 - confusion["none"].get("none", 0) / len(seeds)
    assert single >= 0.9 and false <= 0.05


def test_drift_interval_covers_the_generating_trend():
    """The drift's interval (the trend of the takes' bias shifts, 95 %) against trends drawn
    from a known slope: 4 DUs with their own intercepts, trapezoid takes in trials 1-3 and the
    battery's takes in trial 1, shifts scattered with SD 2 about the trend. Over 400 draws the
    interval holds the generating slope 91-99 % of the time (binomial 3 sd about 95 %); a
    plain +-1 standard error would hold it about 68 % of the time."""
    from mocap.analysis.discrepancy.drift import shift_trend, trend_interval

    rng = np.random.default_rng(7)
    k, hits, narrow = 4.0, 0, 0
    for _ in range(400):
        pts = []
        for du, a in zip((1, 4, 7, 12), rng.normal(0, 3, 4)):
            trials = [1, 2, 3] + [1] * int(rng.integers(3, 8))
            pts += [(t, du, a + k * t + rng.normal(0, 2.0)) for t in trials]
        tr = shift_trend(pts)
        lo, hi = trend_interval(tr)
        hits += lo <= k <= hi
        narrow += abs(tr["slope"] - k) <= tr["slope_se"]
    assert 0.91 <= hits / 400 <= 0.99, hits
    assert narrow / 400 < 0.8, narrow
