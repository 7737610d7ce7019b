"""Cramér-Rao bounds of the general set-ups before any data (``mirror-fg plan --kind kaleidoscope|mixed``,
``--cameras N``): each draw is a noise-free simulation (``simulate/views.py``,
``simulate/rig.py``), and the Fisher information of the general view model at its truth
(``solver/model/views.py``, the same factors ``calibrate`` solves; without a known target with the scale held)
gives the best covariance of every camera's pose on the body and of every rig transform. Bounds are the
quadratic mean over the draws, as ``analysis/plan.py``'s. ``--shared K1,K2,...`` sweeps the number of
placements the cameras of a rig see together, to show how many the rig needs.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mirror_fg.core.transform import Transform
from mirror_fg.io.dataset import dataset_from_dict
from mirror_fg.solver.model.rig import rig_transforms
from mirror_fg.solver.model.views import ViewEstimate, ViewProblem

__all__ = ["ViewsPlan", "plan_views", "format_views_plan"]


@dataclass
class ViewsPlan:
    """Bounds (3-sigma, quadratic mean over draws) of one set-up: per camera ``T_base_cam``
    ``{name: (rotation_deg (3,), position_mm (3,))}`` and per rig transform ``{"a -> b": (...)}``."""

    description: str
    draws: int
    cameras: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    rig: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    images: int = 0

    def to_dict(self) -> dict:
        def entry(b):
            return {"rotation_deg": [float(x) for x in b[0]], "position_mm": [float(x) for x in b[1]]}
        return {"setup": self.description, "draws": self.draws, "images": self.images,
                "sigma3_base_cam": {name: entry(b) for name, b in self.cameras.items()},
                "rig": {name: entry(b) for name, b in self.rig.items()}}


def _simulate(kind: str, cameras: int, seed: int, pixel_sigma: float, **options):
    from mirror_fg.simulate.rig import simulate_rig_mixed, simulate_rig_tree
    from mirror_fg.simulate.views import simulate_kaleidoscope, simulate_mixed

    if cameras >= 2:
        make = simulate_rig_mixed if kind == "mixed" else simulate_rig_tree
        return make(cameras, seed=seed, pixel_sigma=0.0, **options)
    if kind == "kaleidoscope":
        return simulate_kaleidoscope(seed=seed, pixel_sigma=0.0, **options)
    return simulate_mixed(seed=seed, pixel_sigma=0.0, **options)


def _sigma3(covariance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    sigma = 3.0 * np.sqrt(np.maximum(np.diag(covariance), 0.0))
    return np.degrees(sigma[:3]), 1000.0 * sigma[3:]


def plan_views(kind: str = "tree", cameras: int = 1, draws: int = 5, seed: int = 0, pixel_sigma: float = 1.0,
               **options) -> ViewsPlan:
    """The bounds of ``draws`` simulated scenes of the set-up (module docstring); ``options`` go to the
    simulator (``shared``, ``own``, ``placements``, ``num_mirrors``, ``target``, ...)."""
    if pixel_sigma <= 0:
        raise ValueError("plan: --sigma must be > 0")
    per_camera: dict[str, list] = {}
    per_rig: dict[str, list] = {}
    images = 0
    for draw in range(draws):
        data, truth = _simulate(kind, cameras, seed + draw, pixel_sigma, **options)
        data["pixel_sigma"] = pixel_sigma
        dataset = dataset_from_dict(data, source="<plan>")
        images = len(dataset.images)
        problem = ViewProblem(dataset)
        names = problem.cameras

        def truth_camera(name):
            return name if dataset.cameras is not None else None

        estimate = ViewEstimate({n: truth.poses[truth_camera(n)] for n in names},
                                {p: truth.vector(p, truth_camera(problem.owners[p])) for p in problem.placements},
                                {n: truth.points[n] for n in problem.point_names})
        values = problem.values(estimate)
        poses, joint, _, _, _ = problem.covariances(problem.graph(), values, estimate)
        for name in names:
            R, t = estimate.poses[name]
            per_camera.setdefault(name, []).append(Transform(R, t).inverse_covariance(poses[name]))
        if len(names) > 1:
            for link in rig_transforms(names, [estimate.poses[n] for n in names], joint):
                per_rig.setdefault(f"{link.from_camera} -> {link.to_camera}", []).append(link.covariance)
    mean = {name: _sigma3(np.mean(covs, axis=0)) for name, covs in per_camera.items()}
    rig = {name: _sigma3(np.mean(covs, axis=0)) for name, covs in per_rig.items()}
    words = ", ".join(f"{k}={v}" for k, v in options.items() if v is not None)
    description = f"{kind}, {cameras} camera(s), pixel_sigma {pixel_sigma:g} px" + (f", {words}" if words else "")
    return ViewsPlan(description, draws, mean, rig, images)


def format_views_plan(result: ViewsPlan) -> str:
    """The plan in lines a person reads: each camera's and each rig transform's bounds."""
    def triple(values, fmt):
        return "[" + ", ".join(format(float(x), fmt) for x in values) + "]"

    lines = [f"setup: {result.description} ({result.images} images per draw, {result.draws} draws)",
             "3-sigma bounds (Cramér-Rao, at the truth; quadratic mean over draws); T_base_cam is each camera's pose "
             "on the robot, its bounds about and along the base axes (as calibrate prints), a rig transform's about "
             "and along its 'to' camera's axes:"]
    for name, (rot, pos) in result.cameras.items():
        lines.append(f"  {name}: T_base_cam rotation ±{triple(rot, '.3f')} deg, position ±{triple(pos, '.2f')} mm")
    for name, (rot, pos) in result.rig.items():
        lines.append(f"  rig {name}: rotation ±{triple(rot, '.3f')} deg, position ±{triple(pos, '.2f')} mm")
    return "\n".join(lines)

