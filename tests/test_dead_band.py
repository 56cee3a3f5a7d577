"""Backlash in its two forms (issue #15): a play (the dead band trails the command by b after
it releases) and a stick-slip dead band (it releases with a jump to the command).

The simulator writes the stick-slip form as one of its "alt" equations (a plain Python loop in
``mocap.simulate.effects_alt``); the model's compiled kernel is checked against it, and the
workflow's backlash candidate against the simulator's truth on a face whose hysteresis is the
model's family but whose dead band is not the model's play: the candidate keeps the stick-slip
form and reads the half-width to the interval the command steps allow; naming it is a known
limitation (a dead band changes the motion only near reversals, so its gain over the whole
session is small).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import make_session
from hypothesis import given, settings
from hypothesis import strategies as st

from mocap.analysis.discrepancy import (
    DiscrepancySettings,
    candidate_evidence,
    cv_base,
    cv_candidate,
    effective_n,
    heldout,
    passes,
    prepare,
)
from mocap.analysis.face_model import make_effects
from mocap.analysis.model_effects import BASE, StickSlipBacklash
from mocap.analysis.play_kernel import stick_slip
from mocap.discrepancy_input import load_measured
from mocap.simulate import effects_alt
from mocap.simulate.effects import make_effect


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-40, 40), min_size=2, max_size=200), st.floats(0.5, 20))
def test_stick_slip_kernel_is_the_simulators_dead_band(steps, halfwidth):
    c = np.cumsum(np.column_stack([steps, steps[::-1]]), axis=0)
    np.testing.assert_array_equal(stick_slip(c, halfwidth), effects_alt.stick_slip(c, halfwidth))


def test_stick_slip_holds_then_jumps():
    """Up to 100, back down: held at 100 until the command has come back 2 b = 20, then on it."""
    c = np.r_[np.arange(0, 101, 5), np.arange(95, -1, -5)].astype(float)
    out = stick_slip(c[:, None], 10.0)[:, 0]
    top = int(np.argmax(c))
    np.testing.assert_array_equal(out[:top + 1], c[:top + 1])
    back = c[top:] > 100 - 20
    assert np.all(out[top:][back] == 100)
    np.testing.assert_array_equal(out[top:][~back], c[top:][~back])


@pytest.fixture(scope="module")
def dead_band_face(tmp_path_factory):
    """A PI face with straight paths (one DU with narrow loops, one with wide ones) and a hidden
    stick-slip dead band of half-width 12 command units. (The play form of the model's own
    backlash is not separable from a PI skin's own dead band, and the workflow says so when it
    names it: tests/test_discrepancy.py.)"""
    root = tmp_path_factory.mktemp("dead_band")
    make_session(root, seed=2, du_ids=(1, 7), n_markers=10, n_trials=3, labeled=True,
                 labeled_noise_mm=0.03, motion_plans=(), face_family="pi-straight",
                 effect=make_effect("backlash", form="alt"))
    truth = json.loads((root / "truth" / "truth.json").read_text())["effect"]
    ms = load_measured(root / "session")
    prep = prepare(ms.session.fps, ms.marker_names, ms.rest_mm, ms.takes, ms.rest_X,
                   DiscrepancySettings())
    base = cv_base(prep.data, make_effects(BASE))
    cand = cv_candidate(prep.data, base, "backlash", floor=prep.noise_floor_mm)
    return truth, prep, base, cand


def test_backlash_candidate_keeps_the_form_and_width_of_the_truth(dead_band_face):
    """The stick-slip form fits better than the play; the half-width is read as the interval of
    widths that release at the same command rows (the commands step by 12.5-13 units: a band of
    2 b releases after ceil(2 b / step) steps, so every b in 6.5-12.5 fits alike), which holds
    the truth and is no wider than a command step; the value is its centre."""
    truth, prep, base, cand = dead_band_face
    assert cand is not None, "the dead band gave no held-out gain"
    assert cand.cls is StickSlipBacklash, cand.cls
    b = truth["parameters"]["halfwidth"]
    step = prep.data.command_step
    for value, interval in zip(cand.values, cand.intervals):
        assert interval is not None and interval[0] <= b <= interval[1], (interval, b)
        assert interval[1] - interval[0] <= step + 0.5, (interval, step)
        assert value == pytest.approx(0.5 * (interval[0] + interval[1]))


@pytest.mark.xfail(strict=True, reason="known limitation (issue #15): scored against its own "
                   "null (the band at 0 fitted along the same path) the stick-slip band (form "
                   "and interval right) scores -1967 held-out BIC units and explains 33 % of the "
                   "excess, but removes 1.5 % of a noise floor from the RMS (3 % asked); where "
                   "it acts it explains 36 % of the excess on 96 residual vectors (100 asked)")
def test_backlash_passes_the_naming_test(dead_band_face):
    """Scored as the workflow scores it (margin, plausibility, explained excess in the whole
    session or, with ``local``, where it acts), against the base."""
    truth, prep, base, cand = dead_band_face
    data, floor = prep.data, prep.noise_floor_mm
    n_eff = effective_n(heldout(data, base.models)[2], data.used)
    item = candidate_evidence("backlash", cand, base, floor, n_eff)
    assert item["form"] == "stick-slip"
    assert passes(item, DiscrepancySettings(local=True)), item
