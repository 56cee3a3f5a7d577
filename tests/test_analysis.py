"""The paper's analyses on analytic fixtures and on a simulated session with known truth."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from analysis.displacement import normalized, normalized_along
from analysis.linearity import spatial_linearity
from analysis.logistic_fit import fit_logistic
from analysis.plans import PLAN_NAMES, plan
from analysis.properties import du_properties, dyssynchrony, find_ramps
from analysis.response import inverse_sigmoid, sigmoid
from mocap.schedules import sample_commands, trapezoid

FPS = 120.0


def trapezoid_response(alpha, beta_f, beta_b, n_markers=10, beta_sd=0.0, seed=0):
    """Exact forward/backward sigmoids of the continuous ramp command (t = T_s c / 255)."""
    t = np.arange(606) / FPS
    c = sample_commands(trapezoid(4), [4], t)[:, 0]
    cf = 255.0 * t
    cb = 255.0 - 255.0 * (t - 4.0)
    shift = np.random.default_rng(seed).normal(0, beta_sd, n_markers)
    delta = np.where(t[:, None] < 2.5, sigmoid(cf[:, None], alpha, beta_f + shift),
                     sigmoid(cb[:, None], alpha, beta_b + shift))
    return t, c, delta


def test_logistic_fit_recovers_rising_and_falling_curves():
    x = np.linspace(0, 2, 300)
    a = np.array([6.0, 20.0, -9.0])
    b = np.array([0.7, 1.2, 1.0])
    y = sigmoid(x[None], a[:, None], b[:, None])
    y = y + np.random.default_rng(1).normal(0, 0.005, y.shape)
    y[0, ::7] = np.nan  # missing samples are ignored
    f = fit_logistic(x, y)
    np.testing.assert_allclose(f.a, a, rtol=0.02)
    np.testing.assert_allclose(f.b, b, atol=0.005)
    assert f.converged.all()


def test_ramps_of_the_paper_schedule():
    t = np.arange(606) / FPS
    c = sample_commands(trapezoid(4), [4], t)[:, 0]
    fwd, bwd = find_ramps(c, FPS)
    assert fwd.p1 == pytest.approx(255.0, rel=0.01) and abs(fwd.p0) < 3
    assert bwd.p1 == pytest.approx(-255.0, rel=0.01)
    assert fwd.start == 0 and bwd.stop == 606
    assert c[fwd.stop - 1] == 255 and c[bwd.start] == 255


def test_properties_exact_on_analytic_sigmoids():
    _, c, delta = trapezoid_response(0.05, 170.0, 95.0)
    p = du_properties(4, delta, c, FPS, np.ones(delta.shape[1], bool), n_boot=30)
    assert p.fwd.alpha == pytest.approx(0.05, rel=0.01)
    assert p.bwd.alpha == pytest.approx(0.05, rel=0.01)
    assert p.fwd.beta == pytest.approx(170.0, abs=0.5)
    assert p.bwd.beta == pytest.approx(95.0, abs=0.5)
    assert p.hysteresis == pytest.approx(75.0, abs=0.5)
    assert p.sensitivity == pytest.approx(0.05, rel=0.01)
    assert p.dyssynchrony == pytest.approx(0.0, abs=1e-9)  # identical markers
    lo, hi = p.ci["hysteresis"]
    assert lo <= p.hysteresis <= hi


def test_step_dyssynchrony_removes_noise():
    from analysis.properties import dyssynchrony_steps

    t, c, delta = trapezoid_response(0.05, 170.0, 95.0, n_markers=40, beta_sd=8.0)
    keep = np.ones(40, bool)
    clean = dyssynchrony_steps(delta, keep, c)
    noisy = delta + np.random.default_rng(4).normal(0, 0.03, delta.shape)
    corrected = dyssynchrony_steps(noisy, keep, c, np.full(40, 0.03**2))
    assert dyssynchrony_steps(noisy, keep, c) > 1.2 * clean
    assert corrected == pytest.approx(clean, rel=0.1)


def test_dyssynchrony_and_its_noise_correction():
    _, c, delta = trapezoid_response(0.05, 170.0, 95.0, n_markers=40, beta_sd=8.0)
    keep = np.ones(40, bool)
    clean = dyssynchrony(delta, keep)
    u = np.std(delta, axis=1, ddof=1).mean()
    assert clean == pytest.approx(u)
    assert clean > 0.005
    noisy = delta + np.random.default_rng(3).normal(0, 0.02, delta.shape)
    raw = dyssynchrony(noisy, keep)
    corrected = dyssynchrony(noisy, keep, np.full(40, 0.02**2))
    assert raw > 1.5 * clean
    assert corrected == pytest.approx(clean, rel=0.15)


def test_spatial_linearity():
    rng = np.random.default_rng(0)
    s = rng.uniform(0, 3.0, 20000)
    line = np.stack([s, 0.5 * s, -s], axis=-1)[:, None, :]
    assert spatial_linearity(line)[0] == pytest.approx(1.0)
    sigma = 0.1
    noisy = line + rng.normal(0, sigma, line.shape)
    var_along = np.var(s) * (1 + 0.25 + 1)
    expected = (var_along + sigma**2) / (var_along + 3 * sigma**2)
    assert spatial_linearity(noisy)[0] == pytest.approx(expected, abs=0.002)
    assert spatial_linearity(noisy, sigma**2)[0] == pytest.approx(1.0, abs=0.003)
    # a half circle of radius 2: principal variances from the sample covariance
    th = rng.uniform(0, np.pi, 20000)
    arc = np.stack([2 * np.cos(th), 2 * np.sin(th), 0 * th], axis=-1)[:, None, :]
    lam = np.linalg.eigvalsh(np.cov(arc[:, 0].T))
    assert spatial_linearity(arc)[0] == pytest.approx(lam[-1] / lam.sum(), rel=1e-3)
    assert spatial_linearity(arc)[0] < 0.9


def test_displacement_along_is_unbiased_at_rest():
    rng = np.random.default_rng(0)
    n = 600
    y = np.r_[np.zeros(200), np.ones(400)]
    d = y[:, None, None] * np.array([[1.0, 0.0, 0.0]]) * 0.3 + rng.normal(0, 0.01, (n, 1, 3))
    length, delta = normalized(d, 30)
    along, delta_along = normalized_along(d, 30)
    assert length[:200].mean() > 0.012  # |noise| is positive on average
    assert abs(along[:200].mean()) < 0.002
    assert np.median(delta_along[200:]) == pytest.approx(1.0, abs=0.03)


def test_inverse_sigmoid_and_plans():
    d = np.linspace(0.01, 0.99, 50)
    np.testing.assert_allclose(sigmoid(inverse_sigmoid(d, 0.04, 130), 0.04, 130), d, atol=1e-12)
    t = np.linspace(0, 1, 101)
    curves = {p: plan(p, t, 1.0) for p in PLAN_NAMES}
    for p, v in curves.items():
        assert np.all(np.diff(v) >= -1e-12), p
        assert v[0] < 0.01 and v[-1] > 0.99
    # A is the fastest start, E the slowest
    assert curves["A"][20] > curves["B"][20] > curves["C"][20] > curves["D"][20] > curves["E"][20]
    with pytest.raises(ValueError, match="expected one of"):
        plan("F", t, 1.0)


# ---- the whole session -------------------------------------------------------------------

def test_properties_file(small_run):
    props = pd.read_csv(small_run.out_dir / "properties.csv")
    cols = ["du", "name", "alpha_fwd", "beta_fwd", "alpha_bwd", "beta_bwd", "sensitivity",
            "hysteresis", "dyssynchrony", "linearity_mean", "linearity_std",
            "max_displacement_mm", "n_markers"]
    assert list(props.columns[: len(cols)]) == cols
    for k in ("alpha_fwd", "beta_fwd", "hysteresis", "sensitivity"):
        assert (props[f"{k}_ci_lo"] <= props[k]).all() and (props[k] <= props[f"{k}_ci_hi"]).all()
    lin = pd.read_csv(small_run.out_dir / "linearity.csv")
    assert list(lin.columns[:2]) == ["du", "marker"] and "linearity" in lin.columns
    assert lin["linearity"].between(0, 1).all()


def test_properties_match_truth(small_sim, small_run):
    from mocap.simulate import preset
    from mocap.simulate.session_writer import true_properties, virtual_rig_and_face

    cfg = preset("small", seed=11, battery=False)
    _, _, face = virtual_rig_and_face(cfg)
    mp = pd.read_csv(small_run.out_dir / "marker_properties.csv")
    fitted = {du: set(g["marker"][g["fitted"]]) for du, g in mp.groupby("du")}
    truth = true_properties(cfg, face, keep=fitted).set_index("du")
    est = pd.read_csv(small_run.out_dir / "properties.csv").set_index("du")
    for du in truth.index:
        e, t = est.loc[du], truth.loc[du]
        assert e["sensitivity"] == pytest.approx(t["sensitivity"], rel=0.05), du
        assert e["beta_fwd"] == pytest.approx(t["beta_fwd"], abs=2.0), du
        assert e["beta_bwd"] == pytest.approx(t["beta_bwd"], abs=2.0), du
        assert e["hysteresis"] == pytest.approx(t["hysteresis"], abs=3.0), du
        # 3 trials only: the noise-corrected dyssynchrony is within 20 % or 0.001 (what is left
        # of the noise after the correction; the paper preset's 10 trials: benchmarks/)
        assert abs(e["dyssynchrony"] - t["dyssynchrony"]) <= 0.2 * t["dyssynchrony"] + 0.001, du
        assert e["dyssynchrony_raw"] > e["dyssynchrony"]
        # the true paths are straight: the estimator's formula on the noise-free truth gives 1;
        # the noise-corrected linearity (rest-take noise covariance removed) is within 0.02
        assert abs(e["linearity_corrected_mean"] - 1.0) < 0.02, du


def test_property_chart_separates_feedback_dus(small_run):
    props = pd.read_csv(small_run.out_dir / "properties.csv").set_index("du")
    for du in (1, 12):  # position feedback: low sensitivity, small hysteresis
        assert props.loc[du, "sensitivity"] < 0.03 and props.loc[du, "hysteresis"] < 30
    for du in (4, 7):  # open loop
        assert props.loc[du, "sensitivity"] > 0.03 and props.loc[du, "hysteresis"] > 40


def test_figures_exist_and_are_not_blank(small_run):
    import matplotlib.image as mpimg

    fig = small_run.out_dir / "figures"
    expected = ["linearity.png", "property_chart.png"]
    for du in (1, 4, 7, 12):
        expected += [f"du{du:02d}_displacement_field.png", f"du{du:02d}_response.png"]
    expected += [f"motion_smile_du01_07_12_plan{p}.png" for p in "ABCDE"]
    for name in expected:
        path = fig / name
        assert path.is_file(), name
        assert path.stat().st_size > 15_000, name
        img = mpimg.imread(path)
        assert img.shape[0] > 250 and img.shape[1] > 300
        assert img[..., :3].std() > 0.05, name  # drawn, not blank


def test_motion_takes_follow_their_plans(small_run):
    evs = {plan: ev for _, plan, ev in small_run.analysis.motions}
    assert sorted(evs) == list("ABCDE")
    for p, ev in evs.items():
        # no hidden effect: the paper's design tracks its plan closely
        assert ev.rms_forward < 0.12 and ev.rms_backward < 0.12, (p, ev.rms_forward, ev.rms_backward)
        assert abs(ev.lag_s) < 0.15


def test_sample_data_run_writes_every_output(sample_run):
    import matplotlib.image as mpimg

    out = sample_run.out_dir
    for name in ("summary.json", "calibration.toml", "responses.parquet", "rejections.csv",
                 "properties.csv", "linearity.csv", "audit.json", "audit.md", "session.rrd"):
        assert (out / name).is_file(), name
    figs = sorted((out / "figures").glob("*.png"))
    names = {f.name for f in figs}
    for du in (1, 4, 7, 12):
        assert f"du{du:02d}_response.png" in names and f"du{du:02d}_displacement_field.png" in names
    assert {"linearity.png", "property_chart.png"} <= names
    assert sum(n.startswith("motion_") for n in names) == 3
    for f in figs:
        assert f.stat().st_size > 10_000, f.name
        assert mpimg.imread(f)[..., :3].std() > 0.05, f.name
