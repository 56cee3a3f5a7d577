"""Prior intrinsics and static points (issue #50): a thin, strongly distorted rig.

The rig: 3 cameras of 640 x 512 px with a wide lens (focal 450 px, k1 -0.3, k2 0.09), a 300 mm
two-marker wand digitised in 100 frames spread over 33 s (ends often seen by only two cameras),
centroid noise 0.2 px. Truth comes from the simulator's cameras; the reference calibration is a
plain second implementation: the true cameras' poses and the wand refitted by
``scipy.optimize.least_squares`` with the true intrinsics held (what the best possible
calibration from these very sightings can do).
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.optimize import least_squares

from mocap.calib.camera import Camera, CameraRig, rodrigues_from_rotation, rotation_from_rodrigues
from mocap.calib.initialize import initial_intrinsics
from mocap.calib.priors import IntrinsicPrior
from mocap.calib.quality import wand_lengths
from mocap.calib.wand import find_wand
from mocap.calib.wand_calibration import calibrate
from mocap.simulate.capture import CaptureNoise, observe
from mocap.simulate.rig import VOLUME_CENTER, make_rig, wand_motion
from test_rigs import image_space_rms

NOISE_PX = 0.2
OFFSETS = np.array([0.0, 300.0])
F_PX = 450.0
DIST = (-0.3, 0.09, 0.0, 0.0, 0.0)


def thin_rig(seed=5, n=3) -> CameraRig:
    base = make_rig(np.random.default_rng(seed), n, width=640, height=512)
    return CameraRig(tuple(
        Camera(id=c.id, width=640, height=512, K=[[F_PX, 0, c.K[0, 2] / 2], [0, F_PX, c.K[1, 2] / 2],
                                                  [0, 0, 1]], dist=DIST, R=c.R, t=c.t)
        for c in base))


def wand_recording(rig, seed=7, n_frames=100, spread=0.8):
    rng = np.random.default_rng(seed)
    P = wand_motion(rng, n_frames, 3.0, OFFSETS)
    P = VOLUME_CENTER + spread * (P - VOLUME_CENTER)
    blobs, _ = observe(rig, P, rng, noise=CaptureNoise(noise_px=NOISE_PX, dropout=0.0,
                                                       ghost_rate=0.0, merge_px=0.0))
    return P, blobs


@pytest.fixture(scope="module")
def thin():
    rig = thin_rig()
    P, blobs = wand_recording(rig)
    obs = find_wand(blobs, rig.ids, OFFSETS)
    return rig, P, obs


def priors_of(rig, mode, **perturb):
    out = {}
    for c in rig:
        d = np.array(c.dist, float)
        d[0] += perturb.get("k1", 0.0)
        out[c.id] = IntrinsicPrior(c.id, c.focal_px * (1 + perturb.get("f", 0.0)),
                                   tuple(c.K[:2, 2] + perturb.get("pp", 0.0)), tuple(d), mode)
    return out


def run(obs, priors=None, **kw):
    init = [initial_intrinsics(cid, 640, 512, F_PX) for cid in obs.camera_ids]
    return calibrate(obs, init, OFFSETS, priors=priors, **kw)


def reference_fit(truth: CameraRig, obs) -> CameraRig:
    """The true cameras' poses (the first held) and every frame's wand refitted to the sightings
    with the true intrinsics, by least_squares on plain projections."""
    obs_o = obs
    frames = np.unique(obs_o.frame)
    C, F = len(truth), frames.size
    loc = np.searchsorted(frames, obs_o.frame)
    X = triangulate_true(truth, obs_o, frames)
    mid = X.mean(axis=1)
    u = X[:, 1] - X[:, 0]
    az = np.arctan2(u[:, 1], u[:, 0])
    el = np.arcsin(np.clip(u[:, 2] / np.linalg.norm(u, axis=1), -1, 1))
    x0 = np.concatenate([np.concatenate([np.r_[rodrigues_from_rotation(c.R), c.t]
                                         for c in truth[1:]]),
                         np.column_stack([mid, az, el]).ravel()])
    half = 0.5 * (OFFSETS[1] - OFFSETS[0])

    def rig_of(x):
        cams = [truth[0]]
        for j in range(1, C):
            p = x[(j - 1) * 6:j * 6]
            c = truth[j]
            cams.append(Camera(id=c.id, width=c.width, height=c.height, K=c.K, dist=c.dist,
                               R=rotation_from_rodrigues(p[:3]), t=p[3:]))
        return cams

    def fun(x):
        cams = rig_of(x)
        w = x[(C - 1) * 6:].reshape(F, 5)
        d = np.column_stack([np.cos(w[:, 4]) * np.cos(w[:, 3]), np.cos(w[:, 4]) * np.sin(w[:, 3]),
                             np.sin(w[:, 4])])
        ends = np.stack([w[:, :3] - half * d, w[:, :3] + half * d], axis=1)  # (F, 2, 3)
        out = np.empty(obs_o.uv.shape)
        for j, c in enumerate(cams):
            m = obs_o.camera == j
            out[m] = c.project(ends[loc[m]]) - obs_o.uv[m]
        return out.ravel()

    rows = np.arange(obs_o.uv.size).reshape(len(obs_o), -1)
    S = sp.lil_matrix((obs_o.uv.size, x0.size), dtype=int)
    for k, (c, f) in enumerate(zip(obs_o.camera, loc)):
        for r in rows[k]:
            if c > 0:
                S[r, (c - 1) * 6:c * 6] = 1
            S[r, (C - 1) * 6 + f * 5:(C - 1) * 6 + f * 5 + 5] = 1
    res = least_squares(fun, x0, jac_sparsity=S, x_scale="jac")
    return CameraRig(tuple(rig_of(res.x)))


def triangulate_true(truth, obs, frames):
    _, L = wand_lengths(truth, obs)  # (checks the helper runs); positions below
    from mocap.calib.triangulation import triangulate

    loc = np.searchsorted(frames, obs.frame)
    uv = np.full((len(truth), frames.size * 2, 2), np.nan)
    rows = (loc[:, None] * 2 + np.arange(2)[None]).ravel()
    uv[np.repeat(obs.camera, 2), rows] = obs.uv.reshape(-1, 2)
    return triangulate(truth, uv).X.reshape(frames.size, 2, 3)


@pytest.fixture(scope="module")
def fixed(thin):
    return run(thin[2], priors_of(thin[0], "fixed"))


@pytest.fixture(scope="module")
def refined(thin):
    return run(thin[2], priors_of(thin[0], "refine"))


@pytest.fixture(scope="module")
def reference(thin, fixed):
    # the calibration's own end order (two-marker ends look alike), fitted with the truth
    return reference_fit(thin[0], fixed.wand)


def test_thin_recording_is_thin(thin):
    """The recording is the case the issue describes: many frames seen by only two cameras."""
    _, _, obs = thin
    _, views = np.unique(obs.frame, return_counts=True)
    assert np.sum(views == 2) >= 10 and len(np.unique(obs.frame)) <= 100


def test_fixed_priors_match_the_true_intrinsics_fit(thin, fixed, reference):
    truth = thin[0]
    ref = image_space_rms(reference, truth)
    ours = image_space_rms(fixed.rig, truth)
    assert ours <= 1.1 * ref, (ours, ref)
    for c, t in zip(fixed.rig, truth):  # used as given
        np.testing.assert_allclose(c.K, t.K)
        np.testing.assert_allclose(c.dist, t.dist)
    assert all(v["source"] == "prior fixed" for v in fixed.quality["intrinsics_per_camera"].values())


@pytest.fixture(scope="module")
def wand_only(thin):
    return run(thin[2])


def test_refined_priors_no_worse(thin, refined, reference, wand_only):
    """Refined from exact priors: no worse than the wand alone (whose image-space error here is
    1.7 x the true-intrinsics refit's), within 1.5 x that refit (the wand's own noise moves the
    refined intrinsics by about their posterior sd); the report says by how much each moved."""
    truth = thin[0]
    ours = image_space_rms(refined.rig, truth)
    assert ours <= image_space_rms(wand_only.rig, truth)
    assert ours <= 1.5 * image_space_rms(reference, truth)
    rep = refined.quality["prior_refinement"]
    assert set(rep) == set(truth.ids)
    for _cid, v in rep.items():
        assert v["mode"] == "refine"
        for _name, p in v["parameters"].items():
            assert 0.0 <= p["wand_share"] <= 1.0
            assert p["posterior_sd"] <= p["prior_sd"] * 1.0001
            assert abs(p["change"]) <= 4 * p["prior_sd"]
            assert p["estimate"] == pytest.approx(p["prior"] + p["change"])


def test_refined_priors_move_a_wrong_profile_towards_the_truth(thin):
    """A profile off by 1 % in focal length and 3 px in principal point: the wand pulls it back
    (a fixed wrong profile fits worse than the refined one)."""
    truth, _, obs = thin
    wrong = dict(f=0.01, pp=3.0)
    fixed_wrong = run(obs, priors_of(truth, "fixed", **wrong))
    refined_wrong = run(obs, priors_of(truth, "refine", **wrong))
    assert image_space_rms(refined_wrong.rig, truth) < image_space_rms(fixed_wrong.rig, truth)
    f_err = [abs(c.focal_px - t.focal_px) for c, t in zip(refined_wrong.rig, truth)]
    assert np.mean(f_err) < 0.01 * F_PX


@pytest.mark.parametrize("which", ["fixed", "refined"])
def test_every_digitised_point_within_4_sd_and_wand_spread(thin, fixed, refined, reference, which):
    """None dropped: every sighting of a frame another camera saw too is in the adjustment and
    reprojects within 4 sd of the noise; the others are reported as seen by a single camera.
    The wand-length spread is within 1.2 x what the true-intrinsics refit of these sightings
    gives, and within 1.3 x the true cameras' (this recording's calibration-limited floor: the
    refit with the true intrinsics itself is 1.26 x the true cameras')."""
    r = fixed if which == "fixed" else refined
    truth, _, obs = thin
    _, views = np.unique(obs.frame, return_counts=True)
    single = int(np.sum(views == 1))
    s = r.quality["sightings"]
    assert sum(v["found"] for v in s.values()) == len(obs)
    assert sum(v["single_camera"] for v in s.values()) == single
    assert all(v["dropped"] == 0 and v["other"] == 0 for v in s.values())
    assert r.used.all() and len(r.wand) == len(obs) - single
    assert np.abs(r.residuals_px).max() <= 4 * NOISE_PX
    _, ours = wand_lengths(r.rig, r.wand)
    _, ref = wand_lengths(reference, r.wand)
    _, true = wand_lengths(truth, r.wand)
    assert np.nanstd(ours) <= 1.2 * np.nanstd(ref)
    assert np.nanstd(ours) <= 1.3 * np.nanstd(true)


def test_without_priors_the_report_says_where_distortion_was_determined(thin, wand_only):
    """From the wand alone the distortion is judged where the sightings reach; a wand kept near
    the image centres (a third of the volume) reaches a small share of the image, and the
    report says so per camera (beyond it the distortion is extrapolated)."""
    truth, _, obs = thin
    wide = wand_only.quality
    _, blobs = wand_recording(truth, seed=8, spread=0.35)
    central = run(find_wand(blobs, truth.ids, OFFSETS)).quality
    for q in (wide, central):
        for v in q["intrinsics_per_camera"].values():
            assert v["source"] == "wand"
            if q["intrinsics"]["distortion"] != "none":
                assert 0.0 < v["distortion_determined_image_share"] < 1.0
    for cid in truth.ids:
        assert (central["intrinsics_per_camera"][cid]["distortion_determined_image_share"]
                < 0.5 * wide["intrinsics_per_camera"][cid]["distortion_determined_image_share"])
        assert central["coverage"][cid]["wand"] < 0.25
        assert central["coverage"][cid]["both"] == central["coverage"][cid]["wand"]


def test_too_few_frames_for_distortion_is_reported(thin):
    """50 frames: the frame count cannot support the full model; the report names each
    richer model and why it was not used."""
    truth, _, obs = thin
    keep = np.isin(obs.frame, np.unique(obs.frame)[:50])
    q = run(obs.select(keep)).quality
    assert q["intrinsics"]["distortion"] != "k1k2p1p2"
    for _cid, v in q["intrinsics_per_camera"].items():
        assert v["not_determined"] and all("frames" in w or "distortion" in w
                                           for w in v["not_determined"])


def test_static_points_add_correspondences(thin, wand_only, refined):
    """40 static points digitised with the same noise, spread wider than the wand went: they
    join the adjustment (reprojecting at the noise), cover more of each image, and bring the
    calibration closer to the truth, with and without priors."""
    from mocap.calib.static_points import static_points

    truth, P, obs = thin
    rng = np.random.default_rng(3)
    Q = (P.reshape(-1, 3).mean(axis=0) + rng.uniform(-1, 1, (40, 3)) * [350, 280, 120])[:, None]
    blobs, _ = observe(truth, Q, rng, noise=CaptureNoise(noise_px=NOISE_PX, dropout=0.0,
                                                         ghost_rate=0.0, merge_px=0.0))
    pts = static_points(blobs, truth.ids)
    seen = np.sum([c.in_image(c.project(Q[:, 0]), margin_px=1.0) for c in truth], axis=0)
    assert pts.n_points == int(np.sum(seen >= 2)) and pts.skipped["one_camera"] == int(
        np.sum(seen == 1))
    for before, priors in ((wand_only, None), (refined, priors_of(truth, "refine"))):
        after = run(obs, priors, points=pts)
        q = after.quality
        assert q["points"]["points"] == pts.n_points and q["points"]["sightings"] == len(pts)
        assert max(q["points"]["reprojection_rms_px"].values()) < 1.2 * NOISE_PX
        assert all(v["both"] >= v["wand"] for v in q["coverage"].values())
        assert any(v["both"] > v["wand"] for v in q["coverage"].values())
        assert image_space_rms(after.rig, truth) < image_space_rms(before.rig, truth)


def test_schur_solver_with_points_and_prior_agrees_with_least_squares(thin, refined):
    """The hand-written Schur-complement solver, with static points eliminated and a prior on
    the intrinsics, reaches the optimum scipy's least_squares finds on the same residuals."""
    from mocap.calib.bundle import solve, solve_schur
    from mocap.calib.priors import prior_arrays
    from mocap.calib.static_points import static_points
    from mocap.calib.wand_calibration import _bundle_stages, select_frames

    truth, P, _ = thin
    rng = np.random.default_rng(4)
    Q = (P.reshape(-1, 3).mean(axis=0) + rng.uniform(-1, 1, (30, 3)) * [300, 250, 100])[:, None]
    blobs, _ = observe(truth, Q, rng, noise=CaptureNoise(noise_px=NOISE_PX, dropout=0.0,
                                                         ghost_rate=0.0, merge_px=0.0))
    pts = static_points(blobs, truth.ids)
    held, mean, sd = prior_arrays(list(truth), priors_of(truth, "refine"))
    obs = refined.wand
    offsets_rel = OFFSETS - OFFSETS.mean()
    result, problem, _, _, _ = _bundle_stages(
        obs, refined.rig, select_frames(obs), offsets_rel, held, lambda m: None,
        stages=(("linear", 1.0),), prior=(mean, sd), points=pts)
    x = np.concatenate([result.cameras.ravel(), result.frames.ravel(), result.points.ravel()])
    x0 = x.copy()
    x0[6:13 * len(truth)] += rng.normal(0, 1e-4, 13 * len(truth) - 6) * np.abs(x[6:13 * len(truth)])
    a = solve_schur(problem, x0)
    b = solve(problem, x0, max_nfev=400)
    assert a.cost <= b.cost * (1 + 1e-6) and b.cost <= a.cost * (1 + 1e-3)
    # (least_squares' inexact LSMR steps stop a little short: within 0.02 px and 0.01 mm)
    np.testing.assert_allclose(a.cameras[:, 6:9], b.cameras[:, 6:9], atol=0.02)
    np.testing.assert_allclose(a.points, b.points, atol=0.01)


def test_each_camera_steps_down_on_its_own(thin):
    """A camera that saw the wand in 36 frames only cannot support the full model: it steps
    down on its own (reported with the frame count), the others keep what their sightings
    determine, and the report's single `intrinsics` is the simplest used."""
    truth, _, obs = thin
    f3 = np.unique(obs.frame[obs.camera == 2])
    q = run(obs.select(~((obs.camera == 2) & np.isin(obs.frame, f3[36:])))).quality
    per = q["intrinsics_per_camera"]
    assert "frames shared with another camera" in per["cam3"]["not_determined"][0]
    ladder = ["k1k2p1p2", "k1k2", "k1", "none"]
    rank = {cid: ladder.index(v["distortion"]) for cid, v in per.items()}
    assert rank["cam3"] > 0 and len(set(rank.values())) > 1
    assert q["intrinsics"]["distortion"] == ladder[max(rank.values())]
    for cid, v in per.items():
        assert len(v["not_determined"]) == rank[cid]  # one reason per model stepped past
