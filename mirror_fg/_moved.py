"""The import paths of modules that moved when the solver and the tools were split into sub-packages by
concept (docs/layout.md): each old path still imports, for one release, as the module at its new
path (the same module object, so what is patched at one is patched at the other), with a
DeprecationWarning naming the new path. Nothing in mirror_fg itself uses the old paths.
(``mirror_fg.solver.incremental`` is now the package whose calibrator.py holds what the module did; the
package hands on its names.)
"""
from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

__all__ = ["MOVED", "install"]

#: Old module (below ``mirror_fg.``) -> its new place.
MOVED = {
    "solver.analytic": "solver.start.analytic",
    "solver.analytic_solution": "solver.start.analytic_solution",
    "solver.calibration": "solver.result.calibration",
    "solver.camera_labels": "solver.screen.camera_labels",
    "solver.consensus": "solver.screen.consensus",
    "solver.consistency": "solver.screen.consistency",
    "solver.dispersion": "solver.fit.dispersion",
    "solver.graph": "solver.model.graph",
    "solver.incremental_graph": "solver.incremental.graph",
    "solver.incremental_startup": "solver.incremental.startup",
    "solver.incremental_state": "solver.incremental.state",
    "solver.incremental_tree": "solver.incremental.tree",
    "solver.incremental_values": "solver.incremental.values",
    "solver.incremental_views": "solver.incremental.views",
    "solver.incremental_views_start": "solver.incremental.views_start",
    "solver.initial": "solver.start.initial",
    "solver.intrinsics": "solver.batch.intrinsics",
    "solver.intrinsics_observability": "solver.batch.intrinsics_observability",
    "solver.labelling": "solver.screen.labelling",
    "solver.link_point_error": "solver.result.link_point_error",
    "solver.lm": "solver.model.lm",
    "solver.marginals": "solver.model.marginals",
    "solver.peeling": "solver.start.peeling",
    "solver.pixel_problem": "solver.batch.pixel_problem",
    "solver.placement_consensus": "solver.screen.placement_consensus",
    "solver.placement_rule": "solver.start.placement_rule",
    "solver.placement_tree": "solver.start.placement_tree",
    "solver.pnp": "solver.start.pnp",
    "solver.point_error": "solver.result.point_error",
    "solver.propagation": "solver.start.propagation",
    "solver.rechecks": "solver.screen.rechecks",
    "solver.reconstruction": "solver.start.reconstruction",
    "solver.residuals": "solver.model.residuals",
    "solver.result_builder": "solver.result.builder",
    "solver.result_guard": "solver.result.guard",
    "solver.rig": "solver.model.rig",
    "solver.robot_solve": "solver.batch.robot_solve",
    "solver.robot_start": "solver.start.robot_start",
    "solver.robot_views": "solver.model.robot_views",
    "solver.screens": "solver.batch.screens",
    "solver.tree_problem": "solver.batch.tree_problem",
    "solver.validation": "solver.fit.validation",
    "solver.verify": "analysis.verify",
    "solver.verify_priors": "analysis.verify_priors",
    "solver.views": "solver.model.views",
    "solver.views_solve": "solver.batch.views_solve",
    "tools.crb": "solver.information.crb",
    "tools.many": "analysis.many",
    "tools.pattern": "vision.pattern",
    "tools.live": "live.session",
    "tools.live_joints": "live.joints",
    "tools.live_save": "live.save",
    "tools.live_server": "live.server",
    "tools.live_sources": "live.sources",
    "tools.live_verify": "live.verify",
    "tools.montecarlo": "analysis.montecarlo",
    "tools.plan": "analysis.plan",
    "tools.plan_views": "analysis.plan_views",
    "tools.report": "report.writer",
    "tools.report_diagnostics": "report.diagnostics",
    "tools.report_figures": "report.figures",
    "tools.report_general": "report.general",
    "tools.report_pages": "report.pages",
    "tools.report_robot": "report.robot",
    "tools.report_scene": "report.scene",
    "tools.report_screen": "report.screen",
    "tools.report_units": "report.units",
    "tools.report_views": "report.views",
    "tools.residuals": "report.residuals",
    "tools.robot_summary": "report.robot_summary",
    "tools.simulate": "simulate.tree",
    "tools.simulate_rig": "simulate.rig",
    "tools.simulate_views": "simulate.views",
    "tools.suggest": "solver.information.suggest",
    "tools.summary": "report.summary",
    "tools.trial_log": "analysis.trial_log",
    "tools.verdict": "report.verdict",
    "tools.verify_study": "analysis.verify_study",
    "tools.views_truth": "simulate.views_truth",
}


class _MovedFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds an old path and loads it as the module at its new path."""

    def find_spec(self, fullname, path=None, target=None):
        if not fullname.startswith("mirror_fg.") or fullname[len("mirror_fg."):] not in MOVED:
            return None
        return importlib.util.spec_from_loader(fullname, self)

    def create_module(self, spec):
        new = "mirror_fg." + MOVED[spec.name[len("mirror_fg."):]]
        warnings.warn(f"{spec.name} moved to {new}; the old path goes in the next release", DeprecationWarning,
                      stacklevel=3)
        return importlib.import_module(new)

    def exec_module(self, module):
        pass  # the module at the new path is loaded already


def install() -> None:
    """Put the finder last on ``sys.meta_path`` (after the real files), once."""
    if not any(isinstance(finder, _MovedFinder) for finder in sys.meta_path):
        sys.meta_path.append(_MovedFinder())
