"""``SolveOptions`` (solver/options.py): one frozen value for how ``calibrate`` solves.

``calibrate(dataset, options=SolveOptions(...))`` must give exactly what the separate arguments give,
the ``linearization`` must pick the factors it names (eliminated only where no robust kernel is used
and ``lm.ELIMINATE`` allows it, as ``fast=True`` always did), and bad settings are refused.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mirror_fg.solver.model import lm as lm_module
from mirror_fg.solver.calibrate import calibrate
from mirror_fg.solver.options import Linearization, SolveOptions
from mirror_fg.simulate.tree import simulate_base_case


@pytest.fixture(scope="module")
def scene():
    dataset, _ = simulate_base_case(num_images=12, num_points=0, num_mirrors=2, mirror1_placements=3, seed=4)
    return dataset


@pytest.mark.parametrize("settings, options", [
    ({}, SolveOptions()),
    ({"fast": False}, SolveOptions(linearization="reference")),
    ({"robust": "huber", "max_iterations": 50}, SolveOptions(robust="huber", max_iterations=50)),
    ({"compute_covariance": False, "diagnose": False}, SolveOptions(compute_covariance=False, diagnose=False)),
], ids=["default", "reference", "huber", "no-covariance"])
def test_options_give_exactly_what_the_separate_arguments_give(scene, settings, options):
    separate = calibrate(scene, **settings)
    together = calibrate(scene, options=options)
    np.testing.assert_array_equal(together.R_cam_base, separate.R_cam_base)
    np.testing.assert_array_equal(together.t_cam_base, separate.t_cam_base)
    assert together.final_error == separate.final_error
    assert together.iterations == separate.iterations
    assert (together.covariance is None) == (separate.covariance is None)
    if separate.covariance is not None:
        np.testing.assert_array_equal(together.covariance, separate.covariance)


def _graphs_built(monkeypatch, scene, options, eliminate=True, view_model=True):
    """Which graphs ``calibrate`` builds for its LM runs: "eliminated", "stacked" or "reference" per build, on
    the view model (``view_model``, the default: ``ViewProblem.solve_graph`` and ``graph``) or on the tree's
    own factors (``tests/reference/lm.py``: ``build_eliminated_graph`` and ``build_graph``)."""
    if view_model:
        return _view_graphs_built(monkeypatch, scene, options, eliminate)
    import reference.lm as reference_lm

    reference_lm.use_tree_factors(monkeypatch)
    built: list[str] = []
    eliminated_graph, graph = reference_lm.build_eliminated_graph, reference_lm.build_graph

    def eliminated_spy(*args, **kwargs):
        built.append("eliminated")
        return eliminated_graph(*args, **kwargs)

    def graph_spy(dataset, initial, robust=None, fast=True):
        built.append("stacked" if fast else "reference")
        return graph(dataset, initial, robust, fast=fast)

    monkeypatch.setattr(reference_lm, "build_eliminated_graph", eliminated_spy)
    monkeypatch.setattr(reference_lm, "build_graph", graph_spy)
    monkeypatch.setattr(lm_module, "ELIMINATE", eliminate)
    calibrate(scene, options=dataclasses.replace(options, compute_covariance=False, diagnose=False))
    return set(built)


def _view_graphs_built(monkeypatch, scene, options, eliminate):
    from mirror_fg.solver.model.views import ViewProblem

    built: list[str] = []
    solve_graph, graph = ViewProblem.solve_graph, ViewProblem.graph

    def solve_graph_spy(self, estimate, eliminate=True):
        answer = solve_graph(self, estimate, eliminate)
        if answer[2] is not None:  # else it built graph() (the spy below)
            built.append("eliminated")
        return answer

    def graph_spy(self, stacked=True):
        built.append("stacked" if stacked else "reference")
        return graph(self, stacked)

    monkeypatch.setattr(ViewProblem, "solve_graph", solve_graph_spy)
    monkeypatch.setattr(ViewProblem, "graph", graph_spy)
    monkeypatch.setattr(lm_module, "ELIMINATE", eliminate)
    calibrate(scene, options=dataclasses.replace(options, compute_covariance=False, diagnose=False))
    return set(built)


@pytest.mark.parametrize("view_model", [True, False], ids=["view-model", "tree-factors"])
@pytest.mark.parametrize("options, eliminate, expected", [
    (SolveOptions(), True, {"eliminated"}),
    (SolveOptions(), False, {"stacked"}),  # the switch the tests turn off
    (SolveOptions(robust="cauchy"), True, {"stacked"}),  # no elimination under a kernel
    (SolveOptions(linearization=Linearization.STACKED), True, {"stacked"}),
    (SolveOptions(linearization="reference"), True, {"reference"}),
    (SolveOptions(linearization="reference", robust="huber"), True, {"reference"}),
], ids=["eliminated", "ELIMINATE-off", "robust", "stacked", "reference", "reference-huber"])
def test_linearization_picks_the_factors_it_names(monkeypatch, scene, options, eliminate, expected, view_model):
    assert _graphs_built(monkeypatch, scene, options, eliminate, view_model) == expected


def test_stacked_reaches_the_reference_estimate(scene):
    stacked = calibrate(scene, options=SolveOptions(linearization="stacked"))
    reference = calibrate(scene, fast=False)
    assert stacked.converged and reference.converged
    np.testing.assert_allclose(stacked.t_cam_base, reference.t_cam_base, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(stacked.R_cam_base, reference.R_cam_base, rtol=1e-9, atol=1e-12)
    assert np.isclose(stacked.final_error, reference.final_error, rtol=1e-9)


def test_bad_settings_are_refused(scene):
    with pytest.raises(ValueError, match="robust kernel"):
        SolveOptions(robust="tukey")
    with pytest.raises(ValueError):
        SolveOptions(linearization="sparse")
    assert SolveOptions(linearization="stacked").linearization is Linearization.STACKED
    with pytest.raises(dataclasses.FrozenInstanceError):
        SolveOptions().robust = "huber"  # type: ignore[misc]
    with pytest.raises(TypeError, match="options="):
        calibrate(scene, robust="huber", options=SolveOptions())


def test_the_users_options_reach_every_nested_solve(monkeypatch):
    """Rule 2's solve inside the general model's start and the consistency checks' group solves take the
    user's kernel and iteration limit (``SolveOptions.nested``), never a fresh default; no progress or
    iteration hook of the user's is called by them."""
    from mirror_fg.io.dataset import dataset_from_dict
    from mirror_fg.solver.screen import consistency
    from mirror_fg.solver.batch import views_solve
    from mirror_fg.simulate.views import simulate_mixed

    seen: list[SolveOptions] = []
    real_pipeline, real_lm = views_solve.run_pipeline, consistency.levenberg_marquardt

    def pipeline(problem, dataset):
        seen.append(problem.options)
        return real_pipeline(problem, dataset)

    def lm(dataset, start, options, *rest):
        seen.append(options)
        return real_lm(dataset, start, options, *rest)

    monkeypatch.setattr(views_solve, "run_pipeline", pipeline)
    monkeypatch.setattr(consistency, "levenberg_marquardt", lm)
    dataset = dataset_from_dict(simulate_mixed([4, 4], seed=3)[0])
    iterations: list[int] = []
    options = SolveOptions(robust="huber", max_iterations=77, on_iteration=lambda k, *_: iterations.append(k))
    calibrate(dataset, options=options)
    nested = [o for o in seen if o is not options]
    assert nested, "no nested solve ran: the scene does not exercise rule 2"
    assert all(o.robust == "huber" and o.max_iterations == 77 for o in nested)
    assert all(o.on_iteration is None and o.progress is None and not o.compute_covariance for o in nested)
    seen.clear()
    tree, _ = simulate_base_case(num_images=120, num_points=0, mirror1_placements=6, seed=4)
    calibrate(tree, options=options)  # the diagnosis solves groups of images alone (consistency.fit_group)
    assert seen and all(o.robust == "huber" and o.max_iterations == 77 and o.on_iteration is None for o in seen)
