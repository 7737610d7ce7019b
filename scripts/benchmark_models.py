"""The paper's tree solved on the one measurement model (the general view model, the default) beside the
tree's own factors (``tests/reference/``, the reference it is checked against): ``calibrate()``'s wall
time and its stages, alternating in one process, medians of ``--repeats`` runs each.

    python scripts/benchmark_models.py [--repeats 5] [--cases 900 200+60 4800]

Cases (simulator, Sect. 7; two mirrors, 3 fiducials, 1 px, mirror 1 in three placements): 900 images,
200 images + 60 reconstruction points, 4,800 images (``benchmark.py``'s).
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "tests"))  # the tree's own factors (tests/reference/)

CASES = {"900": (900, 0), "200+60": (200, 60), "4800": (4800, 0)}
STAGES = ("pnp", "consensus", "analytic", "build", "optimize", "marginals")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--cases", nargs="*", choices=list(CASES), default=list(CASES))
    args = parser.parse_args(argv)

    from benchmark import COMMON

    import reference.lm as reference_lm
    from mirror_fg import calibrate
    from mirror_fg.simulate.tree import simulate_base_case

    print(f"load average {os.getloadavg()[0]:.2f}; medians of {args.repeats} runs each, alternating")
    for case in args.cases:
        images, points = CASES[case]
        dataset, _ = simulate_base_case(num_images=images, num_points=points, mirror1_placements=3, **COMMON)
        runs: dict[bool, list[tuple[float, dict]]] = {True: [], False: []}
        answers = {}
        for _ in range(args.repeats + 1):  # the first of each: warm-up
            for view_model in (True, False):
                reference_lm.select(tree_factors=not view_model)
                start = time.perf_counter()
                calibration = calibrate(dataset)
                runs[view_model].append((time.perf_counter() - start, calibration.timings))
                answers[view_model] = calibration
        reference_lm.select(tree_factors=False)
        walls = {}
        for view_model, label in ((True, "view model"), (False, "tree factors")):
            kept = runs[view_model][1:]
            walls[view_model] = float(np.median([w for w, _ in kept]))
            stages = " ".join(f"{s} {np.median([t.get(s, 0.0) for _, t in kept]):.3f}" for s in STAGES)
            print(f"{case:>7s} {label:>12s}  {walls[view_model]:.3f} s  ({stages})")
        view, tree = answers[True], answers[False]
        scale = max(np.abs(tree.covariance).max(), 1e-300)
        print(f"{case:>7s}   view / tree  {walls[True] / walls[False]:.2f}x;  |dt| {np.abs(view.t_cam_base - tree.t_cam_base).max():.1e} m, "
              f"|dR| {np.abs(view.R_cam_base - tree.R_cam_base).max():.1e}, covariance {np.abs(view.covariance - tree.covariance).max() / scale:.1e} relative")
    return 0


if __name__ == "__main__":
    sys.exit(main())
