"""Base-face families of the simulator against their equations, computed a second way.

Each family is checked against a plain re-computation written here (a relay-by-relay Preisach,
a fine Euler integration of Bouc-Wen, a loop over samples for the branch play) or against the
qualitative property that tells it apart (flat after a reversal, wiping-out and congruency,
rate-independence, a mid-range bow, a path that leaves off its chord).
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from scipy.special import ndtr

from mocap.core.schedules import trapezoid
from mocap.simulate import SimConfig, simulate
from mocap.simulate.effects import HiddenEffect
from mocap.simulate.face import make_face
from mocap.simulate.families import (
    FAMILIES,
    FAMILY_NAMES,
    PREISACH_CENTRE_SLOPE,
    PREISACH_ETA,
    family_stream,
    resolve_family,
)
from mocap.simulate.motion import normalized_response, true_take

FPS = 120.0
DUS = (1, 4, 7, 12)


def family_face(name: str, seed: int = 3):
    return make_face(np.random.default_rng(seed), 30, DUS, family=resolve_family(name, seed),
                     family_rng=family_stream(seed, "traits"))


def path_through(*levels, step: float = 1.0) -> np.ndarray:
    """A command series (n,) moving by ``step`` units per sample through the given levels."""
    out = [np.array([float(levels[0])])]
    for a, b in zip(levels[:-1], levels[1:]):
        n = max(1, int(round(abs(b - a) / step)))
        out.append(np.linspace(a, b, n + 1)[1:])
    return np.concatenate(out)


def logistic01(x, a, b):
    s = lambda v: 1.0 / (1.0 + np.exp(-a * (v - b)))
    return (s(x) - s(0.0)) / (s(255.0) - s(0.0))


def respond(face, du, c):
    """The face's normalised response (n, n_markers) to command series c (n,) on one DU."""
    rows = np.array([face.du_index(du)])
    return face.response(np.asarray(c, float)[:, None], rows)[:, 0]


# ---- branch play ------------------------------------------------------------------------------

def test_branch_play_is_flat_after_a_reversal_until_it_meets_the_other_branch():
    face = family_face("branchplay-straight")
    i = face.du_index(4)
    c = path_through(0, 230, 60, 230)
    y = respond(face, 4, c)
    r = face.r_half[i]
    F = logistic01(c[:, None], face.alpha[i], face.beta[i] + r)
    B = logistic01(c[:, None], face.traits.alpha_bwd[i], face.beta[i] - r)
    # a plain loop over samples: the state clipped between the two branches
    ref = np.zeros_like(F)
    state = np.zeros(F.shape[1])
    for k in range(len(c)):
        state = np.clip(state, np.minimum(F[k], B[k]), np.maximum(F[k], B[k]))
        ref[k] = state
    np.testing.assert_allclose(y, ref, atol=1e-12)
    top = int(np.argmax(c))  # the reversal at 230
    down = slice(top, top + 171)  # 230 -> 60
    on_b = np.isclose(y[down], B[down], atol=1e-12)
    moved = ~np.isclose(y[down], y[top], atol=1e-12)
    k = np.abs(face.D_mm[i]).sum(axis=1) > 0
    for m in np.flatnonzero(k):
        first = np.argmax(moved[:, m]) if moved[:, m].any() else None
        assert first is not None and first > 3, m  # flat for a while after the reversal
        assert on_b[first:, m].all(), m  # then on the backward branch, and stays on it
    # on the way up from a rise the state is the forward branch
    np.testing.assert_allclose(y[: top + 1], F[: top + 1], atol=1e-12)


# ---- Preisach -----------------------------------------------------------------------------

def relay_preisach(c, alpha, beta, r, n_centres=4000):
    """A relay-by-relay Preisach: per half-width line h_j, relays at n_centres centre quantiles
    of N(mu_j, s^2); each relay switches on at c >= centre + h and off at c <= centre - h. At
    rest (the plays' state 0) the relays with centres <= 0 are on."""
    h = r * (1.0 + 0.5 * PREISACH_ETA)
    w = np.exp(-0.5 * PREISACH_ETA**2)
    w = w / w.sum()
    s = np.pi / np.sqrt(3.0) / alpha
    q = (np.arange(n_centres) + 0.5) / n_centres
    from scipy.special import ndtri

    centres = beta + PREISACH_CENTRE_SLOPE * (h - r)[:, None] + s * ndtri(q)[None, :]
    up = centres + h[:, None]
    lo = centres - h[:, None]
    state = centres <= 0.0
    out = np.empty(len(c))
    for k, x in enumerate(c):
        state |= x >= up
        state &= ~(x <= lo)
        out[k] = np.sum(w * state.mean(axis=1))
    rest = np.sum(w * ndtr((0.0 - beta - PREISACH_CENTRE_SLOPE * (h - r)) / s))
    full = np.sum(w * ndtr((255.0 - h - beta - PREISACH_CENTRE_SLOPE * (h - r)) / s))
    return (out - rest) / (full - rest)


def test_preisach_matches_a_relay_by_relay_computation():
    face = family_face("preisach-straight")
    i = face.du_index(7)
    c = path_through(0, 255, 90, 200, 40, 160, 0, step=3.0)
    y = respond(face, 7, c)
    for m in (0, 7, 19):
        ref = relay_preisach(c, face.alpha[i, m], face.beta[i, m], face.r_half[i, m])
        np.testing.assert_allclose(y[:, m], ref, atol=2e-3)


def test_preisach_wipes_out_and_its_minor_loops_are_congruent():
    face = family_face("preisach-straight")
    # wiping-out: returning to 60 erases the 60 -> 170 -> 60 excursion from the memory
    a = respond(face, 4, path_through(0, 200, 60, 170, 60, 130))
    b = respond(face, 4, path_through(0, 200, 60, 130))
    np.testing.assert_allclose(a[-1], b[-1], atol=1e-12)
    # congruency: minor loops between the same extrema, after different histories, differ by
    # a constant only
    loop = path_through(80, 150, 80)
    h1 = path_through(0, 230, 80)
    h2 = path_through(0, 170, 80)
    y1 = respond(face, 4, np.r_[h1, loop[1:]])[len(h1) - 1:]
    y2 = respond(face, 4, np.r_[h2, loop[1:]])[len(h2) - 1:]
    assert np.abs(y1[0] - y2[0]).max() > 0.01  # the histories leave different states
    np.testing.assert_allclose(y1 - y1[0], y2 - y2[0], atol=1e-12)
    # and they are loops: up and down differ inside the range
    n = 70
    gap = np.abs(y1[n // 2] - y1[n + n // 2])
    assert gap.max() > 0.02


# ---- Bouc-Wen -----------------------------------------------------------------------------

def euler_bouc_wen(x, b, g, A=0.5, n_sub=400):
    """dz = A dx - b |dx| z - g dx |z| by explicit Euler with n_sub sub-steps per sample."""
    z = 0.0
    out = np.empty(len(x))
    prev = 0.0
    for k, xk in enumerate(x):
        dx = (xk - prev) / n_sub
        for _ in range(n_sub):
            z += A * dx - b * abs(dx) * z - g * dx * abs(z)
        prev = xk
        out[k] = z
    return out


def test_bouc_wen_follows_its_differential_equation():
    from mocap.simulate.families import BOUC_WEN_B, BOUC_WEN_G
    from mocap.simulate.hysteresis_ops import bouc_wen_state

    x = path_through(0, 255, 70, 180, 0, step=5.0)
    r = 30.0
    z = bouc_wen_state(x[:, None], BOUC_WEN_B / r, BOUC_WEN_G / r)[:, 0]
    ref = euler_bouc_wen(x, BOUC_WEN_B / r, BOUC_WEN_G / r)
    np.testing.assert_allclose(z, ref, atol=0.02)  # Euler's error at 400 sub-steps
    assert np.abs(z).max() <= r + 1e-9 and np.abs(z).max() > 0.95 * r


def test_bouc_wen_makes_a_loop_and_is_rate_independent():
    face = family_face("boucwen-straight")
    i = face.du_index(4)
    slow = path_through(0, 255, 0, step=0.5)
    fast = path_through(0, 255, 0, step=5.0)
    ys = respond(face, 4, slow)
    yf = respond(face, 4, fast)
    # the fast path's samples are every 10th of the slow path's: the same output there
    np.testing.assert_allclose(yf, ys[::10], atol=1e-9)
    # a loop on a full sweep: at command 128 the way down is above the way up
    up = np.argmin(np.abs(fast[:52] - 128))
    down = 51 + np.argmin(np.abs(fast[51:] - 128))
    k = np.abs(face.D_mm[i]).sum(axis=1) > 0
    assert np.all(yf[down, k] > yf[up, k] + 0.02)
    # after a reversal the hysteretic input a - z moves at once with slope 1 - 2 A b / (b + g) =
    # 0.3 of the command's (unlike the branch play's flat stretch and the PI's 0.2), then
    # steepens smoothly to 1
    from mocap.simulate.families import BOUC_WEN_B, BOUC_WEN_G
    from mocap.simulate.hysteresis_ops import bouc_wen_state

    r = face.r_half[i]
    w = slow[:, None] - bouc_wen_state(slow[:, None], BOUC_WEN_B / r, BOUC_WEN_G / r)
    top = int(np.argmax(slow))
    slope = np.diff(w[top:], axis=0) / np.diff(slow[top:])[:, None]
    # d zeta / du = A + (b - g) |zeta| right after the reversal: slope 1 - A - (b - g) |z_top|,
    # 0.3 once z has saturated at r
    expect = 1.0 - 0.5 - (BOUC_WEN_B - BOUC_WEN_G) / r * np.abs(w[top] - slow[top])
    np.testing.assert_allclose(slope[0], expect, atol=0.01)
    assert np.all((slope[0] > 0.28) & (slope[0] < 0.36))
    assert np.all(np.diff(slope, axis=0) > -1e-12)  # steepening, monotone
    assert np.all(slope[-1] > np.maximum(0.8, slope[0] + 0.4))


# ---- paths --------------------------------------------------------------------------------

def _take(face, du, family_path):
    dus, y = normalized_response(face, HiddenEffect(), trapezoid(du), 606, FPS, 1)
    d = true_take(face, HiddenEffect(), trapezoid(du), 606, FPS, 1, None).positions - face.rest_mm
    i = face.du_index(du)
    return y[:, 0], d, face.D_mm[i], face.traits.path_vec[i]


def test_bow_deviates_perpendicular_to_the_chord_at_mid_range():
    face = family_face("pi-bow")
    y, d, D, B = _take(face, 7, "bow")
    unit = D / np.linalg.norm(D, axis=1, keepdims=True)
    along = np.einsum("fmk,mk->fm", d, unit)
    perp = d - along[..., None] * unit
    np.testing.assert_allclose(along, y * np.linalg.norm(D, axis=1), atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(perp, axis=-1),
                               4 * y * (1 - y) * np.linalg.norm(B, axis=1), atol=1e-9)
    mid = np.abs(y - 0.5) < 0.05
    ratio = np.linalg.norm(perp, axis=-1)[mid] / np.broadcast_to(np.linalg.norm(B, axis=1), y.shape)[mid]
    assert ratio.min() > 0.98 and ratio.max() <= 1.0 + 1e-9  # 4 * 0.25 * |B| at y = 0.5
    k = np.linalg.norm(B, axis=1) / np.linalg.norm(D, axis=1)
    assert 0.3 - 1e-9 <= k.min() and k.max() <= 0.6 + 1e-9


def test_offchord_path_leaves_off_its_chord_and_ends_at_the_peak():
    face = family_face("pi-offchord")
    y, d, D, P1 = _take(face, 7, "offchord")
    big = np.linalg.norm(D, axis=1) > 1.0
    unit = D / np.linalg.norm(D, axis=1, keepdims=True)
    # at a small response the path heads along P1, 40-70 degrees off the chord D
    f = np.argmax(y.mean(axis=1) > 0.02)
    head = d[f] / np.linalg.norm(d[f], axis=1, keepdims=True)
    ang = np.degrees(np.arccos(np.clip(np.sum(head * unit, axis=1), -1, 1)))
    assert np.all((ang[big] > 35) & (ang[big] < 71)), ang[big]
    # it ends where a straight path would: at y D
    top = int(np.argmax(y.mean(axis=1)))
    np.testing.assert_allclose(d[top][big], (y[top, :, None] * D)[big],
                               atol=0.05 * np.linalg.norm(D, axis=1).max())
    # the cubic Bezier, computed directly
    yy = y[..., None]
    ref = 3 * yy * (1 - yy) ** 2 * P1 + 3 * yy**2 * (1 - yy) * (2 * D / 3) + yy**3 * D
    np.testing.assert_allclose(d, ref, atol=1e-9)
    # the sideways deviation peaks early (y ~ 1/3), not at mid-range like the bow
    perp = np.linalg.norm(d - np.einsum("fmk,mk->fm", d, unit)[..., None] * unit, axis=-1)
    rising = slice(0, top)
    m = int(np.argmax(np.linalg.norm(D, axis=1)))
    y_peak = y[rising][np.argmax(perp[rising, m]), m]
    assert 0.2 < y_peak < 0.45, y_peak


def test_coupling_travel_truth_equals_kappa_where_travel_is_the_drive():
    """The coupling's truth as data can read it (travel along each marker's path,
    VirtualFace.travel_kappa): the law's kappa on straight and bowed paths, whose projection on
    the chord is the drive; on paths that end off the chord, each marker's loss from the cubic
    Bezier's projection written out (3 y (1 - y)^2 cos t + 2 y^2 (1 - y) + y^3), averaged as the
    docstring says, plainly, over every pair and over the groups a session drives together."""
    kappa = 0.35
    for name in ("pi-straight", "pi-bow"):
        face = family_face(name)
        assert face.travel_kappa(kappa) == pytest.approx(kappa, abs=1e-9)
        assert face.travel_kappa(kappa, pull_weighted=True) == pytest.approx(kappa, abs=1e-9)
    face = family_face("pi-offchord")
    D, P1 = face.D_mm, face.traits.path_vec
    mag = np.linalg.norm(D, axis=-1)
    pairs = [(a, b) for a in DUS for b in DUS if a < b]
    for pull in (False, True):
        for groups in (None, [(1, 7, 12), (1, 4)]):
            num = den = 0.0
            for group in groups or pairs:
                rows = [DUS.index(g) for g in group]
                for a in rows:
                    for m in range(D.shape[1]):
                        if mag[a, m] == 0:
                            continue
                        x = sum(mag[b, m] / mag[b].max() if pull else 1.0 for b in rows if b != a)
                        y = 1.0 - kappa * x
                        cos_t = float(P1[a, m] @ D[a, m]) / (mag[a, m] * np.linalg.norm(P1[a, m]))
                        travel = 3 * y * (1 - y) ** 2 * cos_t + 2 * y**2 * (1 - y) + y**3
                        w = mag[a, m] ** 2
                        num += w * x * (1.0 - travel)
                        den += w * x * x
            got = face.travel_kappa(kappa, pull_weighted=pull, groups=groups)
            assert got == pytest.approx(num / den, rel=1e-9)
            assert 0.2 < got < kappa  # the travel runs ahead of the drive: less of it is lost


# ---- sessions ---------------------------------------------------------------------------------

def small_labeled(root, family, **kw):
    cfg = SimConfig(seed=kw.pop("seed", 4), du_ids=kw.pop("du_ids", (4, 7)), n_markers=15,
                    n_trials=kw.pop("n_trials", 2), motion_plans=(),
                    battery=kw.pop("battery", False), labeled=True,
                    labeled_noise_mm=0.03, take_format="parquet", face_family=family, **kw)
    simulate(cfg, root)
    return root


def truth_positions(root, take):
    tr = pd.read_parquet(root / "truth" / "trajectories" / f"{take}.parquet")
    n = int(tr["frame"].max()) + 1
    return tr[["x", "y", "z"]].to_numpy().reshape(n, -1, 3)


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_labeled_session_of_every_family(tmp_path, family):
    root = small_labeled(tmp_path / family, family, du_ids=(7,), n_trials=1)
    info = json.loads((root / "truth" / "truth.json").read_text())
    assert info["face_family"]["name"] == family
    df = pd.read_parquet(root / "session" / "takes" / "du07_t01.parquet")
    truth = pd.read_parquet(root / "truth" / "trajectories" / "du07_t01.parquet")
    err = df[["x", "y", "z"]].to_numpy() - truth[["x", "y", "z"]].to_numpy()
    nb = (df["marker"] == info["nose_bridge_marker"]).to_numpy()
    assert np.nanstd(err[~nb]) == pytest.approx(0.03, rel=0.1)
    moved = np.linalg.norm(truth_positions(root, "du07_t01")[300] - truth_positions(root, "du07_t01")[0], axis=-1)
    assert moved.max() > 2.0  # the face responds
    fp = pd.read_parquet(root / "truth" / "face.parquet")
    assert {"alpha_bwd", "path_x", "path_y", "path_z"} <= set(fp.columns)


def test_trial_shift_is_visible_between_trials(tmp_path):
    pi = small_labeled(tmp_path / "pi", "pi", n_trials=6, du_ids=(7,))
    fam = small_labeled(tmp_path / "fam", "pi-straight", n_trials=6, du_ids=(7,))
    info = json.loads((fam / "truth" / "truth.json").read_text())
    takes = [t for t in info["takes"] if t["du"] == 7]
    assert len(takes) == 6 and np.ptp([t["family_shift"]["7"] for t in takes]) > 1.0
    info_pi = json.loads((pi / "truth" / "truth.json").read_text())
    assert all(t["family_shift"]["7"] == 0.0 for t in info_pi["takes"] if t["du"] == 7)
    fp = pd.read_parquet(fam / "truth" / "face.parquet").set_index("marker")
    D = fp[["peak_x", "peak_y", "peak_z"]].to_numpy()
    big = np.linalg.norm(D, axis=1) > 2.0
    ramp = np.r_[12:114, 486:588]  # frames of the rising and falling ramps

    def ramps(root):
        p = np.stack([truth_positions(root, f"du07_t{k:02d}")[ramp][:, big] for k in range(1, 7)])
        return p, np.sqrt(np.mean((p - p.mean(axis=0)) ** 2))

    p_fam, spread_fam = ramps(fam)
    _, spread_pi = ramps(pi)
    assert spread_fam > 1.4 * spread_pi  # sd 1.5 units on top of the base face's 0.4 and jitter
    # a trial whose biases shift up responds later: less displacement along D on the ramps
    along = np.einsum("tfmk,mk->t", p_fam - p_fam.mean(axis=0), D[big])
    shift = np.array([t["bias_shift"]["7"] for t in takes])
    assert np.corrcoef(along, shift)[0, 1] < -0.9


def test_random_family_is_named_in_the_truth_only(tmp_path):
    root = small_labeled(tmp_path / "rnd", "random", du_ids=(4,), n_trials=1, seed=9)
    info = json.loads((root / "truth" / "truth.json").read_text())
    name = info["face_family"]["name"]
    assert name in FAMILIES and info["face_family"]["requested"] == "random"
    assert name == resolve_family("random", 9).name
    text = "".join(p.read_text() for p in (root / "session").rglob("*")
                   if p.is_file() and p.suffix in (".toml", ".csv"))
    assert "family" not in text and name not in text and info["face_family"]["hysteresis"] not in text
    names = {resolve_family("random", s).name for s in range(40)}
    assert len(names) >= 8  # the draw spreads over the families


def test_default_family_is_the_face_of_earlier_versions():
    base = make_face(np.random.default_rng(5), 20, DUS)
    fam = make_face(np.random.default_rng(5), 20, DUS, family=resolve_family("pi", 5))
    assert fam.traits is None and fam.family.trial_shift_sd == 0
    np.testing.assert_array_equal(base.D_mm, fam.D_mm)
    np.testing.assert_array_equal(base.beta, fam.beta)
    # a family keeps the base face's layout and draws its scatter on top
    other = make_face(np.random.default_rng(5), 20, DUS, family=FAMILIES["preisach-bow"],
                      family_rng=family_stream(5, "traits"))
    np.testing.assert_array_equal(other.rest_mm, base.rest_mm)
    assert not np.array_equal(other.beta, base.beta)
    with pytest.raises(ValueError, match="face family"):
        SimConfig(face_family="nope")
    assert "random" in FAMILY_NAMES and "pi" in FAMILY_NAMES


def test_simulate_cli_face_family(tmp_path):
    from mocap.cli import main

    out = tmp_path / "cli"
    rc = main(["simulate", str(out), "--preset", "small", "--dus", "4", "--trials", "1",
               "--markers", "12", "--no-battery", "--labeled", "--labeled-noise-mm", "0.05",
               "--face-family", "boucwen-offchord", "--seed", "2"])
    assert rc == 0
    info = json.loads((out / "truth" / "truth.json").read_text())
    assert info["face_family"]["name"] == "boucwen-offchord"
    assert info["config"]["labeled_noise_mm"] == 0.05


# ---- the hidden effects' alt forms ------------------------------------------------------------

@pytest.fixture(scope="module")
def face():
    return make_face(np.random.default_rng(3), 40, DUS)


def _y(face, effect, rows, n_frames=606, trial=1):
    return normalized_response(face, effect, rows, n_frames, FPS, trial)[1]


def _d(face, effect, rows, n_frames=606):
    return true_take(face, effect, rows, n_frames, FPS, 1, None).positions - face.rest_mm


def test_alt_lag_is_a_critically_damped_second_order():
    from mocap.core.schedules import sample_commands

    rows = pd.DataFrame({"time_s": [0.0], "du": [4], "command": [255]})
    t = np.arange(2000) / (FPS * 4)
    tau = 0.08
    a = HiddenEffect("lag", tau, "alt").command(sample_commands(rows, [4], t), t, None)[:, 0]
    # the step response of (tau/2 s + 1)^-2, sampled exactly
    x = t / (tau / 2)
    np.testing.assert_allclose(a, 255 * (1 - np.exp(-x) * (1 + x)), atol=1e-9)
    # tau is its mean delay: the area between the step and the response
    assert np.trapezoid(255 - a, t) / 255 == pytest.approx(tau, rel=0.01)


def test_alt_deadtime_is_a_distributed_delay_with_mean_l():
    from mocap.core.schedules import sample_commands

    rows = pd.DataFrame({"time_s": [0.0, 0.5], "du": [4, 4], "command": [0, 255]})
    t = np.arange(4800) / (FPS * 4)
    L = 0.1
    sampler = lambda times: sample_commands(rows, [4], times)
    a = HiddenEffect("deadtime", L, "alt").command(sampler(t), t, sampler)[:, 0]
    ramp = 255 * np.clip((t - 0.5 - 0.75 * L) / (0.5 * L), 0, 1)
    assert np.abs(a - ramp).max() <= 255 / 16 + 1e-9  # a 16-tap boxcar of width L / 2
    assert np.all(a[t < 0.5 + 0.75 * L - 1e-9] == 0) and np.all(a[t >= 0.5 + 1.25 * L] == 255)
    assert np.trapezoid(255 * (t >= 0.5) - a, t) / 255 == pytest.approx(L, rel=0.02)


def test_alt_backlash_sticks_then_slips_to_the_command():
    c = np.r_[np.arange(0, 201, 10), np.arange(190, 99, -10)].astype(float)[:, None]
    b = 12.0
    a = HiddenEffect("backlash", b, "alt").command(c, np.arange(len(c)) / FPS, None)[:, 0]
    top = 20
    np.testing.assert_array_equal(a[: top + 1], c[: top + 1, 0])  # follows on the way up
    back = 200 - c[top + 1:, 0]  # how far the command has come back
    np.testing.assert_array_equal(a[top + 1:][back < 2 * b], 200.0)  # holds inside 2 b
    np.testing.assert_array_equal(a[top + 1:][back >= 2 * b], c[top + 1:, 0][back >= 2 * b])
    # the model's play instead stays b behind the command
    p = HiddenEffect("backlash", b).command(c, np.arange(len(c)) / FPS, None)[:, 0]
    assert p[-1] == pytest.approx(c[-1, 0] + b)


def test_alt_coupling_is_a_product_of_the_drives_at_every_marker(face):
    from mocap.core.schedules import trapezoid as trap

    kappa = 0.35
    e = HiddenEffect("coupling", kappa, "alt")
    rows = pd.concat([trap(1), trap(4)], ignore_index=True)
    both = _d(face, e, rows)
    d_a, d_b = _d(face, e, trap(1)), _d(face, e, trap(4))
    y_a = _y(face, HiddenEffect(), trap(1))[:, 0, :, None]
    y_b = _y(face, HiddenEffect(), trap(4))[:, 0, :, None]
    np.testing.assert_allclose(both, d_a * (1 - kappa * y_b) + d_b * (1 - kappa * y_a), atol=1e-9)
    hold = slice(300, 400)
    assert np.abs(both[hold] - (1 - kappa) * (d_a + d_b)[hold]).max() < 0.02 * np.abs(d_a + d_b).max()


def test_alt2_coupling_stiffens_with_the_square_of_the_other_drive(face):
    """The third coupling law (alt2): the other DU's drive enters squared, so half way up it
    costs a quarter of what it costs at full command; at full command kappa, as the alt form."""
    from mocap.core.schedules import trapezoid as trap

    kappa = 0.35
    e = HiddenEffect("coupling", kappa, "alt2")
    assert e.describe()["alt_equation"].startswith("strain-stiffening")
    rows = pd.concat([trap(1), trap(4)], ignore_index=True)
    both = _d(face, e, rows)
    d_a, d_b = _d(face, e, trap(1)), _d(face, e, trap(4))
    y_a = _y(face, HiddenEffect(), trap(1))[:, 0, :, None]
    y_b = _y(face, HiddenEffect(), trap(4))[:, 0, :, None]
    np.testing.assert_allclose(both, d_a * (1 - kappa * y_b**2) + d_b * (1 - kappa * y_a**2),
                               atol=1e-9)
    hold = slice(300, 400)
    assert np.abs(both[hold] - (1 - kappa) * (d_a + d_b)[hold]).max() < 0.02 * np.abs(d_a + d_b).max()
    # not the alt (bilinear) law: they part where the drives are between 0 and 1
    bilinear = _d(face, HiddenEffect("coupling", kappa, "alt"), rows)
    assert np.abs(both - bilinear).max() > 0.05 * kappa * np.abs(d_a + d_b).max()


def test_alt_saturation_compresses_each_du_before_the_sum(face):
    from mocap.core.schedules import trapezoid as trap

    L = 2.0
    e = HiddenEffect("saturation", L, "alt")
    d, d0 = _d(face, e, trap(12)), _d(face, HiddenEffect(), trap(12))
    m, m0 = np.linalg.norm(d, axis=-1), np.linalg.norm(d0, axis=-1)
    np.testing.assert_allclose(m, m0 / np.sqrt(1 + (m0 / L) ** 2), atol=1e-12)
    assert m.max() < L and m0.max() > 3.0
    rows = pd.concat([trap(7), trap(12)], ignore_index=True)
    both = _d(face, e, rows)
    parts = _d(face, e, trap(7)) + _d(face, e, trap(12))
    np.testing.assert_allclose(both, parts, atol=1e-12)  # per DU, then summed


def test_alt_drift_moves_each_markers_bias_with_mean_k(face):
    from mocap.core.schedules import sample_commands
    from mocap.core.schedules import trapezoid as trap
    from mocap.simulate.effects_alt import marker_drift_weights

    k = 4.0
    e = HiddenEffect("drift", k, "alt")
    y3 = _y(face, e, trap(7), trial=3)
    np.testing.assert_allclose(_y(face, e, trap(7), trial=1), _y(face, HiddenEffect(), trap(7)))
    i = np.array([face.du_index(7)])
    w = face.hysteresis_state(sample_commands(trap(7), [7], np.arange(606 * 4) / (FPS * 4)), i)[::4]
    shift = 2 * k * (1 + 0.5 * np.sqrt(2) * np.sin(2.39996 * np.arange(face.n_markers)))
    np.testing.assert_allclose(y3, face.static_map(w, i, beta_shift=shift), atol=1e-12)
    wts = marker_drift_weights(face.n_markers)
    assert abs(wts.mean() - 1) < 0.05 and wts.std() > 0.4  # xi_m / 2: rms 0.5


def test_alt_curvature_is_a_skewed_bow(face):
    from mocap.core.schedules import trapezoid as trap

    kappa = 0.3
    d = _d(face, HiddenEffect("curvature", kappa, "alt"), trap(7))
    d0 = _d(face, HiddenEffect(), trap(7))
    D = face.D_mm[face.du_index(7)]
    y = _y(face, HiddenEffect(), trap(7))[:, 0]
    side = d - d0
    assert np.abs(np.einsum("fmk,mk->fm", side, D)).max() < 1e-9
    np.testing.assert_allclose(np.linalg.norm(side, axis=-1),
                               6.75 * kappa * y * (1 - y) ** 2 * np.linalg.norm(D, axis=-1), atol=1e-9)


def test_alt_effect_recorded_in_the_truth(tmp_path):
    from mocap.cli import main

    out = tmp_path / "alt"
    assert main(["simulate", str(out), "--dus", "4,7", "--trials", "1", "--markers", "12",
                 "--no-battery", "--labeled", "--effect", "lag,coupling", "--effect-form", "alt",
                 "--face-family", "branchplay-bow"]) == 0
    info = json.loads((out / "truth" / "truth.json").read_text())
    forms = {e["name"]: e["form"] for e in info["effect"]["effects"]}
    assert forms == {"lag": "alt", "coupling": "alt"}
    assert all("alt_equation" in e for e in info["effect"]["effects"])
    assert info["effect"]["parameters"] == {"lag": {"tau_s": 0.08}, "coupling": {"kappa": 0.35}}
    with pytest.raises(ValueError, match="form"):
        HiddenEffect("lag", 0.1, "other")


# ---- layering: the truth is made without the analysis -----------------------------------------

SIMULATOR_MAY_IMPORT = ("mocap.simulate", "mocap.core.schedules", "mocap.core.atomic", "mocap.core.session",
                        "mocap.calib")


def test_simulator_imports_nothing_from_the_analysis():
    import ast
    from pathlib import Path

    import mocap.simulate

    bad = []
    for path in sorted(Path(mocap.simulate.__file__).parent.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module] if node.module != "mocap" else [f"mocap.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                continue
            for name in names:
                if name.split(".")[0] != "mocap" or name == "mocap.__version__":
                    continue
                if not name.startswith(SIMULATOR_MAY_IMPORT):
                    bad.append(f"{path.name}:{node.lineno} imports {name}")
    assert not bad, bad


def test_simulating_a_session_loads_no_analysis_module(tmp_path):
    import subprocess
    import sys

    code = ("import sys; from mocap.simulate import SimConfig, make_effect, simulate; "
            "simulate(SimConfig(du_ids=(4, 7), n_trials=1, n_markers=10, battery=False, "
            "labeled=True, motion_plans=('A',), face_family='preisach-bow', "
            "effect=make_effect('lag,coupling', form='alt')), sys.argv[1]); "
            "print(sorted(m for m in sys.modules if m.startswith(('mocap.analysis', "
            "'mocap.reconstruction', 'mocap.workflows.run.pipeline', "
            "'mocap.workflows.run.stages'))))")
    r = subprocess.run([sys.executable, "-c", code, str(tmp_path / "s")], capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]"


def test_realised_drift_is_the_drift_plus_the_recorded_shifts(tmp_path):
    from mocap.simulate import make_effect
    from mocap.simulate.truth import effect_parameters, realised_bias_drift

    root = small_labeled(tmp_path / "d", "pi-bow", du_ids=(7,), n_trials=4,
                         effect=make_effect("drift", 2.0))
    info = json.loads((root / "truth" / "truth.json").read_text())
    assert effect_parameters(info) == {"drift": {"beta_per_trial": 2.0}}
    takes = [t for t in info["takes"] if t["kind"] == "response"]
    trial = np.array([t["trial"] for t in takes], float)
    bias = 2.0 * (trial - 1) + np.array([t["bias_shift"]["7"] for t in takes])
    slope = np.sum((trial - trial.mean()) * (bias - bias.mean())) / np.sum((trial - trial.mean()) ** 2)
    assert realised_bias_drift(info, 7) == pytest.approx(slope, abs=1e-9)
    assert realised_bias_drift(info, 7) != pytest.approx(2.0, abs=1e-3)  # the shifts move it
    # the truth positions follow the realised biases: trial 4's response is the latest
    fp = pd.read_parquet(root / "truth" / "face.parquet")
    D = fp[["peak_x", "peak_y", "peak_z"]].to_numpy()
    big = np.linalg.norm(D, axis=1) > 2.0
    rise = [np.einsum("fmk,mk->", truth_positions(root, f"du07_t{k:02d}")[12:114, big], D[big])
            for k in (1, 2, 3, 4)]
    assert np.argmin(rise) == int(np.argmax(bias))


def test_realised_session_drift_is_the_trend_of_every_takes_bias(tmp_path):
    """The pooled trend (one intercept per DU) over the response trials and the motion takes,
    which are played at trial 1, written out with a plain per-DU centring instead of a design
    matrix; without trial variation it is the drift's k."""
    from mocap.simulate import make_effect
    from mocap.simulate.truth import realised_session_drift

    root = small_labeled(tmp_path / "d", "preisach-bow", du_ids=(4, 7), n_trials=3,
                         battery=True, effect=make_effect("drift", 2.5))
    info = json.loads((root / "truth" / "truth.json").read_text())
    pts = [(int(t["trial"] or 1), d, 2.5 * (int(t["trial"] or 1) - 1) + s)
           for t in info["takes"] for d, s in t["bias_shift"].items()]
    assert {p[0] for p in pts} == {1, 2, 3} and any(t["kind"] == "motion" for t in info["takes"])
    num = den = 0.0
    for d in {p[1] for p in pts}:
        tr = np.array([p[0] for p in pts if p[1] == d], float)
        b = np.array([p[2] for p in pts if p[1] == d])
        num += np.sum((tr - tr.mean()) * (b - b.mean()))
        den += np.sum((tr - tr.mean()) ** 2)
    assert realised_session_drift(info) == pytest.approx(num / den, abs=1e-9)
    assert realised_session_drift(info) != pytest.approx(2.5, abs=1e-3)  # the shifts move it
    flat = {**info, "takes": [{**t, "bias_shift": {d: 0.0 for d in t["bias_shift"]}}
                              for t in info["takes"]]}
    assert realised_session_drift(flat) == pytest.approx(2.5, abs=1e-9)


@pytest.mark.parametrize("family, lo, hi", [("pi", 0.999, 1.0), ("pi-bow", 0.8, 0.98),
                                            ("preisach-offchord", 0.9, 0.99)])
def test_curved_families_bend_paths_like_a_real_face(family, lo, hi):
    """The first principal component's share of each moving marker's positions over the
    trapezoid (the paper's spatial linearity; its faces: 0.8-0.9)."""
    face = family_face(family, seed=1)
    shares = []
    for du in DUS:
        P = true_take(face, HiddenEffect(), trapezoid(du), 606, FPS, 1, None).positions
        big = np.linalg.norm(face.D_mm[face.du_index(du)], axis=1) > 0.5
        X = P[:, big] - P[:, big].mean(axis=0)
        lam = np.linalg.eigvalsh(np.einsum("fmi,fmj->mij", X, X))
        shares.append(lam[:, -1] / lam.sum(axis=1))
    median = np.median(np.concatenate(shares))
    assert lo <= median <= hi, median
