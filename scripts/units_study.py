#!/usr/bin/env python
"""The error at a point and the held-out validation against their references, as four figures and numbers.

    python scripts/units_study.py -o DIR [--runs 100]

1. ``mc.png``: each point's first-order 3-sigma (``Calibration.point_error``) against a Monte Carlo of the
   result's own ``covariance_cam_base`` (each sample's T_cam_base inverted exactly), points at 0.3-2.5 m.
2. ``nees.png``: the point error's NEES (3 dof) against the simulator's truth over ``--runs`` base cases,
   with the chi-square density and the 99 % band of the mean.
3. ``ratios.png``: each image's held-out ratio in a base case of 200 images, clean and with one point
   6 px off (sigma 1 px).
4. ``brute_force.png``: the held-out ratio against the brute force (a full re-solve without the image;
   ``tests/test_validation.brute_force_ratio``) on the tree, a kaleidoscope and a rig.
Frames and units as docs/formats.md ("The answer in the user's units"): metres, millimetres.
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO), str(REPO / "tests")]

from mirror_fg.core.transform import Transform  # noqa: E402
from mirror_fg.io.dataset import dataset_from_dict  # noqa: E402
from mirror_fg.solver.calibrate import calibrate  # noqa: E402
from mirror_fg.solver.fit.validation import validate_calibration  # noqa: E402
from mirror_fg.report.figures import new_figure, png  # noqa: E402
from mirror_fg.simulate.tree import simulate_base_case  # noqa: E402


def monte_carlo(ax) -> str:
    dataset, _ = simulate_base_case(num_images=60, seed=3)
    cal = calibrate(dataset, diagnose=False)
    rng = np.random.default_rng(0)
    samples = rng.multivariate_normal(np.zeros(6), cal.covariance, size=100_000)
    R = Rotation.from_rotvec(samples[:, :3]).as_matrix() @ cal.R_cam_base
    t = cal.t_cam_base + samples[:, 3:]
    ours, theirs = [], []
    for _ in range(20):
        p = np.array([rng.uniform(-0.6, 0.6), rng.uniform(-0.4, 0.4), rng.uniform(0.3, 2.5)])
        moved = np.einsum("nji,nj->ni", R, p - t)
        theirs.append(3000 * np.sqrt(np.diag(np.cov(moved.T))))
        ours.append(cal.point_error(p).sigma3_mm)
    ours, theirs = np.ravel(ours), np.ravel(theirs)
    ax.loglog(theirs, ours, "o", ms=3)
    lim = [theirs.min() * 0.8, theirs.max() * 1.2]
    ax.plot(lim, lim, "k-", lw=0.7)
    ax.set_xlabel("Monte Carlo 3σ, mm")
    ax.set_ylabel("point_error 3σ, mm")
    worst = float(np.max(np.abs(ours / theirs - 1)))
    ax.set_title(f"20 points x 3 axes: largest difference {100 * worst:.2f} %", fontsize=9)
    return f"MC: largest relative difference {100 * worst:.2f} % over 60 axis bounds"


def nees(ax, runs: int) -> str:
    values = []
    for seed in range(runs):
        dataset, truth = simulate_base_case(num_images=60, seed=100 + seed)
        cal = calibrate(dataset, diagnose=False)
        p = [(0.0, 0.0, 0.6), (0.3, -0.2, 1.0), (-0.5, 0.4, 2.0)][seed % 3]
        got = cal.point_error(p)
        e = got.point_base - Transform(truth.R_cam_base, truth.t_cam_base).inverse().apply(p)
        values.append(float(e @ np.linalg.solve(got.covariance, e)))
    values = np.array(values)
    low, high = chi2.ppf(0.005, 3 * runs) / runs, chi2.ppf(0.995, 3 * runs) / runs
    ax.hist(values, bins=25, density=True, alpha=0.6, label="NEES of each run")
    x = np.linspace(0, max(values.max(), 12), 200)
    ax.plot(x, chi2.pdf(x, 3), "k-", lw=0.8, label="χ²(3)")
    ax.axvline(values.mean(), color="tab:red", label=f"mean {values.mean():.2f}")
    ax.axvspan(low, high, color="tab:green", alpha=0.2, label=f"99 % band of the mean [{low:.2f}, {high:.2f}]")
    ax.legend(fontsize=7)
    ax.set_title(f"{runs} runs, 60 images each", fontsize=9)
    return f"NEES: mean {values.mean():.3f} over {runs} runs, band [{low:.3f}, {high:.3f}]"


def ratios(ax) -> str:
    dataset, _ = simulate_base_case(num_images=200, seed=21)
    clean = validate_calibration(dataset, calibrate(dataset, diagnose=False))
    image = dataset.images[77]
    observations = dict(image.observations)
    observations["F0"] = observations["F0"] + np.array([6.0, 0.0])
    images = list(dataset.images)
    images[77] = replace(image, observations=observations)
    bad = replace(dataset, images=images)
    off = validate_calibration(bad, calibrate(bad, diagnose=False))
    x = np.arange(len(clean.ratios))
    ax.plot(x, clean.ratios, ".", ms=4, label=f"clean: RMS {clean.ratio:.3f}")
    ax.plot(x, off.ratios, "x", ms=3, label=f"F0 of {image.id} 6 px off: RMS {off.ratio:.3f}")
    ax.annotate(f"{off.worst[0]} {off.worst[1]:.2f}", (77, off.worst[1]), fontsize=7)
    ax.axhline(1.0, color="k", lw=0.7)
    ax.axhline(2.0, color="tab:red", lw=0.7, ls="--")
    ax.set_xlabel("image")
    ax.set_ylabel("held-out ratio")
    ax.legend(fontsize=7)
    return (f"ratios: clean RMS {clean.ratio:.3f} (worst {clean.worst[1]:.2f}); one point 6 px off: worst "
            f"{off.worst[0]} at {off.worst[1]:.2f}")


def brute_force(ax) -> str:
    from test_validation import brute_force_ratio

    from mirror_fg.simulate.rig import simulate_rig_mixed
    from mirror_fg.simulate.views import simulate_kaleidoscope

    cases = [("tree", simulate_base_case(num_images=40, seed=5)[0]),
             ("kaleidoscope", dataset_from_dict(simulate_kaleidoscope(2, seed=2)[0])),
             ("rig", dataset_from_dict(simulate_rig_mixed(2, seed=1)[0]))]
    worst = 0.0
    for name, dataset in cases:
        cal = calibrate(dataset, diagnose=False)
        validation = validate_calibration(dataset, cal)
        chosen = validation.images[:: max(1, len(validation.images) // 8)][:8]
        fast = [validation.ratios[validation.images.index(i)] for i in chosen]
        slow = [brute_force_ratio(dataset, cal, i) for i in chosen]
        worst = max(worst, float(np.max(np.abs(np.array(fast) / np.array(slow) - 1))))
        ax.plot(slow, fast, "o", ms=4, label=name)
    ax.plot([0, 2.5], [0, 2.5], "k-", lw=0.7)
    ax.set_xlabel("brute force (re-solve without the image)")
    ax.set_ylabel("one Gauss–Newton step (rank-downdate)")
    ax.set_title(f"largest difference {100 * worst:.2f} %", fontsize=9)
    ax.legend(fontsize=7)
    return f"brute force: largest relative difference {100 * worst:.2f} %"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-o", "--output", type=Path, required=True)
    parser.add_argument("--runs", type=int, default=100)
    args = parser.parse_args()
    args.output.mkdir(parents=True, exist_ok=True)
    for name, draw, extra in (("mc", monte_carlo, ()), ("nees", nees, (args.runs,)), ("ratios", ratios, ()),
                              ("brute_force", brute_force, ())):
        fig = new_figure(6.0, 4.0)
        line = draw(fig.add_subplot(1, 1, 1), *extra)
        (args.output / f"{name}.png").write_bytes(png(fig, 100))
        print(line, flush=True)


if __name__ == "__main__":
    main()
