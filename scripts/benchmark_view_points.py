#!/usr/bin/env python
"""The LM stage of ``calibrate()`` on the paper's tree with reconstruction points, on the tree's factors
(``tests/reference/eliminated.py``) and on the general view model (``factors/view_points.py``),
alternating in one process (the same contention for both), and the two results compared.

    python scripts/benchmark_view_points.py [--repeats 7] [--images 200] [--points 60] [--eliminated]

Problem: scripts/benchmark.py's case "200img+60pts" (simulator, Sect. 7: two mirrors, mirror 1 in three
placements, 3 fiducials, 1 px). Printed: each run's ``timings['optimize']`` (seconds) per model, their
medians and the median of the per-pair ratios (view / tree), the iterations and final costs, and the largest
relative differences of the estimates (pose, mirror vectors, points) and of the covariances (pose, mirrors,
points) between the models. ``--eliminated`` adds a third model, timed in the same alternation: the view
model with each photograph's own placement eliminated inside the factors (``factors/view_points_eliminated.py``),
through :func:`eliminated_solve_graph`, the change ``ViewProblem.solve_graph`` would need (applied here by
replacing the method for those runs only).
"""
from __future__ import annotations

import argparse
import os
import sys
from typing import Any

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "tests"))  # the tree's own factors (tests/reference/)

COMMON: dict[str, Any] = {"pixel_sigma": 1.0, "mirror_distance": 0.5, "tilt_deg": 30.0, "seed": 0, "num_mirrors": 2, "num_fiducials": 3}


def _relative(a: np.ndarray, b: np.ndarray) -> float:
    """Largest difference relative to the largest entry of ``b``."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-300))


def compare(view, tree) -> dict[str, float]:
    """Largest relative differences of the view model's calibration from the tree's."""
    out = {"pose": max(_relative(view.R_cam_base, tree.R_cam_base), _relative(view.t_cam_base, tree.t_cam_base)),
           "mirrors": max(_relative(view.mirror_vectors[p], v) for p, v in tree.mirror_vectors.items()),
           "points": max((_relative(view.points[n], x) for n, x in tree.points.items()), default=0.0),
           "pose covariance": _relative(view.covariance, tree.covariance),
           "mirror covariances": max(_relative(view.mirror_covariances[p], c) for p, c in tree.mirror_covariances.items()),
           "point covariances": max((_relative(view.point_covariances[n], c) for n, c in tree.point_covariances.items()),
                                    default=0.0)}
    return out


def eliminated_solve_graph(original):
    """``ViewProblem.solve_graph`` that, where every view sees reconstruction points (a known target,
    intrinsics known, no robust kernel), eliminates their own placements inside the factors
    (``EliminatedViewPointStack``), else ``original``."""
    import gtsam

    from mirror_fg.factors.view_points_eliminated import EliminatedViewPointStack

    def solve_graph(self, estimate, eliminate: bool = True):
        if (eliminate and self.dataset.scale is None and not self.intrinsics and self.robust is None
                and all(f.unique_landmarks for f in self.factors)):
            evaluator = EliminatedViewPointStack(self.factors, estimate.mirror_vectors)
            graph = gtsam.NonlinearFactorGraph()
            for factor in evaluator.factors:
                graph.add(factor)
            self._priors(graph)
            return graph, self.values(estimate, skip=set(evaluator.eliminated)), evaluator
        return original(self, estimate, eliminate)

    return solve_graph


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--images", type=int, default=200)
    parser.add_argument("--points", type=int, default=60)
    parser.add_argument("--eliminated", action="store_true", help="also the view model with own placements eliminated")
    args = parser.parse_args(argv)

    import reference.lm as reference_lm
    from mirror_fg import calibrate, initial_estimate
    from mirror_fg.simulate.tree import simulate_base_case
    from mirror_fg.solver.model.views import ViewProblem

    dataset, _ = simulate_base_case(num_images=args.images, num_points=args.points, mirror1_placements=3, **COMMON)
    initial = initial_estimate(dataset)
    original = ViewProblem.solve_graph
    models = ["tree", "view"] + (["eliminated"] if args.eliminated else [])
    times: dict[str, list[float]] = {name: [] for name in models}
    results = {}
    for _ in range(args.repeats + 1):  # the first round warms up (imports, caches), not counted
        for name in models:
            reference_lm.select(tree_factors=name == "tree")
            if name == "eliminated":
                ViewProblem.solve_graph = eliminated_solve_graph(original)  # type: ignore[method-assign]
            try:
                cal = calibrate(dataset, initial=initial)
            finally:
                reference_lm.select(tree_factors=False)
                ViewProblem.solve_graph = original  # type: ignore[method-assign]
            times[name].append(cal.timings["optimize"])
            results[name] = cal
    print(f"{args.images} images + {args.points} points, {args.repeats} runs each, alternating; load {os.getloadavg()[0]:.2f}")
    tree = np.array(times["tree"][1:])
    for name in models:
        runs = np.array(times[name][1:])
        print(f"{name:10s} optimize (s): " + " ".join(f"{t:.3f}" for t in runs) + f"   median {np.median(runs):.3f}")
    for name in models[1:]:
        print(f"{name} / tree: median of pairs {np.median(np.array(times[name][1:]) / tree):.2f}x")
    for name in models:
        print(f"{name}: {results[name].iterations} iterations, final cost {results[name].final_error:.9f}")
    for name in models[1:]:
        for what, value in compare(results[name], results["tree"]).items():
            print(f"{name}: largest relative difference from the tree, {what}: {value:.1e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
