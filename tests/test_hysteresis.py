"""Play and Prandtl-Ishlinskii operators against hand-worked behaviour."""

import numpy as np
import pytest

from mocap.analysis.model.hysteresis import pi_mean_halfwidth, play, prandtl_ishlinskii


def sweep(n=256):
    up = np.arange(n, dtype=float)
    return np.concatenate([up, up[::-1]])


def test_play_full_sweep_branches():
    x = sweep()
    y = play(x, 20.0)
    up = x[:256]
    # rising from rest: output waits until x exceeds r, then trails by r
    np.testing.assert_allclose(y[:256], np.maximum(up - 20.0, 0.0))
    # falling: output holds at 235 until x + r reaches it, then leads by r
    down = x[256:]
    np.testing.assert_allclose(y[256:], np.minimum(down + 20.0, 235.0))


def test_play_minor_loop_is_flat_for_2r():
    x = np.concatenate([np.arange(0, 151.0), np.arange(149.0, 90.0, -1.0), np.arange(92.0, 200.0)])
    y = play(x, 10.0)
    assert y[150] == 140.0  # the peak x = 150, trailing by r
    # after the reversal the output holds at 140 until x falls below 130 (a 2 r dead band)
    after = slice(151, 210)
    held = x[after] >= 130.0
    assert np.all(y[after][held] == 140.0)
    np.testing.assert_allclose(y[after][~held], x[after][~held] + 10.0)


def test_play_is_rate_independent():
    x = sweep(256)
    fine = np.repeat(x, 3)
    np.testing.assert_allclose(play(fine, 15.0)[2::3], play(x, 15.0))


def test_play_rejects_negative_width():
    with pytest.raises(ValueError, match="r >= 0"):
        play(np.zeros(3), -1.0)


def test_pi_full_sweep_offsets_by_mean_halfwidth():
    thr = np.array([0.0, 10.0, 20.0, 30.0, 40.0])
    w = np.full(5, 0.2)
    x = sweep()
    y = prandtl_ishlinskii(x, thr, w)
    r_bar = pi_mean_halfwidth(thr, w)
    assert r_bar == pytest.approx(20.0)
    up = x[:256]
    sel = up >= 40  # every play engaged
    np.testing.assert_allclose(y[:256][sel], up[sel] - r_bar)
    down = x[256:]
    sel = down <= 255 - 80  # every play released on the way down
    np.testing.assert_allclose(y[256:][sel], down[sel] + r_bar)


def test_pi_moves_at_once_after_reversal():
    thr = np.array([0.0, 10.0, 20.0, 30.0, 40.0])
    w = np.full(5, 0.2)
    x = np.concatenate([np.arange(0, 200.0), np.arange(200.0, 150.0, -1.0)])
    y = prandtl_ishlinskii(x, thr, w)
    # right after the reversal only the zero-width play follows: slope 0.2
    assert y[201] - y[200] == pytest.approx(-0.2)


def test_pi_vectorises_over_channels():
    x = np.stack([sweep(), sweep() * 0.5], axis=1)
    thr = np.array([[0.0, 10.0], [5.0, 15.0]])
    w = np.array([[0.5, 0.5], [0.5, 0.5]])
    y = prandtl_ishlinskii(x, thr, w)
    for ch in range(2):
        np.testing.assert_allclose(y[:, ch], prandtl_ishlinskii(x[:, ch], thr[ch], w[ch]))


def test_pi_logistic_fit_recovers_parameters_from_minor_loops():
    from mocap.analysis.paper.hysteresis_fit import fit_pi_logistic, pi_logistic
    from mocap.core.schedules import ramp_through, sample_commands, trapezoid

    t = np.arange(0, 6.0, 1 / 120)
    c_trap = sample_commands(trapezoid(4), [4], t)[:, 0]
    minor = ramp_through([255 * f for f in (0.8, 0.3, 1.0, 0.1, 0.6, 0.0)], du=4)
    t2 = np.arange(0, float(minor.time_s.max()) + 0.5, 1 / 120)
    c = np.concatenate([c_trap, sample_commands(minor, [4], t2)[:, 0]])
    alpha = np.array([0.03, 0.06, 0.09])
    beta = np.array([120.0, 135.0, 128.0])
    r = np.array([5.0, 30.0, 43.0])
    y = pi_logistic(c, alpha, beta, r) + np.random.default_rng(0).normal(0, 0.01, (c.size, 3))
    fit = fit_pi_logistic(c, y, alpha0=0.05, beta0=128.0, r0=20.0)
    np.testing.assert_allclose(fit.alpha, alpha, rtol=0.05)
    np.testing.assert_allclose(fit.beta, beta, atol=2.0)
    np.testing.assert_allclose(fit.hysteresis, 2 * r, atol=3.0)
    assert np.all(fit.rms < 0.012)


def test_pi_logistic_is_the_virtual_faces_static_model():
    """Fitted on the virtual face's noise-free response, the model returns the face's truth."""
    from mocap.analysis.paper.hysteresis_fit import fit_pi_logistic
    from mocap.core.schedules import sample_commands, trapezoid
    from mocap.simulate.effects import HiddenEffect
    from mocap.simulate.face import make_face
    from mocap.simulate.motion import normalized_response

    face = make_face(np.random.default_rng(2), 20, (4,))
    _, y = normalized_response(face, HiddenEffect(), trapezoid(4), 606, 120.0, 1)
    y = y[:, 0]  # (frames, markers)
    c = sample_commands(trapezoid(4), [4], np.arange(606) / 120.0)[:, 0]
    fit = fit_pi_logistic(c, y, alpha0=0.08, beta0=130.0, r0=40.0)
    big = np.linalg.norm(face.D_mm[0], axis=-1) > 0  # every marker: the curve is noise-free
    np.testing.assert_allclose(fit.alpha[big], face.alpha[0][big], rtol=0.02)
    np.testing.assert_allclose(fit.beta[big], face.beta[0][big], atol=1.0)
    np.testing.assert_allclose(fit.r[big], face.r_half[0][big], atol=1.5)
