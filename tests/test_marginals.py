"""solver/model/marginals.py's one wrap of GTSAM's indeterminant-system error into a SolveError naming the unknown
(one error wrap for LM, Marginals and the intrinsics' Marginals)."""
from __future__ import annotations

from dataclasses import replace

import gtsam
import pytest

from mirror_fg.core.errors import SolveError
from reference.graph import build_graph
from mirror_fg.solver.model.marginals import unconstrained_as_solve_error, unconstrained_message
from mirror_fg.simulate.tree import simulate_base_case


def test_an_indeterminant_system_becomes_a_solve_error_naming_the_unknown():
    dataset, truth = simulate_base_case(num_images=9, num_points=1, pixel_sigma=0.0, seed=1)
    first, *rest = dataset.images  # P0 kept in the first image only: its depth along the ray is free
    without_p0 = [replace(im, observations={n: o for n, o in im.observations.items() if n != "P0"}) for im in rest]
    lonely = replace(dataset, images=[first, *without_p0], source="lonely.json")
    graph, values, layout, _ = build_graph(lonely, truth)
    with pytest.raises(SolveError, match=r"^lonely.json: the data do not constrain point 'P0'"):
        with unconstrained_as_solve_error(lonely.source, lambda error: unconstrained_message(error, layout)):
            gtsam.Marginals(graph, values)
    full_graph, full_values, _, _ = build_graph(dataset, truth)
    with unconstrained_as_solve_error(dataset.source, lambda error: "never called"):  # constrained: no error
        marginals = gtsam.Marginals(full_graph, full_values)
    assert marginals.marginalCovariance(layout.point_keys["P0"]).shape == (3, 3)
