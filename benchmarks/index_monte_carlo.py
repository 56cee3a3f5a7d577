"""Full-size Monte-Carlo of the noise-corrected dyssynchrony and linearity (issue #16).

The same comparison as tests/test_paper_indices.py's Monte-Carlo, with more faces and markers:
numpy-made faces (tests/synthetic_faces.py: bowed or off-chord paths, per-marker timing scatter,
trial shifts), the paper's recipe computed plainly on the noise-free trials (the test's
``plain_spread_and_linearity``) against the corrected estimates on the same trials with
anisotropic white capture noise added. Writes benchmarks/index_monte_carlo.md and .json.

    python benchmarks/index_monte_carlo.py [--seeds 100] [--markers 60]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))


def case(family: str, K: int, sigma: float, seeds: int, markers: int) -> dict:
    from synthetic_faces import FPS, add_noise, make_take
    from test_paper_indices import plain_spread_and_linearity

    from mocap.analysis.noise_corrected import (
        capture_noise_covariance,
        corrected_dyssynchrony,
        corrected_linearity,
    )
    from mocap.analysis.paper_indices import schedule_timing

    rel, lin, raw, lin_raw, gammas = [], [], [], [], []
    for seed in range(seeds):
        rng = np.random.default_rng(10_000 + seed)
        take = make_take(rng, family=family, n_markers=markers, n_trials=K)
        tm = schedule_timing(take.time_s, take.command)
        gamma, linearity = plain_spread_and_linearity(take.trials, take.time_s, take.command, FPS)
        noisy = add_noise(rng, take.trials, sigma)[0]
        noise = capture_noise_covariance(noisy, take.series, FPS)
        g, _ = corrected_dyssynchrony(noisy.mean(axis=0), np.full(noisy.shape[1:3], K),
                                      np.ones(markers, bool), tm, FPS, noise.cov)
        lc = corrected_linearity(noisy, tm, FPS, noise.cov)
        g_raw, l_raw = plain_spread_and_linearity(noisy, take.time_s, take.command, FPS)
        rel.append(g / gamma - 1)
        lin.append(float(np.mean(lc)) - linearity)
        raw.append(g_raw / gamma - 1)
        lin_raw.append(l_raw - linearity)
        gammas.append(gamma)
    rel, lin = np.array(rel), np.array(lin)
    return {"family": family, "trials": K, "noise_mm": sigma, "seeds": seeds,
            "true_dyssynchrony_median": float(np.median(gammas)),
            "dys_mean": float(rel.mean()), "dys_median_abs": float(np.median(np.abs(rel))),
            "dys_p90_abs": float(np.quantile(np.abs(rel), 0.9)), "dys_max_abs": float(np.abs(rel).max()),
            "dys_within_10pct": float(np.mean(np.abs(rel) < 0.1)),
            "raw_dys_mean": float(np.mean(raw)),
            "lin_mean": float(lin.mean()), "lin_max_abs": float(np.abs(lin).max()),
            "raw_lin_mean": float(np.mean(lin_raw))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=100)
    ap.add_argument("--markers", type=int, default=60)
    args = ap.parse_args()
    t0 = time.perf_counter()
    rows = [case(f, K, s, args.seeds, args.markers)
            for f in ("bow", "offchord") for K in (3, 10) for s in (0.02, 0.035, 0.05)]
    dt = time.perf_counter() - t0
    (HERE / "index_monte_carlo.json").write_text(json.dumps(rows, indent=2))
    lines = ["| family | trials | noise (mm) | true dyssynchrony (median) | dyssynchrony: mean error "
             "| median abs | 90 % abs | max abs | share within 10 % | literal: mean error "
             "| linearity: mean error | max abs | literal: mean error |", "|" + "---|" * 13]
    for r in rows:
        lines.append(
            f"| {r['family']} | {r['trials']} | {r['noise_mm']} | {r['true_dyssynchrony_median']:.4f} "
            f"| {100 * r['dys_mean']:+.1f} % | {100 * r['dys_median_abs']:.1f} % "
            f"| {100 * r['dys_p90_abs']:.1f} % | {100 * r['dys_max_abs']:.1f} % "
            f"| {100 * r['dys_within_10pct']:.0f} % | {100 * r['raw_dys_mean']:+.0f} % "
            f"| {r['lin_mean']:+.4f} | {r['lin_max_abs']:.4f} | {r['raw_lin_mean']:+.4f} |")
    text = (f"# Monte-Carlo of the noise-corrected dyssynchrony and linearity\n\n"
            f"`python benchmarks/index_monte_carlo.py --seeds {args.seeds} --markers {args.markers}`: "
            f"{args.seeds} faces per row, {args.markers} markers moving 0.15-3 mm each, errors "
            "against the paper's recipe on the noise-free trials (relative for the dyssynchrony, "
            "absolute for the mean linearity). \"literal\": the recipe on the noisy data.\n\n"
            + "\n".join(lines) + f"\n\n{dt:.0f} s on a shared 2-core machine (under load).\n")
    (HERE / "index_monte_carlo.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
