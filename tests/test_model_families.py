"""The face model on base-face families it does not share (issue #15), scored against the
simulator's truth.

Two families whose hysteresis operator and marker paths are not the model's (a branch play
between each marker's own forward and backward curves with paths that end off the chord;
Bouc-Wen loops with bowed paths; both with per-take bias shifts and per-marker scatter) x three
hidden effects in the simulator's "alt" form (equations the model does not share): the base
model (PI density, each marker's path, a bias shift per take) is fitted on one fold and the
hidden effect identified, and the checks are against truth/truth.json: the parameter within 20 %
of the truth, the held-out RMS of the other fold at most 1.5 x the noise floor, and the effect
winning over the base by the workflow's margin. The full workflow over every family is
benchmarks/cross_family_sweep.py.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import make_session

from mocap.analysis.discrepancy.crossval import (
    cv_base,
    cv_candidate,
    effective_n,
    fit_base,
    heldout,
    n_parameters,
)
from mocap.analysis.discrepancy.drift import drift_step
from mocap.analysis.discrepancy.prepare import prepare
from mocap.analysis.discrepancy.report import parameter_reading
from mocap.analysis.discrepancy.settings import DiscrepancySettings
from mocap.analysis.discrepancy.workflow import run_discrepancy
from mocap.analysis.model.face_model import make_effects
from mocap.analysis.model.coupling import coupling_kappa, travel_path
from mocap.analysis.model.effects import BASE
from mocap.workflows.discrepancy.inputs import load_measured
from mocap.simulate.effects import make_effect
from mocap.simulate.truth import realised_coupling_kappa

FAMILIES = ["branchplay-offchord", "boucwen-bow"]
PARAM = {"lag": "tau_s", "coupling": "kappa", "drift": "beta_per_trial", "deadtime": "delay_s"}


def _prepared(root):
    ms = load_measured(root / "session")
    return prepare(ms.session.fps, ms.marker_names, ms.rest_mm, ms.takes, ms.rest_X,
                   DiscrepancySettings())


def _session(tmp_path_factory, family, effect, seed=5, n_trials=3, form="alt"):
    root = tmp_path_factory.mktemp(f"fam_{family}_{effect}")
    make_session(root, seed=seed, du_ids=(4, 7), n_markers=10, n_trials=n_trials, labeled=True,
                 labeled_noise_mm=0.03, motion_plans=(), face_family=family,
                 effect=make_effect(effect, form=form))
    info = json.loads((root / "truth" / "truth.json").read_text())
    truth = dict(info["effect"]["parameters"])
    if effect == "coupling":  # scored against the loss the takes show, in travel along the paths
        truth["kappa"] = realised_coupling_kappa(info)
    return root, truth


def _check_hidden_effect(root, truth, effect):
    """The hidden effect identified on one fold, scored on the other, against the truth."""
    prep = _prepared(root)
    data, floor = prep.data, prep.noise_floor_mm
    base = cv_base(data, make_effects(BASE))
    cand = cv_candidate(data, base, effect)
    assert cand is not None, "the hidden effect gave no held-out gain"
    _, _, res = heldout(data, base.models)
    n_eff = effective_n(res, data.used)
    score = n_eff * np.log(cand.sse / base.sse) + n_parameters(cand.models[0], effect) * np.log(n_eff)
    assert score < -10, score  # the workflow's margin
    est = float(np.mean(cand.values))
    assert est == pytest.approx(truth[PARAM[effect]], rel=0.2), (est, truth)
    assert cand.rms_mm <= 1.5 * floor, (cand.rms_mm, floor)


@pytest.fixture(scope="module")
def boucwen_bow_lag(tmp_path_factory):
    """The Bouc-Wen bowed face with the alt (second-order) lag, and the workflow on it with the
    two candidates at stake (lag, dead time; the whole catalogue is the sweep's: benchmarks/):
    (root, the effect's true parameters, the noise floor mm, the DiscrepancyResult). Its first
    step weighs the lag against the base exactly as the hidden-effect check does (cv_base,
    cv_candidate, the held-out BIC score with the base's effective n), so the Bouc-Wen lag case
    reads its evidence there instead of fitting both again."""
    root, truth = _session(tmp_path_factory, "boucwen-bow", "lag")
    prep = _prepared(root)
    res = run_discrepancy(prep, DiscrepancySettings(candidates=("lag", "deadtime")))
    return root, truth, prep.noise_floor_mm, res


@pytest.mark.parametrize(("family", "effect"), [("branchplay-offchord", "lag"),
                                                ("branchplay-offchord", "coupling"),
                                                ("boucwen-bow", "coupling")])
def test_hidden_effect_is_identified_on_a_foreign_family(tmp_path_factory, family, effect):
    """(Three of the four cases were known limitations until the base fit's joint polish:
    Bouc-Wen lag and coupling held out at 1.65-1.7 x the noise floor, the branch-play coupling's
    kappa read 20 % low.) The fourth case, Bouc-Wen with the lag, is the next test."""
    root, truth = _session(tmp_path_factory, family, effect)
    _check_hidden_effect(root, truth, effect)


def test_hidden_lag_is_identified_on_the_bouc_wen_bowed_face(boucwen_bow_lag):
    """The hidden-effect check above on the Bouc-Wen bowed face with its second-order lag, from
    the workflow's first step (the lag fitted on each fold against the base, scored on the other
    fold): the same three assertions on the same numbers."""
    _, truth, floor, res = boucwen_bow_lag
    assert res.steps, "the workflow took no step"
    cand = {e["effect"]: e for e in res.steps[0].evidence}.get("lag")
    assert cand is not None and cand.get("testable") and not cand.get("screened_out"), \
        ("the hidden effect gave no held-out gain", cand)
    assert cand["score"] < -10, cand["score"]  # the workflow's margin
    est = float(np.mean(cand["fold_values"]))
    assert est == pytest.approx(truth[PARAM["lag"]], rel=0.2), (est, truth)
    assert cand["heldout_rms_mm"] <= 1.5 * floor, (cand["heldout_rms_mm"], floor)


def test_dead_time_profile_reaches_the_delay_the_base_absorbed(tmp_path_factory):
    """A Bouc-Wen face with straight paths and the model's own dead time (0.06 s): the base fit
    without it widens its loops and moves its biases to hold the delay, and five iterations from
    there re-time the ramps only part of the way, so the profile read from the base was rough
    (a 4-DU face of the sweep: SSE 389 at 0.025 s, 487 at 0.026 s, 464 at 0.05 s; the
    workflow named a lag instead). The profile continues along its grid instead; the check
    is the hidden-effect check against the truth."""
    root, truth = _session(tmp_path_factory, "boucwen-straight", "deadtime", form="model")
    _check_hidden_effect(root, truth, "deadtime")


@pytest.mark.parametrize("family", FAMILIES)
def test_drift_is_told_from_take_to_take_shifts(tmp_path_factory, family):
    """The family shifts every take's biases at random (SD 1.5 command units); the hidden drift
    is a trend over trials on top (one rate for every marker: the alt form's per-marker rates
    are read as their sensitivity-weighted mean, not the plain mean the truth gives): named from
    the trend of the base model's take shifts, with its rate; the base alone fits the held-out
    takes to the noise floor."""
    root, truth = _session(tmp_path_factory, family, "drift", n_trials=5, form="model")
    prep = _prepared(root)
    data, floor = prep.data, prep.noise_floor_mm
    base = cv_base(data, make_effects(BASE))
    assert base.rms_mm <= 1.5 * floor, (base.rms_mm, floor)
    full = fit_base(data, make_effects(BASE), list(range(len(data.takes))))
    step, alt = drift_step(data, full, base.rms_mm, {})
    assert step is not None, alt
    est = step.parameters["beta_per_trial"]
    assert est == pytest.approx(truth["beta_per_trial"], rel=0.2), (est, truth)


def test_second_order_lag_is_named_lag_with_the_dead_time_as_an_alternative(boucwen_bow_lag):
    """The alt lag is second order (two equal poles; Bouc-Wen loops, bowed paths). The hidden set
    is {lag} (from the truth): the workflow names exactly that and reads tau within 20 % of the
    truth. After the first-order lag a small dead time may also fit the step responses: where it
    passes the margin, it is not named but reported with a second-order lag as explanations the
    takes cannot tell apart (with the PI-play base it passed; with the blended-play base it no
    longer does on this face, and nothing but the lag is left to report)."""
    root, truth, _, res = boucwen_bow_lag  # the workflow with the two candidates at stake
    hidden = json.loads((root / "truth" / "truth.json").read_text())["effect"]["name"]
    assert res.named == [hidden] == ["lag"], (res.named, res.alternatives)
    if any(s.effect == "deadtime" for s in res.steps):  # it passed the margin, and was not named
        assert any(set(a["effects"]) == {"deadtime", "second-order lag"} for a in res.alternatives)
    assert res.steps[0].parameters["tau_s"] == pytest.approx(truth["tau_s"], rel=0.2)
    assert all(s.named == (s.effect in res.named) for s in res.steps)



def _truth_heldout_rms(root, data, models) -> tuple[float, dict]:
    """RMS (mm) of each fold model's prediction of the takes it did not see against the
    simulator's true positions (truth/trajectories: no capture noise), over the scored markers;
    and per take. The prediction is the workflow's (the take's own bias shift fitted on the
    measured take, as every family shifts each take at random)."""
    import pandas as pd

    from mocap.analysis.model.fit import take_residual

    names = list(data.marker_names)
    total, count, per = 0.0, 0, {}
    for k, t in enumerate(data.takes):
        tr = pd.read_parquet(root / "truth" / "trajectories" / f"{t.name}.parquet")
        X = (tr.pivot(index="frame", columns="marker", values=["x", "y", "z"])
             .reindex(columns=pd.MultiIndex.from_product([["x", "y", "z"], names])))
        X = X.to_numpy().reshape(-1, 3, len(names)).transpose(0, 2, 1)[data.samples(k)]
        measured_minus_pred = take_residual(data, models[1 - t.fold], k)
        pred = data.observed(k) - measured_minus_pred + data.rest_mm
        e = (X - pred)[:, data.used]
        sq = np.sum(e ** 2, axis=-1)
        ok = np.isfinite(sq)
        total += float(np.sum(sq[ok]))
        count += int(ok.sum())
        per[t.name] = float(np.sqrt(np.mean(sq[ok])))
    return float(np.sqrt(total / count)), per


@pytest.mark.parametrize("family", ["preisach-straight", "branchplay-offchord"])
def test_base_fits_a_foreign_hysteresis_family_to_the_truth(tmp_path_factory, family):
    """No hidden effect, a hysteresis the model does not share: a Preisach face whose wide relays
    switch later (a shallow forward branch, a steep backward one) and a branch play between each
    marker's own forward and backward curves (a dead band after every reversal). The base, fitted
    on one fold, predicts the other fold's takes (minor loops included) within 0.8 x the noise
    floor of the simulator's true, noise-free positions. A sigmoid of a PI operator (one
    steepness on both branches, a density its full sweeps leave free) was 1.22 x (Preisach) and
    1.01 x (branch play) from the truth; the density-weighted mean of sigmoids of blended plays
    (branch parameters mix, kappa per DU; a DU without minor loops in its fold borrowing the
    density of the DUs with some; widths up to 80), 0.39 x and 0.52 x. On the Preisach face
    kappa is positive on every DU: the wide plays are centred later, as the truth's relays
    (centre slope 0.6)."""
    root, _ = _session(tmp_path_factory, family, "none", seed=2)
    prep = _prepared(root)
    data, floor = prep.data, prep.noise_floor_mm
    base = cv_base(data, make_effects(BASE))
    rms, per = _truth_heldout_rms(root, data, base.models)
    assert rms <= 0.8 * floor, (rms / floor, {k: round(v / floor, 2) for k, v in per.items()})
    if family.startswith("preisach"):
        kappa = [m.branch[:, 1].tolist() for m in base.models]
        assert all(k > 0.2 for ks in kappa for k in ks), kappa


def test_travel_path_recovers_a_path_from_samples_along_it():
    """travel_path: samples of a known path d(s) = s c + s (1 - s) (a + b s) at travels s (a,
    b across the chord c; the full-command samples at s = 1), marker by marker: the chord and
    both departure vectors come back, and the path is evaluated where it was never sampled."""
    rng = np.random.default_rng(0)
    M = 4
    c, a, b = rng.normal(0, 2, (M, 3)), rng.normal(0, 0.5, (M, 3)), rng.normal(0, 0.5, (M, 3))
    # the departure is across the chord (the travel is the projection on it)
    a, b = (v - np.sum(v * c, axis=1, keepdims=True) / np.sum(c * c, axis=1, keepdims=True) * c
            for v in (a, b))
    s = np.concatenate([rng.uniform(0, 1, (200, M)), np.ones((30, M))])
    d = s[..., None] * c + (s * (1 - s))[..., None] * (a + s[..., None] * b)
    full = np.arange(len(s)) >= 200  # the samples at full command
    d[3, 2] = np.nan  # a missing sample is skipped
    path = travel_path(d, full, np.ones(M, bool))
    np.testing.assert_allclose(path.chord, c, atol=1e-9)
    np.testing.assert_allclose(path.coef[:, 0], a, atol=1e-6)
    np.testing.assert_allclose(path.coef[:, 1], b, atol=1e-6)
    sv = np.full(M, 0.37)
    np.testing.assert_allclose(path.at(sv), 0.37 * c + 0.37 * 0.63 * (a + 0.37 * b), atol=1e-6)
    assert travel_path(d, np.zeros_like(full), np.ones(M, bool)) is None  # never at full command


@pytest.mark.parametrize(("family", "form", "seed"), [("branchplay-straight", "alt2", 2),
                                                      ("branchplay-offchord", "alt", 6)])
def test_coupling_kappa_is_read_in_travel_whatever_the_models_drive(tmp_path_factory, family,
                                                                    form, seed):
    """kappa read where the pair takes hold both DUs at full command, in travel along each
    marker's measured path, against the simulator's truth in the same terms (its law's kappa
    0.35 on straight paths; 0.31 on that off-chord face, where travel runs ahead of the drive):
    within 5 %, and the uniform law (both forms lose the same at every marker). The base model's
    y is the face's drive only up to a reparametrisation its paths absorb: the scalar law refitted
    in y read 0.179 on the branch-play face with straight paths and 0.256 on the off-chord one."""
    root, truth = _session(tmp_path_factory, family, "coupling", seed=seed, form=form)
    data = _prepared(root).data
    takes = list(range(len(data.takes)))
    model = fit_base(data, make_effects(BASE), takes)
    kappa = coupling_kappa(data, model, takes)
    assert model.info["coupling_law"] == "uniform"
    assert kappa == pytest.approx(truth["kappa"], rel=0.05), (kappa, truth)
    # the step reports how: in travel, the same loss at every marker
    assert "the same loss at every marker" in parameter_reading("coupling", model)
    assert parameter_reading("lag", model) == ""


@pytest.mark.slow  # a 4-DU session and the workflow: minutes
def test_coupling_law_is_named_when_its_own_value_vanishes_on_all_takes(tmp_path):
    """The sweep's Preisach face with straight paths and the alt (uniform) coupling law, 4 DUs,
    seed 4: the law form with pair vectors wins on the folds (kappa read 0.367 on each) while on
    all takes the law's own value is 0.009 (the pair vectors carry the coupling). The all-takes
    plausibility check read that value and named nothing (held-out 10.5 x the noise floor);
    it reads kappa from the whole fit, as the folds do. Scored against the simulator's kappa
    (in travel: the law's own on straight paths)."""
    from mocap.workflows.discrepancy.results import run
    from mocap.simulate import preset, simulate

    cfg = preset("small", seed=4, labeled=True, n_markers=20, labeled_noise_mm=0.03,
                 motion_plans=("A", "C"), face_family="preisach-straight",
                 effect=make_effect("coupling", form="alt"))
    simulate(cfg, tmp_path / "s")
    info = json.loads((tmp_path / "s" / "truth" / "truth.json").read_text())
    res = run(tmp_path / "s" / "session", tmp_path / "out",
              DiscrepancySettings(jobs=1, candidates=("coupling",)), recording=False)
    assert res.named == ["coupling"], [e for s in res.steps for e in s.evidence] or res.final_evidence
    kappa = res.steps[0].parameters["kappa"]
    assert kappa == pytest.approx(realised_coupling_kappa(info), rel=0.2), kappa
    assert res.final_heldout_rms_mm <= 1.5 * res.noise_floor_mm
    step = json.loads((tmp_path / "out" / "discrepancy.json").read_text())["steps"][0]
    assert "same loss at every marker" in step["reading"]  # the alt law: a uniform loss


@pytest.mark.slow  # a 4-DU session and the coupling candidate: a minute and a half
def test_coupling_of_a_shape_the_model_has_no_law_for(tmp_path):
    """The simulator's third coupling law (alt2, strain-stiffening skin: y_n (1 - kappa sum
    y_n'^2)), which no coupling form of the model shares, on a Prandtl-Ishlinskii face with bowed
    paths, seed 2. Scored against the simulator's kappa and the noise floor: with the pair
    vectors of first order only (y_n y_n') the multi-DU takes were left at 1.47 x the noise floor
    (kappa -0.9 %); their second order (y_n^2 y_n', y_n y_n'^2) takes it to 1.30 x."""
    from mocap.workflows.discrepancy.results import run
    from mocap.simulate import preset, simulate

    cfg = preset("small", seed=2, labeled=True, n_markers=20, labeled_noise_mm=0.03,
                 motion_plans=("A", "C"), face_family="pi-bow",
                 effect=make_effect("coupling", form="alt2"))
    simulate(cfg, tmp_path / "s")
    info = json.loads((tmp_path / "s" / "truth" / "truth.json").read_text())
    assert info["effect"]["form"] == "alt2"
    res = run(tmp_path / "s" / "session", tmp_path / "out",
              DiscrepancySettings(jobs=1, candidates=("coupling",)), recording=False)
    assert res.named == ["coupling"], [e for s in res.steps for e in s.evidence] or res.final_evidence
    kappa = res.steps[0].parameters["kappa"]
    assert kappa == pytest.approx(realised_coupling_kappa(info), rel=0.2), kappa
    assert res.final_heldout_rms_mm <= 1.4 * res.noise_floor_mm, res.final_heldout_rms_mm / res.noise_floor_mm


def test_base_fits_in_the_pool_equal_those_in_this_process(tmp_path_factory):
    """With workers (jobs > 1) the workflow fits the base on each fold and on all takes side by
    side in its pool, handed back while they fit (Futures: the candidates' screens start once
    the folds are done): the same model as fitted in this process."""
    from mocap.analysis.discrepancy.crossval import _Runner, fit_base, fold_takes

    root, _ = _session(tmp_path_factory, "pi-bow", "none")
    data = _prepared(root).data
    effects = make_effects(BASE)
    here = fit_base(data, effects, fold_takes(data, 1))
    runner = _Runner(data, 2)
    try:
        (pending,) = runner.base_fits(effects, [fold_takes(data, 1)])
        pooled = pending.result()
    finally:
        runner.close()
    for name in ("alpha", "beta", "r", "D", "B", "density", "branch"):
        np.testing.assert_allclose(getattr(pooled, name), getattr(here, name), rtol=1e-9, atol=1e-12)
    assert pooled.take_shifts.keys() == here.take_shifts.keys()
    for take, shifts in here.take_shifts.items():
        assert pooled.take_shifts[take] == pytest.approx(shifts, rel=1e-9, abs=1e-12), take


def test_multi_du_take_shifts_are_the_faces_not_the_couplings(tmp_path):
    """A 3-DU face (DUs 1, 7, 12 with the smile plans A and C, Preisach skin, straight paths)
    with the simulator's product coupling (alt, kappa 0.35): the coupling model's bias shift of
    every multi-DU take against the shift the simulator drew for that take (truth.json). A
    take's shift and a coupling loss both lower a DU's response; identified before the pair
    vectors, the smiles' shifts held the coupling (measured: 3.6 to 18.7 command units off the
    drawn ones, which are within +-3), and the alternation with the pair vectors did not bring
    them back. Fitted again from 0 as well, the better start kept (measured: within 2.3)."""
    from mocap.analysis.model.effects import UniformCouplingLaw
    from mocap.analysis.model.data import multi_du_takes
    from mocap.analysis.model.fit import fit_curves

    root = make_session(tmp_path, seed=5, du_ids=(1, 7, 12), n_markers=10, n_trials=3,
                        labeled=True, labeled_noise_mm=0.03, motion_plans=("A", "C"),
                        face_family="preisach-straight", effect=make_effect("coupling", form="alt"))
    drawn = {t["name"]: {int(d): v for d, v in t["bias_shift"].items()}
             for t in json.loads((root / "truth" / "truth.json").read_text())["takes"]}
    data = _prepared(root).data
    takes = list(range(len(data.takes)))
    base = fit_base(data, make_effects(BASE), takes)
    model = fit_curves(data, base.effects + (UniformCouplingLaw(0.2),), takes, warm=base, iters=30)
    multi = multi_du_takes(data, takes)
    assert len(multi) == 4 and any(len(data.takes[k].dus) == 3 for k in multi)
    for k in multi:
        t = data.takes[k]
        for d in t.dus:
            err = model.take_shifts[t.name][d] - drawn[t.name][d]
            assert abs(err) < 4.0, (t.name, d, model.take_shifts[t.name], drawn[t.name])
