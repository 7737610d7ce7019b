"""Tracked points through the calibration with one ``pixel_sigma`` (before) and with each track's own
sigma in ``point_sigma`` (after): the reconstructed points' distance to the truth in their sigmas.

The scenes are ``scripts/render_scene.py``'s rendered one-mirror loops (``render_sequence``, 54 frames,
800 x 600, a corner-like P0 and a blob-like P1; about 1.5 s each, nothing cached). Each point is followed
with detect.py's tracker (:class:`~mirror_fg.vision.tracking.PointTracker`: KLT, then refinement onto
the feature; or plain KLT) and its sigma is the tracker's (:meth:`PointTracker.sigma`). Fiducials are
their true pixels plus Gaussian noise (``--fiducial-noise``, as tests/test_tracking_refine.py's study),
weighed with ``pixel_sigma``. Prints, per scene and point, the largest per-axis error in sigmas
(docs/formats.md's 3-sigma convention) and the error in mm, before -> after.

    python scripts/point_sigma_study.py [--seeds 0 1 2 3 4 5] [--tracker refined|klt]
"""
from __future__ import annotations

import argparse
import importlib.util
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def _render_scene():
    if "render_scene" in sys.modules:
        return sys.modules["render_scene"]
    spec = importlib.util.spec_from_file_location("render_scene", REPO / "scripts" / "render_scene.py")
    module = importlib.util.module_from_spec(spec)  # type: ignore[arg-type]
    sys.modules["render_scene"] = module
    spec.loader.exec_module(module)  # type: ignore[union-attr]
    return module


def track(frames, truth: dict, kinds: dict[str, str]) -> tuple[list[dict[str, np.ndarray]], dict[str, float]]:
    """Every frame's tracked pixels (detect.py's call pattern: ``step`` then ``set`` on the first frame)
    and each track's sigma (pixels, per axis)."""
    from mirror_fg.vision.tracking import KLTParams, PointTracker

    tracker = PointTracker(KLTParams())
    out = []
    for k, frame in enumerate(frames):
        tracker.step(frame)
        if k == 0:
            for name, kind in kinds.items():
                tracker.set(name, np.array(truth["pixels"][0][name]), kind=kind)
        out.append({n: tracker.points[n].copy() for n in kinds if n in tracker.points})
    return out, {name: tracker.sigma(name) for name in kinds}


def dataset_dict(truth: dict, tracked: list[dict[str, np.ndarray]], pixel_sigma: float, fiducial_noise_px: float,
                 seed: int, point_sigma: dict[str, float] | None) -> dict:
    """The dataset@1 dictionary: fiducials at their true pixels plus noise, the tracked points as tracked."""
    rng = np.random.default_rng(seed)
    images = []
    for k, (pixels, points) in enumerate(zip(truth["pixels"], tracked)):
        obs = {n: [float(x) for x in np.array(pixels[n]) + rng.normal(0, fiducial_noise_px, 2)] for n in truth["fiducials"]}
        obs.update({n: [float(p[0]), float(p[1])] for n, p in points.items()})
        images.append({"id": f"frame{k}", "mirror_configs": [k], "observations": obs})
    d = {"format": "mirror-fg/dataset@1", "num_mirrors": 1, "camera": truth["camera"], "pixel_sigma": pixel_sigma,
         "fiducials": truth["fiducials"], "images": images}
    if point_sigma:
        d["point_sigma"] = dict(point_sigma)
    return d


def sigma_distances(d: dict, truth: dict) -> dict[str, tuple[float, float, float]]:
    """Calibrate ``d``; per point: (largest per-axis |error| / sigma, NEES, error in mm)."""
    from mirror_fg import calibrate, dataset_from_dict

    cal = calibrate(dataset_from_dict(d, source="rendered loop"))
    out = {}
    for name, spec in truth["points"].items():
        error = cal.points[name] - np.array(spec["xyz"])
        covariance = cal.point_covariances[name]
        out[name] = (float(np.max(np.abs(error) / np.sqrt(np.diag(covariance)))),
                     float(error @ np.linalg.solve(covariance, error)), 1000 * float(np.linalg.norm(error)))
    return out


def study(seed: int, kinds: dict[str, str], pixel_sigma: float = 0.5, fiducial_noise_px: float = 0.2) -> dict:
    """One scene: the tracks' sigmas and errors against the true pixels, and each point before (one
    ``pixel_sigma``) and after (``point_sigma`` = each track's sigma)."""
    frames, truth = _render_scene().render_sequence(seed=seed)
    tracked, sigmas = track(frames, truth, kinds)
    errors = {n: np.array([np.linalg.norm(p[n] - truth["pixels"][k][n]) for k, p in enumerate(tracked) if n in p])
              for n in kinds}
    before = sigma_distances(dataset_dict(truth, tracked, pixel_sigma, fiducial_noise_px, seed, None), truth)
    after = sigma_distances(dataset_dict(truth, tracked, pixel_sigma, fiducial_noise_px, seed, sigmas), truth)
    return {"sigmas": sigmas, "errors": errors, "before": before, "after": after, "frames": len(frames)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(6)))
    parser.add_argument("--tracker", choices=("refined", "klt"), default="refined")
    parser.add_argument("--pixel-sigma", type=float, default=0.5)
    parser.add_argument("--fiducial-noise", type=float, default=0.2)
    args = parser.parse_args(argv)
    kinds = {"P0": "corner", "P1": "blob"} if args.tracker == "refined" else {"P0": "klt", "P1": "klt"}
    for seed in args.seeds:
        r = study(seed, kinds, args.pixel_sigma, args.fiducial_noise)
        parts = []
        for n in kinds:
            b, a, e = r["before"][n], r["after"][n], r["errors"][n]
            parts.append(f"{n} ({kinds[n]}, track median {np.median(e):.2f} max {np.max(e):.2f} px, sigma {r['sigmas'][n]:.2f} px): "
                         f"{b[0]:.2f} sigma -> {a[0]:.2f} sigma (NEES {b[1]:.1f} -> {a[1]:.1f}, {a[2]:.2f} mm)")
        print(f"scene {seed}: " + "; ".join(parts))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
