#!/usr/bin/env python
"""The build stage of a calibration (``cal.timings['build']``) on the paper's tree, solved on its own
factors (``tests/reference/eliminated.py``) and on the general view model (``ViewProblem`` and
its eliminated graph), alternating in one process; and the construction of a rig's ``ViewProblem``.

    python scripts/benchmark_view_build.py [--repeats 5] [--sizes 900 4800]

Printed per tree size (``simulate_base_case(num_images=n, num_points=0, mirror1_placements=3)``, the
settings of ``benchmark.py``): the median and the range of ``timings['build']`` of whole calibrations,
then of the build alone from the same start (tree: ``build_eliminated_graph``; view model:
``ViewProblem`` + ``solve_graph``); then ``ViewProblem(dataset)`` of the rig
``simulate_rig_mixed(3, own=[200] * 3, shared=200, seed=0)``, alone and with its graph (the stacked
factors). The machine is shared: the load average is printed with the figures.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "tests"))  # the tree's own factors (tests/reference/)
from benchmark import COMMON


def _figures(times: list[float]) -> str:
    return f"median {statistics.median(times):.3f} s  (min {min(times):.3f}, max {max(times):.3f}, n={len(times)})"


def _start_of(dataset):
    """The analytical start calibrate() hands to LM (captured from one calibration on the view model)."""
    from mirror_fg import calibrate
    import reference.lm as reference_lm
    from mirror_fg.solver.model import view_lm

    captured: dict = {}
    run = view_lm.view_model_run

    def capture(data, initial, *args, **kwargs):
        captured.setdefault("dataset", data)
        captured.setdefault("initial", initial)
        return run(data, initial, *args, **kwargs)

    reference_lm.select(tree_factors=False)
    view_lm.view_model_run = capture
    try:
        calibrate(dataset)
    finally:
        view_lm.view_model_run = run
    return captured["dataset"], captured["initial"]


def tree(size: int, repeats: int) -> None:
    from mirror_fg import calibrate
    from mirror_fg.simulate.tree import simulate_base_case
    import reference.lm as reference_lm
    from reference.graph import build_eliminated_graph
    from mirror_fg.solver.model.views import ViewEstimate, ViewProblem

    dataset, _ = simulate_base_case(num_images=size, num_points=0, mirror1_placements=3, **COMMON)
    calibrated: dict[bool, list[float]] = {False: [], True: []}
    for _ in range(repeats):
        for view_model in (False, True):
            reference_lm.select(tree_factors=not view_model)
            try:
                calibrated[view_model].append(calibrate(dataset).timings["build"])
            finally:
                reference_lm.select(tree_factors=False)
    used, initial = _start_of(dataset)
    start = ViewEstimate({"camera": (np.asarray(initial.R_cam_base, float), np.asarray(initial.t_cam_base, float))},
                         {p: np.asarray(v, float) for p, v in initial.mirror_vectors.items()}, {})
    alone: dict[bool, list[float]] = {False: [], True: []}
    for _ in range(3 * repeats):
        for view_model in (False, True):
            begin = time.perf_counter()
            if view_model:
                ViewProblem(used, None).solve_graph(start, True)
            else:
                build_eliminated_graph(used, initial)
            alone[view_model].append(time.perf_counter() - begin)
    print(f"tree, {size} images (load {os.getloadavg()[0]:.1f})")
    print(f"  calibrate() build, tree factors : {_figures(calibrated[False])}")
    print(f"  calibrate() build, view model   : {_figures(calibrated[True])}")
    print(f"  build alone, tree factors       : {_figures(alone[False])}")
    print(f"  build alone, view model         : {_figures(alone[True])}")


def rig(repeats: int) -> None:
    from mirror_fg.io.dataset import dataset_from_dict
    from mirror_fg.simulate.rig import simulate_rig_mixed
    from mirror_fg.solver.model.views import ViewProblem

    dataset = dataset_from_dict(simulate_rig_mixed(3, own=[200] * 3, shared=200, seed=0)[0])
    times, graphs = [], []
    for _ in range(3 * repeats):
        begin = time.perf_counter()
        problem = ViewProblem(dataset, None)
        times.append(time.perf_counter() - begin)
        problem.graph()
        graphs.append(time.perf_counter() - begin)
    print(f"rig, 3 cameras, {len(dataset.images)} images (load {os.getloadavg()[0]:.1f})")
    print(f"  ViewProblem(dataset)            : {_figures(times)}")
    print(f"  ViewProblem(dataset).graph()    : {_figures(graphs)}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--sizes", type=int, nargs="+", default=[900, 4800])
    args = parser.parse_args()
    for size in args.sizes:
        tree(size, args.repeats)
    rig(args.repeats)


if __name__ == "__main__":
    main()
