"""The paper's figures for a session (matplotlib), one function per figure.

Each function draws one figure with labelled axes and units and returns the
``matplotlib.figure.Figure``; single-panel figures draw into ``ax`` when given (a notebook's own
axes), multi-panel ones into ``fig``. Figures are made without pyplot, so drawing never touches a
notebook's backend or pyplot's list of open figures; :func:`save` writes one atomically as PNG.
Only the figure modules import matplotlib, and only the command line picks a backend.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from mocap.analysis.paper.response import sigmoid
from mocap.core.atomic import atomic_path

if TYPE_CHECKING:
    from matplotlib.figure import Figure


def _axes(ax, figsize):
    """(figure, axes): ``ax``'s own, or a new figure of ``figsize`` inches with one axes."""
    if ax is not None:
        return ax.figure, ax
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize)
    return fig, fig.subplots()


def _figure(fig, figsize):
    if fig is not None:
        return fig
    from matplotlib.figure import Figure

    return Figure(figsize=figsize)


def save(fig, path) -> Path:
    """Write ``fig`` to ``path`` as PNG (110 dpi), atomically; return the path."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png", bbox_inches="tight")
    return Path(path)


def draw_and_save(path, draw, args) -> Path:
    """``save(draw(*args), path)``: one figure drawn and written (a module-level function, so a
    worker process can be handed it)."""
    return save(draw(*args), path)


def displacement_field(du: int, name: str, rest_mm: np.ndarray, d_mm: np.ndarray,
                       keep: np.ndarray, scale: float | None = None, *, ax=None) -> Figure:
    """Arrows of the displacement at full command on the xy plane over a heat map of length."""
    fig, ax = _axes(ax, (5.2, 7.0))
    length = np.linalg.norm(d_mm, axis=1)
    ok = np.isfinite(length)
    if ok.sum() >= 3:
        tri = ax.tricontourf(rest_mm[ok, 0], rest_mm[ok, 1], length[ok], levels=14, cmap="magma")
        fig.colorbar(tri, ax=ax, label="displacement length |d| at command 255 (mm)")
    peak = np.nanmax(length) if ok.any() else 1.0
    s = scale or 12.0 / max(peak, 1e-9)  # the longest arrow spans about a marker spacing
    k = ok & keep
    ax.quiver(rest_mm[k, 0], rest_mm[k, 1], d_mm[k, 0] * s, d_mm[k, 1] * s, angles="xy",
              scale_units="xy", scale=1.0, color="cyan", width=0.006)
    ax.scatter(rest_mm[~keep & ok, 0], rest_mm[~keep & ok, 1], marker="x", c="w", s=14,
               label="left out")
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(f"DU {du} ({name}): displacement field, measured\n(trial mean at full command, "
                 f"noise not removed); arrows x{s:.1f}", fontsize=9)
    if (~keep & ok).any():
        ax.legend(loc="lower right", fontsize=7)
    return fig


# what a figure's values are, in its labels (docs/outputs.md's naming rule): the paper's
# computation literally (the plain columns) or its noise-free estimate (the ``_corrected`` ones)
KINDS = {"literal": ("", "the paper's computation, literal"),
         "corrected": ("_corrected", "noise-corrected estimate")}


def _kind(kind: str) -> tuple[str, str]:
    """(column suffix, words) of ``kind``: "literal" or "corrected"."""
    try:
        return KINDS[kind]
    except KeyError:
        raise ValueError(f"kind: expected one of {sorted(KINDS)}, got {kind!r}") from None


def linearity_bars(dus, means, stds, corrected=None, *, ax=None) -> Figure:
    """Spatial linearity per DU: bars of the literal mean over markers with their standard
    deviation (properties.csv's ``linearity_mean``, ``linearity_std``), and, when ``corrected``
    is given, its noise-corrected estimate as dots (``linearity_mean_corrected``)."""
    fig, ax = _axes(ax, (max(5.5, 0.5 * len(dus) + 2), 3.8))
    x = np.arange(len(dus))
    means, stds = np.asarray(means, float), np.asarray(stds, float)
    err = np.vstack([np.minimum(stds, means), np.minimum(stds, 1.0 - means)])  # within [0, 1]
    ax.bar(x, means, yerr=err, capsize=3, color="tab:blue", alpha=0.8,
           label="linearity_mean +- linearity_std, the paper's computation, literal")
    if corrected is not None:
        ax.plot(x + 0.2, np.asarray(corrected, float), "D", color="tab:orange", mec="k", ms=5,
                ls="none",
                label="linearity_mean_corrected, noise-corrected estimate")
    ax.set_xticks(x, [str(d) for d in dus])
    ax.set_xlabel("DU")
    ax.set_ylabel("spatial linearity, PC1 share of variance (1)")
    ax.set_ylim(0, 1.25)
    ax.set_yticks(np.linspace(0, 1, 6))
    ax.legend(fontsize=7, loc="upper left")
    ax.set_title("Spatial linearity per DU: literal (bars, mean and std over markers)"
                 + (" and noise-corrected (dots)" if corrected is not None else ""), fontsize=9)
    return fig


def response_curves(du, name, paper, fps: float, corrected: dict | None = None, *,
                    ax=None) -> Figure:
    """The paper's response curves, literal: delta = |d| / max |d| of the measured trial means
    against the paper's abscissa c (forward c = 255 t / T_s, backward c = 255 (t_end - t) / T_s),
    mean and spread over the kept markers, with the sigmoids fitted by the paper's recipe
    (``mocap.analysis.paper.indices``). ``corrected``: properties.csv's ``hysteresis_corrected``
    and ``dyssynchrony_corrected`` (named so), printed under the literal values for comparison."""
    fig, ax = _axes(ax, (5.5, 4.0))
    cgrid = np.linspace(0, paper.timing.top, 256)
    n = paper.delta.shape[0]
    for branch, colour, label, a, b in (("forward", "tab:blue", "fwd", paper.alpha_fwd,
                                         paper.beta_fwd),
                                        ("backward", "tab:red", "bwd", paper.alpha_bwd,
                                         paper.beta_bwd)):
        frames, c = getattr(paper.timing, branch)(n, fps)
        d = paper.delta[frames][:, paper.keep]
        with np.errstate(invalid="ignore"):
            import warnings

            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                m, s = np.nanmean(d, axis=1), np.nanstd(d, axis=1)
        ax.fill_between(c, m - s, m + s, color=colour, alpha=0.2)
        ax.plot(c, m, color=colour, lw=1, alpha=0.7, label=f"measured {branch} (mean +- sd)")
        ax.plot(cgrid, sigmoid(cgrid, a, b), color=colour, lw=2.2,
                label=f"R_{label}, literal fit: alpha_{label} {a:.3f}, beta_{label} {b:.0f}")
    ax.set_xlim(0, paper.timing.top)
    ax.set_ylim(-0.05, 1.1)
    ax.set_xlabel("command c = 255 t / T_s (paper's conversion)")
    ax.set_ylabel("delta = |d| / max |d|, measured (1)")
    title = (f"DU {du} ({name}), the paper's computation, literal: hysteresis "
             f"{paper.hysteresis:.0f}, dyssynchrony {paper.dyssynchrony:.3f}")
    if corrected:
        title += (f"\nnoise-corrected estimates: hysteresis_corrected "
                  f"{corrected['hysteresis_corrected']:.0f}, dyssynchrony_corrected "
                  f"{corrected['dyssynchrony_corrected']:.3f}")
    ax.set_title(title, fontsize=8)
    ax.legend(fontsize=7, loc="upper left")
    return fig


def property_chart(dus, alphas, hysteresis, dyssynchrony, feedback, kind: str, *,
                   ax=None) -> Figure:
    """Sensitivity against hysteresis per DU, coloured by dyssynchrony, all three of one
    ``kind``: "corrected" (properties.csv's ``sensitivity_corrected``, ``hysteresis_corrected``,
    ``dyssynchrony_corrected``) or "literal" (``sensitivity``, ``hysteresis``,
    ``dyssynchrony``); the axes and the title name it."""
    suffix, words = _kind(kind)
    fig, ax = _axes(ax, (6.0, 4.6))
    sc = ax.scatter(alphas, hysteresis, c=dyssynchrony, cmap="viridis", s=80,
                    edgecolors=["k" if f else "none" for f in feedback], linewidths=1.5)
    for d, a, h in zip(dus, alphas, hysteresis):
        ax.annotate(str(d), (a, h), textcoords="offset points", xytext=(5, 4), fontsize=9)
    fig.colorbar(sc, ax=ax, label=f"dyssynchrony{suffix}: gamma, {words} (1)")
    ax.set_xlabel(f"sensitivity{suffix}: alpha, {words} (1/command unit)")
    ax.set_ylabel(f"hysteresis{suffix}: beta_fwd - beta_bwd,\n{words} (command units)")
    ax.set_title(f"Property chart, all three values: {words}\n(black edge: position feedback; "
                 "smaller is better)", fontsize=10)
    ax.grid(alpha=0.3)
    return fig


def motion_result(title, ev, *, ax=None) -> Figure:
    fig, ax = _axes(ax, (6.5, 3.6))
    ax.plot(ev.t, ev.ideal, color="k", lw=2, label="plan P(t)")
    ax.fill_between(ev.t, ev.mean - ev.std, ev.mean + ev.std, color="tab:purple", alpha=0.2)
    ax.plot(ev.t, ev.mean, color="tab:purple", lw=1.5, label="realized (mean +- sd over markers)")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("normalised displacement, measured (1)")
    ax.set_title(f"{title}\nRMS fwd {ev.rms_forward:.3f}, bwd {ev.rms_backward:.3f}, "
                 f"lag {ev.lag_s * 1000:.0f} ms")
    ax.legend(fontsize=8)
    ax.set_ylim(-0.05, 1.15)
    return fig


def audit_visibility(markers, cameras, fraction, *, ax=None) -> Figure:
    """Heat map: share of each marker's reconstructed frames each camera contributed to."""
    fig, ax = _axes(ax, (max(6, 0.12 * len(markers) + 2), 2.8))
    im = ax.imshow(fraction, aspect="auto", cmap="viridis", vmin=0, vmax=1, interpolation="nearest")
    ax.set_yticks(range(len(cameras)), cameras)
    step = max(1, len(markers) // 30)
    ax.set_xticks(range(0, len(markers), step), markers[::step], rotation=90, fontsize=6)
    ax.set_xlabel("marker")
    fig.colorbar(im, ax=ax, label="share of frames seen (1)")
    ax.set_title("Visibility per marker and camera")
    return fig


def audit_noise_map(rest_mm, noise_mm, flagged, names, *, ax=None) -> Figure:
    """Noise floor per marker on the face (xy plane), flagged markers circled."""
    fig, ax = _axes(ax, (5.0, 6.5))
    sc = ax.scatter(rest_mm[:, 0], rest_mm[:, 1], c=noise_mm, cmap="inferno_r", s=60,
                    vmin=0, vmax=np.nanpercentile(noise_mm, 95) * 1.5 if np.isfinite(noise_mm).any() else 1)
    for n in flagged:
        i = names.index(n)
        ax.scatter(rest_mm[i, 0], rest_mm[i, 1], s=220, facecolors="none", edgecolors="tab:blue", lw=2)
        ax.annotate(n, rest_mm[i, :2], textcoords="offset points", xytext=(6, 6), fontsize=8)
    fig.colorbar(sc, ax=ax, label="noise floor, per-axis sd at rest (mm)")
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title("Noise per marker (flagged markers circled)")
    return fig


def discrepancy_localisation(takes, phases, ratio, title, *, ax=None) -> Figure:
    """Held-out residual RMS / noise floor per take (rows) and command phase (columns)."""
    fig, ax = _axes(ax, (1.0 + 0.7 * len(phases), 1.2 + 0.22 * len(takes)))
    im = ax.imshow(ratio, aspect="auto", cmap="viridis", vmin=0.0,
                   vmax=max(3.0, float(np.nanmax(ratio)) if np.isfinite(ratio).any() else 3.0))
    fig.colorbar(im, ax=ax, label="held-out residual RMS / noise floor")
    ys, xs = np.nonzero(ratio > 1.5)
    ax.scatter(xs, ys, marker="o", facecolors="none", edgecolors="r", s=30, label="> 1.5 x noise")
    ax.set_xticks(range(len(phases)), phases, rotation=45, ha="right")
    ax.set_yticks(range(len(takes)), takes, fontsize=7)
    ax.set_xlabel("phase of the command")
    ax.set_title(f"Where the model disagrees ({title})", fontsize=9)
    if len(xs):
        ax.legend(loc="upper right", fontsize=7)
    return fig


def discrepancy_gap(stages, total_mm, per_du_mm, noise_floor_mm, *, ax=None) -> Figure:
    """Held-out RMS after each step (total and per DU set) against the noise floor."""
    fig, ax = _axes(ax, (6.0, 4.0))
    x = np.arange(len(stages))
    for du, vals in per_du_mm.items():
        ax.plot(x, vals, "o-", lw=1, ms=3, alpha=0.6, label=f"DUs {du}")
    ax.plot(x, total_mm, "ks-", lw=2.5, label="all takes")
    ax.axhline(noise_floor_mm, color="r", ls="--", label="noise floor")
    ax.axhline(1.5 * noise_floor_mm, color="r", ls=":", label="1.5 x noise floor")
    ax.set_xticks(x, stages, rotation=20, ha="right")
    ax.set_ylabel("held-out residual RMS (mm)")
    ax.set_yscale("log")
    ax.set_title("The gap shrinks as effects are named")
    ax.legend(fontsize=6, ncol=2)
    return fig


def discrepancy_traces(panels, before, after, *, fig=None) -> Figure:
    """Measured vs simulated displacement (along the marker's direction) before and after.

    panels : list of (title, t (S,) s, measured (S,) mm, before (S,) mm, after (S,) mm).
    """
    fig = _figure(fig, (8.0, 2.4 * len(panels)))
    axes = fig.subplots(len(panels), 1, squeeze=False)
    for ax, (title, t, meas, b, a) in zip(axes[:, 0], panels):
        ax.plot(t, meas, "k.", ms=2, label="measured")
        ax.plot(t, b, "C3-", lw=1.2, label=f"model {before} (held-out)")
        ax.plot(t, a, "C0-", lw=1.2, label=f"model {after} (held-out)")
        ax.set_title(title, fontsize=9)
        ax.set_ylabel("displacement (mm)")
    axes[-1, 0].set_xlabel("time (s)")
    axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    return fig


def discrepancy_marker_map(rest_mm, ratios, stage_names, *, fig=None) -> Figure:
    """Held-out residual RMS / noise floor per marker on the face (xy plane), one panel per stage.

    rest_mm : (M, 3) rest positions, mm.  ratios : list of (M,) arrays (NaN: not scored).
    """
    fig = _figure(fig, (3.6 * len(ratios) + 1.0, 5.2))
    axes = fig.subplots(1, len(ratios), squeeze=False)
    vmax = max(3.0, float(np.nanmax(np.concatenate(ratios)))) if len(ratios) else 3.0
    for ax, r, name in zip(axes[0], ratios, stage_names):
        ok = np.isfinite(r)
        sc = ax.scatter(rest_mm[ok, 0], rest_mm[ok, 1], c=r[ok], cmap="viridis", vmin=1.0,
                        vmax=vmax, s=60, edgecolors="k", linewidths=0.3)
        bad = ok & (r > 1.5)
        ax.scatter(rest_mm[bad, 0], rest_mm[bad, 1], s=140, facecolors="none", edgecolors="r")
        ax.scatter(rest_mm[~ok, 0], rest_mm[~ok, 1], marker="x", c="grey", s=30)
        ax.set_aspect("equal")
        ax.set_xlabel("x (mm)")
        ax.set_title(name, fontsize=9)
    axes[0, 0].set_ylabel("y (mm)")
    fig.colorbar(sc, ax=axes[0].tolist(), label="held-out residual RMS / noise floor (red: > 1.5)")
    return fig


def design_comparison(title, evaluations: dict, *, fig=None) -> Figure:
    """Designed motions side by side: one panel per method (e.g. paper, model, refined), each the
    plan P(t) and the realized normalised displacement (mean +- sd over markers) in closed loop.

    evaluations : method name -> :class:`mocap.analysis.design.evaluation.MotionEvaluation`.
    """
    n = max(len(evaluations), 1)
    fig = _figure(fig, (4.2 * n, 3.4))
    axes = fig.subplots(1, n, sharey=True, squeeze=False)
    for ax, (name, ev) in zip(axes[0], evaluations.items()):
        ax.plot(ev.t, ev.ideal, color="k", lw=2, label="plan P(t)")
        ax.fill_between(ev.t, ev.mean - ev.std, ev.mean + ev.std, color="tab:purple", alpha=0.2)
        ax.plot(ev.t, ev.mean, color="tab:purple", lw=1.5, label="realized (mean +- sd)")
        ax.set_xlabel("time (s)")
        ax.set_title(f"{name}: RMS fwd {ev.rms_forward:.3f}, bwd {ev.rms_backward:.3f}\n"
                     f"lag {ev.lag_s * 1000:.0f} ms", fontsize=9)
        ax.set_ylim(-0.05, 1.15)
    axes[0, 0].set_ylabel("normalised displacement (1)")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(title, fontsize=10, y=1.08)
    return fig


def audit_figures(out: Path, audit: dict, reconstruction, calibration=None) -> list[Path]:
    """The audit's figures (``mocap.workflows.audit.audit_capture``'s report of a reconstruction) into
    ``out/figures``: visibility per marker and camera (raw sessions) and the noise floor per
    marker on the face. Returns the files written."""
    recon = reconstruction
    names = list(recon.markers.names)
    files = []
    if recon.capture.views is not None and calibration is not None:
        mf = np.maximum(recon.capture.marker_frames, 1)
        files.append(save(audit_visibility(names, list(calibration.rig.ids),
                                           recon.capture.views / mf[None]),
                          out / "figures" / "audit_visibility.png"))
    noise = np.array([m["noise_floor_mm"] for m in audit["markers"]])
    files.append(save(audit_noise_map(recon.markers.rest_mm, noise,
                                      [m["marker"] for m in audit["markers"] if m["verdict"] != "pass"],
                                      names), out / "figures" / "audit_noise.png"))
    return files
