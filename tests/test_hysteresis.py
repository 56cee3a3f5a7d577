"""Play and Prandtl-Ishlinskii operators against hand-worked behaviour."""

import numpy as np
import pytest

from analysis.hysteresis import pi_mean_halfwidth, play, prandtl_ishlinskii


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
