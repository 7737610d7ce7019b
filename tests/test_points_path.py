"""The points path of the eliminated factors: reconstruction points make a factor as wide as
6 + 3 (parents + points); its linearisation works on each measurement's nonzero columns (the same
normal equations as the dense projected system, checked here against one built densely) and runs its
small BLAS calls on one thread (a second OpenBLAS thread spinning on a loaded machine took the cores
from the solve). Its speed is measured by scripts/benchmark.py (no timing in tests).
"""
from __future__ import annotations

import numpy as np
import pytest

from reference.graph import build_eliminated_graph
from mirror_fg.simulate.tree import simulate_base_case

threadpoolctl = pytest.importorskip("threadpoolctl")


@pytest.fixture(scope="module")
def wide_factors():
    """40 images, 80 reconstruction points: each of the 3 factors is 6 + 3 + 240 columns wide."""
    dataset, truth = simulate_base_case(num_images=40, num_points=80, mirror1_placements=3, seed=1)
    eliminated = build_eliminated_graph(dataset, truth)
    return eliminated


def test_the_compact_normal_equations_are_the_dense_ones(wide_factors):
    """Against the dense product built here from the same per-measurement Jacobians (reflection_model)."""
    graph, values, evaluator = wide_factors.graph, wide_factors.values, wide_factors.evaluator
    graph.linearize(values)
    _, _, (cross, GR, mirror) = evaluator._model(evaluator._P, True)
    w = evaluator._whiten.T[:, :, None]
    Jv = mirror[evaluator.num_mirrors - 1].transpose(2, 0, 1) * w
    D_inv = evaluator._blocks["D_inv"]
    for f, information in zip(evaluator._factors, evaluator._blocks["information"]):
        lo, hi, width = f["lo"], f["hi"], f["width"]
        J = np.zeros((hi - lo, 2, width + 1))
        J[:, :, :3] = cross.transpose(2, 0, 1)[lo:hi]
        J[:, :, 3:6] = GR.transpose(2, 0, 1)[lo:hi]
        for level in range(evaluator.num_mirrors - 1):
            J[:, :, 6 + 3 * level : 9 + 3 * level] = mirror[level].transpose(2, 0, 1)[lo:hi]
        for m, column in zip(f["landmarks"], f["landmark_columns"]):
            J[m, :, column : column + 3] = GR[:, :, lo + m]
        J[:, :, :width] *= w[lo:hi]
        J[:, :, width] = evaluator._e[lo:hi]
        # project out each placement: (I - J_v D^-1 J_v^T) [J_x | e], one placement at a time
        segment = evaluator._segment_of_measurement[lo:hi]
        for s in np.unique(segment):
            rows = segment == s
            Jvs = Jv[lo:hi][rows].reshape(-1, 3)
            block = J[rows].reshape(-1, width + 1)
            J[rows] = (block - Jvs @ (D_inv[s] @ (Jvs.T @ block))).reshape(-1, 2, width + 1)
        flat = J.reshape(-1, width + 1)
        expected = flat.T @ flat
        scale = np.abs(expected[:width, :width]).max()
        np.testing.assert_allclose(information, expected[:width, :width], rtol=0, atol=1e-10 * scale)


def test_factor_evaluations_run_blas_on_one_thread(wide_factors, monkeypatch):
    import reference.eliminated as eliminated

    seen = []
    model = eliminated.reflection_model

    def recording(*args, **kwargs):
        seen.extend(info["num_threads"] for info in threadpoolctl.threadpool_info() if info["user_api"] == "blas")
        return model(*args, **kwargs)

    monkeypatch.setattr(eliminated, "reflection_model", recording)
    wide_factors.evaluator._state_key = None  # evaluate again, with Jacobians
    wide_factors.graph.linearize(wide_factors.values)
    assert seen and set(seen) == {1}
